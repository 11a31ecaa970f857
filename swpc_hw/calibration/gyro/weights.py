"""The gyro solver's weights and slip cuts: every block's noise scale, re-estimated from its
residuals, and the wheel increments that disagree with the gyro cut from the wheels' runs
(stage 4 of :mod:`swpc_hw.calibration.gyro.solver`).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from swpc_hw.calibration.gyro.bias import walk_variance
from swpc_hw.calibration.gyro.build import (
    ImuRun,
)
from swpc_hw.calibration.gyro.problem import ImuProblem
from swpc_hw.calibration.gyro.rolling_sets import RollingSet, connected_chunks
from swpc_hw.calibration.options import SolverOptions
from swpc_hw.calibration.parameters import R
from swpc_hw.calibration.slip import detect_slip, mad_sigma
from swpc_hw.errors import CalibrationError
from swpc_hw.files.references import StraightDrive

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

DRIVE_SLIP_SHARE = 0.1
"""A straight drive's wheel is cut for a burst only beyond this share of its tape's std dev
(the drive's length reference): a smaller one cannot move the length the drive gives.  The
drive's start and stop carry transients the model does not hold, the same shape on every
wheel at once (1.1-1.4e-5 m on a 5 s drive, docs/figures.md), which the encoders' floor
alone took for slips on all four wheels and the drive fell into pieces."""
MAX_SLIP_FRACTION = 0.1
"""More wheel increments than this fraction disagreeing with the gyro is no slip: refused."""


def spin_levers(prob: ImuProblem, x: FloatArray) -> list[FloatArray]:
    """The lever of every module of every segment at ``x``."""
    X, _, _ = prob.layout.split(x)
    C = prob.contact_points(x)
    return [prob.spin_levers(X, C, rs, s) for s, rs in enumerate(prob.spins)]


def set_gyro_sigma(prob: ImuProblem, run: ImuRun, x: FloatArray) -> None:
    """Std dev of every chunk's gyro yaw: integrated white noise, the bias walk about the
    knots' line (both over ``s^2``) and the wheels' own yaw noise (two nodes:
    ``2 sigma_psi^2 / |g / r|^2``); of every drive's turn: the first two and the knots'
    mean std dev ``sigma_b`` times its duration (the bias between its rests)."""
    X, s, _ = prob.layout.split(x)
    nl = run.noise
    for rs, g in zip(prob.spins, spin_levers(prob, x), strict=True):
        h = g / X[rs.mods, R]
        sig = []
        for la, lb in rs.chunks:
            t_a, t_b = float(rs.t[la]), float(rs.t[lb])
            var = nl.gyro_var * nl.gyro_dt * (t_b - t_a) + walk_variance(
                run.knots, nl.walk_q2, t_a, t_b
            )
            wheels = 2.0 * rs.sigma**2 / max(float(h @ h), 1e-12)
            sig.append(math.sqrt(var / (s * s) + wheels + 1e-30))
        rs.gyro_sigma = np.array(sig)
    for rs in prob.drives:  # the turn over the whole drive (docs/imu.md, the drive's arc)
        t_a, t_b = float(rs.t[0]), float(rs.t[-1])
        var = nl.gyro_var * nl.gyro_dt * (t_b - t_a) + walk_variance(
            run.knots, nl.walk_q2, t_a, t_b
        )
        sigma_b = float(np.mean(prob.knot_sigma))
        rs.gyro_sigma = np.array([math.sqrt(var / (s * s) + (sigma_b * (t_b - t_a)) ** 2)])
    prob.restack()


def rolling_scale(prob: ImuProblem, rs: RollingSet, resid: FloatArray, floor: float) -> float:
    """Noise std dev (rad) of a wheel angle at a node from a set's profiled residuals:
    ``sqrt(sum e^2 / dof)``, ``dof = sum_l (m_l - 1) - (runs - chunks)``, floored."""
    cnt = rs.present.sum(axis=1)
    n_run = np.unique(rs.run[rs.present]).size
    dof = int(np.sum(np.maximum(cnt - 1, 0))) - (n_run - len(rs.chunks))
    if dof <= 0:
        return max(rs.sigma, floor)
    return max(math.sqrt(float(np.sum(resid[rs.present] ** 2)) / dof), floor)


def update_scales(prob: ImuProblem, x: FloatArray, floor: float) -> None:
    """Every rolling set's noise scale from its residuals at ``x``."""
    X, _, _ = prob.layout.split(x)
    for rs, g in zip(prob.spins, spin_levers(prob, x), strict=True):
        rs.sigma = rolling_scale(prob, rs, prob.rolled(X, rs, g)[0], floor)
    for rs in prob.drives:
        rs.sigma = rolling_scale(prob, rs, prob.drive_arc(x, rs)[1], floor)
    prob.restack()


# ------------------------------------------------------------------ slip


def wheel_increments(
    prob: ImuProblem, x: FloatArray
) -> tuple[list[FloatArray], list[FloatArray]]:
    """Every rolling set's wheel increments against a reference, ``(d - k ref, ref)``
    (L-1, m).

    A segment's wheels against the gyro: ``d = r dpsi``, ``ref = g dyaw`` with the gyro's
    yaw (:meth:`RollingSet.gyro_yaw`).  A straight drive's (no rotation for the gyro to
    see) against each other: ``d = r cos(theta - phi) dpsi``, the distance each wheel says
    the robot moved, and ``ref`` the median of the wheels' at that increment.  ``k`` per
    wheel is the median of ``d / ref`` where the reference moves: a radius or lever still
    off (a slipping drive's start) scales a wheel's increments, a slip burst does not
    follow the reference.  Spins first, then drives.
    """
    X, s, knots = prob.layout.split(x)
    inc, ref = [], []
    for rs, g in zip(prob.spins, spin_levers(prob, x), strict=True):
        L = rs.t.size
        dyaw = rs.gyro_yaw(s, knots, np.arange(L - 1), np.arange(1, L))
        d = g[None, :] * dyaw[:, None]
        inc.append(scaled_residual(X[rs.mods, R][None, :] * np.diff(rs.psi, axis=0), d))
        ref.append(d)
    for rs in prob.drives:
        d = (X[rs.mods, R] * prob.drive_arc(x, rs)[0])[None, :] * np.diff(rs.psi, axis=0)
        med = np.median(d, axis=1, keepdims=True)
        # the wheels scaled to agree first: one far off (a radius not yet fitted, a
        # slipping start) no longer moves the median when it slips
        med = np.median(d / wheel_scales(d, med), axis=1, keepdims=True)
        med = np.broadcast_to(med, d.shape)
        inc.append(scaled_residual(d, med))
        ref.append(med)
    return inc, ref


def wheel_scales(d: FloatArray, ref: FloatArray) -> FloatArray:
    """``k`` (m,) per column: the median of ``d / ref`` where ``|ref|`` is over a tenth of
    its largest (1 without such rows)."""
    r = np.broadcast_to(ref, d.shape)
    k = np.ones(d.shape[1])
    for c in range(d.shape[1]):
        moving = np.abs(r[:, c]) > 0.1 * np.abs(r[:, c]).max()
        if moving.any():
            k[c] = float(np.median(d[moving, c] / r[moving, c]))
    return k


def scaled_residual(d: FloatArray, ref: FloatArray) -> FloatArray:
    """``d - k ref`` per column with ``k`` of :func:`wheel_scales`."""
    return np.asarray(d - wheel_scales(d, ref)[None, :] * ref, dtype=float)


MIN_JUDGED_INCREMENTS = 3
"""A series (one wheel in one rolling set) needs this many increments to be judged for
slip in the pooled screen."""


def increment_floors(
    prob: ImuProblem, sizes: list[int], floor: float, slip_sigmas: float
) -> FloatArray:
    """The least std dev (m) of every increment of :func:`cut_slip`'s series (``sizes``
    increments each, every spin's modules, then every drive's): the encoders' ``floor``,
    and on a straight drive at least ``DRIVE_SLIP_SHARE x its tape's std dev / slip_sigmas``
    (:data:`DRIVE_SLIP_SHARE`)."""
    tapes = [r.stddev for r in prob.refs if isinstance(r, StraightDrive)]
    if len(tapes) != len(prob.drives):
        tapes = [0.0] * len(prob.drives)  # a check's drive without its tape: the floor
    per_set = [floor] * len(prob.spins) + [
        max(floor, DRIVE_SLIP_SHARE * tape / slip_sigmas) for tape in tapes
    ]
    out: list[FloatArray] = []
    k = 0
    for rs, f in zip([*prob.spins, *prob.drives], per_set, strict=True):
        for _ in range(rs.mods.size):
            out.append(np.full(sizes[k], f))
            k += 1
    return np.concatenate(out) if out else np.zeros(0)


def cut_slip(
    prob: ImuProblem,
    valid: list[BoolArray],
    x: FloatArray,
    opts: SolverOptions,
    floor: float,
    pooled: bool = False,
) -> list[int]:
    """Find slip bursts, re-cut every rolling set's runs; returns the increments cut in
    every rolling set (spins, then drives).

    A wheel's increment whose residual against its reference (:func:`wheel_increments`)
    is beyond ``slip_sigmas`` robust sigmas of its series (and one either side) slips
    (:func:`.slip.detect_slip`, bursts only: see docs/imu.md).  A slip starts a
    new run of that wheel (its constant jumps); runs of one node are dropped.  A straight
    drive must stay one connected run of nodes (its length is end minus start).
    ``pooled``: one robust sigma for all increments (the coarse problem's series are too
    short for their own).
    """
    sets = [*prob.spins, *prob.drives]
    inc, ref = wheel_increments(prob, x)
    flat_inc, flat_ref, ser, t, where = [], [], [], [], []
    k = 0
    for si, (rs, v) in enumerate(zip(sets, valid, strict=True)):
        ok = v[1:] & v[:-1]
        for c in range(rs.mods.size):
            sel = np.flatnonzero(ok[:, c])
            flat_inc.append(inc[si][sel, c])
            flat_ref.append(ref[si][sel, c])
            ser.append(np.full(sel.size, k))
            t.append(rs.t[sel])
            where += [(si, c, int(i)) for i in sel]
            k += 1
    all_inc, all_ser = np.concatenate(flat_inc), np.concatenate(ser).astype(np.int64)
    if pooled:  # few increments per series: one robust scale for all
        # a series' own scale k (wheel_increments) fits its only increment exactly: series
        # of one or two increments say nothing of the noise and cannot show a burst (short
        # sweeps: their zeros took the pooled sigma to 0 and cut a clean drive)
        judged = np.bincount(all_ser, minlength=k)[all_ser] >= MIN_JUDGED_INCREMENTS
        sigma = max(mad_sigma(all_inc[judged]), floor)
        bad = judged & (np.abs(all_inc) > opts.slip_sigmas * sigma)
        slip = bad.copy()
        same = all_ser[1:] == all_ser[:-1]
        slip[1:] |= bad[:-1] & same
        slip[:-1] |= bad[1:] & same
    else:
        slip = detect_slip(
            all_inc, np.concatenate(flat_ref), all_ser, np.concatenate(t),
            opts.slip_sigmas, opts.drift_chunk, math.inf, np.full(k, 1e-3),
            increment_floors(prob, [len(f) for f in flat_inc], floor, opts.slip_sigmas),
        )
    cut = [np.zeros((rs.t.size - 1, rs.mods.size), dtype=bool) for rs in sets]
    for (si, c, i), bad in zip(where, slip.tolist(), strict=True):
        cut[si][i, c] = bad
    for rs, v, cu in zip(sets, valid, cut, strict=True):
        brk = np.vstack([np.zeros((1, rs.mods.size), dtype=np.int64), np.cumsum(cu, axis=0)])
        key = brk * rs.mods.size + np.arange(rs.mods.size)[None, :]
        present = v.copy()
        _, inv, counts = np.unique(key[present], return_inverse=True, return_counts=True)
        keep = counts[inv] >= 2
        idx = np.flatnonzero(present.ravel())
        present.ravel()[idx[~keep]] = False
        _, dense = np.unique(key[present], return_inverse=True)
        run = np.zeros_like(key)
        run[present] = dense
        rs.present, rs.run = present, run
        rs.chunks = connected_chunks(present, run)
    for rs in prob.drives:
        if rs.chunks != [(0, rs.t.size - 1)]:
            raise CalibrationError(
                f"straight drive {rs.t[0]:g}-{rs.t[-1]:g} s: its wheels disagree with each "
                "other and the gyro's turn at once (every wheel slipped, the gyro and the "
                "wheels disagree, or a wheel's samples are missing): its length cannot be "
                "followed"
            )
    prob.restack()
    return [int(c.sum()) for c in cut]


# ------------------------------------------------------------------ solving


def initial_weights(run: ImuRun, x: FloatArray) -> float:
    """Weights from the noise levels at ``x``; returns the wheel angles' floor (rad).

    A wheel angle at a node: ``sigma_wheel`` (every rolling set); a settled caster:
    ``max(|g|, 0.05 m) sigma_theta`` (its steering's std dev times its lever, as with
    motion capture); every gyro chunk (:func:`set_gyro_sigma`).
    """
    prob = run.problem
    floor = max(run.noise.wheel, 1e-15)
    for rs in [*prob.spins, *prob.drives]:
        rs.sigma = floor
    st = prob.settled
    levers = spin_levers(prob, x)
    lever = [
        abs(float(levers[si][list(prob.spins[si].mods).index(j)]))
        for si, j in zip(st.seg.tolist(), st.mod.tolist(), strict=True)
    ]
    st.sigma = np.maximum(np.array(lever), 0.05) * run.theta_sigma
    set_gyro_sigma(prob, run, x)
    return floor


