"""A pivot probe's fixed point without motion capture: from the free casters' wheel
encoders and the gyro's turn (the fast part of a calibration or check with metrology
``imu``).

The robot turns about its fixed point ``C`` (R) while every module but the locked one and
the driver is free.  A free module's wheel (nominal steering axis ``P_s``, offset ``b``,
radius ``r``; caster angle ``theta = theta_hat + beta`` from its steering encoder,
``u = (cos theta, sin theta)``; contact point ``P_w = P_s + b u``) rolls without slip along
``u``: the ground velocity of ``P_w`` is ``omega z x (P_w - C)`` plus the caster's own
swivel ``b theta_dot n``, which is across ``u`` and rolls nothing.  So at every instant,
swivelling or trailing::

    r dpsi = dyaw ((C_y - P_wy) cos theta + (P_wx - C_x) sin theta)

linear in ``C``.  Summed over the encoder's rows of a part of the roll (``dyaw`` the gyro's
turn between two rows, ``theta`` at their middle), each part gives one row::

    (-sum dyaw sin theta) C_x + (sum dyaw cos theta) C_y
        = sum r dpsi - sum dyaw (P_wx sin theta - P_wy cos theta)

Each free module's roll is cut into :data:`PARTS` parts of equal turn.  A caster that has
swivelled into its trail (``u`` across ``P_w - C``) gives rows that hardly depend on its
angle (their derivative in ``theta`` is ``-u . (C - P_w) dyaw = 0``), so the homing
error, which the calibration measures, barely moves ``C``; a caster still swivelling
gives rows of other directions, which the least squares needs.  Least squares over every
free module's rows gives ``C`` and the RMS residual of the rows (each in metres of roll):
a free module whose wheel or steering turns the other way round, another ratio or whose
nodes are crossed breaks its rows, and the residual shows it.  Two modules or more must be
free: a robot of :data:`~swpc_hw.protocol.GYRO_PRECHECK_MODULES` modules or more.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from swpc_hw.robot.model import RobotParams, contact_point

FloatArray = NDArray[np.float64]

STD = 0.005
"""m: the fixed point's std dev per coordinate (a probe's ``fixed_point_std``): the nominal
radii scale each free wheel's distance to the point, and on the paper's robot, up to
1.8 % off, they put it 7-10 mm off (the gyro's scale error adds 0.3 %).  Its rows'
residual is no std dev of it: it says whether they agree."""
AGREE = 0.002
"""m of roll: the free modules' rows agree when their RMS residual is within this.
Beyond it the fixed point is refused (:class:`TrailingFix`)."""


@dataclass(frozen=True)
class TrailingFix:
    """The fixed point the free modules give (R, m), their rows' RMS residual (m of roll),
    and the module whose rows, left out, leave the others agreeing best (three free
    modules or more; None with two, whose rows each fit alone)."""

    point: tuple[float, float]
    residual: float
    modules: tuple[int, ...]
    worst: int | None

    @property
    def agrees(self) -> bool:
        return self.residual <= AGREE


PARTS = 4
"""Parts of equal turn each free module's roll is cut into (one row each)."""


def _rows(
    nominal: RobotParams, k: int, enc: FloatArray, yaw: FloatArray
) -> FloatArray:
    """Module ``k``'s rows ``[a_x, a_y, rhs]``, one per part of the turn (module
    docstring), from its encoder rows ``(t, theta_hat, psi)`` within the gyro's rows."""
    A = nominal.arrays()
    i = nominal.ids.index(k)
    e = enc[(enc[:, 0] >= yaw[0, 0]) & (enc[:, 0] <= yaw[-1, 0])]
    y = np.interp(e[:, 0], yaw[:, 0], yaw[:, 1])
    dyaw = np.diff(y)
    if dyaw.size == 0 or float(np.sum(dyaw)) == 0.0:
        return np.empty((0, 3))
    theta = 0.5 * (e[1:, 1] + e[:-1, 1]) + float(A.beta[i])
    c, s = np.cos(theta), np.sin(theta)
    px, py = contact_point(A.P_s[i], np.full(theta.shape, A.b[i]), theta).T
    roll = float(A.r[i]) * np.diff(e[:, 2])
    cols = np.column_stack([-dyaw * s, dyaw * c, roll - dyaw * (px * s - py * c)])
    # parts of equal turn: each step's share of the whole turn, cut at 1/PARTS, 2/PARTS...
    done = np.cumsum(dyaw) / float(np.sum(dyaw))
    part = np.minimum((done * PARTS - 1e-9).astype(int), PARTS - 1)
    return np.array([cols[part == q].sum(axis=0) for q in range(PARTS) if np.any(part == q)])


def _solve(rows: FloatArray) -> tuple[FloatArray, float]:
    C, *_ = np.linalg.lstsq(rows[:, :2], rows[:, 2], rcond=None)
    res = rows[:, :2] @ C - rows[:, 2]
    return np.asarray(C, dtype=float), float(np.sqrt(np.mean(res**2)))


def trailing_fixed_point(
    nominal: RobotParams,
    trailing: Mapping[int, FloatArray],
    yaw: FloatArray,
) -> TrailingFix | None:
    """The fixed point of a pivot probe from its free modules' encoder rows ``(t,
    theta_hat, psi)`` (host readings, the config's polarity applied) and the gyro's yaw
    rows ``(t, yaw)`` over the roll (module docstring).  None when fewer than two modules
    are free, or the robot turned less than a degree."""
    if len(trailing) < 2 or len(yaw) < 2:
        return None
    turn = float(yaw[-1, 1] - yaw[0, 1])
    if abs(turn) < math.radians(1.0):
        return None
    ids = sorted(trailing)
    per = {k: _rows(nominal, k, trailing[k], yaw) for k in ids}
    if any(len(per[k]) == 0 for k in ids):
        return None
    C, residual = _solve(np.vstack([per[k] for k in ids]))
    worst = None
    if len(ids) >= 3:  # without one of two, the other's rows alone fit: they name no one
        left = {k: _solve(np.vstack([per[o] for o in ids if o != k]))[1] for k in ids}
        worst = min(left, key=left.__getitem__)
    return TrailingFix((float(C[0]), float(C[1])), residual, tuple(ids), worst)
