"""Simulated motion capture over zenoh, and the simulator's ground-truth channel.

Mocap (what the service uses): poses of R in W on ``mocap/<robot>/pose`` at ``rate``
(100 Hz default, up to 2 kHz) in one of the two encodings of :mod:`swpc_hw.sensors.mocap`:

* ``native`` (``application/x-swpc-pose``, 72 bytes, layout in :mod:`swpc_hw.sensors.mocap`);
* ``ros2-cdr`` (``application/cdr``): a CDR ``geometry_msgs/msg/PoseStamped`` serialised by
  rosbags, byte for byte what zenoh-bridge-ros2dds forwards from a ROS 2 mocap driver.

Samples are taken at simulated times ``k / rate`` and stamped with the *mocap clock*
``t_mocap = stamp + clock_offset``, where ``stamp`` is the simulated time of the sample
unless the simulator gives another (:class:`simulators.virtual_robot.VirtualRobot` gives the
host's wall clock at sampling, see its ``mocap_clock``).  Options model a real system (the
generator's noise options, :class:`simulators.offline.datagen.ExperimentOptions`, are the template):
Gaussian noise on x, y and yaw, dropouts (a sample is not sent), outliers (a jump of
``outlier_magnitude`` in a random direction and ``outlier_magnitude / 0.25`` rad of yaw),
and a transport latency (a sample is published ``latency`` simulated seconds after its
timestamp).

Ground truth (tests and validation only; the service never subscribes to it), kept
apart under ``sim/<robot>/truth/``:

* ``sim/<robot>/truth/pose``: JSON ``{"t", "pose": [x, y, yaw], "twist": [vx, vy, omega],
  "theta": [...], "theta_hat": [...], "psi": [...], "psi_encoder": [...],
  "contact_points": [[x, y], ...], "homed": [...]}`` (SI, true values, no noise; ``t`` on the
  simulated clock, i.e. without the mocap clock offset), at ``truth_rate``;
* ``sim/<robot>/truth/params``: JSON kinematic-file document of the true robot plus
  ``nodes`` (module id -> CAN node) and the simulator settings; published at start and
  every 5 s, and answered by a queryable on the same key (``session.get``).
"""

from __future__ import annotations

import contextlib
import json
import math
from collections import deque
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import zenoh

from simulators.physics.core import FloatArray
from simulators.physics.robot import RobotPhysics
from simulators.sensors.qtm import QtmBody, QtmServer
from swpc_hw.clock import SimClock
from swpc_hw.robot.model import wrap_angle
from swpc_hw.sensors.mocap import (
    PoseEncoding,
    PoseSample,
    encode_pose,
    pose_key,
    zenoh_encoding_name,
)

MAX_RATE_HZ = 2000.0


def truth_pose_key(robot: str) -> str:
    return f"sim/{robot}/truth/pose"


def truth_params_key(robot: str) -> str:
    return f"sim/{robot}/truth/params"


def lockstep_put(clock: SimClock | None, key: str, pub: Any, payload: bytes) -> bool:
    """``pub.put(payload)``, announced to a lockstep ``clock`` first (its receivers'
    arrivals are then waited for before time moves on); False if the put failed."""
    if clock is not None:
        clock.expect(key)
    try:
        pub.put(payload)
    except Exception:  # a closed session while stopping: the caller counts it
        if clock is not None:
            clock.arrived(key)  # nothing will arrive
        return False
    return True


def listened(pub: Any) -> bool:
    """Someone subscribes to ``pub``'s key (zenoh's matching status: under a microsecond);
    False once its session is closed."""
    try:
        return bool(pub.matching_status.matching)
    except Exception:  # a closed session while stopping
        return False


