"""Gyro ingest: a zenoh subscriber on the robot's IMU key (``imu/<robot>/data``).

Every payload is a CDR ``sensor_msgs/msg/Imu`` (:mod:`swpc_hw.imu`: what
zenoh-bridge-ros2dds forwards from a ROS 2 IMU driver, and what the simulators publish);
its z angular velocity (rad/s, the yaw rate of R) is kept with its stamp mapped onto the
service clock by :meth:`~swpc_hw.clock.Clock.from_wall` (the stamps are wall time: the
in-process simulator's simulated wall clock, ``swpc sim``'s host clock, or a robot's clock
synchronised with this host), the way the CAN bus stamps and the poses in clock mode
``wall`` are.  A stamp more than ``max_clock_error`` off its receipt is reported by
:meth:`GyroIngest.clock_problem` (an IMU whose clock is not this host's).

Dropped and counted: undecodable payloads, non-finite values, duplicates (same stamp) and
samples older than the last accepted one (a stamp stepping back by more than
``max_clock_step`` restarts the sequence: the IMU's clock was reset).  A stream whose
newest accepted sample was received more than ``stale_after`` clock seconds ago is
*stale*: a run without motion capture treats that as a fault during motion.

Lockstep (:class:`swpc_hw.clock.SimClock`): every arrival is told to the clock, so a
reader at any simulated time has every sample published up to it.
"""

from __future__ import annotations

import contextlib
import math
import threading
from collections import deque
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from swpc_hw.clock import SYSTEM_CLOCK, Clock, SimClock
from swpc_hw.imu import ImuDecodeError, decode_imu
from swpc_hw.row_ring import RowRing

FloatArray = NDArray[np.float64]

#: columns of :meth:`GyroIngest.samples`
COLUMNS = ("t_source", "t_recv", "t_host", "wz")


class LatestGyro(NamedTuple):
    t_host: float
    wz: float


@dataclass
class ImuCounters:
    received: int = 0
    accepted: int = 0
    decode_errors: int = 0
    non_finite: int = 0
    duplicates: int = 0
    out_of_order: int = 0
    clock_resets: int = 0

    @property
    def dropped(self) -> int:
        return self.received - self.accepted


class GyroIngest:
    """Thread-safe gyro store fed by zenoh (or directly through :meth:`feed`)."""

    def __init__(
        self,
        *,
        clock: Clock = SYSTEM_CLOCK,
        stale_after: float = 0.5,
        capacity: int = 4_000_000,
        max_clock_error: float = 1.0,
        max_clock_step: float = 1.0,
    ) -> None:
        self.clock = clock
        self.stale_after = float(stale_after)
        self.max_clock_error = float(max_clock_error)
        self.max_clock_step = float(max_clock_step)
        self.counters = ImuCounters()
        self._lock = threading.Lock()
        self._rows = RowRing(len(COLUMNS), capacity, initial=1 << 16)
        self._last_source = -math.inf
        self._delay = math.nan  # receipt minus the mapped stamp, newest sample
        self._recent = deque[float](maxlen=8192)  # receive times, for the rate
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
        now = self.clock.now() if t_recv is None else t_recv
        with self._lock:
            c = self.counters
            c.received += 1
            try:
                g = decode_imu(payload)
            except ImuDecodeError:
                c.decode_errors += 1
                return False
            if not (math.isfinite(g.t) and math.isfinite(g.wz)):
                c.non_finite += 1
                return False
            if g.t == self._last_source:
                c.duplicates += 1
                return False
            if g.t < self._last_source:
                if self._last_source - g.t <= self.max_clock_step:
                    c.out_of_order += 1
                    return False
                c.clock_resets += 1  # the IMU's clock was stepped back: a new sequence
            self._last_source = g.t
            t_host = self.clock.from_wall(g.t)
            self._delay = now - t_host
            self._rows.append((g.t, now, t_host, g.wz))
            self._recent.append(now)
            c.accepted += 1
            return True

    # ----------------------------------------------------------------- output
    def samples(self, since_host: float = -math.inf) -> FloatArray:
        """Accepted samples (rows as :data:`COLUMNS`) with host time >= ``since_host``."""
        with self._lock:
            data = self._rows.array()
        i = int(np.searchsorted(data[:, 2], since_host))
        return data[i:]

    def samples_since(
        self, cursor: int, since_host: float = -math.inf
    ) -> tuple[FloatArray, int]:
        """Accepted samples appended after ``cursor`` (0: every one kept) with host time
        >= ``since_host``, and the new cursor (each sample read once by its reader)."""
        with self._lock:
            rows, cursor = self._rows.since(cursor)
        if since_host > -math.inf:
            rows = rows[rows[:, 2] >= since_host]
        return rows, cursor

    def latest(self) -> LatestGyro | None:
        """The newest accepted sample."""
        with self._lock:
            if not len(self._rows):
                return None
            r = self._rows.last()
        return LatestGyro(float(r[2]), float(r[3]))

    def age(self, now: float | None = None) -> float:
        """Clock seconds since the newest accepted sample was received (inf if none)."""
        now = self.clock.now() if now is None else now
        with self._lock:
            return now - float(self._rows.last()[1]) if len(self._rows) else math.inf

    def is_stale(self, now: float | None = None) -> bool:
        return self.age(now) > self.stale_after

    def clock_problem(self) -> str | None:
        """Why the gyro's stamps cannot be used (``None``: they can): the newest one more
        than ``max_clock_error`` clock seconds off its receipt."""
        with self._lock:
            d = self._delay
        if not math.isfinite(d) or abs(d) <= self.max_clock_error:
            return None
        return (
            f"gyro stamps are {d:+.3f} s off the host's wall clock at receipt (limit "
            f"{self.max_clock_error:g} s): the IMU's clock must be synchronised with this "
            "host (PTP, chrony)"
        )

    def stats(self, window: float = 1.0) -> dict[str, float]:
        """Rate (Hz over the last ``window`` s), counters, age (s)."""
        now = self.clock.now()
        with self._lock:
            recent = sum(1 for t in self._recent if t >= now - window)
            c = self.counters
            out = {
                "rate_hz": recent / window,
                "received": float(c.received),
                "accepted": float(c.accepted),
                "dropped": float(c.dropped),
                "decode_errors": float(c.decode_errors),
                "non_finite": float(c.non_finite),
                "duplicates": float(c.duplicates),
                "out_of_order": float(c.out_of_order),
                "clock_resets": float(c.clock_resets),
            }
        out["age_s"] = self.age(now)
        return out
