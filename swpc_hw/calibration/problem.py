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

The Jacobian is analytic (:meth:`JointProblem.jacobian`), with ``u(phi) = (cos phi, sin
phi)``, ``v(phi) = u'(phi) = (-sin phi, cos phi)`` and ``a x b = a_x b_y - a_y b_x``:

* contact point, ``phi_s = a_s + beta_k``: ``dC_s/dP_k = I``, ``dC_s/dbeta_k = b_k
  v(phi_s)``, ``dC_s/db_k = u(phi_s)``;
* settled caster, ``psi = theta_hat + beta_j``, ``d = P_j - C_s``: ``de/dP_j = u(psi)``,
  ``de/dbeta_j = d . v(psi)``, ``de/db_j = 1``, ``de/dC_s = -u(psi)``;
* rolling lever ``g = (P_w,j - C_s) x u(psi) = d x u(psi)`` (``b_j u x u = 0``):
  ``dg/dP_j = (u_y, -u_x)``, ``dg/dbeta_j = d . u(psi)``, ``dg/dC_s = (-u_y, u_x)``; the
  node's residual is linear in the levers (the trapezoid sums ``G`` restarted at each
  run, then the run's mean removed), so its derivatives are the same sums of the levers'
  derivatives, plus ``psi`` for ``r_j``.

Every ``C_s`` derivative is chained to the locked module's parameters.  It replaces
finite differences (20 more residual evaluations per Jacobian, the most of a solve's
time) and agrees with them to their own error (``tests/calibration/mocap``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from swpc_hw.calibration import geometry as geo
from swpc_hw.calibration.parameters import BETA, N_PARAMS, P_S, R, as_matrix
from swpc_hw.calibration.parameters import B as B_COL
from swpc_hw.calibration.rolling import (
    RollingSeries,
    centred_cumulative_sums,
    cumulative_rolling_residuals,
)
from swpc_hw.robot.model import contact_point, steering_direction

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

    def contact_point_jacobian(self, X: FloatArray) -> FloatArray:
        """``dC_s / d(x_s, y_s, beta, b, r)`` of the locked module of every segment,
        (S, 2, 5) (module docstring)."""
        k = self.fixed.static
        phi = self.fixed.angle + X[k, BETA]
        u = steering_direction(phi)
        D = np.zeros((k.size, 2, N_PARAMS))
        D[:, 0, 0] = D[:, 1, 1] = 1.0
        D[:, 0, BETA], D[:, 1, BETA] = -X[k, B_COL] * u[:, 1], X[k, B_COL] * u[:, 0]
        D[:, :, B_COL] = u
        return D

    def jacobian(self, x: FloatArray) -> FloatArray:
        """Jacobian of :meth:`residuals` (rows in block order, columns ``x``'s), analytic
        (module docstring)."""
        n = self.n
        X = as_matrix(x, n)
        C = self.contact_points(X)
        dC = self.contact_point_jacobian(X)
        k = self.fixed.static
        cols = np.arange(N_PARAMS)
        nA, nB, nC = self.block_sizes()
        J = np.zeros((nA + nB + nC, N_PARAMS * n))
        # fixed point: W_s dC_s in the locked module's columns
        S = k.size
        JA = np.einsum("sij,sjp->sip", self.fixed.whiten, dC)
        rows = np.arange(2 * S).reshape(S, 2)
        J[rows[:, :, None], (N_PARAMS * k)[:, None, None] + cols] = JA
        # settled caster
        j, s = self.settled.mod, self.settled.seg
        if j.size:
            u = steering_direction(self.settled.theta + X[j, BETA])
            d = X[j, P_S] - C[s]
            own = np.zeros((j.size, N_PARAMS))
            own[:, :2] = u
            own[:, BETA] = d[:, 0] * -u[:, 1] + d[:, 1] * u[:, 0]
            own[:, B_COL] = 1.0
            via_c = -np.einsum("qi,qip->qp", u, dC[s])
            JB = np.zeros((j.size, N_PARAMS * n))
            r = np.arange(j.size)[:, None]
            np.add.at(JB, (r, (N_PARAMS * j)[:, None] + cols), own)
            np.add.at(JB, (r, (N_PARAMS * k[s])[:, None] + cols), via_c)
            J[nA : nA + nB] = JB / self.settled.sigma[:, None]
        # rolling: the levers' derivatives through the same sums as the levers
        ro = self.rolling
        sel = ro.clean
        if nC:
            j, s = ro.mod[sel], ro.seg[sel]
            u = steering_direction(ro.theta[sel] + X[j, BETA])
            d = X[j, P_S] - C[s]
            own = np.zeros((j.size, N_PARAMS))
            own[:, 0], own[:, 1] = u[:, 1], -u[:, 0]
            own[:, BETA] = np.sum(d * u, axis=1)
            via_c = np.einsum("qi,qip->qp", np.stack([-u[:, 1], u[:, 0]], axis=1), dC[s])
            Dg = np.zeros((j.size, N_PARAMS * n))
            r = np.arange(j.size)[:, None]
            np.add.at(Dg, (r, (N_PARAMS * j)[:, None] + cols), own)
            np.add.at(Dg, (r, (N_PARAMS * k[s])[:, None] + cols), via_c)
            dr = np.zeros_like(Dg)
            dr[np.arange(j.size), N_PARAMS * j + R] = ro.psi[sel]
            JC = centred_cumulative_sums(dr, Dg, ro.yaw[sel], ro.run[sel])
            J[nA + nB :] = JC / ro.sigma[sel][:, None]
        return J

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
