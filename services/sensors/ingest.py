"""What every sensor ingest does: a zenoh subscription, a store of checked samples on the
service clock, counters, staleness.

A sensor ingest (:class:`~services.sensors.mocap.MocapIngest`,
:class:`~services.sensors.gyro.GyroIngest`) decodes and checks each payload in its
:meth:`Ingest.feed`; this base keeps the rest once:

* the subscription (:meth:`Ingest.subscribe`, :meth:`Ingest.close`, idempotent); in
  lockstep (:class:`swpc_hw.clock.SimClock`) every arrival on the key is told to the clock,
  so the simulated time moves on only once every sample published up to now is stored;
* the stamp order (:meth:`Ingest._in_order`): a stamp equal to the last accepted one is a
  duplicate, an older one out of order, unless it stepped back by more than
  ``max_clock_step`` source seconds (the source clock was reset: a new sequence); a stamp
  that moved on more than ``max_clock_step`` beyond its receipt (the stamps advanced
  that much more than the receive times since the last sample: a transport stall only
  ever does the opposite) is the source clock stepped forward, also a new sequence.
  Either is a clock jump (:meth:`Ingest.clock_jump`), which fails a run at once;
* the store (rows ``t_source, t_recv, t_host, ...``), read whole (:meth:`Ingest.samples`)
  or by cursor (:meth:`Ingest.samples_since`), and the stream's age: *stale* when the
  newest accepted sample was received more than ``stale_after`` clock seconds ago;
* the counters every ingest has (:class:`IngestCounters`) and their :meth:`Ingest.stats`.
"""

from __future__ import annotations

import contextlib
import math
import threading
from collections import deque
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from swpc_hw.clock import Clock, SimClock
from swpc_hw.row_ring import KEEP_S, RowRing

FloatArray = NDArray[np.float64]

MAX_CLOCK_STEP_S = 0.5
"""A source clock stepping back, or forward beyond its receipt, by more than this (s of
the service clock) is a clock jump, not a late or reordered sample."""


@dataclass
class IngestCounters:
    received: int = 0
    accepted: int = 0
    decode_errors: int = 0
    non_finite: int = 0
    duplicates: int = 0
    out_of_order: int = 0
    clock_resets: int = 0
    """source clock stepped back, or forward beyond its receipt, by more than
    ``max_clock_step``: the stamp sequence restarts"""

    @property
    def dropped(self) -> int:
        return self.received - self.accepted


