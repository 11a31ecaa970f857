"""Kinematic model: IK then FK returns the commanded twist; the no-slip constraint holds."""

from __future__ import annotations

import numpy as np
import pytest

from swpc_hw.robot.model import (
    RobotParams,
    contact_point,
    cross_z,
    forward_kinematics,
    inverse_kinematics,
    nearest_turn,
    steering_direction,
    steering_normal,
    trailing_steering_angle,
    wrap_angle,
)
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED, PAPER_NOMINAL


def random_robot(rng: np.random.Generator, n: int) -> RobotParams:
    ang = np.sort(rng.uniform(0, 2 * np.pi, n))
    rad = rng.uniform(0.15, 0.4, n)
    P = np.column_stack([rad * np.cos(ang), rad * np.sin(ang)])
    return RobotParams.from_arrays(
        range(1, n + 1), P, rng.uniform(-0.5, 0.5, n), rng.uniform(0.01, 0.04, n),
        rng.uniform(0.04, 0.07, n),
    )


@pytest.mark.parametrize("n", [2, 3, 4, 6])
def test_ik_then_fk_returns_the_twist(n: int) -> None:
    rng = np.random.default_rng(n)
    for _ in range(50):
        robot = random_robot(rng, n).arrays()
        theta_hat = rng.uniform(-np.pi, np.pi, n)
        v = rng.normal(size=2)
        omega = float(rng.normal())
        theta_dot, psi_dot = inverse_kinematics(robot, theta_hat, v, omega)
        twist, residuals = forward_kinematics(robot, theta_hat, theta_dot, psi_dot)
        np.testing.assert_allclose(twist, [v[0], v[1], omega], atol=1e-12)
        assert np.abs(residuals).max() < 1e-12


def test_ik_satisfies_the_no_slip_constraint() -> None:
    a = PAPER_CALIBRATED.arrays()
    theta_hat = np.array([0.3, -1.0, 2.0, 3.0])
    v, omega = np.array([0.2, -0.1]), 0.4
    theta_dot, psi_dot = inverse_kinematics(a, theta_hat, v, omega)
    theta = theta_hat + a.beta
    P_w = contact_point(a.P_s, a.b, theta)
    lhs = v + cross_z(np.full(4, omega), P_w)
    rhs = (a.r * psi_dot)[:, None] * steering_direction(theta) + (a.b * theta_dot)[
        :, None
    ] * steering_normal(theta)
    np.testing.assert_allclose(lhs, rhs, atol=1e-15)


def test_fk_residual_flags_a_slipping_wheel() -> None:
    a = PAPER_NOMINAL.arrays()
    theta_hat = np.zeros(4)
    theta_dot, psi_dot = inverse_kinematics(a, theta_hat, np.array([0.3, 0.0]), 0.0)
    psi_dot[2] *= 1.3
    _, res = forward_kinematics(a, theta_hat, theta_dot, psi_dot)
    norms = np.linalg.norm(res, axis=1)
    assert int(np.argmax(norms)) == 2
    assert norms[2] > 0.01


def test_trailing_angle_is_a_rest_point_behind_the_axis() -> None:
    a = PAPER_CALIBRATED.arrays()
    v, omega = np.array([0.2, 0.05]), 0.3
    th_hat = trailing_steering_angle(a, v, omega)
    theta_dot, psi_dot = inverse_kinematics(a, th_hat, v, omega)
    np.testing.assert_allclose(theta_dot, 0.0, atol=1e-12)
    assert np.all(psi_dot < 0)  # trailing wheels roll towards their steering axis
    th_pure = trailing_steering_angle(a, np.array([1.0, 0.0]), 0.0)
    np.testing.assert_allclose(wrap_angle(th_pure + a.beta - np.pi), 0.0, atol=1e-12)


def test_robot_params_validation() -> None:
    m = PAPER_NOMINAL.modules
    with pytest.raises(ValueError, match="N >= 2"):
        RobotParams(modules=[m[0]])
    with pytest.raises(ValueError, match="duplicate module id 1"):
        RobotParams(modules=[m[0], m[0]])
    with pytest.raises(ValueError):
        RobotParams.from_arrays([1, 2], [[0, 0], [1, 1]], [0, 0], [0.02, -0.01], [0.05, 0.05])
    with pytest.raises(ValueError, match="finite"):
        RobotParams.from_arrays([1, 2], [[0, np.nan], [1, 1]], [0, 0], [0.02, 0.02], [0.05, 0.05])


def test_nearest_turn_is_the_shortest_move_to_the_direction() -> None:
    cur = np.radians([-352.5, 10.0, 370.0, 0.0])
    tgt = np.radians([45.0, 200.0 + 720.0, -10.0, 179.0])
    got = np.degrees(nearest_turn(cur, tgt))
    np.testing.assert_allclose(got, [-315.0, -160.0, 350.0, 179.0], atol=1e-9)
    assert np.all(np.abs(nearest_turn(cur, tgt) - cur) <= np.pi)
    np.testing.assert_allclose(wrap_angle(nearest_turn(cur, tgt) - tgt), 0.0, atol=1e-12)
