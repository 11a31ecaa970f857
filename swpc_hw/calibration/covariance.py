"""The covariance of the joint solution: a sandwich whose middle holds correlated noise.

``Cov = H^-1 M H^-1`` (:func:`~swpc_hw.calibration.uncertainty.sandwich_covariance`) with
``H = J^T J`` of the weighted residuals of :class:`~swpc_hw.calibration.problem.JointProblem`
and ``M = Var(J^T f)`` assembled block by block:

* **fixed point**: each segment's HAC covariance of its fixed point
  (:func:`fixed_point_long_run`);
* **settled caster**: independent residuals, ``J_B^T J_B``;
* **rolling**: the HAC long-run covariance of the scores over each segment's pose nodes,
  the modules at one node summed (they share its yaw noise) (:func:`rolling_long_run`);
* **fixed point x rolling**: both use the same poses (:func:`cross_long_run`).

The reasoning and the measured coverage: ``docs/solver-uncertainty.md``.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from swpc_hw.calibration.fixed_point import FixedPointFit
from swpc_hw.calibration.problem import JointProblem
from swpc_hw.calibration.uncertainty import (
    bartlett_smooth,
    dense_rows,
    long_run_covariance,
    numeric_jacobian,
    sandwich_covariance,
)

FloatArray = NDArray[np.float64]


def fixed_point_long_run(prob: JointProblem, J_A: FloatArray) -> FloatArray:
    """``M`` of the fixed-point block: ``sum_s J_s^T W_s Cov_s W_s^T J_s``.

    ``J_s``: the segment's two weighted rows, ``Cov_s`` its HAC covariance
    (:func:`~swpc_hw.calibration.fixed_point.fit_fixed_point`).
    """
    fx = prob.fixed
    M = np.zeros((J_A.shape[1], J_A.shape[1]))
    for s in range(fx.C_hat.shape[0]):
        Js = J_A[2 * s : 2 * s + 2]
        M += Js.T @ (fx.whiten[s] @ fx.covariance[s] @ fx.whiten[s].T) @ Js
    return M


def rolling_long_run(prob: JointProblem, J_C: FloatArray, f_C: FloatArray) -> FloatArray:
    """``M`` of the rolling block: HAC long-run covariance of its scores, per segment.

    The scores ``J_l^T f_l`` of all modules at one pose node are summed (they share its
    yaw noise); the sequence over the nodes of a segment gets the prewhitened Bartlett
    estimate (:func:`~swpc_hw.calibration.uncertainty.long_run_covariance`).
    """
    series = prob.rolling
    clean = series.clean
    bins, seg = series.bin[clean], series.seg[clean]
    scores = J_C * f_C[:, None]
    M = np.zeros((J_C.shape[1], J_C.shape[1]))
    for s in np.unique(seg):
        sel = seg == s
        k = bins[sel] - int(bins[sel].min())
        S = dense_rows(k, scores[sel])
        present = np.zeros(S.shape[0], dtype=bool)
        present[k] = True
        M += long_run_covariance(S, present)[0]
    return M


def cross_long_run(
    prob: JointProblem, J_A: FloatArray, J_C: FloatArray, f_C: FloatArray,
    fits: list[FixedPointFit],
) -> FloatArray:
    """``M_AC + M_AC^T``: the fixed-point and rolling blocks share the poses' noise.

    Per segment, on its pose grid: the fixed-point block's per-pose scores
    ``q_i = J_s^T W_s s_i / I`` (``s_i`` of :func:`~.fixed_point.fit_fixed_point`) and the
    rolling scores ``c_l = J_l^T f_l`` at their nodes' grid index;
    ``M_AC = sum_{|k| <= L} (1 - |k| / (L + 1)) sum_t q_t c_t+k^T`` with ``L`` six
    integrated autocorrelation times of AR(1) scores (``rho`` of the fit) plus the
    nodes' half width.
    """
    fx, series = prob.fixed, prob.rolling
    p = J_A.shape[1]
    M = np.zeros((p, p))
    clean = series.clean
    seg_c, t_c = series.seg[clean], series.t[clean]
    c_scores = J_C * f_C[:, None]
    for s, fit in enumerate(fits):
        sel = seg_c == s
        if not sel.any() or fit.scores.shape[0] == 0:
            continue
        Js = J_A[2 * s : 2 * s + 2]
        Q = fit.scores @ (Js.T @ fx.whiten[s]).T  # (T, p): per pose J_s^T W_s s_i / I
        t0, dt = fit.grid
        k = np.rint((t_c[sel] - t0) / dt).astype(np.int64)
        inside = (k >= 0) & (k < Q.shape[0])
        Cq = np.zeros_like(Q)
        np.add.at(Cq, k[inside], c_scores[sel][inside])
        rho = min(max(fit.rho, 0.0), 0.97)
        L = min(math.ceil(6.0 * (1.0 + rho) / (1.0 - rho)) + 3, Q.shape[0] - 1)
        cross = bartlett_smooth(Q, L).T @ Cq
        M += cross + cross.T
    return M


def joint_covariance(
    prob: JointProblem, x: FloatArray, fits: list[FixedPointFit]
) -> tuple[FloatArray, FloatArray]:
    """``(Cov, f)``: the sandwich covariance (5N, 5N) at ``x`` and the weighted residuals."""
    J = numeric_jacobian(prob.residuals, x)
    f = prob.residuals(x)
    nA, nB, _ = prob.block_sizes()
    J_A, J_B, J_C = J[:nA], J[nA : nA + nB], J[nA + nB :]
    f_C = f[nA + nB :]
    M = (
        fixed_point_long_run(prob, J_A)
        + J_B.T @ J_B
        + rolling_long_run(prob, J_C, f_C)
        + cross_long_run(prob, J_A, J_C, f_C, fits)
    )
    return sandwich_covariance(J, M), f
