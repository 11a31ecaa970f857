"""The result of an IMU calibration: parameters in the design-fit frame with their
covariance, the gyro's estimates, every reference's residual, quality figures."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from swpc_hw.calibration.gyro.build import ImuRun
from swpc_hw.calibration.gyro.problem import ImuProblem
from swpc_hw.calibration.parameters import N_PARAMS, P_S, PARAM_NAMES, R
from swpc_hw.calibration.prepare import SegmentData
from swpc_hw.calibration.result import (
    BiasKnot,
    CalibrationResult,
    ImuQuality,
    ReferenceResidual,
    SegmentQuality,
)
from swpc_hw.calibration.uncertainty import stddev_of
from swpc_hw.files.dataset import Dataset
from swpc_hw.files.references import reference_label
from swpc_hw.robot.frames import DESIGN_FIT
from swpc_hw.robot.model import ModuleStddev, RobotParams

FloatArray = NDArray[np.float64]

WEAK_RADIUS = 1e-3
"""A wheel radius known to worse than this (relative std dev) is flagged."""
WEAK_SCALE = 2e-3
"""A layout whose mean axis distance is known to worse than this (relative) is flagged."""


def _std(var: float) -> float | None:
    return math.sqrt(var) if math.isfinite(var) and var >= 0 else None


def reference_residuals(
    prob: ImuProblem, x: FloatArray, cov: FloatArray, J: FloatArray, f: FloatArray
) -> list[ReferenceResidual]:
    """Every reference at the solution, with the std dev of what the calibration predicts
    (``d pred / dx = stddev J_row``, ``var = d^T Cov d``)."""
    data = prob.with_blocks(prob.active - {"gauge"})
    sl = data.block_slices(x)
    out = []
    counters = dict.fromkeys(sl, 0)
    for ref in prob.refs:
        s = sl[ref.kind]
        i = s.start + counters[ref.kind]
        counters[ref.kind] += 1
        d = ref.stddev * J[i]
        out.append(
            ReferenceResidual(
                label=reference_label(ref),
                kind=ref.kind,
                value=ref.value,
                stddev=ref.stddev,
                predicted=ref.value + ref.stddev * float(f[i]),
                predicted_std=_std(float(d @ cov @ d)),
            )
        )
    return out


def block_chi2(prob: ImuProblem, x: FloatArray) -> dict[str, float]:
    """Mean square of every data block's weighted residuals."""
    blocks = prob.with_blocks(prob.active - {"gauge"}).blocks(x)
    return {k: float(np.mean(v**2)) for k, v in blocks.items() if v.size}


def notes(X: FloatArray, cov: FloatArray, prob: ImuProblem) -> list[str]:
    """Warnings about what the references pin only weakly."""
    out = []
    n = prob.layout.n
    var_r = np.diag(cov)[R : N_PARAMS * n : N_PARAMS]
    rel = float(np.sqrt(np.max(var_r)) / np.min(X[:, R]))
    if rel > WEAK_RADIUS:
        out.append(
            f"the wheel radii are known to {rel * 100:.2g} % only (a straight_drive of a few "
            "metres pins them to ~1e-4)"
        )
    # the layout's length scale: the mean distance of the steering axes from their centroid
    c = X[:, P_S] - X[:, P_S].mean(axis=0)
    rad = np.linalg.norm(c, axis=1)
    grad = np.zeros(cov.shape[0])
    for i in range(n):
        grad[N_PARAMS * i : N_PARAMS * i + 2] = c[i] / max(rad[i], 1e-9) / n
    rel_scale = math.sqrt(max(float(grad @ cov @ grad), 0.0)) / max(float(rad.mean()), 1e-9)
    if rel_scale > WEAK_SCALE:
        out.append(
            f"the layout's length scale is known to {rel_scale * 100:.2g} % only (more "
            "axis_distance references pin it better)"
        )
    return out


