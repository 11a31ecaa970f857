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
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from swpc_hw.calibration.fixed_point import FixedPointFit
from swpc_hw.calibration.problem import JointProblem
from swpc_hw.calibration.uncertainty import (
    bartlett_smooth,
    dense_rows,
    long_run_covariance,
    sandwich_covariance,
)

FloatArray = NDArray[np.float64]


def fixed_point_long_run(prob: JointProblem, J_A: FloatArray) -> list[FloatArray]:
    """``M`` of the fixed-point block per segment: ``J_s^T W_s Cov_s W_s^T J_s``.

    ``J_s``: the segment's two weighted rows, ``Cov_s`` its HAC covariance
    (:func:`~swpc_hw.calibration.fixed_point.fit_fixed_point`).
    """
    fx = prob.fixed
    out = []
    for s in range(fx.C_hat.shape[0]):
        Js = J_A[2 * s : 2 * s + 2]
        out.append(Js.T @ (fx.whiten[s] @ fx.covariance[s] @ fx.whiten[s].T) @ Js)
    return out


def rolling_long_run(prob: JointProblem, J_C: FloatArray, f_C: FloatArray) -> list[FloatArray]:
    """``M`` of the rolling block per segment: HAC long-run covariance of its scores.

    The scores ``J_l^T f_l`` of all modules at one pose node are summed (they share its
    yaw noise); the sequence over the nodes of a segment gets the prewhitened Bartlett
    estimate (:func:`~swpc_hw.calibration.uncertainty.long_run_covariance`).  A segment
    without clean nodes: zeros.
    """
    series = prob.rolling
    clean = series.clean
    bins, seg = series.bin[clean], series.seg[clean]
    scores = J_C * f_C[:, None]
    p = J_C.shape[1]
    out = []
    for s in range(prob.fixed.C_hat.shape[0]):
        sel = seg == s
        if not sel.any():
            out.append(np.zeros((p, p)))
            continue
        k = bins[sel] - int(bins[sel].min())
        S = dense_rows(k, scores[sel])
        present = np.zeros(S.shape[0], dtype=bool)
        present[k] = True
        out.append(long_run_covariance(S, present)[0])
    return out


def cross_long_run(
    prob: JointProblem, J_A: FloatArray, J_C: FloatArray, f_C: FloatArray,
    fits: list[FixedPointFit],
) -> list[FloatArray]:
    """``M_AC + M_AC^T`` per segment: the fixed-point and rolling blocks share the poses'
    noise.

    Per segment, on its pose grid: the fixed-point block's per-pose scores
    ``q_i = J_s^T W_s s_i / I`` (``s_i`` of :func:`~.fixed_point.fit_fixed_point`) and the
    rolling scores ``c_l = J_l^T f_l`` at their nodes' grid index;
    ``M_AC = sum_{|k| <= L} (1 - |k| / (L + 1)) sum_t q_t c_t+k^T`` with ``L`` six
    integrated autocorrelation times of AR(1) scores (``rho`` of the fit) plus the
    nodes' half width.
    """
    fx, series = prob.fixed, prob.rolling
    p = J_A.shape[1]
    out = []
    clean = series.clean
    seg_c, t_c = series.seg[clean], series.t[clean]
    c_scores = J_C * f_C[:, None]
    for s, fit in enumerate(fits):
        sel = seg_c == s
        if not sel.any() or fit.scores.shape[0] == 0:
            out.append(np.zeros((p, p)))
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
        out.append(cross + cross.T)
    return out


@dataclass(frozen=True)
class SegmentTerms:
    """One segment's share of ``H = J^T J`` and ``M`` (both sums over the segments).

    ``fixed_rows`` (2, p): its weighted fixed-point rows (``H`` += ``rows^T rows``,
    ``M`` += ``fixed_m``); ``settled_h``: ``J_B,s^T J_B,s`` of its settled-caster rows
    (their ``M`` too: independent residuals); ``rolling_h``: ``J_C,s^T J_C,s`` of its
    clean rolling rows; ``rolling_m``: their long-run covariance plus the fixed point x
    rolling cross term.
    """

    fixed_rows: FloatArray
    fixed_m: FloatArray
    settled_h: FloatArray
    rolling_h: FloatArray
    rolling_m: FloatArray

    @property
    def h(self) -> FloatArray:
        return np.asarray(self.fixed_rows.T @ self.fixed_rows + self.settled_h + self.rolling_h)

    @property
    def m(self) -> FloatArray:
        return np.asarray(self.fixed_m + self.settled_h + self.rolling_m)


def segment_terms(
    prob: JointProblem, x: FloatArray, fits: list[FixedPointFit]
) -> tuple[FloatArray, FloatArray, list[SegmentTerms]]:
    """``(J, f, terms)``: the weighted residuals' Jacobian and values at ``x`` and every
    segment's share of ``H`` and ``M`` (:class:`SegmentTerms`)."""
    J = prob.jacobian(x)
    f = prob.residuals(x)
    nA, nB, _ = prob.block_sizes()
    J_A, J_B, J_C = J[:nA], J[nA : nA + nB], J[nA + nB :]
    f_C = f[nA + nB :]
    fixed = fixed_point_long_run(prob, J_A)
    rolling = rolling_long_run(prob, J_C, f_C)
    cross = cross_long_run(prob, J_A, J_C, f_C, fits)
    seg_b = prob.settled.seg
    seg_c = prob.rolling.seg[prob.rolling.clean]
    terms = [
        SegmentTerms(
            fixed_rows=J_A[2 * s : 2 * s + 2],
            fixed_m=fixed[s],
            settled_h=J_B[seg_b == s].T @ J_B[seg_b == s],
            rolling_h=J_C[seg_c == s].T @ J_C[seg_c == s],
            rolling_m=rolling[s] + cross[s],
        )
        for s in range(len(fixed))
    ]
    return J, f, terms


def joint_covariance(
    prob: JointProblem, x: FloatArray, fits: list[FixedPointFit]
) -> tuple[FloatArray, FloatArray]:
    """``(Cov, f)``: the sandwich covariance (5N, 5N) at ``x`` and the weighted residuals."""
    J, f, terms = segment_terms(prob, x, fits)
    M = sum((t.m for t in terms), start=np.zeros((J.shape[1], J.shape[1])))
    return sandwich_covariance(J, M), f
