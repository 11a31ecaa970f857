"""swpc's log lines: structured events, and the one format of every line ``swpc serve`` writes.

Every run event goes to the ``swpc.run`` logger as ``event=<name> run=<id> ...``
(:func:`event`: ``logfmt``, ``key=value``, values quoted when they need it); the service's
own (start-up, locks, disk, the store, installs and roll-backs of the kinematic file
through the API) to ``swpc.service``.  The fields also ride on the record
(:data:`FIELDS`), for the JSON format.

``swpc serve`` sends every line to stderr (the journal under systemd) through one handler
on the root logger (:func:`configure`): swpc's, uvicorn's (its access log included: it
installs no handler of its own, :func:`services.http.edge.server.server`) and any other
library's warnings, in one format (``SWPC_LOG_FORMAT``, ``--log-format``):

* ``text``: ``<time> <LEVEL> <logger> <message>``, the time ISO 8601 with milliseconds and
  the UTC offset (``2026-05-04T09:12:31.207+02:00``).  When stderr is the journal
  (``JOURNAL_STREAM`` names it, as systemd sets it) the time is left out: journald stamps
  every line itself (``journalctl -o short-iso-precise`` shows it to the microsecond).
* ``json``: one object per line, ``time``, ``level``, ``logger``, ``message`` and then
  the fields: an event's name is its ``message`` and each of its fields a key of its
  own; uvicorn's access line adds ``client``, ``method``, ``path`` and ``status``.  The
  time is always there (the lines may be shipped elsewhere).
"""

from __future__ import annotations

import datetime as _dt
import json
import logging
import math
import os
import sys
from collections.abc import Mapping
from typing import Any, TextIO

FIELDS = "swpc_fields"
"""The attribute of a log record that holds an :func:`event`'s fields (name first)."""
RESERVED = ("time", "level", "logger", "message")
"""The keys of every JSON line; a field of the same name is written ``<name>_``."""


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
    """Log ``event=<name> <fields>`` at ``level`` (the fields on the record too, for the
    JSON format); returns the line."""
    line = logfmt(event=name, **fields)
    logger.log(level, line, extra={FIELDS: {"event": name, **fields}})
    return line


def timestamp(record: logging.LogRecord) -> str:
    """The record's time, ISO 8601 in local time with milliseconds and the UTC offset."""
    when = _dt.datetime.fromtimestamp(record.created, tz=_dt.UTC).astimezone()
    return when.isoformat(timespec="milliseconds")


class TextFormatter(logging.Formatter):
    """``<time> <LEVEL> <logger> <message>`` (module docstring); ``timestamps=False``
    under journald.  A traceback follows its line, as the standard formatter writes it."""

    def __init__(self, timestamps: bool = True) -> None:
        super().__init__()
        self.timestamps = timestamps

    def format(self, record: logging.LogRecord) -> str:
        head = f"{record.levelname} {record.name} {record.getMessage()}"
        if self.timestamps:
            head = f"{timestamp(record)} {head}"
        if record.exc_info:
            head += "\n" + self.formatException(record.exc_info)
        return head


def _value(v: Any) -> Any:
    """A field's value as JSON has it (a non-finite float or another object: its text)."""
    if v is None or isinstance(v, (bool, int, str)):
        return v
    if isinstance(v, float):
        return v if math.isfinite(v) else repr(v)
    return str(v)


ACCESS = ("client", "method", "path", "http_version", "status")
"""What uvicorn passes its access line (its arguments, in order): fields in JSON."""


class JsonFormatter(logging.Formatter):
    """One JSON object per line (module docstring)."""

    def format(self, record: logging.LogRecord) -> str:
        out: dict[str, Any] = {
            "time": timestamp(record),
            "level": record.levelname,
            "logger": record.name,
        }
        fields: Mapping[str, Any] = getattr(record, FIELDS, None) or {}
        if fields:
            out["message"] = str(fields.get("event", record.getMessage()))
            fields = {k: v for k, v in fields.items() if k != "event"}
        else:
            out["message"] = record.getMessage()
            args = record.args
            if record.name == "uvicorn.access" and isinstance(args, tuple) and len(args) == 5:
                fields = {k: v for k, v in zip(ACCESS, args, strict=True) if k != "http_version"}
        for k, v in fields.items():
            if v is not None:
                out[f"{k}_" if k in RESERVED else k] = _value(v)
        if record.exc_info:
            out["traceback"] = self.formatException(record.exc_info)
        return json.dumps(out, ensure_ascii=False)


def journald_stream(environ: Mapping[str, str], stream: TextIO) -> bool:
    """``stream`` is the journal: systemd's ``JOURNAL_STREAM`` (``<device>:<inode>``)
    names its file (not merely set: a unit may redirect stderr elsewhere)."""
    value = environ.get("JOURNAL_STREAM", "")
    try:
        dev, ino = (int(x) for x in value.split(":"))
        st = os.fstat(stream.fileno())
    except (ValueError, OSError):
        return False
    return (st.st_dev, st.st_ino) == (dev, ino)


def formatter(fmt: str, stream: TextIO) -> logging.Formatter:
    """The formatter of ``fmt`` (``text`` or ``json``) for lines written to ``stream``
    (module docstring)."""
    if fmt == "json":
        return JsonFormatter()
    return TextFormatter(timestamps=not journald_stream(os.environ, stream))


class _Stderr(logging.StreamHandler[TextIO]):
    """A handler that writes to whatever ``sys.stderr`` is when it writes."""

    def __init__(self) -> None:
        super().__init__(sys.stderr)

    @property
    def stream(self) -> TextIO:
        return sys.stderr

    @stream.setter
    def stream(self, _value: TextIO) -> None:
        pass


OWN = ("swpc", "uvicorn")
"""The loggers at the chosen level; every other one (a library's) at warning at least."""


def configure(level: str = "info", fmt: str = "text") -> None:
    """Every log line to stderr in ``fmt`` (module docstring): one handler on the root
    logger (replacing the one an earlier call put there); ``swpc.*`` and ``uvicorn.*`` at
    ``level``, other libraries at ``warning`` or above."""
    root = logging.getLogger()
    for h in list(root.handlers):
        if isinstance(h, _Stderr):
            root.removeHandler(h)
    h = _Stderr()
    h.setFormatter(formatter(fmt, sys.stderr))
    root.addHandler(h)
    number = logging.getLevelNamesMapping()[level.upper()]
    root.setLevel(max(number, logging.WARNING))
    for name in OWN:
        lg = logging.getLogger(name)
        lg.setLevel(number)
        lg.propagate = True
