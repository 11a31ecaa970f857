"""The virtual robot's gyro over zenoh, and the simulator's tape measure.

Gyro: a z gyro fixed to R, sampled at simulated times ``k / rate`` from the physics' true
yaw rate, with the model of :func:`simulators.offline.datagen_imu.simulate_gyro` and its settings
(:class:`~swpc_hw.sensors.gyro.GyroOptions`: rate, noise density, bias, bias walk, scale
error)::

    wz_k = (1 + scale_error) omega(t_k) + bias_k + n_k
    bias_0 = bias,  bias_k = bias_k-1 + N(0, bias_walk^2 dt),  n_k ~ N(0, noise_density^2 rate)

(:func:`gyro_reading`, :meth:`GyroSim.sample`; ``dt = 1 / rate``).  Every sample is
published at once on ``imu/<robot>/data`` as a CDR ``sensor_msgs/msg/Imu``
(:mod:`swpc_hw.sensors.gyro`), byte for byte what zenoh-bridge-ros2dds forwards from a ROS 2 IMU
driver, stamped like the poses (lockstep: the simulated clock's wall stamp of the sample;
``swpc sim``: the host's wall clock at sampling).  In lockstep every publication is
announced to the simulated clock (:func:`simulators.sensors.mocap.lockstep_put`).

Tape measure: what an operator measures with a tape between two floor marks, from the
simulator's truth: the distance the steering axis of the robot's first module travelled
between two times (:func:`axis_travel`), plus the tape's error (:func:`tape_measure`).
:class:`PoseHistory` keeps the true poses it needs (the in-process simulator's
``GET /simulator/tape-measure``; never available against a real robot).
"""

from __future__ import annotations

import contextlib
import itertools
import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import zenoh

from simulators.physics.core import FloatArray
from simulators.sensors.mocap import SampleGrid, listened, lockstep_put
from swpc_hw.clock import SimClock
from swpc_hw.robot.model import rot
from swpc_hw.row_ring import RowRing
from swpc_hw.sensors.gyro import IMU_ENCODING, GyroOptions, GyroSample, encode_imu

MAX_GYRO_RATE_HZ = 2000.0


def imu_key(robot: str) -> str:
    return f"imu/{robot}/data"


def check_gyro(opt: GyroOptions) -> None:
    """Refuse settings no gyro has (ValueError naming the setting)."""
    if not 0.0 < opt.rate <= MAX_GYRO_RATE_HZ:
        raise ValueError(f"gyro rate {opt.rate} Hz outside (0, {MAX_GYRO_RATE_HZ:g}]")
    for name in ("noise_density", "bias_walk"):
        v = getattr(opt, name)
        if not (math.isfinite(v) and v >= 0.0):
            raise ValueError(f"gyro {name} {v} must be finite and >= 0")
    for name in ("bias", "scale_error"):
        if not math.isfinite(getattr(opt, name)):
            raise ValueError(f"gyro {name} must be finite")
    if abs(opt.scale_error) >= 0.5:
        raise ValueError(f"gyro scale_error {opt.scale_error} outside (-0.5, 0.5)")


def gyro_reading(omega: float, bias: float, noise: float, scale_error: float) -> float:
    """``(1 + scale_error) omega + bias + noise`` (rad/s): the gyro model's one line."""
    return (1.0 + scale_error) * omega + bias + noise


@dataclass
class GyroCounters:
    sampled: int = 0
    published: int = 0
    unheard: int = 0  # sampled while no one subscribed: not sent
    put_errors: int = 0


