"""The log settings' values (``SWPC_LOG_LEVEL``, ``SWPC_LOG_FORMAT``): here, with no
heavy import, for ``swpc serve``'s flags; :mod:`services.store.logs` writes them."""

from __future__ import annotations

from typing import Literal, get_args

LogLevel = Literal["debug", "info", "warning", "error", "critical"]
LogFormat = Literal["text", "json"]
LOG_LEVELS: tuple[str, ...] = get_args(LogLevel)
LOG_FORMATS: tuple[str, ...] = get_args(LogFormat)
