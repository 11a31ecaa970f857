"""Physics core: caster dynamics, RK4, exact trailing solution, poses about a pivot."""

from __future__ import annotations

import math

import numpy as np
import pytest

from simulators.physics.core import (
    caster_rates,
    pose_about_pivot,
    rk4_step,
    se2_step,
    settled_trailing,
    smooth_step,
    spin_angle,
    trailing_about_pivot,
    twist_about_pivot,
)
from swpc_hw.robot.model import (
    contact_point,
    cross_z,
    inverse_kinematics,
    rot,
    steering_direction,
    wrap_angle,
)
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED

A = PAPER_CALIBRATED.arrays()


def _integrate(theta0: np.ndarray, v: np.ndarray, w: float, t_end: float, dt: float = 1e-3):
    state = np.concatenate([[0.0, 0.0, 0.0], theta0, np.zeros(A.n)])
    t = 0.0
    for _ in range(round(t_end / dt)):
        state = rk4_step(A, state, t, dt, lambda _t: (v, w))
        t += dt
    return state


def test_twist_about_pivot_leaves_pivot_still() -> None:
    C = np.array([0.23, -0.11])
    v = twist_about_pivot(C, 0.7)
    assert np.allclose(v + cross_z(0.7, C), 0.0, atol=1e-15)
    assert np.allclose(v, [0.7 * -0.11, -0.7 * 0.23])


def test_caster_rates_match_inverse_kinematics() -> None:
    theta = np.array([0.3, -1.2, 2.9, -3.0])
    v, w = np.array([0.12, -0.05]), 0.4
    th_dot, psi_dot = caster_rates(A, theta, v, w)
    ik_th, ik_psi = inverse_kinematics(A, theta - A.beta, v, w)
    assert np.allclose(th_dot, ik_th, rtol=0, atol=1e-12)
    assert np.allclose(psi_dot, ik_psi, rtol=0, atol=1e-12)


@pytest.mark.parametrize("theta0", [math.pi / 2, -2.5, 3.0, -math.pi / 2 + 0.1])
def test_translation_trailing_converges_to_pi(theta0: float) -> None:
    state = _integrate(np.full(A.n, theta0), np.array([1.0, 0.0]), 0.0, t_end=1.0, dt=2e-3)
    theta = state[3 : 3 + A.n]
    assert np.allclose(wrap_angle(theta - math.pi), 0.0, atol=1e-9)
    # trailing wheels turn backwards: r psi = -distance (1 m) plus the transient
    assert np.all(state[3 + A.n :] < 0.0)


@pytest.mark.parametrize("theta0", [0.0, 1.5, -1.5, 2.8, -2.8])
def test_rotation_trailing_converges_perpendicular_to_radius(theta0: float) -> None:
    C = np.array([0.2, 0.14])  # near module 1: a spin about a locked contact point
    w = 1.0
    state = _integrate(np.full(A.n, theta0), twist_about_pivot(C, w), w, t_end=4.0, dt=2e-3)
    theta = state[3 : 3 + A.n]
    P_w = contact_point(A.P_s, A.b, theta)
    radial = np.einsum("ij,ij->i", P_w - C, steering_direction(theta))
    far = np.hypot(*(A.P_s - C).T) > 0.1  # modules 2..4
    assert np.all(np.abs(radial[far]) < 1e-9)
    target, _ = settled_trailing(A.P_s[far], A.b[far], C, 1.0)
    assert np.allclose(wrap_angle(theta[far] - target), 0.0, atol=1e-9)


