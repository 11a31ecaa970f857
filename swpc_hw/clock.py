"""Time as an input: the clocks that every part of swpc judges time by.

Code that judges time (the CAN driver's supervision, the motion-capture ingest, the
calibration state machine, the simulator and the controller emulator) takes a
:class:`Clock` instead of calling :mod:`time`.  Three kinds:

* :class:`SystemClock` -- the real robot: ``now()`` is ``time.monotonic()``; waits are
  real.  With ``rate = k`` it is the clock of an *external* simulator that runs ``k``
  times faster than real time (``swpc sim --time-scale k`` on vcan): ``now()`` is then
  robot seconds, ``k * time.monotonic()``, so every duration in the code is robot time.
* :class:`SimClock` -- simulated time in lockstep (as ROS's ``use_sim_time``, but
  co-simulated): one *master* (the in-process simulator, or the controller emulator of
  the driver tests) advances it; every *participant* thread blocks in a clock wait
  before time moves on, and everything published before is delivered first.  A starved
  host slows such a run down; it never faults it, and the same seed gives the same run.
* :class:`VirtualClock` -- one thread, no master: ``sleep(dt)`` just adds ``dt``.  For
  pure cores tested without threads or sleeps (the state machine on a fake robot).

Mapping stamps: frames and poses carry *wall* stamps (python-can's bus time stamps,
epoch seconds; a motion-capture system's clock synchronised with this host).  The one
mapping onto the clock's axis is :meth:`Clock.from_wall`::

    SystemClock(rate k):  t = k * (t_wall - (time.time() - time.monotonic()))
    SimClock:             t = t_wall - epoch        (wall() = epoch + now())
"""

from __future__ import annotations

import contextlib
import logging
import math
import threading
import time
from collections.abc import Callable, Iterator
from typing import Protocol, TypeVar, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray

log = logging.getLogger(__name__)

T = TypeVar("T")
FloatArray = NDArray[np.float64]


@runtime_checkable
class Clock(Protocol):
    """What time-judging code needs from a clock (seconds of robot time)."""

    @property
    def rate(self) -> float:
        """Clock seconds per wall second when time flows (1 on a robot)."""
        ...

    def now(self) -> float:
        """The time everything is judged by (monotonic, robot seconds)."""
        ...

    def wall(self) -> float:
        """Epoch seconds of ``now()``: the stamp to put on frames and poses."""
        ...

    def from_wall(self, t_wall: float) -> float:
        """A wall (bus or pose) stamp on the axis of :meth:`now`."""
        ...

    def sleep_until(self, t: float) -> None:
        """Block until ``now() >= t``."""
        ...

    def sleep(self, dt: float) -> None:
        """Block for ``dt`` seconds of this clock."""
        ...

    def poll(self, dt: float) -> None:
        """Block for about ``dt`` seconds between two looks of a polling loop: at least
        ``dt``, and on a lockstep clock until the first step of the simulation at or after
        it (a poll never asks the simulation for a step of its own, :class:`SimClock`)."""
        ...

    def wait(self, cond: threading.Condition, deadline: float) -> None:
        """Wait on ``cond`` (held by the caller) until notified or ``now() >= deadline``.

        Spurious wake-ups are allowed: callers re-check their predicate.
        """
        ...


def from_wall_array(clock: Clock, t_wall: ArrayLike) -> FloatArray:
    """:meth:`Clock.from_wall` on an array of stamps (the one clock mapping)."""
    a = np.asarray(t_wall, dtype=float)
    return np.vectorize(clock.from_wall, otypes=[float])(a) if a.size else a


COINCIDENT_S = 1e-6
"""Instants closer than this are one instant to a lockstep master (:func:`next_instant`)."""


