"""The commissioning probes: small motions whose outcome a right config predicts.

Two kinds of probe, each a few degrees of motion (docs/commissioning.md):

* every **steering move** of the probes is made with the robot pinned (every other
  module's wheel braked and its steering held): the robot cannot move, and its steering
  axis moving more than :data:`MOVE_MARGIN` stops every axis at once
  A steering drive that turns a wheel (the module's steering and
  wheel drives swapped) pushes against the braked wheels and moves nothing; the pivot
  probes then show it (the caster does not turn, the "wheel" does not roll the robot).
* a **pivot probe** locks module ``m`` (steering held at a commanded angle, wheel braked)
  and rolls one other module's wheel, the *driver* ``j``, its steering held across the
  circle about ``m``'s contact point ``C``; the casters of the others trail freely.  The
  robot can only turn about the braked contact point, which motion capture sees as the
  fixed point of the poses (:func:`swpc_hw.calibration.geometry.fixed_point`), and the
  driver's roll turns it by (least squares of the driver's rolling and lateral rows, the
  driver's contact point ``c_j`` at distance ``D`` from ``C``, its heading ``u`` at angle
  ``delta`` from the tangent ``t = z x (c_j - C) / D``)::

      dyaw = r_j cos(delta) dpsi_j / D                                          (1)

  With the driver's heading along ``-t`` (trailing a counter-clockwise turn, as in a
  spin) ``cos(delta) = -1``: rolling backwards turns the robot counter-clockwise.  That
  is a wheel driven at a velocity, its tyre's lateral row as stiff as its rolling one.
  A wheel **pushed** by torque rolls without slip along its heading and scrubs sideways::

      dyaw = r_j dpsi_j / (D cos(delta))                                         (1')

  (the two agree at ``cos(delta) = -1``).  A commissioning pushes where the drive has a
  torque mode (a velocity driver fights a lock held by position control, below); the fast
  part of a calibration drives at a velocity.

A **lock that holds** is what (1) and the fixed point need.  A drive that holds by
position control (a CiA 402 or ODrive axis: no brake) holds only as well as its tyre and
its loop against the driver: a driver heading across the circle about the true contact
point ``T`` (its steering miswired, or steered about a point ``P`` where the config puts
the lock and the lock is not) fights the lock, and the robot turns about a point ``X``
between them.  So a commissioning probe is **pinned** only when its fixed point is where
its driver was steered to turn about (:func:`is_pinned`, within :data:`PINNED_TOL`); else
its driver is steered again about the next estimate (:func:`next_pivot`), up to
:data:`PIVOT_TRIES` rolls, then the next module drives.  A lock that holds
(a brake) gives ``X = T`` at once, and the next roll is pinned; a driver that cannot
head right (its own steering miswired) never is, and its probes say nothing.

What a right config predicts, this module says; what the probes then tell about the
wiring, :mod:`swpc_hw.calibration.commission.analysis`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from swpc_hw.robot.model import RobotParams, contact_point, trailing_steering_angle

PROBE_TURN = math.radians(10.0)
"""rad: how far a pivot probe turns the robot (a right robot)."""
PRECHECK_TURN = math.radians(8.0)
"""rad: how far the fast part of every calibration and check turns the robot about each
module.  A fixed point's error is the pinned wheel's slip over the turn (1 mm of slip in
3 deg puts it 19 mm off: a drive whose hold gives a little), so not much less."""
PROBE_RATE = 0.1
"""rad/s: the yaw rate a pivot probe's roll asks of a right robot."""
PIVOT_ANGLES = (0.0, math.radians(90.0), math.radians(180.0))
"""rad: the locked module's commanded steering angles, one pivot probe each: three points
of the caster's circle give its centre, the steering's polarity, ratio and zero (a
ratio down to 0.5 of the config's: consecutive angles less than half a turn apart)."""
REFINE_ANGLES = (math.radians(270.0), math.radians(360.0))
"""rad: two more commanded angles for a module whose steering's ratio the three of
:data:`PIVOT_ANGLES` found off: a steering that turns less than commanded covers a third
of its circle in those (its ratio good to 5 %, 1 std dev, from 0.5 mm fixed points); five
angles over a whole turn of commands cover more (about 1.5 %), what a corrected config
must hold for the calibration after it."""
MOVE_MARGIN = 0.025
"""m: how far a steering move may move its steering axis (the robot pinned: the braked
tyres' give, the pose noise, and what is left of the previous roll: 11 mm seen on the
lab's time-scaled simulator on the test VM, against 1-3 mm in process)."""
MOVE_TURN = math.radians(2.0)
"""rad: how far the robot may turn during a steering move where no sensor sees position
(the gyro alone): the robot pinned turns by the braked tyres' give, a tenth of a degree."""
WRONG_WAY = math.radians(0.5)
"""rad: a pivot probe whose robot turned this far against the roll's turn stops."""
PINNED_TOL = 0.005
"""m: a fixed point this close to the point its driver was steered to turn about (or 4
std devs, whichever is more) is a pinned probe's (the nominal geometry is a few mm off on
a right robot; a lock fought by a driver 5 deg off its heading moved 9 mm on the CiA 402
simulator)."""
PIVOT_TRIES = 4
"""Rolls of one driver about one lock angle before the next module drives."""
ROLL_MARGIN = 2.5
"""A pivot probe whose driver rolled this many times what :data:`PROBE_TURN` asks
without the robot turning that far stops."""


