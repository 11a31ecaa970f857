"""Pure-numpy physics core of the SWPC simulators (model and symbols of docs/model-and-frames.md).

State of the robot: planar pose ``(x, y, yaw)`` of R in W, and per module its *true*
steering angle ``theta`` (relative to the body) and cumulative wheel angle ``psi``.

Free (trailing) caster
----------------------
With its steering motor free and its wheel rolling without slip, a caster follows the
no-slip constraint for a body twist ``(v, omega)`` given in R::

    v + omega x P_w = r psi_dot u(theta) + b theta_dot n(theta)
    P_w = P_s + b u(theta),  u = (cos, sin),  n = (sin, -cos),  omega x p = omega (-p_y, p_x)

Projecting on ``n`` and ``u`` (they are orthonormal)::

    b theta_dot = (v + omega x P_w) . n(theta)        (steering: the caster trails)
    r psi_dot   = (v + omega x P_w) . u(theta)        (wheel)

For ``v = (1, 0), omega = 0``, ``theta = pi`` (wheel behind the axis) is the stable
equilibrium and ``theta = 0`` the unstable one.  In this sign convention a trailing
wheel turns *backwards* (``psi_dot < 0``): positive ``psi_dot`` moves the body point at
``P_w`` along ``+u``, i.e. from the steering axis towards the contact point.

Rotation about a fixed body point
---------------------------------
Every motion of the calibration experiment is a rotation of the body about a body point
``B`` that stays fixed in the world (the locked contact point ``C`` while spinning, the
locked steering axis ``P_s,k`` while re-steering).  The body twist is then
``v = -omega x B``.  With ``q = P_s - B = |q| (cos alpha, sin alpha)``, ``rho = |q| / b``
and ``x = theta - alpha``, the steering equation no longer depends on time, only on the
body rotation angle ``phi`` (``d phi = omega dt``)::

    dx/dphi = -(1 + rho cos x)
    r dpsi/dphi = |q| sin x = b d/dphi ln|1 + rho cos x|

and has the closed-form solution (for ``rho > 1``; ``h = x0 / 2``)::

    k = sqrt((rho + 1)/(rho - 1)),  lambda = sqrt(rho^2 - 1) / 2,  T = tanh(lambda phi)
    s' = k (sin h - k cos h T),  c' = k cos h - sin h T
    x(phi)            = 2 atan2(s', c')
    psi(phi) - psi0   = (b / r) ln( k^2 sech^2(lambda phi) / (s'^2 + c'^2) )

The caster converges (rate ``sqrt(rho^2 - 1)`` per radian of body rotation) to the
settled angle where ``(P_w - B) . u(theta) = 0`` with ``omega sin x < 0``
(``cos x* = -1/rho``), after which ``r dpsi = -D |dphi|`` with ``D = |P_w - B| =
sqrt(|q|^2 - b^2)``.  :func:`trailing_about_pivot` evaluates this exactly;
:func:`rk4_step` integrates the general dynamics numerically.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from swpc_hw.robot.model import (
    RobotArrays,
    contact_point,
    contact_velocity,
    rot,
    steering_direction,
    steering_normal,
)

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

#: ``twist_fn(t) -> (v (2,), omega)``: body twist in R at time ``t``.
TwistFn = Callable[[float], tuple[FloatArray, float]]


# --------------------------------------------------------------------------- twists


def twist_about_pivot(C: ArrayLike, omega: ArrayLike) -> FloatArray:
    """Linear velocity ``v = -omega x C`` (in R) of a rotation about body point ``C``.

    The body point ``C`` then has zero velocity: ``v + omega x C = 0``.  Shapes: ``C``
    (..., 2), ``omega`` (...) -> (..., 2).
    """
    P = np.asarray(C, dtype=float)
    w = np.asarray(omega, dtype=float)[..., None]
    return np.asarray(w * np.stack([P[..., 1], -P[..., 0]], axis=-1), dtype=float)


def caster_rates(
    arrays: RobotArrays, theta: ArrayLike, v: ArrayLike, omega: float
) -> tuple[FloatArray, FloatArray]:
    """Rates of free casters at true steering ``theta`` (N,) under the body twist ``(v, omega)``.

    ::

        b theta_dot = (v + omega x P_w) . n(theta)
        r psi_dot   = (v + omega x P_w) . u(theta),   P_w = P_s + b u(theta)

    Returns ``(theta_dot, psi_dot)`` (N,) each.
    """
    th = np.asarray(theta, dtype=float)
    P_w = contact_point(arrays.P_s, arrays.b, th)
    vel = contact_velocity(np.asarray(v, dtype=float)[None, :], np.full(arrays.n, omega), P_w)
    theta_dot = np.einsum("ij,ij->i", vel, steering_normal(th)) / arrays.b
    psi_dot = np.einsum("ij,ij->i", vel, steering_direction(th)) / arrays.r
    return theta_dot, psi_dot


# --------------------------------------------------------------------------- poses


def se2_step(pose: ArrayLike, v: ArrayLike, omega: float, dt: float) -> FloatArray:
    """Exact pose after applying the constant body twist ``(v, omega)`` for ``dt``.

    ``p' = p + R(yaw) V(omega dt) v dt``, ``yaw' = yaw + omega dt`` with the SE(2) left
    Jacobian ``V(a) = [[sin a / a, -(1 - cos a)/a], [(1 - cos a)/a, sin a / a]]`` (series
    near ``a = 0``).  Yaw is not wrapped.
    """
    x, y, yaw = (float(c) for c in np.asarray(pose, dtype=float))
    vx, vy = (float(c) for c in np.asarray(v, dtype=float))
    a = omega * dt
    if abs(a) < 1e-6:
        s_a = 1.0 - a * a / 6.0
        c_a = a / 2.0 - a**3 / 24.0
    else:
        s_a = math.sin(a) / a
        c_a = (1.0 - math.cos(a)) / a
    # scalars, not 2-vectors: this runs for every pose the simulator samples
    d0 = (s_a * vx - c_a * vy) * dt
    d1 = (c_a * vx + s_a * vy) * dt
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([x + (c * d0 - s * d1), y + (s * d0 + c * d1), yaw + a])


def pose_about_pivot(pose0: ArrayLike, pivot: ArrayLike, phi: ArrayLike) -> FloatArray:
    """Poses after rotating the body by ``phi`` about the body point ``pivot`` (fixed in W).

    ``C_W = p0 + R(yaw0) C``;  ``yaw = yaw0 + phi``;  ``p = C_W - R(yaw) C``.
    ``phi`` (K,) -> poses (K, 3), yaw not wrapped.
    """
    p0 = np.asarray(pose0, dtype=float)
    C = np.asarray(pivot, dtype=float)
    ph = np.atleast_1d(np.asarray(phi, dtype=float))
    C_W = p0[:2] + rot(p0[2]) @ C
    yaw = p0[2] + ph
    p = C_W[None, :] - np.einsum("kij,j->ki", rot(yaw), C)
    return np.column_stack([p, yaw])


# --------------------------------------------------------------------------- dynamics


def state_derivative(
    arrays: RobotArrays,
    state: FloatArray,
    v: FloatArray,
    omega: float,
    free: BoolArray | None = None,
    locked_steer_rate: FloatArray | None = None,
) -> FloatArray:
    """Time derivative of the combined state ``[x, y, yaw, theta (N), psi (N)]``.

    Pose: ``(x, y)_dot = R(yaw) v``, ``yaw_dot = omega``.  Free modules (``free[i]``,
    default all): :func:`caster_rates`.  Other modules are locked: ``psi_dot = 0`` and
    ``theta_dot = locked_steer_rate[i]`` (default 0, i.e. steering held).
    """
    n = arrays.n
    th = state[3 : 3 + n]
    theta_dot, psi_dot = caster_rates(arrays, th, v, omega)
    if free is not None:
        lock = ~free
        theta_dot = theta_dot.copy()
        psi_dot = psi_dot.copy()
        theta_dot[lock] = 0.0 if locked_steer_rate is None else locked_steer_rate[lock]
        psi_dot[lock] = 0.0
    vw = rot(state[2]) @ v
    return np.concatenate([[vw[0], vw[1], omega], theta_dot, psi_dot])


def rk4_step(
    arrays: RobotArrays,
    state: FloatArray,
    t: float,
    dt: float,
    twist_fn: TwistFn,
    free: BoolArray | None = None,
    locked_steer_rate_fn: Callable[[float], FloatArray] | None = None,
) -> FloatArray:
    """One classical Runge-Kutta (RK4) step of :func:`state_derivative` from ``t`` to ``t + dt``.

    ``k1 = f(t, s)``, ``k2 = f(t + dt/2, s + dt/2 k1)``, ``k3 = f(t + dt/2, s + dt/2 k2)``,
    ``k4 = f(t + dt, s + dt k3)``;  ``s' = s + dt/6 (k1 + 2 k2 + 2 k3 + k4)``.
    """

    def f(tt: float, s: FloatArray) -> FloatArray:
        v, w = twist_fn(tt)
        lr = None if locked_steer_rate_fn is None else locked_steer_rate_fn(tt)
        return state_derivative(arrays, s, v, w, free, lr)

    k1 = f(t, state)
    k2 = f(t + 0.5 * dt, state + 0.5 * dt * k1)
    k3 = f(t + 0.5 * dt, state + 0.5 * dt * k2)
    k4 = f(t + dt, state + dt * k3)
    return state + (dt / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


# --------------------------------------------------------------------------- closed forms


def _log_cosh(y: FloatArray) -> FloatArray:
    """``ln cosh y`` without overflow: ``|y| + log1p(exp(-2|y|)) - ln 2``."""
    a = np.abs(y)
    return np.asarray(a + np.log1p(np.exp(-2.0 * a)) - np.log(2.0), dtype=float)


def trailing_about_pivot(
    P_s: ArrayLike,
    b: ArrayLike,
    r: ArrayLike,
    pivot: ArrayLike,
    theta0: ArrayLike,
    phi: ArrayLike,
) -> tuple[FloatArray, FloatArray]:
    """Exact free-caster motion while the body rotates by ``phi`` about the body point ``pivot``.

    Arguments broadcast: ``P_s``/``pivot`` (..., 2), ``b``, ``r``, ``theta0`` (true steering
    at ``phi = 0``) and ``phi`` (...).  Returns ``(theta, dpsi)``: the true steering angle
    (wrapped to (-pi, pi]) and the wheel rotation since ``phi = 0``; see the module
    docstring for the equations.  Requires ``|P_s - pivot| > b``.
    """
    q = np.asarray(P_s, dtype=float) - np.asarray(pivot, dtype=float)
    bb = np.asarray(b, dtype=float)
    rr = np.asarray(r, dtype=float)
    dist = np.hypot(q[..., 0], q[..., 1])
    alpha = np.arctan2(q[..., 1], q[..., 0])
    rho = dist / bb
    if np.any(rho <= 1.0):
        raise ValueError("trailing_about_pivot: pivot within the caster offset of a steering axis")
    k = np.sqrt((rho + 1.0) / (rho - 1.0))
    lam = 0.5 * np.sqrt(rho * rho - 1.0)
    h = 0.5 * (np.asarray(theta0, dtype=float) - alpha)
    sh, ch = np.sin(h), np.cos(h)
    y = lam * np.asarray(phi, dtype=float)
    T = np.tanh(y)
    s1 = k * (sh - k * ch * T)
    c1 = k * ch - sh * T
    x = 2.0 * np.arctan2(s1, c1)
    theta = np.pi - np.mod(np.pi - (alpha + x), 2.0 * np.pi)
    dpsi = (bb / rr) * (2.0 * np.log(k) - 2.0 * _log_cosh(y) - np.log(s1 * s1 + c1 * c1))
    return np.asarray(theta, dtype=float), np.asarray(dpsi, dtype=float)


def settled_trailing(
    P_s: ArrayLike, b: ArrayLike, pivot: ArrayLike, omega_sign: ArrayLike
) -> tuple[FloatArray, FloatArray]:
    """Settled true steering of free casters spinning about ``pivot``, and their distance ``D``.

    The settled caster satisfies ``(P_w - pivot) . u(theta) = 0`` on the stable side
    (``omega sin x < 0``, ``x = theta - alpha``)::

        cos x* = -b / |q|,  sin x* = -sign(omega) sqrt(1 - b^2/|q|^2),  D = sqrt(|q|^2 - b^2)

    with ``q = P_s - pivot = |q| (cos alpha, sin alpha)``.  Returns ``(theta*, D)`` with
    ``theta*`` wrapped to (-pi, pi]; a settled wheel turns by ``r dpsi = -D |d yaw|``.
    """
    q = np.asarray(P_s, dtype=float) - np.asarray(pivot, dtype=float)
    bb = np.asarray(b, dtype=float)
    dist = np.hypot(q[..., 0], q[..., 1])
    alpha = np.arctan2(q[..., 1], q[..., 0])
    sgn = np.where(np.asarray(omega_sign, dtype=float) < 0.0, -1.0, 1.0)
    D = np.sqrt(np.maximum(dist * dist - bb * bb, 0.0))
    x = np.arctan2(-sgn * D, -bb)
    theta = np.pi - np.mod(np.pi - (alpha + x), 2.0 * np.pi)
    return np.asarray(theta, dtype=float), np.asarray(D, dtype=float)


# --------------------------------------------------------------------------- profiles


def smooth_step(u: ArrayLike) -> FloatArray:
    """Raised-cosine step ``s(u) = (1 - cos(pi u)) / 2`` on [0, 1] (clipped outside).

    ``s(0) = 0``, ``s(1) = 1``, ``s'(0) = s'(1) = 0``.
    """
    uu = np.clip(np.asarray(u, dtype=float), 0.0, 1.0)
    return np.asarray(0.5 * (1.0 - np.cos(np.pi * uu)), dtype=float)


def spin_angle(tau: ArrayLike, omega: float, ramp: float, steady: float) -> FloatArray:
    """Body rotation ``phi(tau)`` of a spin: raised-cosine ramp up, steady ``omega``, ramp down.

    Yaw rate ``omega s(tau/ramp)`` for ``tau < ramp``, ``omega`` for ``steady`` seconds,
    then ``omega (1 - s(tau_d/ramp))``.  Integrals::

        up:     phi = omega (tau/2 - ramp/(2 pi) sin(pi tau/ramp))
        steady: phi = omega (ramp/2 + tau - ramp)
        down:   phi = omega (ramp/2 + steady + tau_d/2 + ramp/(2 pi) sin(pi tau_d/ramp))

    with ``tau_d = tau - ramp - steady``; total ``omega (ramp + steady)``.
    """
    t = np.clip(np.asarray(tau, dtype=float), 0.0, 2.0 * ramp + steady)
    k = ramp / (2.0 * np.pi)
    up = omega * (0.5 * t - k * np.sin(np.pi * t / ramp)) if ramp > 0 else 0.0 * t
    mid = omega * (0.5 * ramp + (t - ramp))
    td = t - ramp - steady
    down = (
        omega * (0.5 * ramp + steady + 0.5 * td + k * np.sin(np.pi * td / ramp))
        if ramp > 0
        else omega * (steady + 0.0 * t)
    )
    out = np.where(t < ramp, up, np.where(t < ramp + steady, mid, down))
    return np.asarray(out, dtype=float)
