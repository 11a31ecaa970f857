"""Run changes pushed to whoever listens (the console's server-sent events).

The state machine calls its ``on_change`` on every transition; the runtime publishes the
run's status here.  Publishing never blocks and never reads a clock: it is called from
the run's thread, which in lockstep is a participant of the simulated clock, so it
numbers the event, keeps it and wakes every subscriber (one per open event stream, each
on an asyncio event loop), and returns.

Every event has a sequence number, increasing over the bus's life; the last
:data:`HISTORY` events are kept, so that a stream reads what it has not sent yet
(:meth:`EventBus.since`) and a client that reconnects gets exactly the events it
missed.  An event's id (:meth:`EventBus.event_id`) is ``<epoch>:<number>``, the epoch a
random name of this bus: an id of another service process (restarted since) is unknown
here, not mistaken for one of ours.  A stream also numbers what it sends that is not
published (its snapshots, the live view) with :meth:`EventBus.mark`, after every event
published so far, so that the ids of one stream increase and any of them says where to
resume.  A stream that falls :data:`HISTORY` events behind, or a client whose id is too
old or unknown, starts over from a snapshot: an event is a whole snapshot of a run, so
the latest one is always enough to show where it is.
"""

from __future__ import annotations

import asyncio
import contextlib
import secrets
import threading
from collections import deque
from collections.abc import Iterator
from typing import Any

Event = dict[str, Any]
HISTORY = 1024
"""Events kept for the streams and the clients that reconnect (a run makes ~100)."""


class Subscription:
    """One listener's wake-up, set from any thread, awaited on its event loop."""

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self.loop = loop
        self._news = asyncio.Event()

    async def wait(self, timeout: float) -> bool:
        """Until something was published since the last call, or ``timeout`` seconds
        (host time) pass; whether something was."""
        try:
            await asyncio.wait_for(self._news.wait(), timeout)
        except TimeoutError:
            return False
        self._news.clear()
        return True


class EventBus:
    """Numbered events, the latest :data:`HISTORY` kept, subscribers woken (thread-safe,
    non-blocking)."""

    def __init__(self, history: int = HISTORY) -> None:
        self._subs: set[Subscription] = set()
        self._lock = threading.Lock()
        self._log: deque[tuple[int, Event]] = deque(maxlen=history)
        self._seq = 0
        self._forgotten = 0  # the number of the newest event no longer kept
        self.epoch = secrets.token_hex(4)
        self.published = 0

    def publish(self, event: Event) -> int:
        """Keep ``event`` under the next number (returned); wake every subscriber."""
        with self._lock:
            self._seq += 1
            if len(self._log) == self._log.maxlen:
                self._forgotten = self._log[0][0]
            self._log.append((self._seq, event))
            self.published += 1
            seq = self._seq
            subs = list(self._subs)
        for sub in subs:
            try:
                sub.loop.call_soon_threadsafe(sub._news.set)
            except RuntimeError:  # its loop is closed: the listener is gone
                with self._lock:
                    self._subs.discard(sub)
        return seq

    def mark(self) -> int:
        """A new number, after every event published so far, for what a stream sends
        that is not published (module docstring)."""
        with self._lock:
            self._seq += 1
            return self._seq

    def since(self, after: int) -> list[tuple[int, Event]] | None:
        """The events kept after number ``after``, oldest first; None when some of them
        are no longer kept or ``after`` is not a number of this bus yet."""
        with self._lock:
            if after < self._forgotten or after > self._seq:
                return None
            return [(n, e) for n, e in self._log if n > after]

    def event_id(self, seq: int) -> str:
        return f"{self.epoch}:{seq}"

    def number(self, event_id: str | None) -> int | None:
        """The number of an id of this bus (``Last-Event-ID``); None for another's or
        none."""
        epoch, _, seq = (event_id or "").strip().partition(":")
        # at most 18 digits: a sequence number fits in 63 bits, and int() of a longer string
        # is work an unauthenticated header should not buy (over 4300 digits: ValueError)
        if epoch != self.epoch or not (seq.isascii() and seq.isdigit()) or len(seq) > 18:
            return None
        return int(seq)

    @contextlib.contextmanager
    def subscribe(self) -> Iterator[Subscription]:
        """A subscription for the running event loop, removed on exit."""
        sub = Subscription(asyncio.get_running_loop())
        with self._lock:
            self._subs.add(sub)
        try:
            yield sub
        finally:
            with self._lock:
                self._subs.discard(sub)

    @property
    def subscribers(self) -> int:
        with self._lock:
            return len(self._subs)
