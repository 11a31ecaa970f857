"""Joint robust calibration solver.

Unknowns: for every module i, ``x_s, y_s, beta, b, r`` (5N, :mod:`.parameters`).  Stages:

1. **Fixed points** (:mod:`.fixed_point`): every segment's fixed point in closed form with
   iterative outlier rejection, and its covariance from the HAC sandwich (correlated
   mocap noise included).
2. **Plausibility before solving** (:mod:`.plausibility`): clocks, units and magnitudes
   against the nominal robot, each segment's fixed-point RMS against the noise the
   poses imply.
3. **Closed-form start**: the paper's geometry generalised to M >= 2 angles
   (:func:`.geometry.steering_circle_fit`); radii from the rolling ratio.
4. **Clock offset** when asked (:mod:`.clock_offset`).
5. **Joint least squares** (:mod:`.problem`: fixed point, settled caster and rolling
   blocks) with :func:`scipy.optimize.least_squares` in an IRLS loop that finds slip
   (:mod:`.slip`: bursts and slow drifts, cut out of the rolling runs) and re-estimates
   each block's noise scale.
6. **Covariance** (:mod:`.covariance`): the sandwich ``H^-1 M H^-1``, ``M`` from the
   fixed points' HAC covariances, the settled-caster block and the HAC long-run
   covariance of the rolling scores (modules of one segment share the yaw noise of each
   node).
7. **Plausibility after solving**: physical values, magnitudes against the nominal robot.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from swpc_hw.calibration import geometry as geo
from swpc_hw.calibration import plausibility
from swpc_hw.calibration.fixed_point import FixedPointFit, fit_fixed_point
from swpc_hw.calibration.mocap.clock_offset import ClockOffset, estimate_clock_offset
from swpc_hw.calibration.mocap.covariance import joint_covariance
from swpc_hw.calibration.options import SolverOptions
from swpc_hw.calibration.parameters import (
    BETA,
    P_S,
    PARAM_NAMES,
    R,
    as_matrix,
    canonical_parameters,
)
from swpc_hw.calibration.parameters import B as B_COL
from swpc_hw.calibration.prepare import (
    SegmentData,
    prepare_segments,
    settled_steering,
)
from swpc_hw.calibration.problem import (
    FixedPointObservations,
    JointProblem,
    SettledObservations,
)
from swpc_hw.calibration.result import CalibrationResult, SegmentQuality
from swpc_hw.calibration.rolling import (
    EncoderTrack,
    RollingSeries,
    build_rolling_series,
    cut_runs,
    decimate,
    encoder_resolution,
    encoder_tracks,
    profiled_series_radius,
    rolling_increments,
    rolling_levers,
)
from swpc_hw.calibration.slip import detect_slip
from swpc_hw.calibration.uncertainty import stddev_of
from swpc_hw.errors import CalibrationError
from swpc_hw.files.dataset import Dataset, load_dataset
from swpc_hw.robot.model import ModuleStddev, RobotParams, contact_point

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

__all__ = [
    "PARAM_NAMES",
    "CalibrationResult",
    "SegmentQuality",
    "SolverOptions",
    "canonical_parameters",
    "solve",
    "solve_directory",
]


# ------------------------------------------------------------------ building the problem


def closed_form_geometry(fits: list[FixedPointFit], segs: list[SegmentData], n: int) -> FloatArray:
    """Initial (N, 5) parameters from the fixed points (generalised eq. 1-3); r = nan."""
    X = np.full((n, 5), np.nan)
    for i in range(n):
        mine = [s for s, sd in enumerate(segs) if sd.static == i]
        pts = np.array([fits[s].C_R for s in mine])
        angles = np.array([segs[s].angle for s in mine])
        P_s, b, beta = geo.steering_circle_fit(pts, angles)
        X[i, P_S], X[i, BETA], X[i, B_COL] = P_s, beta, b
    return X


def rolling_nodes(
    segs: list[SegmentData], interval: float, half_width: float
) -> list[FloatArray]:
    """Pose nodes of every segment, ~``interval`` apart: each the mean (time and pose) of
    the inlier poses within ``half_width`` of a grid time.

    In a steady spin the yaw is linear in time, so the mean pose is a pose of the motion
    at the mean time, with the noise of several.
    """
    out = []
    for sd in segs:
        inl = sd.poses[sd.inliers]
        t = inl[:, 0]
        rows = []
        for i in decimate(t, interval).tolist():
            a, b = np.searchsorted(t, [t[i] - half_width, t[i] + half_width], side="left")
            b = max(b, i + 1)
            if b < t.size and t[b] <= t[i] + half_width:
                b += 1
            rows.append(inl[a:b].mean(axis=0))
        out.append(np.array(rows).reshape(-1, 4))
    return out


def build_problem(
    ds: Dataset,
    segs: list[SegmentData],
    fits: list[FixedPointFit],
    tracks: dict[int, EncoderTrack],
    offset: float,
    X0: FloatArray,
    opts: SolverOptions,
) -> JointProblem:
    """The joint problem of a run (weights of the settled block from the start ``X0``)."""
    n = len(ds.robot.ids)
    # weights from a smooth covariance model (a noisy HAC estimate as weights would cost
    # efficiency); the HAC covariances themselves go into the sandwich
    kappa2 = float(np.median([f.inflation for f in fits])) ** 2
    whiten = np.array([np.eye(2) / math.sqrt(kappa2 * f.white_variance) for f in fits])
    fixed = FixedPointObservations(
        static=np.array([s.static for s in segs], dtype=np.int64),
        angle=np.array([s.angle for s in segs]),
        C_hat=np.array([f.C_R for f in fits]),
        whiten=whiten,
        covariance=np.array([f.covariance for f in fits]),
    )
    floor = opts.steer_sigma_floor
    if floor is None:
        floor = encoder_resolution(ds) / math.sqrt(12.0)
    seg, mod, theta, sig_theta = settled_steering(ds, segs, offset, floor)
    series = build_rolling_series(
        tracks,
        ds.robot.ids,
        [s.static for s in segs],
        rolling_nodes(segs, opts.increment_interval, opts.node_half_width),
        offset,
    )
    prob = JointProblem(n, fixed, SettledObservations(seg, mod, theta, sig_theta), series)
    C0 = prob.contact_points(X0)
    lever = np.abs(geo.rolling_lever(X0[mod, P_S], X0[mod, B_COL], theta + X0[mod, BETA], C0[seg]))
    prob.settled.sigma = np.maximum(lever, 0.05) * sig_theta
    return prob


def radius_init(prob: JointProblem, X: FloatArray) -> FloatArray:
    """Per-module median over its series of the least-squares ratio ``r = g dyaw / dpsi``."""
    C = prob.contact_points(X)
    _, r_ser = profiled_series_radius(X, C, prob.rolling)
    nd = prob.rolling
    r = np.full(prob.n, np.nan)
    for j in range(prob.n):
        sers = np.unique(nd.ser[nd.mod == j])
        if sers.size == 0:
            raise CalibrationError(
                f"module index {j}: no wheel-encoder data while another module was locked"
            )
        r[j] = abs(float(np.median(r_ser[sers])))
    return r


# ------------------------------------------------------------------ solving


def rolling_noise(prob: JointProblem, X: FloatArray, C: FloatArray) -> FloatArray:
    """Noise std dev of every node: the RMS of its series' clean cumulative residuals."""
    series = prob.rolling
    Rv = prob.rolling_block(X, C)
    clean = series.clean
    runs, ser = series.run[clean], series.ser[clean]
    out = np.ones(series.size)
    sig = np.zeros(Rv.size)
    for k in np.unique(ser):
        sel = ser == k
        dof = max(int(sel.sum()) - np.unique(runs[sel]).size, 1)
        sig[sel] = max(math.sqrt(float(np.sum(Rv[sel] ** 2)) / dof), 1e-12)
    out[clean] = sig
    return out


