"""``swpc serve``'s HTTP server: uvicorn with bounded connections.

uvicorn closes a connection idle *between* requests (``timeout_keep_alive``) but not one
that never completes a request: a client that opens connections and sends nothing (or
a header a byte at a time) holds a file descriptor each, for ever, until the service runs
out of them (with 256, it stopped answering ``/health`` for 50 s while asyncio logged
every failed accept).  :class:`GuardedH11` adds:

* a head timeout: a connection must send a complete request within ``header_timeout``
  host seconds of connecting (or of its first byte after an idle keep-alive), else it is
  closed;
* a connection cap: beyond ``max_connections`` open connections, or beyond a quarter of
  them from one client address (:attr:`GuardedH11.per_client`, 8 at least: a client
  flooding the service closes only its own), one is closed to make room for the new one, so that a
  new client (an abort, ``/health``) is served: the one idle
  longest after a response (kept alive), else the oldest that has sent no whole request
  for :data:`GRACE` s, else the oldest event stream (the browser reconnects and resumes it
  by ``Last-Event-ID``), else the oldest read in progress (a GET or HEAD: a slow reader of
  a download), and only then the oldest connection younger than :data:`GRACE` still
  sending its first request (asyncio accepts connections in batches: in a flood, a
  client's connection would otherwise be closed by the ones accepted after it before its
  request was read).  A connection carrying a request that may change something (each
  with the token) is never closed; with none to close, the new connection is.  Event
  streams are also bounded where they begin, to fewer than the cap
  (:class:`services.http.edge.streams.StreamGate`).

The unit's ``LimitNOFILE=`` leaves room above the cap for the bus, zenoh and files.

Secrets never reach a log: uvicorn's access log line carries the request's query string,
where a client may put the token (``?token=...``, refused with 401 all the same);
:class:`RedactSecrets` replaces the values of secret-looking query parameters (``token``,
``pw``, ``bearer``, ``password``, ``key``...) and the service's token wherever it appears,
percent-encoded or not (a path is decoded, as the server decodes it, before it is
searched, its control characters escaped), before the line is written.

``swpc serve`` binds the listening socket itself (:func:`listen_socket`) before the
service opens anything, so that a port in use is one line on stderr, not uvicorn's
start-up and shut-down log and exit status 3.
"""

from __future__ import annotations

import asyncio
import logging
import re
import signal
import socket
import time
from collections.abc import Callable, Iterable
from typing import Any
from urllib.parse import unquote

import h11
import uvicorn
from uvicorn.protocols.http.h11_impl import H11Protocol

from swpc_hw.errors import SwpcError

MAX_HEADER_BYTES = 16 << 10
GRACE = 1.0
"""Host seconds a new connection has to send its first request before the cap may close
it for another."""


class ListenError(SwpcError):
    """The HTTP address cannot be listened on (the port in use, an address that is not
    this host's, a port below 1024 without the capability)."""


def listen_socket(host: str, port: int) -> socket.socket:
    """A TCP socket bound to ``host``:``port`` (as uvicorn binds it: ``SO_REUSEADDR``,
    the first address ``host`` resolves to); the server listens on it."""
    sock: socket.socket | None = None
    try:
        family, kind, proto, _, addr = socket.getaddrinfo(
            host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE
        )[0]
        sock = socket.socket(family, kind, proto)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(addr)
    except OSError as exc:
        if sock is not None:
            sock.close()
        raise ListenError(
            f"cannot listen on {host}:{port}: {exc.strerror or exc} "
            "(--host/--port, SWPC_HOST/SWPC_PORT)"
        ) from None
    return sock


