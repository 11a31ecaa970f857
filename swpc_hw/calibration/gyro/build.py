"""Building the IMU problem from a dataset, and its starting point.

* **Noise levels** (:class:`NoiseLevels`): the encoders' quantization steps (the settled
  steering's floor, a wheel reading's std dev) and the gyro's white-noise variance and
  bias walk from its rest windows (:mod:`.bias`); or given (the Fisher analysis of an
  experiment, :mod:`swpc_hw.calibration.plan.identifiability`).
* **Observations**: the settled casters (as with motion capture), every segment's wheels
  at nodes ``increment_interval`` apart, the straight drives' wheels, the gyro's integrals
  at every node, the bias knots.
* **Start** (:func:`initial_parameters`): the nominal robot; every ``beta`` from the
  settled steering (the angle a caster of the current geometry settles at, minus the
  reported one, averaged over the segments, repeated as the contact points move); the
  radii from the straight drive (``r_j = value / |dpsi_j|``) or the wheel_radius
  references; ``s = 1``; the knots at their rest means.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from swpc_hw.calibration import geometry as geo
from swpc_hw.calibration.gyro import bias
from swpc_hw.calibration.gyro.problem import ImuLayout, ImuProblem
from swpc_hw.calibration.gyro.rolling_sets import RollingSet, connected_chunks
from swpc_hw.calibration.options import SolverOptions
from swpc_hw.calibration.parameters import BETA, P_S, R
from swpc_hw.calibration.parameters import B as B_COL
from swpc_hw.calibration.prepare import LOCK_TOL, SegmentData, settled_steering
from swpc_hw.calibration.problem import SettledObservations
from swpc_hw.calibration.rolling import EncoderTrack, decimate, encoder_resolution, encoder_tracks
from swpc_hw.errors import CalibrationError, DatasetError
from swpc_hw.files.dataset import Dataset
from swpc_hw.files.references import AxisDistance, StraightDrive, WheelRadius
from swpc_hw.robot.model import contact_point

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass(frozen=True)
class NoiseLevels:
    """Noise the weights start from (SI): ``steer`` a steering reading's std dev floor
    (rad), ``wheel`` a wheel reading's (rad), ``gyro_var`` the gyro's per-sample white
    variance ((rad/s)^2) at period ``gyro_dt`` (s), ``walk_q2`` its bias walk (rad^2/s^3)."""

    steer: float
    wheel: float
    gyro_var: float
    gyro_dt: float
    walk_q2: float


@dataclass
class ImuRun:
    """A built problem with what it was built from."""

    problem: ImuProblem
    knots: bias.BiasKnots
    noise: NoiseLevels
    tracks: dict[int, EncoderTrack]
    drive_refs: list[StraightDrive]
    theta_sigma: FloatArray
    """Std dev (rad) of every settled steering reading (its spread, floored)."""


def node_times(rows: FloatArray, start: float, end: float, interval: float) -> FloatArray:
    """Encoder sample times inside ``[start, end]``, ~``interval`` apart (by time)."""
    t = rows[(rows[:, 0] >= start) & (rows[:, 0] <= end), 0]
    return np.asarray(t[decimate(t, interval)], dtype=float)


def rolling_set(
    tracks: dict[int, EncoderTrack],
    ids: list[int],
    mods: list[int],
    theta: FloatArray,
    t: FloatArray,
    wz: bias.CumulativeIntegral,
    basis: bias.CumulativeIntegral,
) -> RollingSet:
    """The wheels ``mods`` (indices) at the nodes ``t``, with the gyro's integrals there."""
    m = len(mods)
    psi = np.zeros((t.size, m))
    present = np.zeros((t.size, m), dtype=bool)
    for c, j in enumerate(mods):
        tr = tracks[ids[j]]
        inside = (t >= tr.t0) & (t <= tr.t1)
        psi[inside, c] = tr.wheel(t[inside])
        present[:, c] = inside
    run = np.broadcast_to(np.arange(m), (t.size, m)).copy()
    return RollingSet(
        mods=np.array(mods, dtype=np.int64),
        theta=np.asarray(theta, dtype=float),
        t=t,
        psi=psi,
        present=present,
        run=run,
        I_wz=wz.at(t)[:, 0],
        W_bias=basis.at(t),
        chunks=connected_chunks(present, run),
    )


ANGLE_FLOOR = 1e-8
"""Least std dev of an encoder reading (rad): exact (simulated) data stay solvable."""
GYRO_FLOOR = 1e-6
"""Least std dev of a gyro sample (rad/s), likewise."""


