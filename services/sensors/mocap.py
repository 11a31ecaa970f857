"""Motion-capture ingest: a zenoh subscriber on the robot's pose key.

Every payload is decoded (native or ROS 2 CDR ``PoseStamped``, configured or detected)
and checked; accepted samples are kept with their source timestamp and their time on the
service clock (:mod:`swpc_hw.clock`: robot seconds).  Dropped and counted: undecodable
payloads, NaN/inf values, non-unit quaternions (``| |q| - 1 | > quaternion_tol``),
duplicates (same source time) and out-of-order samples (source time older than the last
accepted one).

Time bases (``clock_mode``), each sample's time ``t_host`` on the clock's axis:

* ``wall``: the stamps are the host's wall clock (``swpc sim`` on this machine, the
  in-process simulator's simulated wall clock, or a mocap PC synchronised by PTP or
  chrony): ``t_host = clock.from_wall(t_source)``, exact, the way the driver maps the CAN
  bus time stamps.  A stamp more than ``max_clock_error`` off its receipt (an
  unsynchronised source) is reported by :meth:`MocapIngest.clock_problem`, which the
  calibration's precheck refuses to start on.
* ``source`` (default): any mocap clock, mapped by the lower envelope of the delays,
  ``t_host = s t_source + min over the last sync_window of (t_recv - s t_source)`` (the
  classic one-way clock estimate, a sliding minimum that follows drift; ``s`` =
  ``source_rate``, clock seconds per source second).  Poses keep the mocap's exact
  spacing, late by the *smallest* transport delay of the window: a CPU-bound publisher
  (``swpc sim`` under emulation: a 12-23 ms floor, measured) shifts every pose against the
  CAN feedback, whose bus stamps carry no such delay, and biases the wheel radius
  (0.1-0.2 mm at 12-23 ms in the VM).  Use ``wall`` when the clocks are synchronised.
* ``receive``: ``t_host`` is the receive time itself (transport jitter, no drift).

The subscription, the stamp order, the store, staleness and the common counters are every
ingest's (:mod:`services.sensors.ingest`); a stale stream is a fault during motion.
"""

from __future__ import annotations

import bisect
import contextlib
import json
import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from services.sensors.ingest import MAX_CLOCK_STEP_S, Ingest, IngestCounters
from swpc_hw.clock import SYSTEM_CLOCK, Clock
from swpc_hw.sensors.mocap import (
    PoseDecodeError,
    PoseEncoding,
    PoseSample,
    decode_pose,
    detect_encoding,
)

FloatArray = NDArray[np.float64]

#: pose time bases of :class:`MocapIngest` (module docstring)
CLOCK_MODES = ("source", "receive", "wall")

#: upper bounds (s) of the pose delay histogram (:meth:`MocapIngest.delay_histogram`)
DELAY_BUCKETS = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0)

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
class PoseCounters(IngestCounters):
    non_unit_quaternion: int = 0


