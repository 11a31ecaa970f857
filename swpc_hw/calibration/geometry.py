"""Closed-form geometry of the calibration experiment (pure functions, batched).

Every function accepts arbitrary leading batch dimensions ``(...)`` so that thousands of
robots can be processed in one numpy call.  Notation (docs/model-and-frames.md): during a spin
about the locked module k the body point ``C_R`` (the contact point, in R) stays at
``C_W`` in the world::

    p_i + R(yaw_i) C_R = C_W                      (fixed point, every pose i)
    C_R = P_s,k + b_k u(a + beta_k)               (contact point of the locked module:
                                                   :func:`swpc_hw.robot.model.contact_point`)
    (P_w,j - C_R) . u(theta_j) = 0                 (settled free caster j)
    r_j dpsi_j = ((P_w,j - C_R) x u(theta_j)) dyaw  (rolling of free caster j)
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from swpc_hw.robot.model import contact_point, cross2, rot, steering_direction, wrap_angle

FloatArray = NDArray[np.float64]


def fixed_point(
    poses: ArrayLike, weights: ArrayLike | None = None
) -> tuple[FloatArray, FloatArray]:
    """Weighted least-squares fixed point of a planar motion.

    Minimises ``sum_i w_i |p_i + R(yaw_i) C_R - C_W|^2`` over ``C_R`` and ``C_W``.
    Eliminating ``C_W = p_bar + R_bar C_R`` (weighted means) leaves
    ``A_i = R_i - R_bar = [[alpha_i, -beta_i], [beta_i, alpha_i]]`` with
    ``alpha_i = cos yaw_i - mean cos``, ``beta_i = sin yaw_i - mean sin`` and
    ``A_i^T A_i = (alpha_i^2 + beta_i^2) I``, so::

        C_R = - sum_i w_i A_i^T (p_i - p_bar) / sum_i w_i (alpha_i^2 + beta_i^2)

    ``poses``: (..., K, 3) rows (x, y, yaw).  Returns ``(C_R, C_W)`` each (..., 2).
    """
    P = np.asarray(poses, dtype=float)
    w = np.ones(P.shape[:-1]) if weights is None else np.asarray(weights, dtype=float)
    sw = w.sum(axis=-1, keepdims=True)
    c, s = np.cos(P[..., 2]), np.sin(P[..., 2])
    alpha = c - (w * c).sum(axis=-1, keepdims=True) / sw
    beta = s - (w * s).sum(axis=-1, keepdims=True) / sw
    e = P[..., :2] - (w[..., None] * P[..., :2]).sum(axis=-2, keepdims=True) / sw[..., None]
    den = (w * (alpha**2 + beta**2)).sum(axis=-1)
    num_x = (w * (alpha * e[..., 0] + beta * e[..., 1])).sum(axis=-1)
    num_y = (w * (-beta * e[..., 0] + alpha * e[..., 1])).sum(axis=-1)
    C_R = -np.stack([num_x, num_y], axis=-1) / den[..., None]
    R = rot(P[..., 2])
    C_W = (w[..., None] * (P[..., :2] + np.einsum("...ij,...j->...i", R, C_R[..., None, :]))).sum(
        axis=-2
    ) / sw
    return C_R, C_W


def fixed_point_information(poses: ArrayLike, weights: ArrayLike | None = None) -> FloatArray:
    """Information (per unit noise variance) of ``C_R`` after profiling out ``C_W``.

    ``I = sum_i w_i (alpha_i^2 + beta_i^2)`` (isotropic: the covariance of ``C_R`` is
    ``sigma^2 / I * identity``).  Shape (...).
    """
    P = np.asarray(poses, dtype=float)
    w = np.ones(P.shape[:-1]) if weights is None else np.asarray(weights, dtype=float)
    sw = w.sum(axis=-1, keepdims=True)
    c, s = np.cos(P[..., 2]), np.sin(P[..., 2])
    alpha = c - (w * c).sum(axis=-1, keepdims=True) / sw
    beta = s - (w * s).sum(axis=-1, keepdims=True) / sw
    return np.asarray((w * (alpha**2 + beta**2)).sum(axis=-1), dtype=float)


def fixed_point_residuals(poses: ArrayLike, C_R: ArrayLike, C_W: ArrayLike) -> FloatArray:
    """Residual vectors ``p_i + R(yaw_i) C_R - C_W``, shape (..., K, 2)."""
    P = np.asarray(poses, dtype=float)
    R = rot(P[..., 2])
    cr = np.asarray(C_R, dtype=float)[..., None, :]
    return np.asarray(
        P[..., :2] + np.einsum("...ij,...j->...i", R, cr) - np.asarray(C_W)[..., None, :],
        dtype=float,
    )


def circle_fit_kasa(points: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Algebraic (Kasa) circle fit: minimise ``sum (x^2 + y^2 + D x + E y + F)^2``.

    Returns ``(center, radius)`` with ``center = (-D/2, -E/2)``,
    ``radius = sqrt(D^2/4 + E^2/4 - F)``.  ``points``: (..., K, 2).
    """
    Q = np.asarray(points, dtype=float)
    mean = Q.mean(axis=-2, keepdims=True)
    X = Q - mean  # centre for conditioning
    A = np.concatenate([X, np.ones((*X.shape[:-1], 1))], axis=-1)
    rhs = -(X**2).sum(axis=-1)
    AtA = np.einsum("...ki,...kj->...ij", A, A)
    Atb = np.einsum("...ki,...k->...i", A, rhs)
    sol = np.linalg.solve(AtA, Atb[..., None])[..., 0]
    center = -0.5 * sol[..., :2] + mean[..., 0, :]
    radius = np.sqrt(np.maximum(0.25 * (sol[..., 0] ** 2 + sol[..., 1] ** 2) - sol[..., 2], 0.0))
    return center, radius


