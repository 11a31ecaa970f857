"""The fast part's fixed point without motion capture
(:mod:`swpc_hw.calibration.commission.trailing`): the free casters' wheels and the gyro's
turn, the casters swivelling on the simulator's caster equations
(:func:`simulators.physics.core.caster_rates`), against the point the robot turned about."""

from __future__ import annotations

import math

import numpy as np
import pytest

from simulators.physics.core import caster_rates
from swpc_hw.calibration.commission.trailing import AGREE, trailing_fixed_point
from swpc_hw.robot.model import RobotParams, contact_point
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED, PAPER_NOMINAL

FREE = (2, 4)  # module 1 locked, module 3 driving: the fast part's first probe


def roll_about(
    truth: RobotParams, C: np.ndarray, theta0: np.ndarray, turn: float = math.radians(8.0)
) -> tuple[dict[int, np.ndarray], np.ndarray]:
    """The robot turned ``turn`` about ``C`` (R) at 0.1 rad/s: the free modules' encoder
    rows ``(t, theta_hat, psi)`` at 200 Hz (``theta_hat = theta - beta``, the truth's) and
    the gyro's yaw rows, the casters starting at ``theta0`` (true angles)."""
    A = truth.arrays()
    omega, dt = 0.1, 0.005
    v = np.array([omega * C[1], -omega * C[0]])  # R's origin about C: v = -omega z x C
    theta, psi = theta0.astype(float).copy(), np.zeros(A.n)
    enc: dict[int, list[list[float]]] = {m: [] for m in FREE}
    yaw = []
    steps = round(turn / omega / dt)
    for k in range(steps + 1):
        t = k * dt
        for m in FREE:
            i = truth.ids.index(m)
            enc[m].append([t, theta[i] - A.beta[i], psi[i]])
        yaw.append([t, omega * t])
        for _ in range(10):  # the casters' equations at a tenth of the rows' step
            th_dot, psi_dot = caster_rates(A, theta, v, omega)
            theta += 0.1 * dt * th_dot
            psi += 0.1 * dt * psi_dot
    return {m: np.array(r) for m, r in enc.items()}, np.array(yaw)


def locked_contact(truth: RobotParams, angle: float) -> np.ndarray:
    A = truth.arrays()
    return np.asarray(contact_point(A.P_s[0], A.b[0], angle + A.beta[0]), dtype=float)


@pytest.mark.parametrize("start_deg", [0.0, 90.0, 180.0])
def test_the_fixed_point_from_swivelling_casters_is_the_locked_contact_point(
    start_deg: float,
) -> None:
    """The truth's own geometry: the point within 0.1 mm, whichever way the free casters
    pointed when the roll began (a half turn of swivel in the first degrees)."""
    C = locked_contact(PAPER_CALIBRATED, math.radians(45.0))
    enc, yaw = roll_about(PAPER_CALIBRATED, C, np.full(4, math.radians(start_deg)))
    fix = trailing_fixed_point(PAPER_CALIBRATED, enc, yaw)
    assert fix is not None and fix.modules == FREE
    assert math.dist(fix.point, C) < 1e-4, (fix.point, C)
    assert fix.agrees and fix.residual < 1e-4


def test_the_nominal_geometry_puts_it_millimetres_off_and_still_agreeing() -> None:
    """The nominal config (the homing errors 0.6-1.5 deg, the axes 0.3-2.3 mm and the
    radii 0.5-1.8 % off the truth): the radii scale each wheel's distance to the point, so
    it is mm off (7.6 mm): the crossed nodes' check needs it a robot's size off."""
    C = locked_contact(PAPER_CALIBRATED, math.radians(45.0))
    enc, yaw = roll_about(PAPER_CALIBRATED, C, np.full(4, math.radians(90.0)))
    fix = trailing_fixed_point(PAPER_NOMINAL, enc, yaw)
    assert fix is not None and fix.agrees
    off = math.dist(fix.point, C)
    assert 1e-3 < off < 10e-3, off
    print(f"\nnominal geometry: {1000 * off:.1f} mm off, residual {1000 * fix.residual:.2f} mm")


@pytest.mark.parametrize("which", ["wheel", "steer"])
def test_a_free_module_turning_the_other_way_breaks_the_agreement(which: str) -> None:
    """Module 4's wheel, or its steering, read the other way round: its rows no longer
    meet module 2's at one point."""
    C = locked_contact(PAPER_CALIBRATED, math.radians(45.0))
    enc, yaw = roll_about(PAPER_CALIBRATED, C, np.full(4, math.radians(90.0)))
    col = 2 if which == "wheel" else 1
    enc[4][:, col] = -enc[4][:, col]
    fix = trailing_fixed_point(PAPER_CALIBRATED, enc, yaw)
    assert fix is not None and not fix.agrees and fix.residual > 2 * AGREE, fix
    assert fix.worst is None  # two free modules: either one's rows fit alone


def test_too_little_turn_or_too_few_free_modules_tell_nothing() -> None:
    C = locked_contact(PAPER_CALIBRATED, math.radians(45.0))
    enc, yaw = roll_about(PAPER_CALIBRATED, C, np.zeros(4), turn=math.radians(0.8))
    assert trailing_fixed_point(PAPER_CALIBRATED, enc, yaw) is None
    enc, yaw = roll_about(PAPER_CALIBRATED, C, np.zeros(4))
    assert trailing_fixed_point(PAPER_CALIBRATED, {2: enc[2]}, yaw) is None