class Ingest:
    """Thread-safe store of one sensor's samples, fed by zenoh or :meth:`feed`."""

    counters: IngestCounters

    def __init__(
        self,
        columns: tuple[str, ...],
        *,
        clock: Clock,
        stale_after: float,
        capacity: int,
        max_clock_error: float,
        max_clock_step: float,
        recent: int,
    ) -> None:
        self.clock = clock
        self.stale_after = float(stale_after)
        self.max_clock_error = float(max_clock_error)
        self.max_clock_step = float(max_clock_step)
        self._lock = threading.Lock()
        # the receive times (column 1) of the last KEEP_S seconds at most, up to capacity
        self._rows = RowRing(len(columns), capacity, 1 << 16, keep=KEEP_S, time_column=1)
        self._last_source = -math.inf
        self._last_recv = math.nan
        self.last_clock_step = 0.0
        """How far the source clock last stepped at a reset (s of source time; > 0: back,
        < 0: forward)."""
        self._recent = deque[float](maxlen=recent)  # receive times, for the rate
        self._subscriber: Any = None
        self._lockstep_key: str | None = None

    # ------------------------------------------------------------------ zenoh
    @property
    def subscribed(self) -> bool:
        return self._subscriber is not None

    def subscribe(self, session: Any, key: str) -> None:
        """Declare the zenoh subscriber (its callback runs on zenoh's threads)."""
        clock = self.clock

        def on_sample(sample: Any) -> None:
            try:
                self.feed(sample.payload.to_bytes())
            finally:
                if isinstance(clock, SimClock):
                    clock.arrived(key)

        if isinstance(clock, SimClock):
            clock.subscribe(key)
            self._lockstep_key = key
        self._subscriber = session.declare_subscriber(key, on_sample)

    def close(self) -> None:
        """Undeclare the subscriber (idempotent)."""
        sub, self._subscriber = self._subscriber, None
        if sub is not None:
            with contextlib.suppress(Exception):  # session already closed
                sub.undeclare()
        key, self._lockstep_key = self._lockstep_key, None
        if key is not None and isinstance(self.clock, SimClock):
            self.clock.unsubscribe(key)

    # ------------------------------------------------------------------ input
    def feed(self, payload: bytes, t_recv: float | None = None) -> bool:
        """Decode, check and store one payload; returns whether it was accepted."""
        raise NotImplementedError

    def _in_order(self, t: float, now: float, scale: float = 1.0) -> bool:
        """Whether stamp ``t``, received at ``now``, follows the last accepted one (module
        docstring), counting what it is not; ``scale``: clock seconds per source second
        (the step's unit).  Called under the lock."""
        c = self.counters
        if t == self._last_source:
            c.duplicates += 1
            return False
        if t < self._last_source:
            if (self._last_source - t) * scale <= self.max_clock_step:
                c.out_of_order += 1
                return False
            c.clock_resets += 1  # the source clock was stepped back: a new sequence
            self.last_clock_step = self._last_source - t
        elif (t - self._last_source) * scale - (now - self._last_recv) > self.max_clock_step:
            c.clock_resets += 1  # stepped forward: a new sequence too
            self.last_clock_step = -((t - self._last_source) - (now - self._last_recv) / scale)
        self._last_source = t
        self._last_recv = now
        return True

    def _store(self, row: tuple[float, ...], now: float) -> None:
        """Keep an accepted sample (under the lock)."""
        self._rows.append(row)
        self._recent.append(now)
        self.counters.accepted += 1

    # ----------------------------------------------------------------- output
    def samples(self, since_host: float = -math.inf) -> FloatArray:
        """Accepted samples with host time (column 2) >= ``since_host``."""
        with self._lock:
            data = self._rows.array()
        i = int(np.searchsorted(data[:, 2], since_host))
        return data[i:]

    def samples_since(
        self, cursor: int, since_host: float = -math.inf
    ) -> tuple[FloatArray, int]:
        """Accepted samples appended after ``cursor`` (0: every one kept) with host time
        >= ``since_host``, and the new cursor (each sample read once by a reader that
        keeps it)."""
        with self._lock:
            rows, cursor = self._rows.since(cursor)
        if since_host > -math.inf:
            rows = rows[rows[:, 2] >= since_host]
        return rows, cursor

    def age(self, now: float | None = None) -> float:
        """Clock seconds since the newest accepted sample was received (inf if none)."""
        now = self.clock.now() if now is None else now
        with self._lock:
            return now - float(self._rows.last()[1]) if len(self._rows) else math.inf

    def is_stale(self, now: float | None = None) -> bool:
        return self.age(now) > self.stale_after

    def clock_jump(self, resets_before: int, what: str, key: str) -> str | None:
        """Why the samples since ``resets_before`` clock resets cannot be trusted (None:
        none since): during a run, the source's clock stepping back is a second publisher
        on ``key`` or a clock reset, and a step forward a clock set anew; either makes the
        run's data wrong."""
        with self._lock:
            n, step = self.counters.clock_resets, self.last_clock_step
        if n == resets_before:
            return None
        if step < 0:
            return (
                f"{what} clock jumped forward by {-step:.3f} s during the run (its clock was "
                "set anew): its samples cannot be trusted"
            )
        return (
            f"{what} clock jumped back by {step:.3f} s during the run (a second publisher on "
            f"{key}, or its clock reset): its samples cannot be trusted"
        )

    def stats(self, window: float = 1.0) -> dict[str, float]:
        """Rate (Hz over the last ``window`` s), every counter, age (s)."""
        now = self.clock.now()
        with self._lock:
            recent = sum(1 for t in self._recent if t >= now - window)
            c = self.counters
            out = {"rate_hz": recent / window, **{k: float(v) for k, v in asdict(c).items()}}
            out["dropped"] = float(c.dropped)
        out["age_s"] = self.age(now)
        return out