class GuardedH11(H11Protocol):
    """H11Protocol with a head timeout and a connection cap (module docstring)."""

    header_timeout = 10.0
    max_connections = 128
    stream_paths: frozenset[str] = frozenset({"/events"})

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        self._head: asyncio.TimerHandle | None = None
        self._idle_since: float | None = time.monotonic()
        self._busy_since = 0.0
        self._served = False  # a response was sent on it: idle now means kept alive
        super().connection_made(transport)
        self._peer = self.client[0] if self.client else ""
        mine = [c for c in self.connections if isinstance(c, GuardedH11) and c._peer == self._peer]
        for over, among in (
            (len(mine) > self.per_client, mine),
            (len(self.connections) > self.max_connections, self.connections),
        ):
            if over:
                victim = self._victim(among)
                if victim is None:
                    self.transport.close()
                    return
                victim.transport.close()
                self.connections.discard(victim)
        self._arm()

    @property
    def per_client(self) -> int:
        """Open connections one client address holds at most: a quarter of the cap (8 at
        least)."""
        return max(8, self.max_connections // 4)

    def _eviction_rank(self, now: float) -> tuple[int, float] | None:
        """How readily this connection is closed for a new one (lower first, then the
        oldest), or None when it is not (module docstring)."""
        if self._idle_since is not None:
            if self._served:
                return (0, self._idle_since)
            return (1 if now - self._idle_since >= GRACE else 4, self._idle_since)
        scope = self.scope
        if scope is None:  # no request parsed: not reached (idle until it is)
            return None
        if scope.get("path") in self.stream_paths:
            return (2, self._busy_since)
        if scope.get("method") in ("GET", "HEAD"):
            return (3, self._busy_since)
        return None

    def _victim(self, among: Iterable[Any]) -> GuardedH11 | None:
        now = time.monotonic()
        ranked = [
            (rank, c)
            for c in among
            if isinstance(c, GuardedH11) and c is not self
            and (rank := c._eviction_rank(now)) is not None
        ]  # fmt: skip
        return min(ranked, key=lambda rc: rc[0])[1] if ranked else None

    def _arm(self) -> None:
        if self._head is None:
            self._head = self.loop.call_later(self.header_timeout, self._expire)

    def _disarm(self) -> None:
        if self._head is not None:
            self._head.cancel()
            self._head = None

    def _expire(self) -> None:
        self._head = None
        if not self.transport.is_closing() and self.conn.their_state is not h11.DONE:
            self.transport.close()

    def data_received(self, data: bytes) -> None:
        self._arm()
        super().data_received(data)
        if self.conn.their_state in (h11.DONE, h11.MUST_CLOSE, h11.CLOSED, h11.ERROR):
            self._disarm()
            if self._idle_since is not None:
                self._busy_since = time.monotonic()
            self._idle_since = None

    def on_response_complete(self) -> None:
        super().on_response_complete()
        self._idle_since = time.monotonic()
        self._served = True

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm()
        super().connection_lost(exc)


SECRET_PARAMS = re.compile(
    r"(?i)([?&;](?:[^=&#;]*(?:token|auth|key|secret|pass|pw|bearer|cred|sig|session)"
    r"[^=&#;]*)=)[^&#;\s]*"
)
"""A query parameter whose name says it holds a secret, up to its value."""
REDACTED = "[redacted]"
_CONTROL = re.compile(r"[\x00-\x1f\x7f]")


def _decoded(text: str) -> str:
    """``text`` with its percent-escapes decoded (up to three times: a twice-encoded token
    is the token to anyone who reads the log) and control characters escaped (a decoded
    ``%0a`` must not start a forged log line)."""
    for _ in range(3):
        if "%" not in text:
            break
        text = unquote(text, errors="backslashreplace")
    return _CONTROL.sub(lambda m: f"\\x{ord(m.group()):02x}", text)


class RedactSecrets(logging.Filter):
    """Redact secrets from a log record (module docstring): the values of secret-looking
    query parameters and ``token()`` wherever it appears, encoded or not; the record is
    kept."""

    def __init__(self, token: Callable[[], str]) -> None:
        super().__init__("swpc.redact")
        self.token = token

    def redact(self, text: str) -> str:
        text = SECRET_PARAMS.sub(lambda m: m.group(1) + REDACTED, _decoded(text))
        token = self.token()
        return text.replace(token, REDACTED) if token else text

    def filter(self, record: logging.LogRecord) -> bool:
        if isinstance(record.args, tuple):
            record.args = tuple(
                self.redact(a) if isinstance(a, str) else a for a in record.args
            )
        if isinstance(record.msg, str):
            record.msg = self.redact(record.msg)
        return True


def redact_access_log(token: Callable[[], str]) -> None:
    """Put :class:`RedactSecrets` on uvicorn's access and error loggers (once)."""
    for name in ("uvicorn.access", "uvicorn.error"):
        lg = logging.getLogger(name)
        for f in list(lg.filters):
            if isinstance(f, RedactSecrets):
                lg.removeFilter(f)
        lg.addFilter(RedactSecrets(token))


class Server(uvicorn.Server):
    """uvicorn's server that tells the app which signal stopped it (a run in progress
    then ends "stopped (SIGTERM)", not "aborted by the operator")."""

    def handle_exit(self, sig: int, frame: Any) -> None:
        app = getattr(self.config, "app", None)
        state = getattr(app, "state", None)
        if state is not None:
            state.stop_signal = signal.Signals(sig).name
        super().handle_exit(sig, frame)


def server(app: Any, *, host: str, port: int, header_timeout: float, max_connections: int,
           log_level: str = "info") -> Server:
    """The configured server (``.run()`` serves until SIGTERM/SIGINT); its logs redacted
    (:class:`RedactSecrets`, the app's token) and written by the root logger's handler
    (:func:`services.store.logs.configure`), in swpc's format."""
    state = getattr(app, "state", None)
    redact_access_log(lambda: str(getattr(state, "token", "") or ""))
    protocol = type(
        "GuardedH11",
        (GuardedH11,),
        {"header_timeout": header_timeout, "max_connections": max_connections},
    )
    config = uvicorn.Config(
        app,
        host=host,
        port=port,
        http=protocol,
        log_level=log_level,
        log_config=None,  # no handler or format of its own: its lines go to swpc's
        timeout_keep_alive=min(5, max(1, int(header_timeout))),
        h11_max_incomplete_event_size=MAX_HEADER_BYTES,
        server_header=False,
        backlog=max_connections,
    )
    return Server(config)