def estimate_noise(ds: Dataset, knots: bias.BiasKnots) -> NoiseLevels:
    """Noise levels from the data: quantization steps over sqrt(12), the rests' scatter
    (floored by :data:`ANGLE_FLOOR` and :data:`GYRO_FLOOR`, far below any real sensor's)."""
    imu = ds.imu if ds.imu is not None else np.zeros((0, 2))
    var = max(bias.white_variance(imu, knots), GYRO_FLOOR**2)
    dt = float(np.median(np.diff(imu[:, 0]))) if imu.shape[0] > 1 else 0.0
    knot_var = var / np.maximum(knots.n, 1)
    return NoiseLevels(
        steer=max(encoder_resolution(ds, 1) / math.sqrt(12.0), ANGLE_FLOOR),
        wheel=max(encoder_resolution(ds, 2) / math.sqrt(12.0), ANGLE_FLOOR),
        gyro_var=var,
        gyro_dt=dt,
        walk_q2=bias.bias_walk_intensity(knots, knot_var),
    )


def check_references(ds: Dataset, source: str) -> None:
    """Refuse an experiment whose references cannot fix what odometry needs (naming it)."""
    kinds = {r.kind for r in ds.references}
    missing = []
    if not kinds & {"straight_drive", "wheel_radius"}:
        missing.append(
            "nothing fixes the wheels' absolute radius (a straight_drive, or wheel_radius)"
        )
    if "axis_distance" not in kinds:
        missing.append(
            "nothing fixes the length scale of the module layout (axis_distance; the "
            "sides and diagonals between the steering axes)"
        )
    if missing:
        have = ", ".join(sorted(kinds)) if kinds else "none"
        raise CalibrationError(
            f"{source}/references.yaml: missing references ({have} given): "
            + "; ".join(missing)
        )


def build_imu_problem(
    ds: Dataset,
    segs: list[SegmentData],
    opts: SolverOptions,
    source: str = "dataset",
    noise: NoiseLevels | None = None,
    reference: FloatArray | None = None,
) -> ImuRun:
    """Observations and weights of an IMU run (module docstring).  ``reference``: a
    check's file parameters (N, 5): the gauge fits to its layout and fixes its scales
    (:class:`~swpc_hw.calibration.gyro.problem.ImuProblem`'s ``scale_ref``)."""
    if ds.imu is None:
        raise DatasetError(f"{source}/imu.csv: missing file (no poses.csv either)")
    imu = ds.imu
    ids = ds.robot.ids
    n = len(ids)
    res = max(encoder_resolution(ds, 1), encoder_resolution(ds, 2))
    knots = bias.bias_knots(imu, bias.rest_windows(ds, res))
    if knots.size == 0:
        raise CalibrationError(
            f"{source}: no rest window (every encoder still for >= {bias.MIN_REST:g} s with "
            "gyro samples): the gyro's bias cannot be measured"
        )
    for sd in segs:
        if not (np.min(knots.tau) < sd.segment.start and np.max(knots.tau) > sd.segment.end):
            raise CalibrationError(
                f"{source}/segments.csv: segment {sd.row + 1} (module "
                f"{sd.segment.static_module}, {sd.segment.start:g}-{sd.segment.end:g} s) has "
                "no rest window before and after it: the gyro's bias cannot be interpolated"
            )
    nl = noise or estimate_noise(ds, knots)
    tracks = encoder_tracks(ds)
    wz = bias.CumulativeIntegral.of(imu[:, 0], imu[:, 1])
    basis = bias.CumulativeIntegral.of(imu[:, 0], bias.linear_basis(knots.tau, imu[:, 0]))
    seg, mod, theta, sig = settled_steering(ds, segs, 0.0, nl.steer)
    spins = []
    for si, sd in enumerate(segs):
        sel = seg == si
        mods = [int(j) for j in mod[sel] if ids[int(j)] in tracks]
        th = np.array([theta[sel][list(mod[sel]).index(j)] for j in mods])
        first = ds.encoders[ids[mods[0]]]
        t = node_times(first, sd.segment.start, sd.segment.end, opts.increment_interval)
        rs = rolling_set(tracks, ids, mods, th, t, wz, basis)
        rs.static, rs.angle = sd.static, sd.angle
        spins.append(rs)
    drive_refs = [r for r in ds.references if isinstance(r, StraightDrive)]
    drives = [drive_set(ds, r, tracks, opts, wz, basis, source) for r in drive_refs]
    refs = [r for r in ds.references if not isinstance(r, StraightDrive)] + drive_refs
    prob = ImuProblem(
        layout=ImuLayout(n, knots.size, len(segs)),
        settled=SettledObservations(seg, mod, theta, sig),
        seg_static=np.array([s.static for s in segs], dtype=np.int64),
        seg_angle=np.array([s.angle for s in segs]),
        seg_sign=spin_directions(ds, segs, mod, seg, theta),
        angle_sigma=nl.steer,
        spins=spins,
        drives=drives,
        knot_mean=knots.mean.copy(),
        knot_sigma=np.sqrt(nl.gyro_var / knots.n + nl.walk_q2 * knots.T / 12.0 + 1e-30),
        refs=refs,
        ids=ids,
        P_nom=ds.robot.arrays().P_s if reference is None else reference[:, P_S].copy(),
        scale_ref=None if reference is None else reference[:, R].copy(),
    )
    return ImuRun(prob, knots, nl, tracks, drive_refs, sig.copy())