@dataclass(frozen=True)
class SteerMove:
    """One watched steering move: ``module`` (configured) turned by ``step`` (rad), its
    steering axis ``moved`` (m, the farthest, the budget ``budget``), the robot's yaw
    ``turned`` (rad, the farthest) meanwhile; ``stopped`` when over the budget."""

    module: int
    step: float
    moved: float
    turned: float
    budget: float
    stopped: bool

    def document(self) -> dict[str, float | int | bool]:
        return {
            "module": self.module,
            "step_deg": round(math.degrees(self.step), 2),
            "moved_mm": round(1000 * self.moved, 2),
            "budget_mm": round(1000 * self.budget, 2),
            "turned_deg": round(math.degrees(self.turned), 3),
            "stopped": self.stopped,
        }


@dataclass(frozen=True)
class PivotProbe:
    """What one pivot probe saw (module docstring).  Angles and rolls are the host's (the
    drives' readings with the config's polarity); ``fixed_point`` is in the sensor's
    body frame (R if the body is R's), None when the robot turned too little to tell."""

    module: int
    steering: float
    """rad: the locked module's steering reading during the roll."""
    driver: int
    driver_steering: float
    """rad: the driver's steering reading during the roll."""
    roll: float
    """rad: the driver's wheel reading's change."""
    turn: float
    """rad: the robot's yaw change (the sensor's)."""
    fixed_point: tuple[float, float] | None
    fixed_point_std: float
    """m: the fixed point's std dev per coordinate (inf without one)."""
    stopped: str | None = None
    """Why the probe ended before its turn, if it did."""
    pushed: bool = False
    """The driver's wheel pushed by torque (1'); else driven at a velocity (1)."""
    pinned: bool = True
    """False: its fixed point was not where its driver was steered to turn about (the
    module docstring): it tells neither the lock nor the driver's wheel."""

    def document(self) -> dict[str, object]:
        return {
            "module": self.module,
            "steering_deg": round(math.degrees(self.steering), 2),
            "driver": self.driver,
            "driver_steering_deg": round(math.degrees(self.driver_steering), 2),
            "roll_deg": round(math.degrees(self.roll), 2),
            "turn_deg": round(math.degrees(self.turn), 3),
            "fixed_point_mm": None
            if self.fixed_point is None
            else [round(1000 * c, 2) for c in self.fixed_point],
            "fixed_point_std_mm": round(1000 * self.fixed_point_std, 3)
            if math.isfinite(self.fixed_point_std)
            else None,
            "stopped": self.stopped,
            "pushed": self.pushed,
            "pinned": self.pinned,
        }


