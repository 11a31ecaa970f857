"""The square path, its options and its follower: pure functions of the pose, the leg and
the options.

The square-path validation (:mod:`swpc_hw.validation`) drives it over the drives; the plan
(:mod:`swpc_hw.calibration.plan`) predicts its error from a calibration's covariance.

Follower (per control step of ``dt`` robot seconds, world frame = odometry frame):

* line ``A -> B`` with heading ``h``: along-track remaining distance ``s_r = (B - p) . d``,
  lateral offset ``e_l = (p - A) . n`` (``d = (B - A)/|B - A|``, ``n = z x d``);
  speed target ``sign(s_r) min(v_max, sqrt(2 a |s_r|), k_p |s_r|)``, slew-limited by
  ``a dt``; world velocity ``s d - k_l e_l n``, yaw rate ``k_h wrap(h - yaw)``;
* turn in place to yaw ``h``: ``e = h - yaw``, yaw-rate target
  ``sign(e) min(w_max, sqrt(2 alpha |e|), k_p |e|)`` slew-limited by ``alpha dt``; the
  position is held with ``-k_l (p - corner)``;
* body twist ``v_R = R(-yaw) v_W``; the controller scales the whole twist down if a wheel
  or steering rate limit would be exceeded (re-orienting casters), and the follower's
  speed memory takes the applied (scaled) value.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

from swpc_hw.robot.model import wrap_angle

Direction = Literal["cw", "ccw"]


@dataclass(frozen=True)
class SquareOptions:
    """The square path test: its path, its follower's gains, its runs (SI units, robot
    time)."""

    side: float = 2.5  # m
    speed: float = 0.2  # m/s along the legs
    accel: float = 0.2  # m/s^2
    yaw_rate: float = 0.3  # rad/s at the corners
    yaw_accel: float = 0.4  # rad/s^2
    runs: int = 4  # per direction and file
    directions: tuple[Direction, ...] = ("cw", "ccw")
    control_rate: float = 25.0  # Hz of robot time
    k_position: float = 2.5  # 1/s, final approach along the leg / to the target yaw
    k_lateral: float = 1.0  # 1/s, cross-track and corner hold
    k_heading: float = 1.5  # 1/s, heading hold on the legs
    position_tol: float = 3e-3  # m, leg done
    yaw_tol: float = 2e-3  # rad, turn done
    settle: float = 0.6  # s still before and after each run (truth averaged over it)
    max_wheel_rate: float | None = 16.0  # rad/s (controller scales the twist)
    max_steer_rate: float | None = 0.8  # rad/s
    lead_time: float | None = None
    """s, steering prediction of the inverse kinematics (default: half a control period
    plus 5 ms of feedback age and command delay)."""

    def __post_init__(self) -> None:
        if not (self.side > 0 and self.speed > 0 and self.accel > 0 and self.yaw_rate > 0
                and self.yaw_accel > 0 and self.control_rate > 0 and self.settle > 0):
            raise ValueError("square options: side, speeds, accelerations, rates must be > 0")
        if self.runs < 1:
            raise ValueError("square options: runs must be >= 1")
        bad = [d for d in self.directions if d not in ("cw", "ccw")]
        if bad or not self.directions:
            raise ValueError(f"square options: directions must be cw and/or ccw (got {bad})")


@dataclass(frozen=True)
class Leg:
    """One piece of the path in the odometry frame: a straight line or a turn in place."""

    kind: Literal["line", "turn"]
    start: tuple[float, float]
    end: tuple[float, float]
    yaw: float  # heading held on a line; target (continuous) yaw of a turn


def square_plan(pose: Sequence[float], side: float, direction: Direction) -> list[Leg]:
    """The square from ``pose = (x, y, yaw)``: 4 x (line of ``side`` ahead, turn of +-90 deg).

    Counter-clockwise (``ccw``) turns left (+pi/2), clockwise right; the path ends at the
    start point with yaw ``yaw +- 2 pi`` (continuous).
    """
    x, y, h = (float(v) for v in pose)
    sgn = 1.0 if direction == "ccw" else -1.0
    legs: list[Leg] = []
    p = (x, y)
    for _ in range(4):
        q = (p[0] + side * math.cos(h), p[1] + side * math.sin(h))
        legs.append(Leg("line", p, q, h))
        h_new = h + sgn * math.pi / 2.0
        legs.append(Leg("turn", q, q, h_new))
        p, h = q, h_new
    return legs


def _profile(err: float, vmax: float, acc: float, k: float) -> float:
    """``sign(err) min(vmax, sqrt(2 0.8 acc |err|), k |err|)``: stop at ``err = 0``.

    The braking curve uses 80 % of the acceleration limit, so that the slew limit never
    binds while braking and the discrete loop does not overshoot (no reversal at the end
    of a leg, which would swing the casters round)."""
    a = abs(err)
    return math.copysign(min(vmax, math.sqrt(1.6 * acc * a), k * a), err)


def _slew(target: float, prev: float, step: float) -> float:
    return min(prev + step, max(prev - step, target))


def _clip_norm(vx: float, vy: float, limit: float) -> tuple[float, float]:
    n = math.hypot(vx, vy)
    if n > limit:
        return vx * limit / n, vy * limit / n
    return vx, vy


def follow_step(
    leg: Leg, pose: Sequence[float], speed: float, dt: float, opt: SquareOptions
) -> tuple[tuple[float, float, float], float, bool]:
    """One control step of the follower (module docstring).

    ``speed`` is the follower's memory (signed leg speed, or yaw rate on a turn) from the
    previous step.  Returns the body twist ``(v_x, v_y, omega)``, the new memory and whether
    the leg is done (then the twist is zero).
    """
    x, y, yaw = (float(v) for v in pose)
    if leg.kind == "line":
        ax, ay = leg.start
        bx, by = leg.end
        length = math.hypot(bx - ax, by - ay)
        dx, dy = (bx - ax) / length, (by - ay) / length
        rem = (bx - x) * dx + (by - y) * dy
        lat = (x - ax) * -dy + (y - ay) * dx
        if abs(rem) < opt.position_tol and abs(speed) <= 2.0 * opt.accel * dt:
            return (0.0, 0.0, 0.0), 0.0, True
        s = _slew(_profile(rem, opt.speed, opt.accel, opt.k_position), speed, opt.accel * dt)
        cx, cy = _clip_norm(-opt.k_lateral * lat * -dy, -opt.k_lateral * lat * dx, 0.05)
        vwx, vwy = s * dx + cx, s * dy + cy
        om = max(-opt.yaw_rate, min(opt.yaw_rate, opt.k_heading * float(wrap_angle(leg.yaw - yaw))))
        new = s
    else:
        e = leg.yaw - yaw
        if abs(e) < opt.yaw_tol and abs(speed) <= 2.0 * opt.yaw_accel * dt:
            return (0.0, 0.0, 0.0), 0.0, True
        om = _slew(_profile(e, opt.yaw_rate, opt.yaw_accel, opt.k_position), speed,
                   opt.yaw_accel * dt)
        cx_, cy_ = leg.start
        vwx, vwy = _clip_norm(-opt.k_lateral * (x - cx_), -opt.k_lateral * (y - cy_), 0.05)
        new = om
    c, s_ = math.cos(yaw), math.sin(yaw)
    return (c * vwx + s_ * vwy, -s_ * vwx + c * vwy, om), new, False