def lever_uncertainty(
    prob: JointProblem, X: FloatArray, C: FloatArray, fits: list[FixedPointFit]
) -> FloatArray:
    """Per rolling series, the relative std dev of its lever the fixed points allow.

    ``g = (P_w,j - C_s) x u``: ``C_s`` and ``P_w,j`` are each known to about the segment's
    fixed-point std dev, so ``std(g) / |g| ~ sqrt(2) std(C_s) / |g|``.
    """
    series = prob.rolling
    g = np.abs(rolling_levers(X, C, series))
    nser = int(np.max(series.ser)) + 1 if series.size else 0
    mean_g = np.bincount(series.ser, weights=g, minlength=nser) / np.maximum(
        np.bincount(series.ser, minlength=nser), 1
    )
    seg_of = np.zeros(nser, dtype=np.int64)
    seg_of[series.ser] = series.seg
    std_c = np.array([fits[s].std for s in seg_of])
    return np.asarray(math.sqrt(2.0) * std_c / np.maximum(mean_g, 1e-6), dtype=float)


def fit_joint(
    prob: JointProblem,
    X0: FloatArray,
    opts: SolverOptions,
    fits: list[FixedPointFit],
    wheel_resolution: float = 0.0,
) -> tuple[FloatArray, BoolArray]:
    """IRLS: slip detection and noise scales alternate with the trust-region solve.

    Returns the flat solution and the slip flag of every increment.  At least two
    iterations: the first finds slip bursts only.  ``wheel_resolution`` (rad): an
    increment's noise is at least ``r q / sqrt(6)`` (two quantized readings).
    """
    from scipy.optimize import least_squares  # at first use: see swpc_hw.calibration

    n = prob.n
    increment_floor = max(float(np.nanmax(X0[:, R])) * wheel_resolution / math.sqrt(6.0), 1e-12)
    series = prob.rolling
    x = X0.ravel().copy()
    slip = np.zeros(series.pairs().size, dtype=bool)
    for it in range(max(2, opts.irls_iterations)):
        X = as_matrix(x, n)
        C = prob.contact_points(X)
        idx, inc, dG = rolling_increments(X, C, series)
        # drifts are slopes against the model: tested once the radii are fitted (the
        # closed-form start's radii carry the bursts' bias)
        slip = detect_slip(
            inc, dG, series.ser[idx], series.t[idx],
            opts.slip_sigmas, opts.drift_chunk, opts.drift_sigmas if it > 0 else math.inf,
            lever_uncertainty(prob, X, C, fits), increment_floor,
        )
        series.run = cut_runs(series, slip)
        series.sigma = rolling_noise(prob, X, C)
        sol = least_squares(
            prob.residuals, x, jac=prob.jacobian, method="trf", x_scale="jac",
            xtol=1e-15, ftol=1e-15, gtol=1e-15, max_nfev=200,
        )
        x = canonical_parameters(as_matrix(sol.x, n)).ravel()
        _, Bv, _ = prob.blocks(x)
        zb = Bv / prob.settled.sigma
        rms_b = math.sqrt(float(np.mean(zb**2))) if zb.size else 1.0
        if rms_b > 1.0:  # settled block noisier than its prior: inflate (never deflate)
            prob.settled.sigma = prob.settled.sigma * rms_b
    return x, slip