def next_instant(t: float, candidates: list[float], eps: float = COINCIDENT_S) -> float:
    """The next step of a lockstep master at ``t``: the earliest candidate later than
    ``t + eps``, moved on to the latest candidate within ``eps`` after it.

    Times on a :class:`SimClock` are rounded to its wall-stamp grid (``2**-22`` s), so a
    participant's wake-up and the master's own period drift apart by fractions of a
    microsecond; taken apart, they cost a whole extra step each time (a fifth of all the
    simulator's steps did).  A candidate at or before ``t + eps`` (already due) is left to
    the next step.
    """
    later = [c for c in candidates if c > t + eps]
    if not later:
        return math.nextafter(t, math.inf)
    first = min(later)
    return max(c for c in later if c <= first + eps)


def wait_until(
    clock: Clock,
    cond: threading.Condition,
    predicate: Callable[[], T],
    deadline: float,
) -> T:
    """Wait (``cond`` held) until ``predicate()`` is truthy or the deadline passes;
    returns its last value.  The shared loop of every condition wait on a clock."""
    while True:
        value = predicate()
        if value or clock.now() >= deadline:
            return value
        clock.wait(cond, deadline)


# --------------------------------------------------------------------------- real time


def wall_minus_monotonic(tries: int = 3) -> float:
    """``time.time() - time.monotonic()``, read so that a preemption between the two reads
    does not shift it: the wall clock is read between two monotonic reads and the tightest
    of ``tries`` brackets wins (a thread switched out between two bare reads on a busy host
    mapped a frame's stamp 12 ms early, and the driver's history ran backwards)."""
    best_width = math.inf
    best = 0.0
    for _ in range(tries):
        m0 = time.monotonic()
        w = time.time()
        m1 = time.monotonic()
        if m1 - m0 < best_width:
            best_width, best = m1 - m0, w - 0.5 * (m0 + m1)
            if best_width < 20e-6:
                break
    return best


class SystemClock:
    """The host's monotonic clock, optionally scaled to an external simulator's rate."""

    def __init__(self, rate: float = 1.0) -> None:
        if not (rate > 0.0 and math.isfinite(rate)):
            raise ValueError(f"clock rate must be finite and > 0, got {rate}")
        self._rate = float(rate)

    @property
    def rate(self) -> float:
        return self._rate

    def now(self) -> float:
        return self._rate * time.monotonic()

    def wall(self) -> float:
        return time.time()

    def from_wall(self, t_wall: float) -> float:
        return self._rate * (t_wall - wall_minus_monotonic())

    def sleep_until(self, t: float) -> None:
        dt = (t - self.now()) / self._rate
        if dt > 0:
            time.sleep(dt)

    def sleep(self, dt: float) -> None:
        if dt > 0:
            time.sleep(dt / self._rate)

    def poll(self, dt: float) -> None:
        self.sleep(dt)

    def wait(self, cond: threading.Condition, deadline: float) -> None:
        left = (deadline - self.now()) / self._rate
        if left > 0:
            cond.wait(left)


SYSTEM_CLOCK = SystemClock()
"""The real robot's clock."""


# --------------------------------------------------------------------------- simulated


class _EpochClock:
    """A simulated time ``t`` whose wall stamps are ``epoch + t`` (the shared arithmetic of
    :class:`VirtualClock` and :class:`SimClock`)."""

    _t: float
    _epoch: float

    @property
    def epoch(self) -> float:
        return self._epoch

    def to_wall(self, t: float) -> float:
        """The wall stamp of clock time ``t``."""
        return self._epoch + t

    def now(self) -> float:
        return self._t

    def wall(self) -> float:
        return self._epoch + self._t

    def from_wall(self, t_wall: float) -> float:
        return t_wall - self._epoch


# --------------------------------------------------------------------------- one thread


