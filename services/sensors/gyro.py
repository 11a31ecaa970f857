"""Gyro ingest: a zenoh subscriber on the robot's IMU key (``imu/<robot>/data``).

Every payload is a CDR ``sensor_msgs/msg/Imu`` (:mod:`swpc_hw.sensors.gyro`: what
zenoh-bridge-ros2dds forwards from a ROS 2 IMU driver, and what the simulators publish);
its z angular velocity (rad/s, the yaw rate of R) is kept with its stamp mapped onto the
service clock by :meth:`~swpc_hw.clock.Clock.from_wall` (the stamps are wall time: the
in-process simulator's simulated wall clock, ``swpc sim``'s host clock, or a robot's clock
synchronised with this host), the way the CAN bus stamps and the poses in clock mode
``wall`` are.  A stamp more than ``max_clock_error`` off its receipt is reported by
:meth:`GyroIngest.clock_problem` (an IMU whose clock is not this host's).

Dropped and counted: undecodable payloads, non-finite values, and what every ingest drops
(:mod:`services.sensors.ingest`: duplicates, out of order; a clock reset restarts the
sequence).  A stale stream is a fault during the motion of a run with the IMU metrology.
"""

from __future__ import annotations

import math
from typing import NamedTuple

from services.sensors.ingest import MAX_CLOCK_STEP_S, Ingest, IngestCounters
from swpc_hw.clock import SYSTEM_CLOCK, Clock
from swpc_hw.sensors.gyro import ImuDecodeError, decode_imu

#: columns of :meth:`GyroIngest.samples`
COLUMNS = ("t_source", "t_recv", "t_host", "wz")


class LatestGyro(NamedTuple):
    t_host: float
    wz: float


class GyroIngest(Ingest):
    """Thread-safe gyro store fed by zenoh (or directly through :meth:`feed`)."""

    def __init__(
        self,
        *,
        clock: Clock = SYSTEM_CLOCK,
        stale_after: float = 0.5,
        capacity: int = 4_000_000,
        max_clock_error: float = 1.0,
        max_clock_step: float = MAX_CLOCK_STEP_S,
    ) -> None:
        super().__init__(
            COLUMNS,
            clock=clock,
            stale_after=stale_after,
            capacity=capacity,
            max_clock_error=max_clock_error,
            max_clock_step=max_clock_step,
            recent=8192,
        )
        self.counters = IngestCounters()
        self._delay = math.nan  # receipt minus the mapped stamp, newest sample
        rate = clock.rate  # clock seconds per stamp (wall) second; a lockstep clock's: 1
        self._scale = float(rate) if math.isfinite(rate) else 1.0

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
            if not self._in_order(g.t, now, self._scale):
                return False
            t_host = self.clock.from_wall(g.t)
            self._delay = now - t_host
            self._store((g.t, now, t_host, g.wz), now)
            return True

    # ----------------------------------------------------------------- output
    def latest(self) -> LatestGyro | None:
        """The newest accepted sample."""
        with self._lock:
            if not len(self._rows):
                return None
            r = self._rows.last()
        return LatestGyro(float(r[2]), float(r[3]))

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