def check_rolling_left(prob: JointProblem, slip: BoolArray, ids: list[int], source: str) -> None:
    """Refuse a module whose wheel has no rolling increment left after the slip cuts: its
    radius is then not measured (the least squares leave it anywhere: 8e7 m was seen on
    a soft-tyred physics whose wheel slipped through every spin), named, with how many
    of its increments were cut."""
    series = prob.rolling
    mods = series.mod[series.pairs()]
    for j, mid in enumerate(ids):
        mine = mods == j
        if mine.any() and not (mine & ~slip).any():
            raise CalibrationError(
                f"{source}: module {mid}'s wheel: all {int(mine.sum())} of its rolling "
                "increments were cut as slip, so its radius is not measured (a wheel "
                "slipping in every spin: its tyre, the floor, or a spin torque it cannot "
                "pass)"
            )


# ------------------------------------------------------------------ the solve


@dataclass(frozen=True)
class JointSolution:
    """A solve with what it was solved from: the joint problem, the flat solution ``x``
    and the segments' fixed-point fits (the covariance's parts, e.g. per segment:
    :func:`~swpc_hw.calibration.mocap.covariance.segment_terms`)."""

    result: CalibrationResult
    problem: JointProblem
    x: FloatArray
    fits: list[FixedPointFit]


def solve(
    ds: Dataset,
    options: SolverOptions | None = None,
    source: str = "dataset",
    start: RobotParams | None = None,
) -> CalibrationResult:
    """Calibrate all modules from a dataset (see the module docstring for the method).

    ``start``: the parameters to start from instead of stage 3's closed form (a check,
    :mod:`swpc_hw.calibration.check.verdict`: the file in force, in the dataset's frame); the
    dataset may then lock some modules at one angle, or not at all, as long as the joint
    problem determines every parameter (else the covariance is unknown)."""
    return solve_joint(ds, options, source, start).result


