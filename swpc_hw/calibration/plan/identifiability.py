"""What an experiment without motion capture determines: its Fisher information.

For weighted residuals ``f(x)`` (unit noise) of the IMU problem (:mod:`.gyro.problem`)
the Fisher information of the unknowns is ``F = J^T J`` at the
truth (:func:`fisher_information`).  Every direction ``v`` with ``F v = 0`` is one the data
cannot see.  Expected ones (:func:`gauge_directions`), for ``x = [X, s, b, da]``:

* **translation x, y**: ``dP_s,i = e_x`` / ``e_y`` for every module;
* **rotation**: ``dP_s,i = (-y_s,i, x_s,i)``, ``dbeta_i = 1`` (every direction of the frame
  turns with it);
* **length scale**: ``dP_s = P_s``, ``db = b`` (the layout scaled) and ``ds = s`` (the
  levers grow, the wheels' yaw shrinks, the gyro must read less of it);
* **wheel-radius scale**: ``dr = r``, ``ds = -s`` (every wheel rolls further per radian,
  the yaw grows, and only an unknown gyro scale absorbs it);
* **all lengths**: their sum, ``dP_s = P_s``, ``db = b``, ``dr = r``: every length
  scaled, the gyro unchanged (what is left when its scale is known).

:func:`analyse` reports the rank, which of these named directions lie in the null space
and how many null directions they leave unexplained, the condition number of the
information on the rest (Jacobi-scaled: unit-free), and the std devs of derived figures in
the design-fit frame (infinite when the data leave them free; :func:`derived_figures`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from swpc_hw.calibration.gyro.problem import ImuProblem
from swpc_hw.calibration.parameters import BETA, N_PARAMS, P_S, X_S, Y_S, R
from swpc_hw.calibration.parameters import B as B_COL

FloatArray = NDArray[np.float64]

NULL_TOL = 1e-13
"""An eigenvalue of the Jacobi-scaled information below this times the largest is zero
(the exact null directions sit at ~1e-15, a reference pinning a direction weakly at
~1e-11)."""


def fisher_information(prob: ImuProblem, x: FloatArray) -> FloatArray:
    """``F = J^T J`` of the active blocks' weighted residuals at ``x`` (``p x p``)."""
    J = prob.jacobian(x)
    return np.asarray(J.T @ J, dtype=float)


def gauge_directions(prob: ImuProblem, x: FloatArray) -> dict[str, FloatArray]:
    """The directions the data of an IMU experiment may not see (module docstring)."""
    lay = prob.layout
    X = lay.split(x)[0]
    n = lay.n

    def vec(cols: dict[int, FloatArray], s: float = 0.0) -> FloatArray:
        v = np.zeros(lay.size)
        V = v[: N_PARAMS * n].reshape(n, N_PARAMS)
        for c, val in cols.items():
            V[:, c] = val
        v[lay.scale] = s
        return v

    one = np.ones(n)
    s = float(x[lay.scale])
    return {
        "translation x": vec({X_S: one}),
        "translation y": vec({Y_S: one}),
        "rotation": vec({X_S: -X[:, Y_S], Y_S: X[:, X_S], BETA: one}),
        "length scale": vec({X_S: X[:, X_S], Y_S: X[:, Y_S], B_COL: X[:, B_COL]}, s),
        "wheel-radius scale": vec({R: X[:, R]}, -s),
        "all lengths": vec({X_S: X[:, X_S], Y_S: X[:, Y_S], B_COL: X[:, B_COL], R: X[:, R]}),
    }


def derived_figures(prob: ImuProblem, x: FloatArray) -> dict[str, tuple[FloatArray, float]]:
    """Gradients of figures odometry depends on, with the unit they are shown in.

    ``r`` (mean over the modules of ``r_j``, relative), ``length scale`` (mean distance of
    the steering axes from their centroid, relative), ``beta difference`` (``beta_2 -
    beta_1``, deg), ``b`` (module 1, mm), ``gyro scale`` (``s``, relative).
    """
    lay = prob.layout
    X = lay.split(x)[0]
    n = lay.n
    out: dict[str, tuple[FloatArray, float]] = {}
    g = np.zeros(lay.size)
    g[R : N_PARAMS * n : N_PARAMS] = 1.0 / (n * X[:, R])
    out["r"] = (g, 1.0)
    c = X[:, P_S] - X[:, P_S].mean(axis=0)
    rad = np.linalg.norm(c, axis=1)
    g = np.zeros(lay.size)
    for i in range(n):
        g[N_PARAMS * i : N_PARAMS * i + 2] = c[i] / rad[i] / (n * rad.mean())
    out["length scale"] = (g, 1.0)
    g = np.zeros(lay.size)
    g[BETA], g[N_PARAMS + BETA] = -1.0, 1.0
    out["beta difference"] = (g, 180.0 / math.pi)
    g = np.zeros(lay.size)
    g[B_COL] = 1.0
    out["b"] = (g, 1e3)
    g = np.zeros(lay.size)
    g[lay.scale] = 1.0
    out["gyro scale"] = (g, 1.0)
    return out