def driver_of(ids: Sequence[int], module: int) -> int:
    """The module whose wheel turns the robot about ``module``: the one half the robot's
    modules on (across the robot: every module drives once and is locked once)."""
    i = list(ids).index(module)
    return ids[(i + max(1, len(ids) // 2)) % len(ids)]


@dataclass(frozen=True)
class PivotPlan:
    """What a right robot does in one pivot probe (nominal geometry): the driver's
    steering (host rad, trailing a counter-clockwise turn about ``C``), the roll rate
    (rad/s) for :data:`PROBE_RATE` and the roll per radian of turn from (1)."""

    pivot: tuple[float, float]
    driver_steering: float
    roll_rate: float
    roll_per_turn: float


def pivot_plan(nominal: RobotParams, module: int, steering: float, driver: int) -> PivotPlan:
    """The plan of a pivot probe about ``module`` locked at ``steering`` (host rad)
    rolled by ``driver`` (module docstring, nominal geometry)."""
    A = nominal.arrays()
    k = nominal.ids.index(module)
    C = contact_point(A.P_s[k], np.array(A.b[k]), steering + A.beta[k])
    return plan_about(nominal, (float(C[0]), float(C[1])), driver)


def plan_about(nominal: RobotParams, pivot: tuple[float, float], driver: int) -> PivotPlan:
    """The plan of a roll by ``driver`` that turns the robot about ``pivot`` (R, m): the
    driver trailing the counter-clockwise turn about it, nominal geometry."""
    A = nominal.arrays()
    j = nominal.ids.index(driver)
    C = np.array(pivot, dtype=float)
    v = -np.array([-C[1], C[0]])  # the velocity of R's origin turning about C at 1 rad/s
    target = float(trailing_steering_angle(A, v, 1.0)[j])
    c_j = contact_point(A.P_s[j], np.array(A.b[j]), target + A.beta[j])
    D = float(np.hypot(*(c_j - C)))
    per_turn = -D / float(A.r[j])  # (1) with cos(delta) = -1, solved for dpsi
    return PivotPlan((float(C[0]), float(C[1])), target, per_turn * PROBE_RATE, per_turn)


def is_pinned(probe: PivotProbe, pivot: tuple[float, float], turns: Sequence[float]) -> bool:
    """Whether ``probe`` is pinned (module docstring): its fixed point within
    :data:`PINNED_TOL` (or 4 std devs) of ``pivot``, the point its driver was steered to
    turn about, the sensor's axes turned by one of ``turns`` (rad: a motion-capture
    body turned from R reports ``R(-gamma) C``)."""
    if probe.fixed_point is None:
        return False
    tol = max(PINNED_TOL, 4.0 * probe.fixed_point_std)
    x, y = probe.fixed_point
    for g in turns:
        c, s = math.cos(g), math.sin(g)
        if math.hypot(c * x - s * y - pivot[0], s * x + c * y - pivot[1]) <= tol:
            return True
    return False


def next_pivot(
    history: Sequence[tuple[tuple[float, float], tuple[float, float]]],
) -> tuple[float, float]:
    """The point to steer the next roll about, from the rolls so far: ``(P_k, X_k)``, the
    point each was steered about and its fixed point.  A fought lock turns the robot
    about a point between the lock's contact point ``T`` and ``P``, modelled as::

        X = T + alpha (P - T),   0 <= alpha < 1

    From the last two rolls (the secant, Aitken's extrapolation)::

        alpha = (X_1 - X_2) . (P_1 - P_2) / |P_1 - P_2|^2,   T = (X_2 - alpha P_2) / (1 - alpha)

    With one roll, or an ``alpha`` outside ``[0, 0.95]`` (the model does not hold), the
    last fixed point ``X``: the iteration ``P <- X`` converges to ``T`` as ``alpha^k``."""
    (p2, x2) = history[-1]
    if len(history) >= 2:
        (p1, x1) = history[-2]
        dp = (p1[0] - p2[0], p1[1] - p2[1])
        dx = (x1[0] - x2[0], x1[1] - x2[1])
        n2 = dp[0] * dp[0] + dp[1] * dp[1]
        if n2 > 1e-12:
            alpha = (dx[0] * dp[0] + dx[1] * dp[1]) / n2
            if 0.0 <= alpha <= 0.95:
                return (
                    (x2[0] - alpha * p2[0]) / (1.0 - alpha),
                    (x2[1] - alpha * p2[1]) / (1.0 - alpha),
                )
    return x2