def assemble_imu_result(
    run: ImuRun,
    ds: Dataset,
    segs: list[SegmentData],
    x: FloatArray,
    cov: FloatArray,
    J: FloatArray,
    f: FloatArray,
    cut: list[int],
    spin_cuts: Sequence[str] = (),
) -> CalibrationResult:
    """Assemble the :class:`CalibrationResult` (``mode="imu"``, frame design-fit).

    ``cut``: the wheel increments left out of every rolling set (spins, then drives);
    ``spin_cuts``: the spins cut whole, described (a note each)."""
    prob = run.problem
    lay = prob.layout
    n = lay.n
    X, s, knots = lay.split(x)
    std_all = stddev_of(cov)
    std = std_all[: N_PARAMS * n].reshape(n, N_PARAMS)
    params = RobotParams.from_matrix(prob.ids, X, robot=ds.robot.robot, frame=DESIGN_FIT)
    params = params.model_copy(
        update={
            "modules": [
                m.model_copy(
                    update={"stddev": ModuleStddev(**dict(zip(PARAM_NAMES, row, strict=True)))}
                )
                if np.all(np.isfinite(row))
                else m
                for m, row in zip(params.modules, std.tolist(), strict=True)
            ]
        }
    )
    bias_std = std_all[lay.knots]
    nl = run.noise
    quality = ImuQuality(
        gyro_scale_error=s - 1.0,
        gyro_scale_error_std=_finite(std_all[lay.scale]),
        bias=[
            BiasKnot(float(t), float(b), _finite(sd))
            for t, b, sd in zip(run.knots.tau, knots, bias_std, strict=True)
        ],
        gyro_noise_density=math.sqrt(nl.gyro_var * nl.gyro_dt),
        bias_walk=math.sqrt(nl.walk_q2),
        references=reference_residuals(prob, x, cov, J, f),
        block_chi2=block_chi2(prob, x),
        notes=[
            *(f"{c}: cut whole, its wheels' ratios do not fit the geometry" for c in spin_cuts),
            *notes(X, cov, prob),
        ],
    )
    blocks = prob.with_blocks(prob.active - {"gauge"}).blocks(x)
    dof = max(f.size - (x.size - 3), 1)
    C = prob.contact_points(x)
    seg_q = []
    for si, (sd, rs) in enumerate(zip(segs, prob.spins, strict=True)):
        g = prob.spin_levers(X, C, rs, si)
        resid, _ = prob.rolled(X, rs, g)
        sel = prob.settled.seg == si
        settled_raw = blocks["settled"][sel] * prob.settled.sigma[sel]
        seg_q.append(
            SegmentQuality(
                row=sd.row,
                static_module=prob.ids[sd.static],
                angle=sd.angle,
                poses_used=0,
                poses_rejected=0,
                fixed_point_rms=math.nan,
                fixed_point=(float(C[si, 0]), float(C[si, 1])),
                increments_used=int(np.sum(rs.present[1:] & rs.present[:-1])),
                increments_rejected=cut[si],
                rolling_rms=(
                    float(np.sqrt(np.mean(resid[rs.present] ** 2)))
                    if rs.present.any()
                    else math.nan
                ),
                settled_rms=float(np.sqrt(np.mean(settled_raw**2))) if sel.any() else None,
            )
        )
    full = cov[: N_PARAMS * n, : N_PARAMS * n]
    return CalibrationResult(
        params=params,
        nominal=ds.robot,
        segments=seg_q,
        time_offset=0.0,
        time_offset_std=None,
        time_offset_mode="given",
        poses_used=0,
        poses_rejected=0,
        increments_used=int(sum(q.increments_used for q in seg_q)),
        increments_rejected=int(sum(cut)),
        reduced_chi2=float(f @ f) / dof,
        covariance=full if np.all(np.isfinite(full)) else None,
        mode="imu",
        imu=quality,
    )


def _finite(v: float) -> float | None:
    return float(v) if math.isfinite(v) else None