def test_rk4_matches_exact_trailing_solution_with_ramped_spin() -> None:
    """Time-varying yaw rate (raised-cosine ramps): RK4 vs the closed form in phi."""
    C = np.array([-0.19, 0.13])
    w0, ramp, steady = -0.5, 1.0, 1.5
    theta0 = np.array([0.4, -2.0, 1.0, 2.5])
    dt = 1e-3
    state = np.concatenate([[0.3, -0.2, 1.0], theta0, np.zeros(A.n)])
    t = 0.0

    def twist(tt: float) -> tuple[np.ndarray, float]:
        h = 1e-7
        w = float(spin_angle(tt + h, w0, ramp, steady) - spin_angle(tt - h, w0, ramp, steady))
        w /= 2 * h
        return twist_about_pivot(C, w), w

    n_steps = round((2 * ramp + steady) / dt)
    for _ in range(n_steps):
        state = rk4_step(A, state, t, dt, twist)
        t += dt
    phi = float(spin_angle(t, w0, ramp, steady))
    assert phi == pytest.approx(w0 * (ramp + steady), abs=1e-12)
    th, dpsi = trailing_about_pivot(A.P_s, A.b, A.r, C, theta0, phi)
    far = np.hypot(*(A.P_s - C).T) > 0.1
    assert np.allclose(wrap_angle(state[3 : 3 + A.n][far] - th[far]), 0.0, atol=1e-8)
    assert np.allclose(state[3 + A.n :][far], dpsi[far], atol=1e-7)
    pose = pose_about_pivot([0.3, -0.2, 1.0], C, phi)[0]
    assert np.allclose(state[:3], pose, atol=1e-8)


def test_exact_solution_settles_and_wheel_rate_is_distance() -> None:
    C = np.array([0.2, 0.14])
    for sign in (1.0, -1.0):
        target, D = settled_trailing(A.P_s, A.b, C, sign)
        th1, p1 = trailing_about_pivot(A.P_s[1:], A.b[1:], A.r[1:], C, 0.3, sign * 10.0)
        _, p2 = trailing_about_pivot(A.P_s[1:], A.b[1:], A.r[1:], C, 0.3, sign * 11.0)
        assert np.allclose(wrap_angle(th1 - target[1:]), 0.0, atol=1e-12)
        # settled: r dpsi = -D |dphi|, D = sqrt(|q|^2 - b^2)
        assert np.allclose(A.r[1:] * (p2 - p1), -D[1:], rtol=1e-12)
        q = A.P_s[1:] - C
        assert np.allclose(D[1:] ** 2, np.sum(q * q, axis=1) - A.b[1:] ** 2, rtol=1e-12)
        # the settled angle is an equilibrium of the dynamics
        th_dot, _ = caster_rates(A, target, twist_about_pivot(C, sign), sign)
        assert np.allclose(th_dot[1:], 0.0, atol=1e-12)


def test_se2_step_equals_rotation_about_pivot() -> None:
    C = np.array([0.21, 0.12])
    pose0 = np.array([1.0, -2.0, 0.7])
    for w, dt in ((0.5, 0.3), (-2.0, 1.1), (1e-9, 0.5)):
        p = se2_step(pose0, twist_about_pivot(C, w), w, dt)
        ref = pose_about_pivot(pose0, C, w * dt)[0]
        assert np.allclose(p, ref, atol=1e-14)
        C_W = pose0[:2] + rot(pose0[2]) @ C
        assert np.allclose(p[:2] + rot(p[2]) @ C, C_W, atol=1e-14)


def test_profiles() -> None:
    assert smooth_step(0.0) == 0.0
    assert smooth_step(1.0) == 1.0
    assert smooth_step(0.5) == pytest.approx(0.5)
    tau = np.linspace(0.0, 4.0, 4001)
    phi = spin_angle(tau, 0.5, 1.0, 2.0)
    rate = np.gradient(phi, tau)
    assert rate[0] == pytest.approx(0.0, abs=1e-3)
    assert rate[2000] == pytest.approx(0.5, abs=1e-9)
    assert rate[-1] == pytest.approx(0.0, abs=1e-3)
    assert phi[-1] == pytest.approx(0.5 * 3.0, abs=1e-12)
    assert np.all(np.diff(phi) >= 0.0)
