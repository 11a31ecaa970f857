"""Motion-capture ingest: a zenoh subscriber on the robot's pose key.

Every payload is decoded (native or ROS 2 CDR ``PoseStamped``, configured or detected)
and checked; accepted samples are kept with their source timestamp and the host's
monotonic receive time.  Dropped and counted: undecodable payloads, NaN/inf values,
non-unit quaternions (``| |q| - 1 | > quaternion_tol``), duplicates (same source time)
and out-of-order samples (source time older than the last accepted one).

Clock mapping: the mocap clock and the host clock differ by an offset plus a positive
transport delay; each sample's host time is ``t_source / s + offset`` with the lower
envelope ``offset = min(t_recv - t_source / s)`` over the last ``sync_window`` seconds
(the classic one-way clock estimate, as a sliding minimum so that it follows drift;
``s`` is the rate of a source clock that runs faster than real time, 1 for a real mocap
and for ``swpc sim``, which stamps its poses with the host clock at sampling).  Recorded
poses thus keep the mocap's exact spacing on the host clock, free of transport jitter.
A sliding minimum follows an offset, not a change of *rate*: for a source whose clock
rate varies (a simulator stamping its own slowing clock) use ``clock_mode="receive"``,
which takes the host receive time itself (transport jitter, but no drift).

The lower envelope is the clock offset plus the *smallest* transport delay of the window,
which is only ~0 when some samples get through at once.  A publisher that is itself
CPU-bound (``swpc sim`` under emulation: 12-23 ms floor, measured) shifts every pose that
much later than the CAN feedback of the same instant, whose bus time stamps carry no
such delay, and a shift of the poses against the wheel encoders biases the wheel radius
(0.1-0.2 mm at 12-23 ms in the VM run of ``make test-vcan``).  When the source stamps the
host's own wall clock (``swpc sim`` on this machine) or a clock synchronised with it (PTP,
chrony), ``clock_mode="wall"`` maps each stamp exactly, the way the driver maps the CAN
bus time stamps: ``t_host = t_source / s - (wall - monotonic)``.  A stamp more than
``max_clock_error`` off the host's wall clock (an unsynchronised source) is reported by
:meth:`MocapIngest.clock_problem`, which the calibration's precheck refuses to start on.

A stream whose newest accepted sample is older than ``stale_after`` seconds (host
time) is *stale*; during motion the state machine treats that as a fault.
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from swpc_hw.mocap import PoseDecodeError, PoseEncoding, PoseSample, decode_pose
from swpc_hw.row_ring import RowRing

FloatArray = NDArray[np.float64]

#: pose time bases of :class:`MocapIngest` (module docstring)
CLOCK_MODES = ("source", "receive", "wall")

#: columns of :meth:`MocapIngest.samples`
COLUMNS = ("t_source", "t_recv", "t_host", "x", "y", "yaw")


class LatestPose(NamedTuple):
    t_source: float
    """the mocap's own clock (the host's wall clock for ``swpc sim``)"""
    t_host: float
    x: float
    y: float
    yaw: float


@dataclass
class IngestCounters:
    received: int = 0
    accepted: int = 0
    decode_errors: int = 0
    non_finite: int = 0
    non_unit_quaternion: int = 0
    duplicates: int = 0
    out_of_order: int = 0
    clock_resets: int = 0
    """source clock stepped back by more than ``max_clock_step``: the stamp sequence restarts"""

    @property
    def dropped(self) -> int:
        return self.received - self.accepted


class MocapIngest:
    """Thread-safe pose store fed by zenoh (or directly through :meth:`feed`)."""

    def __init__(
        self,
        *,
        encoding: PoseEncoding | str = PoseEncoding.AUTO,
        stale_after: float = 0.25,
        quaternion_tol: float = 1e-3,
        capacity: int = 2_000_000,
        clock: Callable[[], float] = time.monotonic,
        time_scale: float = 1.0,
        sync_window: float = 1.0,
        clock_mode: str = "source",
        wall_clock: Callable[[], float] = time.time,
        max_clock_error: float = 1.0,
        max_clock_step: float = 1.0,
    ) -> None:
        self.encoding = PoseEncoding(encoding)
        self.stale_after = float(stale_after)
        self.quaternion_tol = float(quaternion_tol)
        self.clock = clock
        self.time_scale = float(time_scale)
        """Source seconds per host second (a simulator running faster than real time)."""
        self.counters = IngestCounters()
        self.detected_encoding: PoseEncoding | None = None
        self._lock = threading.Lock()
        self._rows = RowRing(len(COLUMNS), capacity, initial=1 << 16)
        self._last_source = -math.inf
        self.sync_window = float(sync_window)
        if clock_mode not in CLOCK_MODES:
            raise ValueError(f"clock_mode must be one of {CLOCK_MODES}, not {clock_mode!r}")
        self.clock_mode = clock_mode
        self.wall_clock = wall_clock
        self.max_clock_error = float(max_clock_error)
        self.max_clock_step = float(max_clock_step)
        self._wall_delay = math.nan  # clock_mode "wall": receive minus mapped stamp, last sample
        self._offset = math.inf  # sliding min(t_recv - t_source / s)
        self._delays: deque[tuple[float, float]] = deque()  # (t_recv, delay), increasing delay
        self._recent = deque[float](maxlen=4096)  # receive times for the rate
        self._latency = deque[float](maxlen=4096)
        self._subscriber: Any = None

    # ------------------------------------------------------------------ zenoh
    def subscribe(self, session: Any, key: str) -> None:
        """Declare the zenoh subscriber (callback runs on zenoh's threads)."""

        def on_sample(sample: Any) -> None:
            self.feed(sample.payload.to_bytes())

        self._subscriber = session.declare_subscriber(key, on_sample)

    def close(self) -> None:
        """Undeclare the subscriber (idempotent)."""
        sub, self._subscriber = self._subscriber, None
        if sub is not None:
            with contextlib.suppress(Exception):  # session already closed
                sub.undeclare()

    # ------------------------------------------------------------------ input
    def feed(self, payload: bytes, t_recv: float | None = None) -> bool:
        """Decode, check and store one payload; returns whether it was accepted."""
        now = self.clock() if t_recv is None else t_recv
        with self._lock:
            c = self.counters
            c.received += 1
            try:
                enc = self.encoding
                p = decode_pose(payload, enc)
                if enc is PoseEncoding.AUTO and self.detected_encoding is None:
                    from swpc_hw.mocap import detect_encoding

                    self.detected_encoding = detect_encoding(payload)
            except PoseDecodeError:
                c.decode_errors += 1
                return False
            if not self._finite(p):
                c.non_finite += 1
                return False
            if abs(p.quaternion_norm - 1.0) > self.quaternion_tol:
                c.non_unit_quaternion += 1
                return False
            if p.t == self._last_source:
                c.duplicates += 1
                return False
            if p.t < self._last_source:
                if (self._last_source - p.t) / self.time_scale <= self.max_clock_step:
                    c.out_of_order += 1
                    return False
                # the source clock was stepped back (mocap PC restarted, clock re-synced):
                # restart the stamp sequence and the delay envelope rather than refusing
                # every pose from now on
                c.clock_resets += 1
                self._delays.clear()
            self._last_source = p.t
            delay = now - p.t / self.time_scale
            dq = self._delays  # monotonic queue: sliding-window minimum in O(1)
            while dq and dq[-1][1] >= delay:
                dq.pop()
            dq.append((now, delay))
            while dq[0][0] < now - self.sync_window:
                dq.popleft()
            self._offset = dq[0][1]
            if self.clock_mode == "wall":
                t_host = p.t / self.time_scale - (self.wall_clock() - self.clock())
                self._wall_delay = now - t_host
            elif self.clock_mode == "receive":
                t_host = now
            else:
                t_host = p.t / self.time_scale + self._offset
            self._rows.append((p.t, now, t_host, p.x, p.y, p.yaw))
            self._recent.append(now)
            self._latency.append(now - p.t / self.time_scale)
            c.accepted += 1
            return True

    @staticmethod
    def _finite(p: PoseSample) -> bool:
        return all(math.isfinite(v) for v in (p.t, p.x, p.y, p.z, p.qx, p.qy, p.qz, p.qw))

    # ----------------------------------------------------------------- output
    def samples(self, since_host: float = -math.inf) -> FloatArray:
        """Accepted samples (rows as :data:`COLUMNS`) with host time >= ``since_host``.

        ``t_host`` is fixed when the sample arrives (the clock offset of that moment).
        """
        with self._lock:
            data = self._rows.array()
        i = int(np.searchsorted(data[:, 2], since_host))
        return data[i:]

    def latest(self) -> LatestPose | None:
        """The newest accepted sample."""
        with self._lock:
            if not len(self._rows):
                return None
            r = self._rows.last()
            return LatestPose(float(r[0]), float(r[2]), float(r[3]), float(r[4]), float(r[5]))

    def age(self, now: float | None = None) -> float:
        """Host seconds since the newest accepted sample was received (inf if none)."""
        now = self.clock() if now is None else now
        with self._lock:
            return now - float(self._rows.last()[1]) if len(self._rows) else math.inf

    def is_stale(self, now: float | None = None) -> bool:
        return self.age(now) > self.stale_after

    def clock_problem(self) -> str | None:
        """Why the pose stamps cannot be used as they are (``None``: they can).

        Only ``clock_mode="wall"`` trusts the source clock; it needs the newest stamp to be
        within ``max_clock_error`` of its receive time on the host's wall clock.
        """
        with self._lock:
            d = self._wall_delay
        if self.clock_mode != "wall" or not math.isfinite(d) or abs(d) <= self.max_clock_error:
            return None
        return (
            f"motion-capture stamps are {d:+.3f} s off the host's wall clock at receipt "
            f"(limit {self.max_clock_error:g} s): clock mode 'wall' needs the mocap clock "
            "synchronised with this host (PTP, chrony), else use 'source'"
        )

    @property
    def clock_offset(self) -> float:
        """Host minus mocap clock (lower envelope of the receive delays)."""
        return self._offset

    def stats(self, window: float = 1.0) -> dict[str, float]:
        """Rate (Hz over the last ``window`` s), latency percentiles (s), counters."""
        now = self.clock()
        with self._lock:
            recent = [t for t in self._recent if t >= now - window]
            lat = np.array(self._latency) - (self._offset if math.isfinite(self._offset) else 0)
            c = self.counters
            out = {
                "rate_hz": len(recent) / window,
                "received": float(c.received),
                "accepted": float(c.accepted),
                "dropped": float(c.dropped),
                "decode_errors": float(c.decode_errors),
                "non_finite": float(c.non_finite),
                "non_unit_quaternion": float(c.non_unit_quaternion),
                "duplicates": float(c.duplicates),
                "out_of_order": float(c.out_of_order),
                "clock_resets": float(c.clock_resets),
            }
        out["age_s"] = self.age(now)
        if lat.size:
            out["latency_p50_s"] = float(np.percentile(lat, 50))
            out["latency_p99_s"] = float(np.percentile(lat, 99))
        return out