class VirtualClock(_EpochClock):
    """Virtual time for one thread: ``sleep(dt)`` advances the clock by ``dt`` at once.

    For pure cores (e.g. the calibration state machine on a fake robot): a minute of
    protocol runs in milliseconds, and ``on_sleep`` callbacks (a fake robot's physics)
    run at every step so that the world moves with the clock.
    """

    def __init__(self, start: float = 0.0, epoch: float = 1.0e9) -> None:
        self._t = float(start)
        self._epoch = float(epoch)
        self.on_sleep: list[Callable[[float], None]] = []

    @property
    def rate(self) -> float:
        return math.inf

    def advance(self, dt: float) -> None:
        if dt > 0:
            self._t += dt
            for fn in list(self.on_sleep):
                fn(self._t)

    def sleep_until(self, t: float) -> None:
        self.advance(t - self._t)

    def sleep(self, dt: float) -> None:
        self.advance(dt)

    def poll(self, dt: float) -> None:
        self.sleep(dt)

    def wait(self, cond: threading.Condition, deadline: float) -> None:
        self.advance(max(0.0, min(deadline - self._t, 1e-3)))


# --------------------------------------------------------------------------- lockstep


class SimClockError(RuntimeError):
    """The lockstep is broken (a participant never blocked again, a closed clock)."""


