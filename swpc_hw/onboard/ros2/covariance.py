"""Covariances of the odometry's pose and twist, for ``nav_msgs/msg/Odometry``.

Two sources, kept apart because they behave differently over time:

1. **Wheel readings (white, per step).**  Each module's encoder velocity ``g_i`` is taken as
   isotropic noise of standard deviation ``sigma / sqrt(w_i)``: ``sigma`` is the
   odometry's residual scale of that step (``scale_abs + scale_rel * rms|g|``,
   :class:`~swpc_hw.onboard.odometry.OdometryOptions`) and ``w_i`` its slip weight (IRLS, 1 =
   trusted, -> 0 = slipping).  The weighted least-squares twist then has::

       Sigma_meas = sigma^2 (A^T W A)^-1,   A_i = [[1, 0, -Q_y,i], [0, 1, Q_x,i]],  W = diag(w_i)

   (``Q_i``: the wheel's effective contact point of the step).  A slipping wheel adds no
   information, so the twist's covariance grows while it slips.

2. **Calibration (systematic).**  The kinematic file's parameter covariance ``Sigma_p``
   (``covariance``, else the ``stddev``s squared, else none) through the twist's sensitivity
   ``J = d twist / d p`` (3 x 5N, forward differences through the odometry's own weighted
   step, at its slip weights)::

       Sigma_twist = Sigma_meas + J Sigma_p J^T

Pose (world frame ``odom``, first order).  Over a step of length ``h`` from yaw ``psi_0``
with world displacement ``(dx, dy)`` and mid-step heading ``psi_m``::

    F = [[1, 0, -dy], [0, 1, dx], [0, 0, 1]],   G = [[R(psi_m), 0], [0, 1]]
    P <- F P F^T + h^2 G Sigma_meas G^T        (white part, accumulates as a random walk)
    S <- F S + h G J                           (3 x 5N: pose sensitivity to the parameters)
    Sigma_pose = P + S Sigma_p S^T

A calibration error is the same at every step, so its pose error grows with the distance,
not its square root: ``S`` carries it exactly to first order.  When a new kinematic file is
installed, the part accumulated so far is frozen into ``P`` (``P += S Sigma_p S^T``) and
``S`` restarts at zero.

Not modelled (and not claimed): wheel-ground contact beyond the slip weights, the time
delay between modules, and motion out of the floor plane.  z, roll and pitch (pose) and
v_z, omega_x, omega_y (twist) are not estimated: their variances are
:data:`UNESTIMATED_VARIANCE`, their covariances 0.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

# The odometry's own step (same package layer): the contact points and the weighted solve.
from swpc_hw.onboard.odometry import (
    OdometryError,
    Row,
    _contact_velocities,
    geometry_row,
)
from swpc_hw.robot.model import PARAM_NAMES

FloatArray = NDArray[np.float64]

UNESTIMATED_VARIANCE = 1.0e6
"""Variance of the components a planar odometry does not estimate (ROS convention: large)."""

PLANAR = (0, 1, 5)
"""Indices of x, y, yaw (pose) and v_x, v_y, omega_z (twist) in ROS's 6 x 6 covariances."""

_MIN_WEIGHT = 1e-6
_PARAMS = len(PARAM_NAMES)  # x_s, y_s, beta, b, r (the kinematic file's order)


def measurement_covariance(
    qx: Sequence[float], qy: Sequence[float], weights: Sequence[float], sigma: float
) -> FloatArray:
    """``Sigma_meas = sigma^2 (A^T W A)^-1`` of the twist (module docstring), 3 x 3.

    ``A^T W A = sum w_i [[1, 0, -Q_y], [0, 1, Q_x], [-Q_y, Q_x, |Q|^2]]`` summed in plain
    floats."""
    W = X = Y = S = 0.0
    for x, y, w in zip(qx, qy, weights, strict=True):
        w = max(float(w), _MIN_WEIGHT)
        W += w
        X += w * x
        Y += w * -y
        S += w * (y * y + x * x)
    N = np.array([[W, 0.0, Y], [0.0, W, X], [Y, X, S]])
    return np.asarray(sigma * sigma * np.linalg.inv(N), dtype=np.float64)


def twist_sensitivity(
    rows: Sequence[Row],
    dt: float,
    theta_hat0: Sequence[float],
    theta_hat1: Sequence[float],
    psi0: Sequence[float],
    psi1: Sequence[float],
    weights: Sequence[float],
) -> FloatArray:
    """``J = d twist / d p`` (3 x 5N; p = modules in order, each x_s, y_s, beta, b, r) of
    the weighted step at fixed weights, by forward differences (step 1e-7 in SI units).

    A parameter of module i moves only that module's contact point and velocity: each
    difference computes those again and solves the weighted twist
    (:func:`~swpc_hw.onboard.odometry._weighted_twist`'s sums and closed form) from the
    sums over modules 0..i-1, unchanged, with module i's new terms and then the others'
    added in the same order: the same floats as solving it all again."""
    n = len(rows)
    qx, qy, gx, gy, _ = _contact_velocities(rows, dt, theta_hat0, theta_hat1, psi0, psi1)
    terms = [_terms(weights[i], qx[i], qy[i], gx[i], gy[i]) for i in range(n)]
    prefix = [(0.0,) * 7]
    for t in terms:
        prefix.append(_add(prefix[-1], t))
    base = np.array(_solve(prefix[n]))
    twists: list[tuple[float, float, float]] = []
    eps = 1e-7
    for i, row in enumerate(rows):
        th0, th1, ps0, ps1 = (theta_hat0[i],), (theta_hat1[i],), (psi0[i],), (psi1[i],)
        for k in range(_PARAMS):
            p = list(row[:_PARAMS])
            p[k] += eps
            (qxi,), (qyi,), (gxi,), (gyi,), _ = _contact_velocities(
                (geometry_row(*p),), dt, th0, th1, ps0, ps1)
            acc = _add(prefix[i], _terms(weights[i], qxi, qyi, gxi, gyi))
            for t in terms[i + 1:]:
                acc = _add(acc, t)
            twists.append(_solve(acc))
    J = np.zeros((3, _PARAMS * n))
    if twists:
        J[:] = (np.array(twists).T - base[:, None]) / eps
    return J