# ----------------------------------------------------------------- the paper's equations


def offset_from_chord(P1: ArrayLike, P2: ArrayLike, dtheta: ArrayLike) -> FloatArray:
    """Eq. (1): ``|P1 P2| = 2 b sin(|dtheta| / 2)``  =>  ``b = |P1 P2| / (2 sin(|dtheta|/2))``."""
    chord = np.linalg.norm(np.asarray(P2, dtype=float) - np.asarray(P1, dtype=float), axis=-1)
    return np.asarray(chord / (2.0 * np.sin(np.abs(np.asarray(dtheta)) / 2.0)), dtype=float)


def chord_to_center_angle(dtheta: ArrayLike) -> FloatArray:
    """Eq. (2): ``phi = sign(dtheta) (pi - |dtheta|) / 2``."""
    d = np.asarray(dtheta, dtype=float)
    return np.asarray(np.sign(d) * (np.pi - np.abs(d)) / 2.0, dtype=float)


def steering_axis_from_chord(
    P1: ArrayLike, P2: ArrayLike, b: ArrayLike, dtheta: ArrayLike
) -> FloatArray:
    """Eq. (3): ``P_s = P1 + b rot(phi) (P2 - P1) / |P1 P2|``."""
    p1 = np.asarray(P1, dtype=float)
    chord = np.asarray(P2, dtype=float) - p1
    unit = chord / np.linalg.norm(chord, axis=-1, keepdims=True)
    R = rot(chord_to_center_angle(dtheta))
    return np.asarray(
        p1 + np.asarray(b)[..., None] * np.einsum("...ij,...j->...i", R, unit), dtype=float
    )


def homing_error(P1: ArrayLike, P_s: ArrayLike, a1: ArrayLike) -> FloatArray:
    """``beta = angle(P1 - P_s) - a1``: the true direction of the wheel at reported angle a1."""
    d = np.asarray(P1, dtype=float) - np.asarray(P_s, dtype=float)
    return wrap_angle(np.arctan2(d[..., 1], d[..., 0]) - np.asarray(a1))


def rolling_distance_perpendicular(
    P_s_dyn: ArrayLike, b_dyn: ArrayLike, C: ArrayLike
) -> FloatArray:
    """Distance D from the pivot C to a settled caster's contact point (paper, Fig. 7).

    The settled wheel satisfies ``(P_w - C) . (P_w - P_s) = 0`` (right angle at P_w), so
    ``D = sqrt(|P_s - C|^2 - b^2)``.
    """
    d2 = np.sum((np.asarray(P_s_dyn, dtype=float) - np.asarray(C, dtype=float)) ** 2, axis=-1)
    return np.asarray(np.sqrt(np.maximum(d2 - np.asarray(b_dyn) ** 2, 0.0)), dtype=float)


def radius_from_rotation(D: ArrayLike, dpsi: ArrayLike, dyaw: ArrayLike) -> FloatArray:
    """Eq. (4): ``r dpsi = D dyaw``  =>  ``r = D |dyaw| / |dpsi|``."""
    return np.asarray(
        np.asarray(D, dtype=float) * np.abs(np.asarray(dyaw)) / np.abs(np.asarray(dpsi)),
        dtype=float,
    )


# ------------------------------------------------------- generalisation to M >= 2 angles