def spin_directions(
    ds: Dataset, segs: list[SegmentData], mod: IntArray, seg: IntArray, theta: FloatArray
) -> FloatArray:
    """The sign of every segment's yaw rate, from the settled steering (not the gyro: its
    sign is what :func:`.plausibility.check_gyro_ratio` checks; nor the wheels: a trailing
    wheel turns backwards either way).  A caster settles on one side or the other of the
    line from the pivot: of the angles the nominal robot (beta 0) would settle at for
    either sign, the one nearer the reported steering wins (they are ~170 deg apart)."""
    a = ds.robot.arrays()
    out = np.ones(len(segs))
    for si, sd in enumerate(segs):
        k = sd.static
        C = contact_point(a.P_s[k], a.b[k], sd.angle)
        sel = seg == si
        cost = [
            float(np.sum(1.0 - np.cos(
                geo.settled_angle(a.P_s[mod[sel]], a.b[mod[sel]], C, sign) - theta[sel]
            )))
            for sign in (1.0, -1.0)
        ]
        out[si] = 1.0 if cost[0] <= cost[1] else -1.0
    return out


def drive_set(
    ds: Dataset,
    ref: StraightDrive,
    tracks: dict[int, EncoderTrack],
    opts: SolverOptions,
    wz: bias.CumulativeIntegral,
    basis: bias.CumulativeIntegral,
    source: str,
) -> RollingSet:
    """The wheels of a straight drive, their held steering checked."""
    ids = ds.robot.ids
    where = f"{source}/references.yaml: straight_drive {ref.start:g}-{ref.end:g} s"
    theta = []
    for mid in ids:
        rows = ds.encoders[mid]
        steer = rows[(rows[:, 0] >= ref.start) & (rows[:, 0] <= ref.end), 1]
        if steer.size < 2:
            raise DatasetError(f"{where}: no encoder samples of module {mid} in its window")
        steer = steer[0] + (np.mod(steer - steer[0] + math.pi, 2 * math.pi) - math.pi)
        med = float(np.median(steer))
        if float(np.max(np.abs(steer - med))) > LOCK_TOL:
            raise DatasetError(
                f"{where}: module {mid}'s steering moved "
                f"{math.degrees(float(np.ptp(steer))):.1f} deg: not a straight drive"
            )
        theta.append(med)
    t = node_times(ds.encoders[ids[0]], ref.start, ref.end, opts.increment_interval)
    return rolling_set(tracks, ids, list(range(len(ids))), np.array(theta), t, wz, basis)


def initial_parameters(
    run: ImuRun, ds: Dataset, iterations: int = 8, start: FloatArray | None = None
) -> FloatArray:
    """The starting point (module docstring); ``start`` (N, 5): a check's file, its
    ``beta`` kept."""
    prob = run.problem
    a = ds.robot.arrays()
    X = np.column_stack([a.P_s, np.zeros(a.n), a.b, a.r]) if start is None else start.copy()
    if start is not None:
        iterations = 0
    st = prob.settled
    k = prob.seg_static
    for _ in range(iterations):
        C = contact_point(X[k, P_S], X[k, B_COL], prob.seg_angle + X[k, BETA])
        th = geo.settled_angle(X[st.mod, P_S], X[st.mod, B_COL], C[st.seg], prob.seg_sign[st.seg])
        d = th - st.theta
        for j in range(a.n):
            sel = st.mod == j
            if sel.any():
                X[j, BETA] = math.atan2(
                    float(np.sin(d[sel]).mean()), float(np.cos(d[sel]).mean())
                )
    for ref in prob.refs:
        if isinstance(ref, WheelRadius):
            X[prob.ids.index(ref.module), R] = ref.value
    for ref, rs in zip(run.drive_refs, prob.drives, strict=True):
        X[rs.mods, R] = drive_radii(rs.psi, ref.value)
    x = np.zeros(prob.layout.size)
    x[: X.size] = X.ravel()
    x[prob.layout.scale] = 1.0
    x[prob.layout.knots] = run.knots.mean
    return x


def drive_radii(psi: FloatArray, length: float) -> FloatArray:
    """Radii from a straight drive's wheel angles ``psi`` (L, m), robust to slip bursts.

    Per increment the wheels' rotations against their median, ``rho_j = median_l(dpsi_jl /
    median_k dpsi_kl)`` over the increments that move; the median wheel turned
    ``Psi = sum_l median_k dpsi_kl``; so ``r_j = length / |rho_j Psi|`` (a burst in one
    wheel moves neither median).
    """
    d = np.diff(psi, axis=0)
    med = np.median(d, axis=1)
    moving = np.abs(med) > 0.1 * np.abs(med).max()
    rho = np.median(d[moving] / med[moving, None], axis=0)
    return np.asarray(length / np.abs(rho * med.sum()), dtype=float)


def axis_distance_refs(prob: ImuProblem) -> list[AxisDistance]:
    """The axis-distance references of a problem."""
    return [r for r in prob.refs if isinstance(r, AxisDistance)]
