"""Noiseless, vectorised calibration experiment for many random robots (the paper's Table 3).

Everything is closed form (no integration, no Python loop over trials).  Shapes: ``T``
trials, ``N`` modules, ``M`` steering angles of the static module, ``K`` poses per segment.
Index ``k`` of the second axis is the static module, ``m`` the angle; the last ``N`` axis
of per-module arrays is the module ``j``.

Sign conventions (docs/model-and-frames.md):

* the body rotates about the true contact point ``C = P_s,k + b_k u(a_m + beta_k)`` of the
  static module by ``dyaw = sweep`` (``sweep > 0``: counter-clockwise);
* the free casters have settled on the trailing side: ``(P_w,j - C) . u(theta_j) = 0`` and
  ``omega sin(theta_j - alpha_j) < 0`` with ``alpha_j`` the direction of ``P_s,j - C``
  (:func:`simulators.physics.core.settled_trailing`);
* a trailing wheel turns backwards in this convention: ``r_j dpsi_j = -D_j |dyaw|`` with
  ``D_j = |P_w,j - C|`` (the signed rolling distance of the contact point along ``u``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from simulators.physics.core import FloatArray, settled_trailing
from swpc_hw.protocol import DEFAULT_PROTOCOL
from swpc_hw.robot.model import RobotParams, contact_point, wrap_angle
from swpc_hw.robot.paper_robot import PAPER_NOMINAL

_DEG = math.pi / 180.0
DEFAULT_ANGLES = tuple(math.radians(a) for a in DEFAULT_PROTOCOL.angles_deg)
"""The default protocol's steering angles (rad)."""


class BatchRobots(NamedTuple):
    """Parameters of ``T`` random robots: ``P_s`` (T, N, 2), ``beta``, ``b``, ``r`` (T, N)."""

    P_s: FloatArray
    beta: FloatArray
    b: FloatArray
    r: FloatArray

    def robot(self, i: int, ids: list[int] | None = None) -> RobotParams:
        """Trial ``i`` as a :class:`RobotParams` (ids ``1..N`` unless given)."""
        n = self.P_s.shape[1]
        return RobotParams.from_arrays(
            ids if ids is not None else list(range(1, n + 1)),
            self.P_s[i], self.beta[i], self.b[i], self.r[i],
        )


def random_robots(
    n_trials: int,
    rng: np.random.Generator,
    nominal: RobotParams = PAPER_NOMINAL,
    *,
    pos_frac: float = 0.30,
    beta_max: float = 30.0 * _DEG,
    br_frac: float = 0.10,
) -> BatchRobots:
    """Random robots around ``nominal`` as in the paper's simulation (uniform draws).

    ``P_s = P_s,nom (1 + U(-pos_frac, pos_frac))`` per coordinate, ``beta = U(-beta_max,
    beta_max)``, ``b = b_nom (1 + U(-br_frac, br_frac))`` and likewise ``r``.
    """
    a = nominal.arrays()
    T, n = int(n_trials), a.n
    P_s = a.P_s[None] * (1.0 + rng.uniform(-pos_frac, pos_frac, (T, n, 2)))
    beta = rng.uniform(-beta_max, beta_max, (T, n))
    b = a.b[None] * (1.0 + rng.uniform(-br_frac, br_frac, (T, n)))
    r = a.r[None] * (1.0 + rng.uniform(-br_frac, br_frac, (T, n)))
    return BatchRobots(P_s, beta, b, r)


@dataclass(frozen=True)
class BatchExperiment:
    """Exact noiseless observations of every segment (see the module docstring).

    ``poses`` (T, N, M, K, 3): ``x, y, yaw`` of R in W, yaw wrapped to (-pi, pi], an exact
    rotation about ``fixed_points`` (each segment starts at its own random world pose);
    ``static_theta_hat`` (T, N, M) the held angle; ``theta_hat`` (T, N, M, N) settled
    reported steering, wrapped (static entry = held angle); ``theta`` the same, true;
    ``dpsi`` (T, N, M, N) wheel increments over the segment (0 for the static module);
    ``dyaw`` (T, N, M) unwrapped yaw change; ``fixed_points`` (T, N, M, 2) ``C`` in R;
    ``fixed_points_world`` (T, N, M, 2) ``C`` in W; ``D`` (T, N, M, N) ``|P_w,j - C|``.
    """

    angles: FloatArray
    poses: FloatArray
    static_theta_hat: FloatArray
    theta_hat: FloatArray
    theta: FloatArray
    dpsi: FloatArray
    dyaw: FloatArray
    fixed_points: FloatArray
    fixed_points_world: FloatArray
    D: FloatArray


