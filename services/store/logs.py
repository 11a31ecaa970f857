"""Structured log lines: ``logfmt`` (``key=value``, values quoted when they need it).

Every run event goes to the ``swpc.run`` logger as ``event=<name> run=<id> ...``; the
service's own (start-up, locks, disk, the store, installs and roll-backs of the kinematic
file through the API) to ``swpc.service``.  ``swpc serve`` sends
them to stderr (the journal under systemd) with :func:`configure`.
"""

from __future__ import annotations

import json
import logging
from typing import Any

FORMAT = "%(levelname)s %(name)s %(message)s"


def logfmt(**fields: Any) -> str:
    """``k=v`` pairs in order; ``None`` left out; strings with spaces, quotes, ``=`` or
    newlines JSON-quoted; floats to 6 significant digits."""
    parts = []
    for k, v in fields.items():
        if v is None:
            continue
        if isinstance(v, float):
            text = f"{v:.6g}"
        elif isinstance(v, bool):
            text = "true" if v else "false"
        else:
            text = str(v)
        if not text or any(c in text for c in ' "=\\\n\t'):
            text = json.dumps(text)
        parts.append(f"{k}={text}")
    return " ".join(parts)


def event(logger: logging.Logger, level: int, name: str, **fields: Any) -> str:
    """Log ``event=<name> <fields>`` at ``level``; returns the line."""
    line = logfmt(event=name, **fields)
    logger.log(level, line)
    return line


def configure(level: str | int = "info") -> None:
    """Send ``swpc.*`` log lines to stderr (once; uvicorn keeps its own handlers)."""
    lg = logging.getLogger("swpc")
    lg.setLevel(level.upper() if isinstance(level, str) else level)
    if not any(getattr(h, "_swpc", False) for h in lg.handlers):
        h = logging.StreamHandler()
        h.setFormatter(logging.Formatter(FORMAT))
        h._swpc = True  # type: ignore[attr-defined]
        lg.addHandler(h)
        lg.propagate = False