@dataclass
class Identifiability:
    """What an experiment's information determines (:func:`analyse`)."""

    size: int
    """Unknowns with any information (a block the experiment lacks leaves its own out)."""
    rank: int
    null: list[str]
    """Named directions (:func:`gauge_directions`) in the null space."""
    unexplained: int
    """Null directions the named ones do not span."""
    condition: float
    """``lambda_max / lambda_min`` of the Jacobi-scaled information over its range."""
    std: dict[str, float] = field(default_factory=dict)
    """Std dev of every derived figure in the design-fit frame (inf: not determined; nan:
    not an unknown of the experiment)."""
    eigenvalues: FloatArray = field(default_factory=lambda: np.zeros(0))

    @property
    def null_dim(self) -> int:
        return self.size - self.rank


def analyse(
    prob: ImuProblem,
    x: FloatArray,
    F: FloatArray | None = None,
    known: tuple[int, ...] = (),
    tol: float = NULL_TOL,
) -> Identifiability:
    """Rank, null space, condition number and derived std devs of ``F`` (default: the
    information of the data blocks of ``prob`` at ``x``, the ``gauge`` block left out: it
    is no measurement).  Unknowns without information and those in ``known`` (indices,
    e.g. the gyro scale taken as known) are left out.
    """
    if F is None:
        F = fisher_information(prob.with_blocks(prob.active - {"gauge"}), x)
    d = np.diag(F).copy()
    keep = d > 0
    keep[list(known)] = False
    idx = np.flatnonzero(keep)
    root = np.sqrt(d[idx])
    Fs = F[np.ix_(idx, idx)] / np.outer(root, root)
    w, V = np.linalg.eigh(Fs)
    zero = w <= tol * w[-1]
    rank = int((~zero).sum())
    N = V[:, zero]
    names: list[str] = []
    vecs: list[FloatArray] = []
    for name, v in gauge_directions(prob, x).items():
        u = v[idx] * root
        if np.linalg.norm(u) == 0:
            continue
        u = u / np.linalg.norm(u)
        in_null = np.linalg.norm(N.T @ u) > 1.0 - 1e-4
        # named only if it adds a dimension (all lengths = the two scales together)
        if in_null and np.linalg.matrix_rank(np.array([*vecs, u]), tol=1e-6) > len(vecs):
            names.append(name)
            vecs.append(u)
    spanned = len(vecs)
    cond = float(w[-1] / w[~zero].min())
    return Identifiability(
        size=idx.size,
        rank=rank,
        null=names,
        unexplained=int(zero.sum()) - int(spanned),
        condition=cond,
        std=design_fit_std(prob, x, Fs, idx, root, tol),
        eigenvalues=w,
    )


def design_fit_std(
    prob: ImuProblem,
    x: FloatArray,
    Fs: FloatArray,
    idx: NDArray[np.int64],
    root: FloatArray,
    tol: float,
) -> dict[str, float]:
    """Std devs of :func:`derived_figures` in the design-fit frame from the scaled
    information ``Fs`` of the unknowns ``idx`` (``root``: their scales):
    ``Cov = Z (Z^T F Z)^+ Z^T`` with ``Z`` the null space of the frame's conditions; a
    figure with a component along a null direction of ``Z^T F Z`` is not determined."""
    from scipy.linalg import null_space  # at first use: see swpc_hw.calibration

    A = prob.gauge_jacobian()
    Z = null_space(A[:, idx] / root)
    H = Z.T @ Fs @ Z
    w, V = np.linalg.eigh(H)
    zero = w <= tol * w[-1]
    out = {}
    for name, (g, unit) in derived_figures(prob, x).items():
        if not np.any(g[idx]):  # not an unknown of this experiment (or taken as known)
            out[name] = math.nan
            continue
        u = Z.T @ (g[idx] / root)
        a = V.T @ u
        if np.linalg.norm(a[zero]) > 1e-3 * np.linalg.norm(a):  # beyond numerical mixing
            out[name] = math.inf
        else:
            out[name] = unit * math.sqrt(float(np.sum(a[~zero] ** 2 / w[~zero])))
    return out
