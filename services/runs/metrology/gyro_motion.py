"""What the gyro and the wheel encoders say of the robot's motion, without motion capture.

Pure functions and small stores of the samples (their times on the run's clock and their
values): no clock, no I/O, so the run without motion capture (:mod:`services.runs.metrology.imu`)
and the tests feed them samples and get the same answer on any host.

* :class:`RecentRows`: the newest rows of a sensor read by cursor (each row once), kept
  for a while;
* :func:`stillness`: the gyro's mean rate and the wheels' and steering's motion over a
  window (the rests: ``limits.rest_yaw_rate`` and ``limits.rest_speed``);
* :class:`GyroYaw`: the yaw turned since a time, the gyro's rate minus a bias integrated
  sample by sample (a spin's sweep and its rate,
  :class:`services.runs.metrology.pose_motion.SpinWindow`);
* :func:`wheel_travel`: how far the wheels rolled (the straight drive, nominal radii).

The gyro's mean at rest includes its bias (0.1 deg/s for the simulator's, a few for a
poor MEMS gyro): ``limits.rest_yaw_rate`` must exceed it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from swpc_hw.robot.model import FloatArray


class RecentRows:
    """Rows ``(t, values...)`` sorted by time, the newest ``keep`` seconds of them."""

    def __init__(self, n_columns: int, keep: float) -> None:
        self.keep = float(keep)
        self.cursor = 0
        """The source's cursor after the rows read so far."""
        self.rows: FloatArray = np.zeros((0, n_columns))

    def add(self, rows: FloatArray) -> None:
        if rows.shape[0]:
            self.rows = np.vstack([self.rows, rows])
            cut = int(np.searchsorted(self.rows[:, 0], self.rows[-1, 0] - self.keep))
            if cut:
                self.rows = self.rows[cut:]

    def between(self, t0: float, t1: float) -> FloatArray:
        """The rows with ``t0 <= t <= t1``."""
        t = self.rows[:, 0]
        return self.rows[int(np.searchsorted(t, t0)) : int(np.searchsorted(t, t1, "right"))]

    @property
    def last(self) -> FloatArray | None:
        return self.rows[-1] if self.rows.shape[0] else None


@dataclass(frozen=True)
class Stillness:
    """The motion over a window: the gyro's mean rate (rad/s, its bias included), the
    fastest wheel (m/s, nominal radii) and the largest steering change (rad)."""

    rate: float
    speed: float
    steer: float
    covered: bool
    """The gyro's and every encoder's samples span most of the window."""

    def still(self, rest_yaw_rate: float, rest_speed: float) -> bool:
        return self.covered and abs(self.rate) <= rest_yaw_rate and self.speed <= rest_speed


def stillness(
    gyro: FloatArray,
    encoders: Mapping[int, FloatArray],
    radius: Mapping[int, float],
    t0: float,
    t1: float,
) -> Stillness:
    """:class:`Stillness` of gyro rows ``(t, wz)`` and per-module encoder rows
    ``(t, theta_hat, psi)`` inside ``[t0, t1]``; ``covered`` when each has samples over at
    least 80 % of it."""
    span = 0.8 * (t1 - t0)
    g = gyro[(gyro[:, 0] >= t0) & (gyro[:, 0] <= t1)]
    covered = g.shape[0] >= 2 and g[-1, 0] - g[0, 0] >= span
    rate = float(np.mean(g[:, 1])) if g.shape[0] else math.nan
    speed, steer = 0.0, 0.0
    for m, rows in encoders.items():
        e = rows[(rows[:, 0] >= t0) & (rows[:, 0] <= t1)]
        if e.shape[0] < 2 or e[-1, 0] - e[0, 0] < span:
            covered = False
            continue
        speed = max(speed, float(np.ptp(e[:, 2])) * radius[m] / float(e[-1, 0] - e[0, 0]))
        steer = max(steer, float(np.ptp(e[:, 1])))
    return Stillness(rate, speed, steer, covered)


@dataclass
class GyroYaw:
    """The yaw turned since the first sample fed (rad): ``sum (wz_k - bias) (t_k - t_k-1)``
    (the rate held from each sample to the next)."""

    bias: float = 0.0
    yaw: float = 0.0
    t: float | None = None
    _wz: float = 0.0

    def add(self, t: float, wz: float) -> float:
        """The sample ``(t, wz)``; returns the yaw turned up to ``t``."""
        if self.t is not None:
            self.yaw += (self._wz - self.bias) * (t - self.t)
        self.t, self._wz = t, wz
        return self.yaw


def wheel_travel(
    start: Mapping[int, float], now: Mapping[int, float], radius: Mapping[int, float]
) -> float:
    """Mean distance (m) the wheels rolled from their angles ``start`` to ``now`` (rad),
    with the nominal radii: ``mean_j |psi_j - psi0_j| r_j``."""
    return float(np.mean([abs(now[m] - start[m]) * radius[m] for m in start]))


def wheel_speed(rows: Mapping[int, FloatArray], radius: Mapping[int, float]) -> float:
    """The fastest wheel (m/s) over per-module rows ``(t, theta_hat, psi)``: each module's
    first to last row (0 with fewer than two rows)."""
    out = 0.0
    for m, e in rows.items():
        if e.shape[0] >= 2 and e[-1, 0] > e[0, 0]:
            out = max(out, abs(float(e[-1, 2] - e[0, 2])) * radius[m] / float(e[-1, 0] - e[0, 0]))
    return out