class MocapIngest(Ingest):
    """Thread-safe pose store fed by zenoh (or directly through :meth:`feed`)."""

    def __init__(
        self,
        *,
        clock: Clock = SYSTEM_CLOCK,
        encoding: PoseEncoding | str = PoseEncoding.AUTO,
        stale_after: float = 0.25,
        quaternion_tol: float = 1e-3,
        capacity: int = 2_000_000,
        source_rate: float | None = None,
        sync_window: float = 1.0,
        clock_mode: str = "source",
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
            recent=4096,
        )
        self.encoding = PoseEncoding(encoding)
        self.quaternion_tol = float(quaternion_tol)
        rate = clock.rate if source_rate is None else source_rate
        self.source_rate = float(rate) if math.isfinite(rate) else 1.0
        """Clock seconds per source second (``swpc sim --time-scale k`` stamps host wall
        time, on a clock that runs k times faster: k)."""
        self.counters: PoseCounters = PoseCounters()
        self.detected_encoding: PoseEncoding | None = None
        self.sync_window = float(sync_window)
        if clock_mode not in CLOCK_MODES:
            raise ValueError(f"clock_mode must be one of {CLOCK_MODES}, not {clock_mode!r}")
        self.clock_mode = clock_mode
        self._wall_delay = math.nan  # clock_mode "wall": receive minus mapped stamp, last sample
        self._offset = math.inf  # sliding min(t_recv - s t_source)
        self._delays: deque[tuple[float, float]] = deque()  # (t_recv, delay), increasing delay
        self._latency = deque[float](maxlen=4096)
        self._delay_counts = [0] * (len(DELAY_BUCKETS) + 1)  # the last: above every bound
        self._delay_sum = 0.0

    # ------------------------------------------------------------------ input
    def feed(self, payload: bytes, t_recv: float | None = None) -> bool:
        """Decode, check and store one payload; returns whether it was accepted."""
        clock = self.clock
        now = clock.now() if t_recv is None else t_recv
        with self._lock:
            c = self.counters
            c.received += 1
            try:
                enc = self.encoding
                p = decode_pose(payload, enc)
                if enc is PoseEncoding.AUTO and self.detected_encoding is None:
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
            resets = c.clock_resets
            if not self._in_order(p.t, now, self.source_rate):
                return False
            if c.clock_resets != resets:
                # the source clock was stepped back (mocap PC restarted, clock re-synced):
                # the delay envelope restarts with the stamp sequence
                self._delays.clear()
            s = self.source_rate
            delay = now - s * p.t
            dq = self._delays  # monotonic queue: sliding-window minimum in O(1)
            while dq and dq[-1][1] >= delay:
                dq.pop()
            dq.append((now, delay))
            while dq[0][0] < now - self.sync_window:
                dq.popleft()
            self._offset = dq[0][1]
            if self.clock_mode == "wall":
                t_host = clock.from_wall(p.t)
                self._wall_delay = now - t_host
            elif self.clock_mode == "receive":
                t_host = now
            else:
                t_host = s * p.t + self._offset
            self._store((p.t, now, t_host, p.x, p.y, p.yaw), now)
            self._latency.append(now - s * p.t)
            delay = max(0.0, now - t_host)
            self._delay_counts[bisect.bisect_left(DELAY_BUCKETS, delay)] += 1
            self._delay_sum += delay
            return True

    @staticmethod
    def _finite(p: PoseSample) -> bool:
        return all(math.isfinite(v) for v in (p.t, p.x, p.y, p.z, p.qx, p.qy, p.qz, p.qw))

    # ----------------------------------------------------------------- output
    def latest(self) -> LatestPose | None:
        """The newest accepted sample."""
        with self._lock:
            if not len(self._rows):
                return None
            r = self._rows.last()
            return LatestPose(float(r[0]), float(r[2]), float(r[3]), float(r[4]), float(r[5]))

    def clock_problem(self) -> str | None:
        """Why the pose stamps cannot be used as they are (``None``: they can).

        Only ``clock_mode="wall"`` trusts the source clock; it needs the newest stamp to be
        within ``max_clock_error`` clock seconds of its receipt.
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

    def frame_rate(self, window: float = 2.0) -> float | None:
        """The motion capture's frame rate (Hz of its own clock): one over the median
        spacing of the source time stamps accepted in the last ``window`` clock seconds;
        None with fewer than 10 of them (no poses, or a stream just starting).  A lost
        frame widens one spacing, which the median ignores."""
        rows = self.samples(self.clock.now() - window)
        dt = np.diff(rows[:, 0])
        dt = dt[dt > 0]
        if dt.size < 9:
            return None
        return float(1.0 / np.median(dt))

    @property
    def clock_offset(self) -> float:
        """Host minus mocap clock (lower envelope of the receive delays)."""
        return self._offset

    def delay_histogram(self) -> tuple[list[tuple[float, int]], float, int]:
        """Cumulative counts of the accepted poses' delays, receipt minus ``t_host`` (the
        mapped sampling time: the transport latency in clock mode ``wall``, the delay above
        the window's smallest in ``source``, 0 in ``receive``), by upper bound, ending with
        ``inf``; their sum (s) and count."""
        with self._lock:
            counts, total = list(self._delay_counts), self._delay_sum
        out, acc = [], 0
        for bound, n in zip((*DELAY_BUCKETS, math.inf), counts, strict=True):
            acc += n
            out.append((bound, acc))
        return out, total, acc

    def stats(self, window: float = 1.0) -> dict[str, float]:
        """Rate (Hz over the last ``window`` s), counters, age and latency percentiles (s)."""
        out = super().stats(window)
        with self._lock:
            lat = np.array(self._latency) - (self._offset if math.isfinite(self._offset) else 0)
        if lat.size:
            out["latency_p50_s"] = float(np.percentile(lat, 50))
            out["latency_p99_s"] = float(np.percentile(lat, 99))
        return out


class SourceStatus:
    """The status the robot's motion-capture bridge last published (``swpc mocap`` on
    ``mocap/<robot>/source``: its source, body, rate and counts, whether it sees the body;
    :meth:`services.sensors.bridge.Bridge.status_document`), kept with its receipt on
    ``clock`` (host seconds).  A robot whose poses come another way has none."""

    FRESH_S = 5.0
    """A status older than this (host s) is no longer the bridge's word: it is gone."""

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self.clock = clock
        self._doc: dict[str, Any] | None = None
        self._at = -math.inf
        self._subscriber: Any = None

    def feed(self, payload: bytes) -> bool:
        """Keep a status document; False (and nothing kept) for one that is not."""
        try:
            doc = json.loads(payload)
        except (ValueError, UnicodeDecodeError):
            return False
        if not isinstance(doc, dict) or not {"source", "body", "seen"} <= doc.keys():
            return False
        self._doc, self._at = doc, self.clock()
        return True

    def latest(self) -> dict[str, Any] | None:
        """The last status with its age (``age_s``), None when none is fresh."""
        doc, age = self._doc, self.clock() - self._at
        if doc is None or age > self.FRESH_S:
            return None
        return {**doc, "age_s": round(age, 3)}

    def subscribe(self, session: Any, key: str) -> None:
        self._subscriber = session.declare_subscriber(
            key, lambda sample: self.feed(bytes(sample.payload.to_bytes()))
        )

    def close(self) -> None:
        sub, self._subscriber = self._subscriber, None
        if sub is not None:
            with contextlib.suppress(Exception):  # session already closed
                sub.undeclare()
