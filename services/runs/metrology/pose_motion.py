"""What the motion capture says of the robot's motion: at rest, and how far a spin went.

Pure functions of the poses (their sample times on the run's clock and their values):
no clock, no I/O, so the calibration run (:mod:`services.runs.protocol`) and the tests
feed them poses and get the same answer on any host.

* :func:`motion_rates`: speed and yaw rate as least-squares slopes (the REST state waits
  until they are within the limits over :data:`REST_WINDOW`);
* :class:`SpinWindow`: a spin's unwrapped yaw, its rate over :data:`YAW_RATE_WINDOW`
  (checked against ``limits.max_yaw_rate``) and the segment window that opens at the
  first pose sampled ``settle_time`` after the spin began.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from swpc_hw.robot.model import FloatArray, wrap_angle

REST_WINDOW = 0.5
"""s of robot time over which the robot must be still before a module is locked."""
YAW_RATE_WINDOW = 0.2
"""s of robot time over which the spin's yaw rate is checked against its limit."""


def motion_rates(
    t: FloatArray, x: FloatArray, y: FloatArray, yaw: FloatArray
) -> tuple[float, float]:
    """Speed (m/s) and yaw rate (rad/s) of poses ``(t_k, x_k, y_k, yaw_k)``: the slopes of
    least-squares lines through them (noise-averaging, unlike end-point differences)::

        s_q = sum_k (t_k - t_mean)(q_k - q_mean) / sum_k (t_k - t_mean)^2,  q in {x, y, yaw}
        speed = hypot(s_x, s_y),   yaw rate = s_yaw   (yaw unwrapped first)

    Needs at least two distinct times.
    """
    tc = t - np.mean(t) if t.shape[0] else t
    den = float(tc @ tc)
    if den <= 0.0:
        raise ValueError("motion_rates needs poses at two distinct times at least")
    q = np.column_stack([x, y, np.unwrap(yaw)])
    s = tc @ (q - q.mean(axis=0)) / den
    return float(math.hypot(s[0], s[1])), float(s[2])


@dataclass
class SpinWindow:
    """One spin, fed the poses as they come (:meth:`add`).

    ``t_spin`` is when the torque was applied; ``t0, yaw0`` the pose at hand then.  The
    yaw is accumulated wrapped step by step (a spin of several turns); the rate is the
    accumulated yaw over at least :data:`YAW_RATE_WINDOW` of the poses' own times; the
    window opens at the first pose *sampled* ``settle_time`` after ``t_spin`` (not the
    newest at that moment: with late poses that one may predate the steady spin).
    """

    t_spin: float
    settle_time: float
    t0: float
    yaw0: float
    yaw_acc: float = 0.0
    rate: float | None = None
    start: float | None = None
    end: float | None = None
    _acc_at_start: float = 0.0

    def __post_init__(self) -> None:
        self._yaw_prev = self.yaw0
        self._rate_t, self._rate_acc = self.t0, 0.0

    def add(self, t: float, yaw: float) -> None:
        """The pose sampled at ``t`` (run clock, s) with ``yaw`` (rad)."""
        self.yaw_acc += float(wrap_angle(yaw - self._yaw_prev))
        self._yaw_prev = yaw
        if t - self._rate_t >= YAW_RATE_WINDOW:
            self.rate = (self.yaw_acc - self._rate_acc) / (t - self._rate_t)
            self._rate_t, self._rate_acc = t, self.yaw_acc
        if self.start is None and t - self.t_spin >= self.settle_time:
            self.start, self._acc_at_start = t, self.yaw_acc
        self.end = t

    @property
    def sweep(self) -> float:
        """Yaw (rad, >= 0) swept since the window opened (0 before)."""
        return 0.0 if self.start is None else abs(self.yaw_acc - self._acc_at_start)
