"""The solver's unknowns: one row per module, one named column per parameter.

``X`` is an (N, 5) matrix, row i = module i in robot order, columns in the order of
:data:`swpc_hw.robot.model.PARAM_NAMES` (``x_s, y_s, beta, b, r``).  The least-squares vector
``x`` is ``X`` flattened row by row.  Code indexes the columns by these names, never by number::

    X[j, P_S]      steering axis P_s,j (2,)        X[j, BETA]   homing error beta_j
    X[j, B]        caster offset b_j               X[j, R]      wheel radius r_j
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from swpc_hw.robot.model import PARAM_NAMES

__all__ = ["PARAM_NAMES"]  # the column names, in column order (re-exported)

FloatArray = NDArray[np.float64]

X_S, Y_S, BETA, B, R = range(len(PARAM_NAMES))
P_S = slice(X_S, Y_S + 1)
"""Both coordinates of the steering axis: ``X[:, P_S]`` is (N, 2)."""
N_PARAMS = len(PARAM_NAMES)


def as_matrix(x: FloatArray, n: int) -> FloatArray:
    """The (N, 5) view of a flat parameter vector."""
    return x.reshape(n, N_PARAMS)


def canonical_parameters(X: FloatArray) -> FloatArray:
    """The representative with ``b >= 0`` of every module's mirror pair.

    The model only sees ``b u(theta + beta)`` and ``r dpsi``, and
    ``u(theta + beta + pi) = -u(theta + beta)``, so

        (x_s, y_s, beta, b, r)  and  (x_s, y_s, beta + pi, -b, -r)

    give identical residuals in all three blocks (fixed point: ``C_R = P_s + b u(a + beta)``;
    settled caster: ``(P_s - C_R) . u(theta + beta) + b`` changes sign; rolling: the lever
    ``g = (P_w - C) x u(theta)`` and ``r`` both change sign).  The trust-region step can
    cross ``b = 0`` into the mirror; this maps such a module back, ``beta`` wrapped to
    ``[-pi, pi)``.  ``X``: (N, 5); returns a copy.
    """
    Y = np.array(X, dtype=float, copy=True)
    mirror = Y[:, B] < 0
    Y[mirror, BETA] += np.pi
    Y[mirror, B] *= -1.0
    Y[mirror, R] *= -1.0
    Y[:, BETA] = (Y[:, BETA] + np.pi) % (2 * np.pi) - np.pi
    return Y