@dataclass
class GyroSim:
    """The gyro: sample the true yaw rate, add its errors, publish it on zenoh.

    ``session`` None: samples are only kept in :attr:`sent` (tests without zenoh).
    Time is the simulated clock (s).
    """

    robot: str
    options: GyroOptions = field(default_factory=GyroOptions)
    session: Any = None
    seed: int = 0
    frame_id: str = "base_link"
    keep_sent: int = 0
    """Keep the last ``keep_sent`` samples in :attr:`sent` (0: none)."""
    clock: SimClock | None = None
    """Lockstep: announce every publication to this simulated clock."""

    def __post_init__(self) -> None:
        check_gyro(self.options)
        self.key = imu_key(self.robot)
        self.counters = GyroCounters()
        self.bias = float(self.options.bias)
        self._rng = np.random.default_rng([self.seed, 21])
        self._grid = SampleGrid(self.options.rate)
        self.sent: deque[GyroSample] = deque(maxlen=max(self.keep_sent, 1))
        opt = self.options
        self._walk_sd = opt.bias_walk * math.sqrt(1.0 / opt.rate)
        self._noise_sd = opt.noise_density * math.sqrt(opt.rate)
        self._pub: Any = None
        if self.session is not None:
            # as the poses: each sample at once, and never dropped by zenoh's queue
            self._pub = self.session.declare_publisher(
                self.key,
                encoding=IMU_ENCODING,
                express=True,
                congestion_control=zenoh.CongestionControl.BLOCK,
            )

    def due_times(self, t0: float, t1: float) -> list[float]:
        """Sample times ``k / rate`` in ``(t0, t1]`` (the first call also includes ``t0``)."""
        return self._grid.due(t0, t1)

    def sample(self, omega: float, stamp: float) -> GyroSample:
        """The reading of the true yaw rate ``omega`` (rad/s), stamped ``stamp``; the bias
        walks one step first (except at the first sample), then it is published."""
        if self.counters.sampled:
            self.bias += float(self._rng.normal(0.0, self._walk_sd)) if self._walk_sd else 0.0
        noise = float(self._rng.normal(0.0, self._noise_sd)) if self._noise_sd else 0.0
        self.counters.sampled += 1
        g = GyroSample(
            stamp,
            gyro_reading(omega, self.bias, noise, self.options.scale_error),
            frame_id=self.frame_id,
            wz_variance=self._noise_sd**2,
        )
        self._publish(g)
        return g

    def _publish(self, g: GyroSample) -> None:
        if self.keep_sent:
            self.sent.append(g)
        if self._pub is not None:
            if not listened(self._pub):
                self.counters.unheard += 1  # no subscriber: not even encoded
                return
            if not lockstep_put(self.clock, self.key, self._pub, encode_imu(g, self.frame_id)):
                self.counters.put_errors += 1  # a closed session while stopping
                return
        self.counters.published += 1

    def close(self) -> None:
        pub, self._pub = self._pub, None
        if pub is not None:
            with contextlib.suppress(Exception):  # already closed with its session
                pub.undeclare()


# --------------------------------------------------------------------------- tape measure


def axis_travel(pose0: FloatArray, pose1: FloatArray, P_s: FloatArray) -> float:
    """Distance (m) the body point ``P_s`` (in R) travelled from pose ``(x, y, yaw)``
    ``pose0`` to ``pose1``: ``|p1 + R(yaw1) P_s - p0 - R(yaw0) P_s|``."""
    a = np.asarray(pose0, dtype=float)
    b = np.asarray(pose1, dtype=float)
    q0 = a[:2] + rot(float(a[2])) @ np.asarray(P_s, dtype=float)
    q1 = b[:2] + rot(float(b[2])) @ np.asarray(P_s, dtype=float)
    return float(np.linalg.norm(q1 - q0))


def tape_measure(travel: float, stddev: float, rng: np.random.Generator) -> float:
    """A tape's reading of the distance ``travel`` (m): ``travel + N(0, stddev^2)``."""
    if not (math.isfinite(stddev) and stddev >= 0.0):
        raise ValueError(f"tape stddev {stddev} must be finite and >= 0")
    return travel + (float(rng.normal(0.0, stddev)) if stddev > 0 else 0.0)


def measure_axis_distances(
    P_s: FloatArray, ids: Sequence[int], stddev: float, rng: np.random.Generator, readings: int
) -> list[tuple[int, int, list[float]]]:
    """A tape's readings between the steering axes ``P_s`` (in R) of every pair of modules
    ``ids``: per pair ``(a, b, [reading, ...])``, ``readings`` :func:`tape_measure` readings
    of the true distance ``|P_s,a - P_s,b|`` (drawn from ``rng`` pair by pair, in order)."""
    P = P_s
    return [
        (ids[i], ids[j], [
            tape_measure(float(np.linalg.norm(P[i] - P[j])), stddev, rng)
            for _ in range(readings)
        ])
        for i, j in itertools.combinations(range(len(ids)), 2)
    ]  # fmt: skip


class PoseHistory:
    """The true poses ``(t, x, y, yaw)`` at most every ``period`` simulated seconds, the
    newest ``capacity`` (20 Hz for 12 h by default: 28 MB at most)."""

    def __init__(self, period: float = 0.05, capacity: int = 864_000) -> None:
        self.period = float(period)
        self._rows = RowRing(4, capacity)
        self._next = -math.inf

    def add(self, t: float, pose: FloatArray) -> None:
        if t >= self._next:
            self._rows.append((t, float(pose[0]), float(pose[1]), float(pose[2])))
            self._next = t + self.period

    def at(self, t: float) -> FloatArray:
        """The pose recorded nearest ``t`` (``(x, y, yaw)``); ValueError outside the
        recorded span (by more than a period)."""
        rows = self._rows.array()
        if not rows.shape[0] or not rows[0, 0] - self.period <= t <= rows[-1, 0] + self.period:
            span = f"{rows[0, 0]:.3f}-{rows[-1, 0]:.3f} s" if rows.shape[0] else "nothing"
            raise ValueError(f"no true pose at {t:.3f} s (recorded: {span})")
        i = int(np.argmin(np.abs(rows[:, 0] - t)))
        return np.asarray(rows[i, 1:], dtype=float)
