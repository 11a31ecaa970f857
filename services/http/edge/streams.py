"""Who may hold an event stream open: :class:`StreamGate`.

A server-sent event stream (``GET /events``) holds its HTTP connection for as long as the
client keeps it, so streams are what could fill the server's connection cap
(:class:`services.http.edge.server.GuardedH11`) and leave no connection for an abort.  The
gate bounds them before a stream begins:

* at most ``max_streams`` streams open at once, fewer than the connection cap
  (``SWPC_MAX_STREAMS``, at most half of ``SWPC_MAX_CONNECTIONS``): the rest of the
  connections stay for control (abort, ``/health``);
* a client without the bearer token holds at most ``per_client`` of them (by its
  address) and, all such clients together, at most half of ``max_streams``;
* a stream with the token (the console sends it once the operator has given it) is
  refused only when ``max_streams`` streams with the token are open: one beyond the cap
  ends the oldest stream without the token (:attr:`Ticket.evicted`; the stream stops
  within one live period and the browser reconnects, to a 429 until there is room).

A refused stream is answered 429 with ``Retry-After`` before any event.  The gate is
pure bookkeeping under a lock (no I/O, no clock): the route asks :meth:`StreamGate.admit`
before the stream starts and the stream releases its ticket when it ends; a ticket whose
stream never started is released when it is garbage-collected.
"""

from __future__ import annotations

import itertools
import threading
import weakref
from dataclasses import dataclass, field


class StreamRefusedError(Exception):
    """No room for another event stream of this client (the reason says which cap)."""


@dataclass
class _Held:
    client: str
    authenticated: bool
    evicted: threading.Event = field(default_factory=threading.Event)


class Ticket:
    """One admitted stream; :meth:`release` (idempotent) gives its place back."""

    def __init__(self, gate: StreamGate, number: int, held: _Held) -> None:
        self.number = number
        self._held = held
        self._release = weakref.finalize(self, gate._release, number)

    @property
    def evicted(self) -> bool:
        """A stream with the token took this one's place: end the stream."""
        return self._held.evicted.is_set()

    @property
    def authenticated(self) -> bool:
        return self._held.authenticated

    def release(self) -> None:
        self._release()


class StreamGate:
    """The caps of the module docstring."""

    def __init__(self, max_streams: int, per_client: int) -> None:
        if max_streams < 2 or per_client < 1:
            raise ValueError("max_streams >= 2 and per_client >= 1")
        self.max_streams = max_streams
        self.per_client = per_client
        self.max_anonymous = max_streams // 2
        self._lock = threading.Lock()
        self._open: dict[int, _Held] = {}
        self._numbers = itertools.count(1)
        self.refused = 0
        """Streams refused since start (``/metrics``)."""

    def counts(self) -> tuple[int, int]:
        """Open streams ``(with the token, without)``."""
        with self._lock:
            auth = sum(h.authenticated for h in self._open.values())
            return auth, len(self._open) - auth

    def admit(self, client: str, authenticated: bool) -> Ticket:
        """A ticket for a new stream of ``client``, or :class:`StreamRefusedError`."""
        with self._lock:
            held = [(n, h) for n, h in self._open.items() if not h.evicted.is_set()]
            anonymous = [(n, h) for n, h in held if not h.authenticated]
            if authenticated:
                if len(held) - len(anonymous) >= self.max_streams:
                    return self._refuse(f"{self.max_streams} event streams with the token "
                                        "are open (SWPC_MAX_STREAMS)")  # fmt: skip
                if len(held) >= self.max_streams:  # the oldest without the token makes room
                    anonymous[0][1].evicted.set()
            else:
                mine = sum(h.client == client for _, h in anonymous)
                if mine >= self.per_client:
                    return self._refuse(f"{client} holds {mine} event streams without the "
                                        "token (SWPC_STREAMS_PER_CLIENT); send the token "
                                        "or close one")  # fmt: skip
                if len(anonymous) >= self.max_anonymous or len(held) >= self.max_streams:
                    return self._refuse(
                        f"{len(anonymous)} event streams without the token are open (half "
                        "of SWPC_MAX_STREAMS); send the token"
                    )
            number = next(self._numbers)
            h = _Held(client, authenticated)
            self._open[number] = h
        return Ticket(self, number, h)

    def _refuse(self, why: str) -> Ticket:
        self.refused += 1
        raise StreamRefusedError(f"no room for another event stream: {why}")

    def _release(self, number: int) -> None:
        with self._lock:
            self._open.pop(number, None)