def batch_experiment(
    P_s: FloatArray,
    beta: FloatArray,
    b: FloatArray,
    r: FloatArray,
    angles: tuple[float, ...] = DEFAULT_ANGLES,
    n_poses: int = 36,
    sweep: float = 2.0 * math.pi,
    seed: int = 0,
) -> BatchExperiment:
    """Closed-form observations of the calibration experiment for ``T`` robots at once.

    ``C[t,k,m] = P_s[t,k] + b[t,k] u(angles[m] + beta[t,k])``; pose ``i`` of a segment:
    ``yaw_i = yaw0 + sweep i / (K - 1)``, ``p_i = C_W - R(yaw_i) C`` with random ``yaw0 ~
    U(-pi, pi)`` and ``C_W ~ U(-1, 1)^2`` m (from ``seed``).  Settled casters and wheel
    increments from :func:`simulators.physics.core.settled_trailing`:
    ``dpsi_j = -D_j |sweep| / r_j``.
    """
    P = np.asarray(P_s, dtype=float)
    be = np.asarray(beta, dtype=float)
    bb = np.asarray(b, dtype=float)
    rr = np.asarray(r, dtype=float)
    T, n = be.shape
    ang = np.asarray(angles, dtype=float)
    M = ang.shape[0]
    K = int(n_poses)
    if K < 2:
        raise ValueError("n_poses must be >= 2")
    rng = np.random.default_rng(seed)

    # fixed points (T, N, M, 2)
    th_static = ang[None, None, :] + be[:, :, None]  # (T, N, M)
    C = contact_point(P[:, :, None, :], bb[:, :, None], th_static)

    # settled casters (T, N, M, N)
    theta, D = settled_trailing(
        P[:, None, None, :, :], bb[:, None, None, :], C[:, :, :, None, :], np.sign(sweep)
    )
    eye = np.eye(n, dtype=bool)[None, :, None, :]  # (1, N(k), 1, N(j))
    eye_b = np.broadcast_to(eye, theta.shape)
    theta = np.where(eye_b, np.broadcast_to(th_static[..., None], theta.shape), theta)
    D = np.where(eye_b, 0.0, D)
    theta_hat = np.asarray(wrap_angle(theta - be[:, None, None, :]), dtype=float)
    theta_hat = np.where(eye_b, np.broadcast_to(ang[None, None, :, None], theta.shape), theta_hat)
    dpsi = -D * abs(sweep) / rr[:, None, None, :]

    # poses (T, N, M, K, 3)
    yaw0 = rng.uniform(-math.pi, math.pi, (T, n, M))
    C_W = rng.uniform(-1.0, 1.0, (T, n, M, 2))
    yaw = yaw0[..., None] + sweep * np.arange(K) / (K - 1)  # (T, N, M, K)
    c, s = np.cos(yaw), np.sin(yaw)
    Cx, Cy = C[..., 0][..., None], C[..., 1][..., None]
    x = C_W[..., 0][..., None] - (c * Cx - s * Cy)
    y = C_W[..., 1][..., None] - (s * Cx + c * Cy)
    poses = np.stack([x, y, wrap_angle(yaw)], axis=-1)

    return BatchExperiment(
        angles=ang,
        poses=poses,
        static_theta_hat=np.broadcast_to(ang[None, None, :], (T, n, M)).copy(),
        theta_hat=theta_hat,
        theta=np.asarray(wrap_angle(theta), dtype=float),
        dpsi=dpsi,
        dyaw=np.full((T, n, M), float(sweep)),
        fixed_points=C,
        fixed_points_world=C_W,
        D=D,
    )


__all__ = ["BatchExperiment", "BatchRobots", "batch_experiment", "random_robots"]