class SimClock(_EpochClock):
    """Simulated time in lockstep with one master (see the module docstring).

    *Participants* (threads inside :meth:`participant`) run only while the master waits:
    :meth:`advance_to` first waits until every participant is blocked in a clock wait and
    every expected delivery (:meth:`expect` / :meth:`arrived`) has arrived, then moves the
    time, runs the hooks (e.g. the CAN driver's receive and supervision step), wakes the
    sleepers that are due and waits until the participants among them block again.  So a
    participant sees, at every wake-up, everything that happened up to ``now()``.

    Unpaced (``max_speed`` 0: as fast as the host can), time flows only while someone
    waits on it (:meth:`demanded`): an idle service on the in-process simulator costs no
    CPU, and a run starts from the same state whatever the wall time of its start.  Paced
    (``max_speed`` > 0 simulated s per wall s: ``make console`` at 1), it flows at that
    rate whether or not anyone waits, as a robot's time does: the drives' heartbeats and
    the motion capture go on while the service is idle (frozen, a service whose first pose
    came after its last wait stayed "motion capture stale" for good).
    """

    def __init__(
        self,
        start: float = 0.0,
        *,
        epoch: float | None = None,
        max_speed: float = 0.0,
        delivery_timeout: float = 5.0,
        stall_warning: float = 10.0,
    ) -> None:
        # an integer epoch keeps the same time grid in every run of this century; times
        # are kept on it, so from_wall(wall()) == now() exactly
        self._epoch = float(math.floor(time.time()) if epoch is None else epoch)
        self._t = self._on_grid(float(start))
        self.max_speed = float(max_speed)
        self.delivery_timeout = float(delivery_timeout)
        self.stall_warning = float(stall_warning)
        self._cv = threading.Condition()
        self._sleepers: dict[int, float] = {}  # token -> wake time
        self._sleeper_thread: dict[int, int] = {}  # token -> thread ident
        self._polls: set[int] = set()  # sleepers woken by any advance
        self._lenient: set[int] = set()  # sleepers whose wake time next_wake leaves out
        self._participants: dict[int, int] = {}  # thread ident -> nesting depth
        self._running: set[int] = set()  # participants not blocked in a clock wait
        self._hooks: list[Callable[[float], None]] = []
        self._subscribed: dict[str, int] = {}
        self._in_flight: dict[str, int] = {}
        self._token = 0
        self._closed = False
        self._pace_wall = 0.0
        self._pace_t = 0.0
        self._stop_master: threading.Event | None = None
        self.advances = 0

    # ------------------------------------------------------------------ the Clock
    @property
    def rate(self) -> float:
        return self.max_speed if self.max_speed > 0 else math.inf

    def _on_grid(self, t: float) -> float:
        """The first time ``>= t`` that ``epoch + t`` holds exactly (round trips through
        the wall stamp are exact, and an advance to ``t`` reaches ``t``)."""
        w = self._epoch + t
        if w - self._epoch < t:
            w = math.nextafter(w, math.inf)
        return w - self._epoch

    def sleep_until(self, t: float) -> None:
        self._sleep(t, poll=False)

    def poll(self, dt: float) -> None:
        """Until the first advance at or after ``now() + dt``, an instant the master does
        not step to for this wait alone (:meth:`next_wake` leaves it out): a polling loop
        every 20 ms out of phase with the simulator's 10 ms physics once split a third of
        its steps in two (2026-12-01: 6760 steps for a 46 s run, 4610 with polls)."""
        self._sleep(self._t + max(dt, 0.0), poll=False, lenient=True)

    def _sleep(self, t: float, poll: bool, lenient: bool = False) -> None:
        """Block until an advance reaches ``t`` (``poll``: or until the next advance;
        ``lenient``: ``t`` is no wake time for :meth:`next_wake`)."""
        me = threading.get_ident()
        with self._cv:
            if self._closed:
                raise SimClockError("the simulated clock is closed (its simulator stopped)")
            if t <= self._t and me not in self._participants:
                return
            # a participant always yields, even for a time already reached: it resumes
            # once everything due now has been delivered (deterministic reads)
            self._token += 1
            token = self._token
            self._sleepers[token] = t
            if poll or t <= self._t:
                self._polls.add(token)
            if lenient:
                self._lenient.add(token)
            self._sleeper_thread[token] = me
            self._running.discard(me)
            self._cv.notify_all()
            try:
                while token in self._sleepers:
                    if self._closed:
                        raise SimClockError("the simulated clock was closed while waiting")
                    self._cv.wait(1.0)
            finally:
                self._sleepers.pop(token, None)
                self._sleeper_thread.pop(token, None)
                self._polls.discard(token)
                self._lenient.discard(token)

    def sleep(self, dt: float) -> None:
        self.sleep_until(self._t + max(dt, 0.0))

    def wait(self, cond: threading.Condition, deadline: float) -> None:
        """Release ``cond``, sleep until the next advance (or the deadline), re-acquire.

        Condition notifications are not waited for: a participant re-checks its
        predicate at every advance of the clock (the master's natural steps), when the
        world is quiescent.
        """
        cond.release()
        try:
            self._sleep(deadline, poll=True)
        finally:
            cond.acquire()

    # ------------------------------------------------------------------ participants
    @contextlib.contextmanager
    def participant(self) -> Iterator[None]:
        """Run the calling thread in lockstep: time does not move on while it runs."""
        me = threading.get_ident()
        with self._cv:
            depth = self._participants.get(me, 0)
            self._participants[me] = depth + 1
            if depth == 0:
                self._running.add(me)
        try:
            yield
        finally:
            with self._cv:
                if depth == 0:
                    self._participants.pop(me, None)
                    self._running.discard(me)
                else:
                    self._participants[me] = depth
                self._cv.notify_all()

    def add_hook(self, fn: Callable[[float], None]) -> None:
        """``fn(now)`` after every advance, on the master's thread, before sleepers wake."""
        with self._cv:
            self._hooks = [*self._hooks, fn]

    def remove_hook(self, fn: Callable[[float], None]) -> None:
        with self._cv:
            self._hooks = [h for h in self._hooks if h != fn]

    # ------------------------------------------------------------------ deliveries
    def subscribe(self, channel: str) -> None:
        """A lockstep receiver listens on ``channel``: its deliveries are waited for."""
        with self._cv:
            self._subscribed[channel] = self._subscribed.get(channel, 0) + 1

    def unsubscribe(self, channel: str) -> None:
        with self._cv:
            n = self._subscribed.get(channel, 0) - 1
            if n <= 0:
                self._subscribed.pop(channel, None)
                self._in_flight.pop(channel, None)
            else:
                self._subscribed[channel] = n
            self._cv.notify_all()

    def expect(self, channel: str, n: int = 1) -> None:
        """A sender is about to publish ``n`` messages on ``channel`` (counted only when
        a lockstep receiver has subscribed)."""
        with self._cv:
            subs = self._subscribed.get(channel, 0)
            if subs:
                self._in_flight[channel] = self._in_flight.get(channel, 0) + n * subs

    def arrived(self, channel: str, n: int = 1) -> None:
        """A lockstep receiver got ``n`` messages on ``channel``."""
        with self._cv:
            left = self._in_flight.get(channel, 0) - n
            if left <= 0:
                self._in_flight.pop(channel, None)
            else:
                self._in_flight[channel] = left
            self._cv.notify_all()

    # ------------------------------------------------------------------ the master
    def demanded(self) -> bool:
        """Time is to move on: someone waits for it (a participant that yields counts), or
        the clock is paced (class docstring)."""
        with self._cv:
            return bool(self._sleepers) or self.max_speed > 0

    def wait_for_demand(self, stop: threading.Event, timeout: float = 0.1) -> bool:
        """Block (wall time, up to ``timeout``) until time is to move on (:meth:`demanded`)."""
        with self._cv:
            if not self._sleepers and self.max_speed <= 0:
                self._cv.wait(timeout)
            demanded = bool(self._sleepers) or self.max_speed > 0
        if not demanded:
            self._pace_wall = 0.0  # time stood still: pacing restarts from here
        return demanded and not stop.is_set()

    def next_wake(self) -> float:
        """The earliest wake time of a sleeper after now (inf when none; polling sleepers
        count with their deadline: any advance wakes them anyway; a :meth:`poll` does not
        count: it wakes at the master's first step at or after its time)."""
        with self._cv:
            later = [
                w for k, w in self._sleepers.items() if w > self._t and k not in self._lenient
            ]
            return min(later) if later else math.inf

    def advance_to(self, t: float, stop: threading.Event | None = None) -> None:
        """Move the time to ``t`` (master only; see the class docstring).  ``stop``: the
        master's own stop request, which ends the waits for participants (a participant
        may be the very thread that stops the master)."""
        self._stop_master = stop
        with self._cv:
            self._settle("before advancing")
            t = self._on_grid(t)
            if t > self._t:
                self._t = t
            hooks = self._hooks
        for fn in hooks:
            fn(self._t)
        with self._cv:
            due = [k for k, w in self._sleepers.items() if w <= self._t or k in self._polls]
            for k in due:
                del self._sleepers[k]
                th = self._sleeper_thread.get(k)
                if th is not None and th in self._participants:
                    self._running.add(th)
            if due:
                self._cv.notify_all()
            self._settle("after waking its sleepers")
        self.advances += 1
        self._pace()

    def _settle(self, when: str) -> None:
        """(lock held) Wait until no participant runs and nothing is in flight."""
        start = time.monotonic()
        warned = False
        delivery_start: float | None = None
        while not self._closed:
            if self._stop_master is not None and self._stop_master.is_set():
                return
            if self._running:
                delivery_start = None
            elif self._in_flight:
                # participants blocked: only deliveries are pending; a lost one must not
                # hang the simulation for ever
                now = time.monotonic()
                delivery_start = delivery_start or now
                if now - delivery_start > self.delivery_timeout:
                    log.warning(
                        "simulated clock: %s never arrived within %.1f s; going on",
                        dict(self._in_flight),
                        self.delivery_timeout,
                    )
                    self._in_flight.clear()
                    break
            else:
                return
            if not warned and time.monotonic() - start > self.stall_warning:
                warned = True
                log.warning(
                    "simulated clock stalled %s for %.0f s: %d participant(s) running, "
                    "in flight %s",
                    when,
                    self.stall_warning,
                    len(self._running),
                    dict(self._in_flight),
                )
            self._cv.wait(0.05)

    def _pace(self) -> None:
        if self.max_speed <= 0:
            return
        now_wall = time.monotonic()
        if self._pace_wall == 0.0:
            self._pace_wall, self._pace_t = now_wall, self._t
            return
        ahead = (self._t - self._pace_t) / self.max_speed - (now_wall - self._pace_wall)
        if ahead > 0:
            time.sleep(ahead)
        elif ahead < -0.5:  # far behind: do not burst to catch up
            self._pace_wall, self._pace_t = now_wall, self._t

    def close(self) -> None:
        """End the lockstep: every waiter raises :class:`SimClockError` (idempotent)."""
        with self._cv:
            self._closed = True
            self._cv.notify_all()

    @property
    def closed(self) -> bool:
        return self._closed
