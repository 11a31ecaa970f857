"""The joint least-squares problem: three residual blocks over all modules' parameters.

For every segment s (spin about the locked module k at reported steering ``a_s``) the
model's contact point is ``C_s(X) = P_s,k + b_k u(a_s + beta_k)``
(:func:`swpc_hw.robot.model.contact_point`).  The blocks:

**fixed point** (one 2-vector per segment)
    ``W_s (C_s(X) - C_hat_s)``: the stage-1 fixed point, weighted by the inverse of its
    variance (white-noise variance of the segment times the run's median inflation for
    correlated noise; see :mod:`swpc_hw.calibration.fixed_point`).
**settled caster** (one per segment and dynamic module j)
    ``((P_s,j - C_s) . u(theta_hat_j + beta_j) + b_j) / sigma``: the caster's contact
    point lies on the perpendicular through the pivot
    (:func:`swpc_hw.calibration.geometry.settled_residual`).
**rolling** (one per node of a clean run)
    ``(r_j psi_j - G_j - c_run) / sigma_node`` (:mod:`swpc_hw.calibration.rolling`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from swpc_hw.calibration import geometry as geo
from swpc_hw.calibration.parameters import BETA, P_S, as_matrix
from swpc_hw.calibration.parameters import B as B_COL
from swpc_hw.calibration.rolling import RollingSeries, cumulative_rolling_residuals
from swpc_hw.robot.model import contact_point

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass
class FixedPointObservations:
    """Stage-1 fixed points: locked module index and angle, ``C_hat`` (S, 2).

    ``whiten`` (S, 2, 2): the weights, ``W^T W`` = the inverse of a smooth model of the
    covariance (each segment's white-noise variance times the run's median inflation:
    stable weights); ``covariance`` (S, 2, 2): each fixed point's own HAC covariance,
    for the uncertainty of the result.
    """

    static: IntArray
    angle: FloatArray
    C_hat: FloatArray
    whiten: FloatArray
    covariance: FloatArray


@dataclass
class SettledObservations:
    """Settled steering of every (segment, dynamic module): ``theta`` (reported), ``sigma`` (m)."""

    seg: IntArray
    mod: IntArray
    theta: FloatArray
    sigma: FloatArray


@dataclass
class JointProblem:
    """All observations of a run; residual blocks as functions of the flat parameters."""

    n: int
    fixed: FixedPointObservations
    settled: SettledObservations
    rolling: RollingSeries

    def contact_points(self, X: FloatArray) -> FloatArray:
        """``C_s = P_s,k + b_k u(a_s + beta_k)`` of every segment, (S, 2)."""
        k = self.fixed.static
        return contact_point(X[k, P_S], X[k, B_COL], self.fixed.angle + X[k, BETA])

    def fixed_point_block(self, X: FloatArray) -> FloatArray:
        """Raw residuals ``C_s(X) - C_hat_s`` (S, 2) (m)."""
        return np.asarray(self.contact_points(X) - self.fixed.C_hat, dtype=float)

    def settled_caster_block(self, X: FloatArray, C: FloatArray) -> FloatArray:
        """Raw residuals ``(P_s,j - C_s) . u(theta_hat_j + beta_j) + b_j`` (Q,) (m)."""
        j, s = self.settled.mod, self.settled.seg
        return geo.settled_residual(X[j, P_S], X[j, B_COL], self.settled.theta + X[j, BETA], C[s])

    def rolling_block(self, X: FloatArray, C: FloatArray) -> FloatArray:
        """Raw centred cumulative rolling residuals of the clean nodes (m)."""
        return cumulative_rolling_residuals(X, C, self.rolling)

    def blocks(self, x: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Raw residual blocks: fixed point (S, 2), settled caster (Q,), rolling (clean nodes,)."""
        X = as_matrix(x, self.n)
        C = self.contact_points(X)
        return self.fixed_point_block(X), self.settled_caster_block(X, C), self.rolling_block(X, C)

    def block_sizes(self) -> tuple[int, int, int]:
        """Number of weighted residuals in each block."""
        return 2 * self.fixed.C_hat.shape[0], self.settled.seg.size, int(self.rolling.clean.sum())

    def residuals(self, x: FloatArray) -> FloatArray:
        """All weighted residuals (dimensionless), in block order."""
        A, Bv, Rv = self.blocks(x)
        return np.concatenate(
            [
                np.einsum("sij,sj->si", self.fixed.whiten, A).ravel(),
                Bv / self.settled.sigma,
                Rv / self.rolling.sigma[self.rolling.clean],
            ]
        )