def solve_joint(
    ds: Dataset,
    options: SolverOptions | None = None,
    source: str = "dataset",
    start: RobotParams | None = None,
) -> JointSolution:
    """:func:`solve`, keeping the problem it solved (:class:`JointSolution`)."""
    opts = options or SolverOptions()
    ids = ds.robot.ids
    n = len(ids)
    if not ds.has_poses:
        raise CalibrationError(
            f"{source}: no poses: the motion-capture solver needs poses.csv "
            "(imu.csv: use the IMU solver, gyro.solver.solve_imu)"
        )
    plausibility.check_dataset(ds, source)
    auto = opts.time_offset == "auto"
    offset = 0.0 if auto else float(opts.time_offset)
    calibration = start is None
    segs = prepare_segments(ds, offset, source, calibration)
    fits = [fit_fixed_point(sd.poses, opts.outlier_sigmas) for sd in segs]
    for sd, fit in zip(segs, fits, strict=True):
        sd.inliers = fit.inliers
    plausibility.check_fixed_points(ds, segs, fits, source)
    if start is None:
        X0 = closed_form_geometry(fits, segs, n)
    else:
        if start.ids != ids:
            raise CalibrationError(f"{source}: start modules {start.ids} are not {ids}")
        a = start.arrays()
        X0 = np.column_stack([a.P_s, a.beta, a.b, np.full(n, np.nan)])
    tracks = encoder_tracks(ds)
    clock = ClockOffset(offset, None, "given")
    if auto:
        Xs = np.nan_to_num(X0)
        k = np.array([s.static for s in segs])
        angles = np.array([s.angle for s in segs])
        C0 = contact_point(Xs[k, P_S], Xs[k, B_COL], angles + Xs[k, BETA])
        clock = estimate_clock_offset(ds, segs, Xs, C0, tracks, opts)
        offset = clock.value
        if offset != 0.0:  # the locked angles are read at the shifted encoder times
            again = prepare_segments(ds, offset, source, calibration)
            for sd, shifted in zip(segs, again, strict=True):
                sd.angle = shifted.angle
    prob = build_problem(ds, segs, fits, tracks, offset, X0, opts)
    X0[:, R] = radius_init(prob, X0)
    x, slip = fit_joint(prob, X0, opts, fits, encoder_resolution(ds, 2))
    check_rolling_left(prob, slip, ids, source)
    X = as_matrix(x, n)
    plausibility.check_result(X, ds.robot)
    if clock.mode == "estimated":  # refined with the solution's levers
        C = prob.contact_points(X)
        clock = estimate_clock_offset(ds, segs, X, C, tracks, opts, around=clock.value)
    cov, f = joint_covariance(prob, x, fits)
    std = as_matrix(stddev_of(cov), n)
    dof = max(f.size - x.size, 1)
    params = RobotParams.from_matrix(ids, X, robot=ds.robot.robot, frame=ds.robot.frame)
    # a module whose uncertainty is not known carries no stddev (never a 0 = "exact")
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
    inc_rej = int(slip.sum())
    result = CalibrationResult(
        params=params,
        nominal=ds.robot,
        segments=segment_quality(prob, segs, fits, x, ids, slip),
        time_offset=clock.value if clock.mode == "estimated" else offset,
        time_offset_std=clock.std,
        time_offset_mode=clock.mode,
        poses_used=int(sum(int(s.inliers.sum()) for s in segs)),
        poses_rejected=int(sum(int((~s.inliers).sum()) for s in segs)),
        increments_used=int(slip.size) - inc_rej,
        increments_rejected=inc_rej,
        reduced_chi2=float(f @ f) / dof,
        covariance=cov if np.all(np.isfinite(cov)) else None,
    )
    return JointSolution(result, prob, x, fits)


def segment_quality(
    prob: JointProblem,
    segs: list[SegmentData],
    fits: list[FixedPointFit],
    x: FloatArray,
    ids: list[int],
    slip: BoolArray,
) -> list[SegmentQuality]:
    """Quality figures of every segment at the solution."""
    _, Bv, Rv = prob.blocks(x)
    C = prob.contact_points(as_matrix(x, prob.n))
    series: RollingSeries = prob.rolling
    node_seg = series.seg[series.clean]
    inc_seg = series.seg[series.pairs()]
    out = []
    for si, (sd, fit) in enumerate(zip(segs, fits, strict=True)):
        seln, seli, selb = node_seg == si, inc_seg == si, prob.settled.seg == si
        out.append(
            SegmentQuality(
                row=sd.row,
                static_module=ids[sd.static],
                angle=sd.angle,
                poses_used=int(sd.inliers.sum()),
                poses_rejected=int((~sd.inliers).sum()),
                fixed_point_rms=fit.rms,
                fixed_point=(float(C[si, 0]), float(C[si, 1])),
                fixed_point_std=fit.std,
                increments_used=int((seli & ~slip).sum()),
                increments_rejected=int((seli & slip).sum()),
                rolling_rms=float(np.sqrt(np.mean(Rv[seln] ** 2))) if seln.any() else 0.0,
                settled_rms=float(np.sqrt(np.mean(Bv[selb] ** 2))) if selb.any() else 0.0,
                noise_inflation=fit.inflation,
                noise_rho=fit.rho,
            )
        )
    return out


def solve_directory(path: str | Path, options: SolverOptions | None = None) -> CalibrationResult:
    """Load a dataset directory and solve it."""
    return solve(load_dataset(path), options, source=str(path))
