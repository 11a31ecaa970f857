"""Options of the square-path validation and its error type."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from swpc_hw.errors import SwpcError

Direction = Literal["cw", "ccw"]


class ValidationError(SwpcError, RuntimeError):
    """The validation drive could not run or complete (fault, no truth, timeout)."""


@dataclass(frozen=True)
class SquareOptions:
    """The test (SI units, robot time)."""

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