_Sums = tuple[float, float, float, float, float, float, float]


def _terms(w: float, qx: float, qy: float, gx: float, gy: float) -> _Sums:
    """One module's terms of ``W, X, Y, S, G_x, G_y, T`` (odometry module docstring)."""
    return (w, w * qx, w * qy, w * (qx * qx + qy * qy), w * gx, w * gy,
            w * (qx * gy - qy * gx))  # fmt: skip


def _add(a: _Sums, b: _Sums) -> _Sums:
    return (a[0] + b[0], a[1] + b[1], a[2] + b[2], a[3] + b[3], a[4] + b[4], a[5] + b[5],
            a[6] + b[6])  # fmt: skip


def _solve(sums: _Sums) -> tuple[float, float, float]:
    """The weighted twist from its sums (as
    :func:`~swpc_hw.onboard.odometry._weighted_twist`)."""
    W, X, Y, S, Gx, Gy, T = sums
    D = S - (X * X + Y * Y) / W
    if not D > 1e-12 * S:
        raise OdometryError("odometry: the weighted contact points are degenerate")
    om = (T + (Y * Gx - X * Gy) / W) / D
    return (Gx + om * Y) / W, (Gy - om * X) / W, om


def contact_points(
    rows: Sequence[Row],
    dt: float,
    theta_hat0: Sequence[float],
    theta_hat1: Sequence[float],
    psi0: Sequence[float],
    psi1: Sequence[float],
) -> tuple[list[float], list[float]]:
    """Each wheel's effective contact point ``Q_i`` of the step (swpc_hw.onboard.odometry)."""
    qx, qy, _, _, _ = _contact_velocities(rows, dt, theta_hat0, theta_hat1, psi0, psi1)
    return qx, qy


def ros_covariance(planar: FloatArray) -> list[float]:
    """A 3 x 3 (x, y, yaw) covariance as ROS's row-major 6 x 6 (x, y, z, rx, ry, rz)."""
    out = np.zeros((6, 6))
    for k in (2, 3, 4):
        out[k, k] = UNESTIMATED_VARIANCE
    for a, ia in enumerate(PLANAR):
        for b, ib in enumerate(PLANAR):
            out[ia, ib] = planar[a, b]
    return [float(v) for v in out.ravel()]


class OdometryCovariance:
    """The pose and twist covariances of a running odometry (module docstring)."""

    def __init__(self, parameter_covariance: FloatArray) -> None:
        self._sp = np.asarray(parameter_covariance, dtype=np.float64)
        n = self._sp.shape[0]
        self._P = np.zeros((3, 3))
        self._S = np.zeros((3, n))
        self.twist = np.zeros((3, 3))

    @property
    def pose(self) -> FloatArray:
        """``Sigma_pose = P + S Sigma_p S^T`` (x, y, yaw in ``odom``), 3 x 3."""
        return np.asarray(self._P + self._S @ self._sp @ self._S.T, dtype=np.float64)

    def set_parameter_covariance(self, parameter_covariance: FloatArray) -> None:
        """A new kinematic file: freeze the systematic part so far into ``P``, restart ``S``."""
        sp = np.asarray(parameter_covariance, dtype=np.float64)
        self._P = self.pose
        self._sp = sp
        self._S = np.zeros((3, sp.shape[0]))

    def step(
        self,
        pose0: tuple[float, float, float],
        pose1: tuple[float, float, float],
        dt: float,
        meas: FloatArray,
        J: FloatArray,
    ) -> None:
        """Propagate over one odometry step (twist parts ``meas`` = Sigma_meas and ``J``)."""
        x0, y0, yaw0 = pose0
        x1, y1, yaw1 = pose1
        F = np.array([[1.0, 0.0, -(y1 - y0)], [0.0, 1.0, x1 - x0], [0.0, 0.0, 1.0]])
        m = 0.5 * (yaw0 + yaw1)
        c, s = math.cos(m), math.sin(m)
        G = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        self._P = F @ self._P @ F.T + dt * dt * (G @ meas @ G.T)
        self._S = F @ self._S + dt * (G @ J)
        self.twist = meas + J @ self._sp @ J.T


def parameter_covariance(
    n_modules: int,
    covariance: ArrayLike | None,
    stddevs: Sequence[Sequence[float] | None],
) -> FloatArray:
    """``Sigma_p`` (5N x 5N) of a kinematic file: its ``covariance``, else the ``stddev``s
    squared on the diagonal (modules without stddev: 0), else zeros."""
    if covariance is not None:
        return np.asarray(covariance, dtype=np.float64).reshape(_PARAMS * n_modules,
                                                                _PARAMS * n_modules)
    d = np.zeros(_PARAMS * n_modules)
    for i, sd in enumerate(stddevs):
        if sd is not None:
            d[_PARAMS * i:_PARAMS * (i + 1)] = np.square(np.asarray(sd, dtype=np.float64))
    return np.diag(d)


__all__ = [
    "PLANAR",
    "UNESTIMATED_VARIANCE",
    "OdometryCovariance",
    "contact_points",
    "measurement_covariance",
    "parameter_covariance",
    "ros_covariance",
    "twist_sensitivity",
]
