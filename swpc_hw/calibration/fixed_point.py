"""Stage 1 of the joint solver: the fixed point of every spin, its outliers and its covariance.

During a spin about the locked module every pose satisfies ``p_i + R(yaw_i) C_R = C_W``
(:func:`swpc_hw.calibration.geometry.fixed_point`: closed form, linear in ``C_R, C_W``).
Eliminating ``C_W`` leaves ``C_R = -I^-1 sum_i A_i^T (p_i - p_bar)`` with
``A_i = R(yaw_i) - R_bar``, ``A_i^T A_i = a_i identity`` and ``I = sum_i a_i``
(isotropic), so the error of ``C_R`` is ``-I^-1 sum_i s_i`` with the scores
``s_i = A_i^T e_i`` of the residuals ``e_i``.  White noise of std dev ``sigma`` per
coordinate gives ``Cov(C_R) = sigma^2 / I`` (``I`` =
:func:`~swpc_hw.calibration.geometry.fixed_point_information`); correlated noise gives
``Omega / I^2`` with ``Omega`` the long-run covariance of the scores
(:func:`swpc_hw.calibration.uncertainty.long_run_covariance`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from swpc_hw.calibration import geometry as geo
from swpc_hw.calibration.uncertainty import dense_rows, grid_index, long_run_covariance
from swpc_hw.robot.model import rot

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

SIGMA_FLOOR = 1e-9
"""Smallest noise std dev (m) a fixed point is credited with (noise-free simulations)."""


@dataclass(frozen=True)
class FixedPointFit:
    """The fixed point of one spin and what is known about its error.

    ``covariance``: (2, 2) covariance of ``C_R`` (m^2), from the correlation-robust
    sandwich; ``white_variance``: ``sigma^2 / I`` per coordinate, what white noise of the
    residuals' size would give; ``inflation``: the std dev over the white-noise one (1
    for white noise, ~3 for AR(1) noise with rho 0.8); ``sigma``: per-coordinate RMS of the inlier
    residuals (m); ``rho``: lag-1 autocorrelation of the scores (frame to frame);
    ``bandwidth``: Bartlett bandwidth after prewhitening.
    """

    C_R: FloatArray
    C_W: FloatArray
    inliers: BoolArray
    sigma: float
    covariance: FloatArray
    white_variance: float
    inflation: float
    rho: float
    bandwidth: int
    grid: tuple[float, float] = (0.0, 1.0)
    """``(t_0, dt)`` of the pose grid the scores live on."""
    scores: FloatArray = field(default_factory=lambda: np.zeros((0, 2)))
    """(T, 2) scores ``A_i^T e_i / I`` on that grid: ``C_R``'s error is minus their sum."""

    @property
    def std(self) -> float:
        """``sqrt(trace(Cov) / 2)``: the fixed point's std dev per coordinate (m)."""
        return math.sqrt(0.5 * float(np.trace(self.covariance)))

    @property
    def rms(self) -> float:
        """RMS length of the inlier residual vectors ``|p + R C_R - C_W|`` (m)."""
        return self.sigma * math.sqrt(2.0)


def robust_fixed_point(
    poses: FloatArray, outlier_sigmas: float = 4.0, max_iter: int = 20
) -> tuple[FloatArray, FloatArray, BoolArray, float]:
    """Fixed point of one segment with iterative outlier rejection.

    Residual norms of a 2-D Gaussian are Rayleigh distributed: ``sigma = median|e| /
    sqrt(2 ln 2)``; poses with ``|e| > outlier_sigmas * sigma`` are rejected and the
    closed form re-solved until the inlier set is stable.  ``poses``: (K, 3) (x, y, yaw).
    Returns ``(C_R, C_W, inliers, sigma)`` with ``sigma`` the per-coordinate noise of the
    inliers.
    """
    mask = np.ones(poses.shape[0], dtype=bool)
    C_R, C_W = geo.fixed_point(poses)
    for _ in range(max_iter):
        e = np.linalg.norm(geo.fixed_point_residuals(poses, C_R, C_W), axis=-1)
        scale = float(np.median(e[mask])) / math.sqrt(2.0 * math.log(2.0))
        new = e <= max(outlier_sigmas * scale, 1e-12)
        if new.sum() < 5:
            new = np.ones_like(mask)
        if np.array_equal(new, mask):
            break
        mask = new
        C_R, C_W = geo.fixed_point(poses[mask])
    e = geo.fixed_point_residuals(poses[mask], C_R, C_W)
    dof = max(2 * int(mask.sum()) - 4, 1)
    sigma = math.sqrt(float(np.sum(e**2)) / dof)
    return C_R, C_W, mask, sigma


def fixed_point_scores(poses: FloatArray, C_R: FloatArray, C_W: FloatArray) -> FloatArray:
    """Scores ``s_i = A_i^T e_i``, ``A_i = R(yaw_i) - R_bar``, ``e_i = p_i + R_i C_R - C_W``.

    ``poses``: (K, 3) (x, y, yaw).  Returns (K, 2); ``sum_i s_i = 0`` at the solution.
    """
    R_i = rot(poses[:, 2])
    A = R_i - R_i.mean(axis=0)
    e = geo.fixed_point_residuals(poses, C_R, C_W)
    return np.asarray(np.einsum("kji,kj->ki", A, e), dtype=float)


def fit_fixed_point(poses_t: FloatArray, outlier_sigmas: float = 4.0) -> FixedPointFit:
    """Robust fixed point of one spin with its correlation-robust covariance.

    ``poses_t``: (K, 4) rows (t, x, y, yaw unwrapped).  The scores of the inliers are put
    on the regular grid of the pose rate (median time step; dropped and rejected poses
    are zero rows), and ``Cov(C_R) = Omega / I^2`` with ``Omega`` their Bartlett long-run
    covariance and ``I`` the information (module docstring).
    """
    C_R, C_W, mask, sigma = robust_fixed_point(poses_t[:, 1:], outlier_sigmas)
    inl = poses_t[mask]
    info = float(geo.fixed_point_information(inl[:, 1:]))
    dt = float(np.median(np.diff(inl[:, 0]))) if inl.shape[0] > 1 else 1.0
    k = grid_index(inl[:, 0], max(dt, 1e-9))
    scores = dense_rows(k, fixed_point_scores(inl[:, 1:], C_R, C_W))
    present = np.zeros(scores.shape[0], dtype=bool)
    present[k] = True
    omega, rho, L = long_run_covariance(scores, present)
    dof_factor = 2.0 * mask.sum() / max(2.0 * mask.sum() - 4.0, 1.0)
    floor = SIGMA_FLOOR**2 / max(info, 1e-30)
    cov = omega * dof_factor / max(info, 1e-30) ** 2 + floor * np.eye(2)
    white = max(sigma, SIGMA_FLOOR) ** 2 / max(info, 1e-30)
    inflation = math.sqrt(0.5 * float(np.trace(cov)) / white)
    grid = (float(inl[0, 0]), max(dt, 1e-9))
    per_pose = scores / max(info, 1e-30)
    return FixedPointFit(C_R, C_W, mask, sigma, cov, white, inflation, rho, L, grid, per_pose)
