"""Run changes pushed to whoever listens (the console's server-sent events).

The state machine calls its ``on_change`` on every transition; the runtime publishes the
run's status here, and every subscriber (one per open event stream, each on an asyncio
event loop) gets it in its own bounded queue.  Publishing never blocks and never reads a
clock: it is called from the run's thread, which in lockstep is a participant of the
simulated clock, so it hands the event to each subscriber's loop and returns.

A subscriber that falls behind loses its *oldest* events, never the newest: an event is
a whole snapshot of a run, so the latest one is always enough to show where it is.
"""

from __future__ import annotations

import asyncio
import contextlib
import threading
from collections.abc import Iterator
from typing import Any

Event = dict[str, Any]


class Subscription:
    """One listener's queue, filled from any thread, read on its event loop."""

    def __init__(self, loop: asyncio.AbstractEventLoop, maxsize: int) -> None:
        self.loop = loop
        self.queue: asyncio.Queue[Event] = asyncio.Queue(maxsize)
        self.dropped = 0

    def _put(self, event: Event) -> None:  # on the subscriber's loop
        if self.queue.full():
            self.queue.get_nowait()
            self.dropped += 1
        self.queue.put_nowait(event)

    async def get(self, timeout: float) -> Event | None:
        """The next event, or None after ``timeout`` seconds (host time) without one."""
        try:
            return await asyncio.wait_for(self.queue.get(), timeout)
        except TimeoutError:
            return None


class EventBus:
    """Fan-out of events to :class:`Subscription` s (thread-safe, non-blocking)."""

    def __init__(self, maxsize: int = 256) -> None:
        self._subs: set[Subscription] = set()
        self._lock = threading.Lock()
        self._maxsize = maxsize
        self.published = 0

    def publish(self, event: Event) -> None:
        with self._lock:
            subs = list(self._subs)
            self.published += 1
        for sub in subs:
            try:
                sub.loop.call_soon_threadsafe(sub._put, event)
            except RuntimeError:  # its loop is closed: the listener is gone
                with self._lock:
                    self._subs.discard(sub)

    @contextlib.contextmanager
    def subscribe(self) -> Iterator[Subscription]:
        """A subscription for the running event loop, removed on exit."""
        sub = Subscription(asyncio.get_running_loop(), self._maxsize)
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