def steering_circle_fit(
    points: ArrayLike, angles: ArrayLike, weights: ArrayLike | None = None
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Steering axis, offset and homing error from M >= 2 fixed points, in closed form.

    With ``u(a + beta) = R(a) u(beta)`` the fixed points are linear in ``P_s`` and
    ``w = b u(beta)``::

        P_m = P_s + R(a_m) w          m = 1..M

    Weighted linear least squares gives ``(P_s, w)``; then ``b = |w|``,
    ``beta = atan2(w_y, w_x)``.  For M = 2 this is exactly eq. (1)-(3).
    ``points``: (..., M, 2); ``angles``: (..., M).  Returns ``(P_s, b, beta)``.
    """
    Pm = np.asarray(points, dtype=float)
    a = np.asarray(angles, dtype=float)
    w = np.ones(a.shape) if weights is None else np.asarray(weights, dtype=float)
    Ra = rot(a)  # (..., M, 2, 2)
    eye = np.broadcast_to(np.eye(2), Ra.shape)
    A = np.concatenate([eye, Ra], axis=-1)  # (..., M, 2, 4)
    A = A.reshape((*A.shape[:-3], -1, 4))  # (..., 2M, 4)
    y = Pm.reshape((*Pm.shape[:-2], -1))
    ww = np.repeat(w, 2, axis=-1)
    AtA = np.einsum("...ki,...k,...kj->...ij", A, ww, A)
    Aty = np.einsum("...ki,...k,...k->...i", A, ww, y)
    z = np.linalg.solve(AtA, Aty[..., None])[..., 0]
    P_s = z[..., :2]
    wv = z[..., 2:]
    return P_s, np.linalg.norm(wv, axis=-1), np.arctan2(wv[..., 1], wv[..., 0])


def rolling_lever(P_s: ArrayLike, b: ArrayLike, theta: ArrayLike, C: ArrayLike) -> FloatArray:
    """Signed rolling lever ``g = (P_w - C) x u(theta)``: ``r dpsi = g dyaw``.

    For a settled caster ``|g| = D`` (the paper's distance); the sign is the rolling
    direction.
    """
    P_w = contact_point(P_s, b, theta)
    return cross2(P_w - np.asarray(C, dtype=float), steering_direction(theta))


def settled_angle(P_s: ArrayLike, b: ArrayLike, C: ArrayLike, omega_sign: ArrayLike) -> FloatArray:
    """True steering angle at which a free caster settles while the body spins about ``C``.

    With ``q = P_s - C = |q| (cos alpha, sin alpha)`` the caster trails where
    ``(P_w - C) . u(theta) = 0`` on the stable side, ``omega sin(theta - alpha) < 0``::

        cos x* = -b / |q|,  sin x* = -sign(omega) sqrt(1 - b^2 / |q|^2),  theta* = alpha + x*

    (the generator's physics, :func:`simulators.physics.core.settled_trailing`, by the same
    equations).  Wrapped to (-pi, pi].
    """
    q = np.asarray(P_s, dtype=float) - np.asarray(C, dtype=float)
    bb = np.asarray(b, dtype=float)
    dist = np.hypot(q[..., 0], q[..., 1])
    sgn = np.where(np.asarray(omega_sign, dtype=float) < 0.0, -1.0, 1.0)
    D = np.sqrt(np.maximum(dist * dist - bb * bb, 0.0))
    return wrap_angle(np.arctan2(q[..., 1], q[..., 0]) + np.arctan2(-sgn * D, -bb))


def settled_lever(
    P_s: ArrayLike, b: ArrayLike, C: ArrayLike, omega_sign: ArrayLike
) -> FloatArray:
    """Signed rolling lever of a settled caster: ``g = -sign(omega) sqrt(|P_s - C|^2 - b^2)``.

    The caster trails with a right angle at its contact point, ``(P_w - C) . u = 0``, so
    ``|g| = |P_w - C| = sqrt(|P_s - C|^2 - b^2)``; it rolls backwards
    (``r dpsi = g dyaw < 0`` for ``dyaw > 0``).  Broadcasts; (...).
    """
    d2 = np.sum((np.asarray(P_s) - np.asarray(C)) ** 2, axis=-1) - np.asarray(b) ** 2
    return np.asarray(-np.sign(omega_sign) * np.sqrt(np.maximum(d2, 0.0)), dtype=float)


def settled_residual(P_s: ArrayLike, b: ArrayLike, theta: ArrayLike, C: ArrayLike) -> FloatArray:
    """``(P_w - C) . u(theta) = (P_s - C) . u(theta) + b``: zero for a settled caster."""
    u = steering_direction(theta)
    d = np.asarray(P_s, dtype=float) - np.asarray(C, dtype=float)
    return np.asarray(np.sum(d * u, axis=-1) + np.asarray(b), dtype=float)
