"""The gyro solver's covariance in the design-fit frame (stage 6 of
:mod:`swpc_hw.calibration.gyro.solver`): the sandwich on the subspace the frame's
conditions leave, the wheels' blocks with a HAC middle over their nodes; data that leave
more than the frame free are refused, naming the directions.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from swpc_hw.calibration.gyro.problem import ImuProblem
from swpc_hw.calibration.gyro.rolling_sets import RollingSet
from swpc_hw.calibration.parameters import PARAM_NAMES
from swpc_hw.calibration.uncertainty import dense_rows, long_run_covariance
from swpc_hw.errors import CalibrationError

FloatArray = NDArray[np.float64]


def rolling_middle(rs: RollingSet, J: FloatArray, f: FloatArray) -> FloatArray:
    """HAC long-run covariance of a rolling set's scores, the modules of a node summed."""
    node = np.broadcast_to(np.arange(rs.t.size)[:, None], rs.present.shape)[rs.present]
    S = dense_rows(node, J * f[:, None])
    present = np.zeros(S.shape[0], dtype=bool)
    present[node] = True
    return long_run_covariance(S, present)[0]


def imu_covariance(prob: ImuProblem, x: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``(Cov, J, f)``: the covariance of all unknowns in the design-fit frame, and the
    Jacobian and residuals of the data blocks (the gauge block left out).

    ``Cov = Z (Z^T H Z)^-1 Z^T M Z (Z^T H Z)^-1 Z^T`` with ``H = J^T J``, ``Z`` a basis of
    the null space of the design-fit conditions' Jacobian, ``M`` the scores' covariance:
    HAC over the nodes for the wheels' blocks (``spin`` per segment, ``drive``),
    ``J_b^T J_b`` for the others (independent residuals of known std dev).  Computed in
    parameters scaled to unit Jacobian columns.  A singular ``Z^T H Z`` raises
    :class:`CalibrationError` naming the least determined parameters.
    """
    from scipy.linalg import null_space  # at first use: see swpc_hw.calibration

    data = prob.with_blocks(prob.active - {"gauge"})
    J = data.jacobian(x)
    f = data.residuals(x)
    sl = data.block_slices(x)
    p = x.size
    M = np.zeros((p, p))
    for name, s in sl.items():
        Jb, fb = J[s], f[s]
        if name not in ("spin", "drive"):
            M += Jb.T @ Jb
            continue
        i = 0
        for rs in prob.spins if name == "spin" else prob.drives:
            k = int(rs.present.sum())
            M += rolling_middle(rs, Jb[i : i + k], fb[i : i + k])
            i += k
    norms = np.linalg.norm(J, axis=0)
    norms = np.where(norms > 0, norms, 1.0)
    Js = J / norms
    Z = null_space(prob.gauge_jacobian() / norms)
    Hz = Z.T @ (Js.T @ Js) @ Z
    w, V = np.linalg.eigh(Hz)
    if w[0] <= w[-1] * 1e-12:
        weak = Z @ V[:, 0]
        raise CalibrationError(
            "the data do not determine the calibration in the design-fit frame: a direction "
            f"with no information moves {undetermined_names(prob, weak)}"
        )
    Hi = (V / w) @ V.T
    G = Z @ Hi @ Z.T
    cov = G @ (M / np.outer(norms, norms)) @ G
    cov = cov / np.outer(norms, norms)
    return 0.5 * (cov + cov.T), J, f


def parameter_names(prob: ImuProblem) -> list[str]:
    """Names of the unknowns: ``x_s[1]``..., ``s``, ``bias[1]``..."""
    lay = prob.layout
    names = [f"{k}[{mid}]" for mid in prob.ids for k in PARAM_NAMES]
    knots = [f"bias[{i + 1}]" for i in range(lay.n_knots)]
    return [*names, "gyro scale", *knots, *[f"da[{i + 1}]" for i in range(lay.n_segments)]]


def undetermined_names(prob: ImuProblem, v: FloatArray, top: int = 4) -> str:
    """The unknowns with the largest share of a (scaled) direction ``v``."""
    names = parameter_names(prob)
    order = np.argsort(-np.abs(v))[:top]
    return ", ".join(names[i] for i in order)