@dataclass(frozen=True)
class MocapOptions:
    """Simulated mocap stream (SI units; random draws seeded by ``seed``)."""

    rate: float = 100.0  # Hz, <= 2000
    encoding: str = "native"  # "native" | "ros2-cdr"
    frame_id: str = "world"  # header.frame_id of ros2-cdr samples
    sigma_xy: float = 0.0  # m
    sigma_yaw: float = 0.0  # rad
    dropout: float = 0.0  # probability that a sample is not sent
    outliers: float = 0.0  # probability that a sent sample is an outlier
    outlier_magnitude: float = 0.05  # m (yaw jump outlier_magnitude / 0.25 rad)
    latency: float = 0.0  # s of simulated time between a sample's timestamp and its publication
    clock_offset: float = 0.0  # s, mocap clock - simulated clock
    seed: int = 0
    qtm_port: int | None = None
    """Serve the poses as a QTM real-time server on this loopback port (0: a free one)
    instead of publishing them: a lab's bridge (``swpc mocap --source qtm://...``) puts
    them on the pose key, as it would a real QTM's (:mod:`simulators.sensors.qtm`)."""

    def __post_init__(self) -> None:
        if self.qtm_port is not None and not 0 <= self.qtm_port <= 65535:
            raise ValueError(f"mocap qtm_port {self.qtm_port} outside [0, 65535]")
        if not 0.0 < self.rate <= MAX_RATE_HZ:
            raise ValueError(f"mocap rate {self.rate} Hz outside (0, {MAX_RATE_HZ:g}]")
        PoseEncoding(self.encoding)
        if self.encoding == PoseEncoding.AUTO:
            raise ValueError("mocap encoding must be native or ros2-cdr")
        for name in ("dropout", "outliers"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise ValueError(f"mocap {name} {v} outside [0, 1]")
        if self.latency < 0.0 or self.sigma_xy < 0.0 or self.sigma_yaw < 0.0:
            raise ValueError("mocap latency and noise must be >= 0")


def corrupt_pose(
    rng: np.random.Generator, pose: FloatArray, opt: MocapOptions
) -> tuple[FloatArray | None, bool]:
    """Measured pose from the true ``(x, y, yaw)``: ``(None, False)`` if dropped.

    ``x += N(0, sigma_xy)``, ``y += N(0, sigma_xy)``, ``yaw += N(0, sigma_yaw)``; with
    probability ``outliers`` the position jumps by ``outlier_magnitude`` in a uniformly
    random direction and yaw by ``+-outlier_magnitude / 0.25`` rad.  Returns
    ``(pose, is_outlier)``.
    """
    if opt.dropout > 0.0 and rng.random() < opt.dropout:
        return None, False
    p = np.array(pose, dtype=float)
    if opt.sigma_xy > 0.0:
        p[:2] += rng.normal(0.0, opt.sigma_xy, 2)
    if opt.sigma_yaw > 0.0:
        p[2] += rng.normal(0.0, opt.sigma_yaw)
    outlier = opt.outliers > 0.0 and rng.random() < opt.outliers
    if outlier:
        a = rng.uniform(-math.pi, math.pi)
        p[0] += opt.outlier_magnitude * math.cos(a)
        p[1] += opt.outlier_magnitude * math.sin(a)
        p[2] += (1.0 if rng.random() < 0.5 else -1.0) * opt.outlier_magnitude / 0.25
    return p, outlier


@dataclass
class MocapCounters:
    sampled: int = 0
    published: int = 0
    dropped: int = 0
    outliers: int = 0
    put_errors: int = 0


class SampleGrid:
    """The sample times of a sensor sampled every ``1 / rate`` s of simulated time,
    ``t_k = k / rate`` (exact multiples: no drift however long it runs)."""

    def __init__(self, rate: float) -> None:
        self.rate = float(rate)
        self._k_next: int | None = None

    def due(self, t0: float, t1: float) -> list[float]:
        """Sample times in ``(t0, t1]`` (the first call also includes ``t0``)."""
        rate = self.rate
        if self._k_next is None:
            self._k_next = math.ceil(t0 * rate - 1e-9)
        out = []
        while self._k_next / rate <= t1 + 1e-12:
            out.append(self._k_next / rate)
            self._k_next += 1
        return out


@dataclass
class MocapSim:
    """The mocap system: sample the true pose, corrupt it, delay it, publish it on zenoh.

    ``session`` is a zenoh session (None: samples are only kept in :attr:`sent`, for
    tests without zenoh).  Time is the simulated clock (s).
    """

    robot: str
    options: MocapOptions = field(default_factory=MocapOptions)
    session: Any = None
    keep_sent: int = 0
    """Keep the last ``keep_sent`` published samples in :attr:`sent` (0: none)."""
    clock: SimClock | None = None
    """Lockstep: announce every publication to this simulated clock."""

    def __post_init__(self) -> None:
        self.key = pose_key(self.robot)
        self.counters = MocapCounters()
        self._rng = np.random.default_rng(self.options.seed)
        self._queue: deque[tuple[float, PoseSample]] = deque()
        self._seq = 0
        self._grid = SampleGrid(self.options.rate)
        self.sent: deque[PoseSample] = deque(maxlen=max(self.keep_sent, 1))
        self._pub: Any = None
        self._encoding = PoseEncoding(self.options.encoding)
        self.qtm: QtmServer | None = None
        if self.options.qtm_port is not None:
            self.qtm = QtmServer([self.robot], port=self.options.qtm_port,
                                 frequency=self.options.rate)  # fmt: skip
            self.qtm.start()
        elif self.session is not None:
            # express: each pose goes out at once, not batched with the next (a motion
            # capture system's latency is its own; lockstep waits for every delivery).
            # BLOCK: zenoh's default for puts drops a sample when its queue is full, which
            # on a starved host lost ~2 % of the poses; a lost pose is the simulated mocap's
            # dropout model to decide (MocapOptions), never the host's load.
            self._pub = self.session.declare_publisher(
                self.key,
                encoding=zenoh_encoding_name(self._encoding),
                express=True,
                congestion_control=zenoh.CongestionControl.BLOCK,
            )

    def due_times(self, t0: float, t1: float) -> list[float]:
        """Sample times ``k / rate`` in ``(t0, t1]`` (the first call also includes ``t0``)."""
        return self._grid.due(t0, t1)

    def heard(self) -> bool:
        """Someone subscribes to the poses (zenoh's matching status; False without a
        session), or a client streams them from the QTM server."""
        if self.qtm is not None:
            return self.qtm.streaming > 0
        return self._pub is not None and listened(self._pub)

    def sample(self, t: float, pose: FloatArray, stamp: float | None = None) -> None:
        """Take the sample of simulated time ``t`` from the true pose ``(x, y, yaw)``,
        stamped ``stamp`` (default ``t``) plus the clock offset."""
        self.counters.sampled += 1
        meas, outlier = corrupt_pose(self._rng, pose, self.options)
        if meas is None:
            self.counters.dropped += 1
            return
        self.counters.outliers += int(outlier)
        ps = PoseSample.planar(
            (t if stamp is None else stamp) + self.options.clock_offset,
            float(meas[0]),
            float(meas[1]),
            float(meas[2]),
            seq=self._seq,
        )
        self._seq += 1
        self._queue.append((t + self.options.latency, ps))

    def flush(self, now: float) -> int:
        """Publish the queued samples whose publication time is ``<= now``; return how many."""
        n = 0
        q = self._queue
        while q and q[0][0] <= now + 1e-12:
            _, ps = q.popleft()
            self._publish(ps)
            n += 1
        return n

    def _publish(self, ps: PoseSample) -> None:
        if self.keep_sent:
            self.sent.append(ps)
        if self.qtm is not None:
            self._serve(ps)
        elif self._pub is not None:
            if self._encoding is PoseEncoding.CDR:
                ps = PoseSample(
                    ps.t,
                    ps.x,
                    ps.y,
                    ps.z,
                    ps.qx,
                    ps.qy,
                    ps.qz,
                    ps.qw,
                    ps.seq,
                    self.options.frame_id,
                )
            if not lockstep_put(self.clock, self.key, self._pub, encode_pose(ps, self._encoding)):
                self.counters.put_errors += 1  # a closed session while stopping
                return
        self.counters.published += 1

    def _serve(self, ps: PoseSample) -> None:
        """One QTM frame: the pose in mm, its rotation column-major, its time stamp in us
        of the mocap's clock; announced to a lockstep clock as a pose on the key the bridge
        puts it on (a frame no bridge streams is not waited for)."""
        assert self.qtm is not None
        c, s = math.cos(ps.yaw), math.sin(ps.yaw)
        body = QtmBody((1e3 * ps.x, 1e3 * ps.y, 1e3 * ps.z), (c, s, 0.0, -s, c, 0.0, 0.0, 0.0, 1.0))
        if self.clock is not None and self.qtm.streaming:
            self.clock.expect(self.key)
        self.qtm.publish(round(ps.t * 1e6), (ps.seq + 1) & 0xFFFFFFFF, [body])

    def close(self) -> None:
        if self.qtm is not None:
            self.qtm.stop()
        pub, self._pub = self._pub, None
        if pub is not None:
            with contextlib.suppress(Exception):  # already closed with its session
                pub.undeclare()


@dataclass
class TruthPublisher:
    """Ground truth on ``sim/<robot>/truth/{pose,params}`` (see the module docstring)."""

    robot: str
    params_doc: dict[str, Any]
    session: Any = None
    rate: float = 50.0
    params_period: float = 5.0
    clock: SimClock | None = None

    def __post_init__(self) -> None:
        self.pose_key = truth_pose_key(self.robot)
        self.params_key = truth_params_key(self.robot)
        self.published = 0
        self._params_payload = json.dumps(self.params_doc).encode()
        self._next_pose: float | None = None
        self._next_params: float | None = None
        self._pub: Any = None
        self._pub_params: Any = None
        self._queryable: Any = None
        if self.session is not None:
            self._pub = self.session.declare_publisher(self.pose_key, encoding="application/json")
            self._pub_params = self.session.declare_publisher(
                self.params_key, encoding="application/json"
            )
            self._queryable = self.session.declare_queryable(self.params_key, self._on_query)

    def _on_query(self, query: Any) -> None:
        query.reply(self.params_key, self._params_payload, encoding="application/json")

    def due(self, now: float) -> bool:
        """True when a truth pose is due at simulated time ``now`` (and schedules the next)
        and someone listens (the service never does: its document is not even built)."""
        if self.rate <= 0.0 or (self._pub is not None and not listened(self._pub)):
            return False
        if self._next_pose is None or now >= self._next_pose - 1e-12:
            base = now if self._next_pose is None else self._next_pose
            self._next_pose = max(base + 1.0 / self.rate, now)
            return True
        return False

    def publish_pose(self, doc: dict[str, Any]) -> None:
        if self._pub is not None and not lockstep_put(
            self.clock, self.pose_key, self._pub, json.dumps(doc).encode()
        ):
            return  # session closed while stopping
        self.published += 1

    def maybe_publish_params(self, now: float) -> None:
        if self._next_params is None or now >= self._next_params:
            self._next_params = now + self.params_period
            if self._pub_params is not None:
                try:
                    self._pub_params.put(self._params_payload)
                except Exception:  # session closed while stopping
                    return

    def close(self) -> None:
        for name in ("_pub", "_pub_params", "_queryable"):
            obj = getattr(self, name)
            setattr(self, name, None)
            if obj is not None:
                with contextlib.suppress(Exception):  # already closed with its session
                    obj.undeclare()


def truth_pose_document(t: float, robot: RobotPhysics, homed: list[bool]) -> dict[str, Any]:
    """The document on ``sim/<robot>/truth/pose`` (module docstring): the true state of
    ``robot`` at simulated time ``t``; ``homed``: each module's steering drive homed."""
    r = robot
    A = r.arrays
    return {
        "t": t,
        "pose": r.pose.tolist(),
        "twist": r.twist.tolist(),
        "theta": r.theta.tolist(),
        "theta_hat": wrap_angle(r.theta - A.beta).tolist(),
        "psi": r.psi.tolist(),
        "psi_encoder": r.psi_encoder.tolist(),
        "contact_points": r.contact_points().tolist(),
        "homed": homed,
    }


def options_doc(opt: MocapOptions) -> dict[str, Any]:
    """The mocap options as a JSON-able dict (for the truth/params document)."""
    return asdict(opt)
