"""A check without motion capture: the file against the robot's shape (pure functions).

Without motion capture the robot's own sensors (wheel and steering encoders, the gyro)
do not see five directions of the parameters (docs/imu.md): a planar rigid motion of the
frame (``t_x``, ``t_y``, a rotation ``phi`` that turns every ``beta`` with it), the
layout's length scale (every ``P_s`` and ``b`` times ``lambda``) and the radii's common
scale (every ``r`` times ``mu``, absorbed by the gyro's unknown scale).  A check with
the gyro (:func:`swpc_hw.calibration.gyro.solver.solve_imu_check`) therefore measures the
robot's *shape*; what it compares with the file must not depend on those five.

**The gauge directions** at the file's parameters ``p`` (5N), linearised, the columns of
``G`` (5N, 5) (:func:`gauge_directions`), per module i with ``c`` the axes' centroid::

    t_x: (1, 0, 0, 0, 0)     t_y: (0, 1, 0, 0, 0)
    phi: (-(y_i - c_y), x_i - c_x, 1, 0, 0)
    lambda: (x_i - c_x, y_i - c_y, 0, b_i, 0)          mu: (0, 0, 0, 0, r_i)

**Module k against the others.**  The change ``d = p_check - p_file`` (both in one gauge:
the check's estimate is fitted to the file) is aligned on the *anchor* modules ``A``
(k not among them) by weighted least squares over the five directions, and what is left
of module k is its change relative to them::

    g = (G_A^T W_A G_A)^-1 G_A^T W_A d_A           W = diag(1 / Cov(d)_ii)
    e_k = d_k - G_k g = L_k d
    Cov(e_k) = L_k Cov(d) L_k^T,   Cov(d) = C_check + C_file + diag(s_rep^2)
    chi2_k = e_k^T Cov(e_k)^-1 e_k                 (5 degrees of freedom)

``e_k`` is zero for any ``d`` along the gauge (``L_k G = 0``): neither the check's frame
nor the file's enters, only the shape.  Any rank-deficient part of ``C_check`` along the
gauge is removed by ``L_k`` as well.

**Which modules changed** (the anchors made robust): every module is tested against all
the others; the one with the largest ``chi2_k`` beyond the threshold is *drifted* and
leaves the anchors; the rest are tested again against the remaining anchors, until no
module passes the threshold or one module is left untested.  A changed module then no
longer tilts the alignment of the unchanged ones.  The thresholds are those of the check
with motion capture (:func:`swpc_hw.calibration.check.verdict.thresholds`: Sidak over the
modules).

**What cannot be seen** (said in the verdict's notes): a change along the five
directions; of real changes, every wheel wearing by the same fraction (the radii's common
scale).  A robot of two modules: each is tested against the other, so a change of one
is found in both.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from swpc_hw.calibration.check.verdict import (
    CheckVerdict,
    ModuleCheck,
    ParameterChange,
    change_and_covariance,
    chi2_of,
    judged_module,
    thresholds,
    verdict_of,
)
from swpc_hw.calibration.parameters import BETA, N_PARAMS
from swpc_hw.errors import CalibrationError

FloatArray = NDArray[np.float64]

GAUGE_NAMES = ("t_x", "t_y", "phi", "lambda", "mu")
"""The five directions a check without motion capture does not see (module docstring)."""

UNSEEN_NOTE = (
    "Checked without motion capture: the robot's shape is compared with the file's (each "
    "module against the others), not its frame or its scales; every wheel wearing by the "
    "same fraction is not seen (a check with motion capture, or a calibration, sees it)."
)


def gauge_directions(X: FloatArray) -> FloatArray:
    """``G`` (5N, 5): the five unseen directions at the parameters ``X`` (N, 5), module
    docstring; columns in :data:`GAUGE_NAMES` order."""
    X = np.asarray(X, dtype=float)
    n = X.shape[0]
    c = X[:, :2].mean(axis=0)
    dx, dy = X[:, 0] - c[0], X[:, 1] - c[1]
    G = np.zeros((n, N_PARAMS, 5))
    G[:, 0, 0] = 1.0
    G[:, 1, 1] = 1.0
    G[:, 0, 2], G[:, 1, 2], G[:, BETA, 2] = -dy, dx, 1.0
    G[:, 0, 3], G[:, 1, 3], G[:, 3, 3] = dx, dy, X[:, 3]
    G[:, 4, 4] = X[:, 4]
    return G.reshape(n * N_PARAMS, 5)


def relative_map(G: FloatArray, weights: FloatArray, k: int, anchors: list[int]) -> FloatArray:
    """``L_k`` (5, 5N): module ``k``'s change left after aligning the ``anchors`` (module
    indices, ``k`` not among them) on the gauge directions ``G`` with ``weights`` (5N,)
    (module docstring)."""
    if k in anchors or not anchors:
        raise ValueError("module k must be tested against other modules")
    p = G.shape[0]
    rows = np.concatenate([np.arange(N_PARAMS * a, N_PARAMS * (a + 1)) for a in anchors])
    Ga = G[rows] * np.sqrt(weights[rows])[:, None]
    # g = pinv(Ga) sqrt(W_A) d_A: a least-squares solve that tolerates a near-singular
    # alignment (one anchor of a robot whose wheel sits on its axis, b = 0)
    P = np.linalg.pinv(Ga) * np.sqrt(weights[rows])[None, :]
    sl = slice(N_PARAMS * k, N_PARAMS * (k + 1))
    L = np.zeros((N_PARAMS, p))
    L[:, sl] = np.eye(N_PARAMS)
    L[:, rows] -= G[sl] @ P
    return L


def module_statistic(
    L: FloatArray, d: FloatArray, C: FloatArray
) -> tuple[float, FloatArray, FloatArray]:
    """``(chi2, e, sd)``: module statistic of the relative change ``e = L d`` with
    ``Cov(e) = L C L^T``; ``sd`` its std devs.  A ``Cov(e)`` that is not positive definite
    is a :class:`~swpc_hw.errors.CalibrationError`."""
    e = L @ d
    Ce = L @ C @ L.T
    return chi2_of(e, Ce, "a module relative to the others"), e, np.sqrt(np.diag(Ce))


def compare_shape(
    check: FloatArray,
    C_check: FloatArray,
    file: FloatArray,
    C_file: FloatArray,
    ids: list[int],
    *,
    false_alarm: float = 0.05,
    whole_robot: float = 0.5,
    repeatability: Any = None,
) -> CheckVerdict:
    """The verdict of a check without motion capture (module docstring) from the (N, 5)
    estimates (modules in the order ``ids``, SI, one gauge: the check fitted to the file),
    their (5N, 5N) covariances and the ``repeatability`` (5,) (None: zero).  The result's
    table gives per module its change relative to the other modules."""
    n = len(ids)
    if n < 2:
        raise CalibrationError("a check without motion capture needs two modules or more")
    d2, C = change_and_covariance(check, C_check, file, C_file, n, repeatability)
    d = d2.ravel()
    G = gauge_directions(file)
    diag = np.diag(C).copy()
    weights = np.where(diag > 0, 1.0 / np.where(diag > 0, diag, 1.0), 0.0)
    _, q, z_m = thresholds(false_alarm, n)
    anchors = list(range(n))
    drifted: list[int] = []
    stats: dict[int, tuple[float, FloatArray, FloatArray]] = {}
    while True:
        for k in range(n):
            if k in drifted:
                continue
            others = [a for a in anchors if a != k]
            stats[k] = module_statistic(relative_map(G, weights, k, others), d, C)
        open_ = [k for k in range(n) if k not in drifted]
        worst = max(open_, key=lambda k: stats[k][0])
        if stats[worst][0] <= q:
            break
        drifted.append(worst)
        anchors.remove(worst)
        if len(open_) <= 2:  # one module left: nothing to test it against but the drifted
            break
    modules: list[ModuleCheck] = []
    changes: list[ParameterChange] = []
    for i, mid in enumerate(ids):
        stat, e, sd = stats[i]
        module, rows = judged_module(mid, stat, file[i], e, sd, i in drifted, z_m)
        modules.append(module)
        changes += rows
    out = verdict_of(modules, changes, false_alarm, whole_robot)
    out.notes.append(UNSEEN_NOTE)
    return out
