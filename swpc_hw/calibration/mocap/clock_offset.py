"""The clock offset between encoders and poses, from the rolling consistency of the spins.

``delta`` = encoder clock - pose clock.  During a steady spin a shift of the encoders by
``delta`` adds ``r psi_dot delta``, a constant, to the cumulative rolling residual, which
its intercept absorbs: steady spinning says nothing about ``delta``.  The ramps do: the
wheel speed changes there.  So the whole *hold* period of every segment is used (the
locked module within 0.02 deg of its angle: alignment tail, ramp up, spin, ramp down).

Cost (smooth in ``delta``, :mod:`swpc_hw.calibration.rolling`): fixed pose nodes (inlier
poses ~``offset_node_interval`` apart, chosen once, inside the hold window for every
``delta`` of the search range), encoders from cubic splines at ``t + delta``; per series
the radius and per clean run the intercept are profiled out by linear least squares::

    e_l(delta) = r_ser (psi(t_l + delta) - psi_bar_run) - (G_l(delta) - G_bar_run)

1. coarse: a grid over ``offset_bounds``, Cauchy cost of the increments (robust to slip
   bursts while ``delta`` is still wrong);
2. slip bursts found at the coarse minimum cut the series into runs (fixed thereafter);
3. fine: bounded Brent on ``sum (e / sigma_ser)^2``; after the joint solve, once more
   with its parameters (the closed-form start's levers are cruder: their error during
   the ramps, where the casters turn, does not scale out with the radius);
4. std dev: the HAC sandwich ``sqrt(Omega) / H`` with ``H = sum j_l^2``,
   ``j = de/d delta`` and ``Omega`` the variance of the score sum ``sum j_l e_l`` from
   the yaw noise it carries, node by node, AR(1) measured from the data
   (:mod:`swpc_hw.calibration.mocap.yaw_noise`: while the casters swing round at the start of
   a hold window one node's noise is carried into every later cumulative residual).
5. what the noise does not explain (a wheel slipping steadily through one module's
   spins pulls the estimate 1 ms and more, 15 of those std devs): in the refinement the
   fine search once more without each locked module's segments, the leave-one-module-out
   spread ``sqrt((G - 1) / G sum (delta_g - delta_bar)^2)`` (:func:`jackknife_std`); when
   it exceeds :data:`JACKKNIFE_RATIO` times the sandwich's, it is the std dev.

A std dev above ``offset_max_std`` (or no information at all, as in a dataset of steady
spins only) is reported as **not observable**: 0 is assumed, harmless because then the
parameters do not depend on it either.  An estimate at the edge of the search range is
refused.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from swpc_hw.calibration.fixed_point import robust_fixed_point
from swpc_hw.calibration.mocap.yaw_noise import score_variance
from swpc_hw.calibration.options import SolverOptions
from swpc_hw.calibration.prepare import SegmentData
from swpc_hw.calibration.rolling import (
    EncoderTrack,
    RollingSeries,
    build_rolling_series,
    cut_runs,
    decimate,
    encoder_resolution,
    profiled_series_radius,
    rolling_levers,
)
from swpc_hw.calibration.slip import burst_slip, mad_sigma
from swpc_hw.errors import ImplausibleDataError
from swpc_hw.files.dataset import Dataset

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

REFINE_HALF_WIDTH = 0.002
"""Half width (s) of the refinement's search around a previous estimate."""
HOLD_TOLERANCE = math.radians(0.02)
"""The locked module is holding its angle while within this of it (rad), or within three
encoder counts if those are coarser.  Tight: as the locked module starts to re-steer the
body turns about its steering axis, not about the contact point the cost assumes, and
that error sits where the timing is observed (0.2 deg gave std devs ~20 % small)."""


@dataclass(frozen=True)
class ClockOffset:
    """The clock offset (encoder - pose, s), its std dev and how it was obtained.

    ``mode``: ``given``, ``estimated`` or ``not observable`` (``value`` 0 assumed, ``std``
    None).  ``information_std``: the std dev the data would give even when judged not
    observable (inf without information).
    """

    value: float
    std: float | None
    mode: str
    information_std: float = math.inf


def hold_window(ds: Dataset, sd: SegmentData, tol: float = HOLD_TOLERANCE) -> tuple[float, float]:
    """Encoder-clock interval around the segment in which the locked module holds its angle."""
    enc = ds.encoders[sd.segment.static_module]
    t = enc[:, 0]
    ok = np.abs(enc[:, 1] - sd.angle) <= tol
    mid = int(np.searchsorted(t, 0.5 * (sd.segment.start + sd.segment.end)))
    mid = min(max(mid, 0), t.shape[0] - 1)
    lo = mid
    while lo > 0 and ok[lo - 1]:
        lo -= 1
    hi = mid
    while hi < t.shape[0] - 1 and ok[hi + 1]:
        hi += 1
    return float(t[lo]), float(t[hi])


def offset_nodes(
    ds: Dataset,
    segs: list[SegmentData],
    tracks: dict[int, EncoderTrack],
    bounds: tuple[float, float],
    interval: float,
    outlier_sigmas: float,
) -> list[FloatArray]:
    """Fixed pose nodes (K, 4) of every segment's hold window, valid for every offset in ``bounds``.

    A pose at ``t`` is a node if ``t + delta`` stays inside the hold window and inside
    every module's encoder track for all ``delta`` in ``bounds``; fixed-point outliers
    are left out.  A segment without enough poses gets an empty array.
    """
    lo, hi = bounds
    t0 = max(tr.t0 for tr in tracks.values())
    t1 = min(tr.t1 for tr in tracks.values())
    nodes: list[FloatArray] = []
    tol = max(HOLD_TOLERANCE, 3.0 * encoder_resolution(ds))
    for sd in segs:
        a, b = hold_window(ds, sd, tol)
        first, last = max(a, t0) - lo, min(b, t1) - hi
        sel = (ds.poses[:, 0] >= first) & (ds.poses[:, 0] <= last)
        poses = ds.poses[sel].copy()
        if poses.shape[0] < 10:
            nodes.append(np.zeros((0, 4)))
            continue
        poses[:, 3] = np.unwrap(poses[:, 3])
        _, _, mask, _ = robust_fixed_point(poses[:, 1:], outlier_sigmas)
        inl = poses[mask]
        nodes.append(inl[decimate(inl[:, 0], interval)])
    return nodes


def profiled_rolling_residuals(
    X: FloatArray, C: FloatArray, series: RollingSeries
) -> FloatArray:
    """``e = r_ser psi~ - G~`` per clean node: radius per series, intercept per run profiled.

    ``~``: centred within the run.  Uses ``series.run`` (clean runs).
    """
    sel = series.clean
    run = series.run[sel]
    ser = series.ser[sel]
    g = rolling_levers(X, C, series)[sel]
    yaw, psi = series.yaw[sel], series.psi[sel]
    dG = np.zeros_like(g)
    same = run[1:] == run[:-1]
    dG[1:] = np.where(same, 0.5 * (g[1:] + g[:-1]) * (yaw[1:] - yaw[:-1]), 0.0)
    G = np.cumsum(dG)
    counts = np.maximum(np.bincount(run), 1)
    Gc = G - (np.bincount(run, weights=G) / counts)[run]
    pc = psi - (np.bincount(run, weights=psi) / counts)[run]
    nser = int(np.max(series.ser)) + 1
    num = np.bincount(ser, weights=pc * Gc, minlength=nser)
    den = np.bincount(ser, weights=pc * pc, minlength=nser)
    r = np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)
    return np.asarray(r[ser] * pc - Gc, dtype=float)


def estimate_clock_offset(
    ds: Dataset,
    segs: list[SegmentData],
    X: FloatArray,
    C: FloatArray,
    tracks: dict[int, EncoderTrack],
    opts: SolverOptions,
    around: float | None = None,
) -> ClockOffset:
    """Estimate the clock offset (module docstring).  ``C``: (S, 2) contact points of ``segs``.

    ``around``: a previous estimate (with cruder parameters ``X``): the coarse grid is
    skipped and the fine search spans :data:`REFINE_HALF_WIDTH` either side of it.
    """
    ids = ds.robot.ids
    lo, hi = opts.offset_bounds
    all_nodes = offset_nodes(
        ds, segs, tracks, opts.offset_bounds, opts.offset_node_interval, opts.outlier_sigmas
    )
    keep = [i for i, nd in enumerate(all_nodes) if nd.shape[0] >= 4]
    if not keep:
        return ClockOffset(0.0, None, "not observable")
    static = [segs[i].static for i in keep]
    nodes = [all_nodes[i] for i in keep]
    C_kept = C[keep]

    def build(delta: float) -> RollingSeries:
        return build_rolling_series(tracks, ids, static, nodes, delta)

    base = build(0.5 * (lo + hi))
    if base.size == 0:
        return ClockOffset(0.0, None, "not observable")
    inc0, _ = profiled_series_radius(X, C_kept, base)
    ser0 = base.ser[base.pairs()]
    scale = np.array([max(mad_sigma(inc0[ser0 == k]), 1e-12) for k in range(int(np.max(ser0)) + 1)])

    def coarse_cost(delta: float) -> float:
        inc, _ = profiled_series_radius(X, C_kept, build(delta))
        z = inc / scale[ser0]
        c = opts.cauchy_c
        return float(0.5 * np.sum(c * c * np.log1p((z / c) ** 2)))

    step = opts.offset_grid_step
    if around is None:
        grid = np.arange(lo, hi + 0.5 * step, step)
        best = float(grid[int(np.argmin([coarse_cost(float(d)) for d in grid]))])
    else:
        best = around
    sigma = scale / math.sqrt(2.0)
    half = step if around is None else REFINE_HALF_WIDTH
    whole = {
        (sg, md): sr
        for sg, md, sr in zip(base.seg.tolist(), base.mod.tolist(), base.ser.tolist(), strict=True)
    }

    def fine(sel: list[int], start: float, width: float) -> tuple[float, RollingSeries, IntArray]:
        """The fine search over the segments ``sel`` (indices into the kept ones): the
        estimate, its nodes and their clean runs (slip bursts at ``start``)."""
        from scipy.optimize import minimize_scalar  # at first use: see swpc_hw.calibration

        def build_sel(delta: float) -> RollingSeries:
            return build_rolling_series(
                tracks, ids, [static[i] for i in sel], [nodes[i] for i in sel], delta
            )

        C_sel = C_kept[sel]
        s0 = build_sel(start)
        inc, _ = profiled_series_radius(X, C_sel, s0)
        runs = cut_runs(s0, burst_slip(inc, s0.ser[s0.pairs()], opts.slip_sigmas))
        # every series' weight: that of the same segment and module in the whole set
        n_ser = int(np.max(s0.ser)) + 1 if s0.ser.size else 0
        sig = np.ones(n_ser)
        for sg, md, sr in zip(s0.seg.tolist(), s0.mod.tolist(), s0.ser.tolist(), strict=True):
            sig[sr] = sigma[whole[(sel[sg], md)]]

        def res_sel(delta: float) -> FloatArray:
            sr = build_sel(delta)
            sr.run = runs
            return profiled_rolling_residuals(X, C_sel, sr) / sig[sr.ser[runs >= 0]]

        out = minimize_scalar(
            lambda d: float(np.sum(res_sel(d) ** 2)),
            bounds=(max(lo, start - width), min(hi, start + width)),
            method="bounded",
            options={"xatol": 1e-6},
        )
        v = float(out.x)
        sv = build_sel(v)
        sv.run = runs
        return v, sv, runs

    everything = list(range(len(keep)))
    value, s_val, runs = fine(everything, best, half)

    def residuals(delta: float) -> FloatArray:
        sr = build(delta)
        sr.run = runs
        return profiled_rolling_residuals(X, C_kept, sr) / sigma[sr.ser[runs >= 0]]

    std = _sandwich_std(residuals, value, s_val, rolling_levers(X, C_kept, s_val), sigma)
    if around is not None and math.isfinite(std):
        spread = jackknife_std(
            [fine([i for i in everything if static[i] != k], value, JACKKNIFE_HALF_WIDTH)[0]
             for k in sorted(set(static))]
        )
        if spread > JACKKNIFE_RATIO * std:  # the modules disagree: slip, not noise
            std = spread
    if not math.isfinite(std) or std > opts.offset_max_std:
        return ClockOffset(0.0, None, "not observable", std)
    if value - lo < step or hi - value < step:
        raise ImplausibleDataError(
            f"clock offset: the best fit {value * 1e3:.1f} ms is at the edge of the search "
            f"range {lo * 1e3:.0f}..{hi * 1e3:.0f} ms: the encoder and pose clocks differ "
            "by more than that (give --time-offset in seconds)"
        )
    return ClockOffset(value, std, "estimated", std)


JACKKNIFE_HALF_WIDTH = 0.02
"""Half width (s) of a leave-one-module-out search around the estimate."""
JACKKNIFE_RATIO = 2.0
"""The leave-one-module-out spread replaces the sandwich std dev beyond this ratio: with
four modules (three degrees of freedom) noise alone exceeds it 0.7 % of the time."""


def jackknife_std(values: list[float]) -> float:
    """Leave-one-group-out std dev ``sqrt((G - 1) / G sum (v_g - v_bar)^2)`` (0 for fewer
    than two groups)."""
    v = np.asarray(values, dtype=float)
    if v.size < 2:
        return 0.0
    return math.sqrt((v.size - 1) / v.size * float(np.sum((v - v.mean()) ** 2)))


def _sandwich_std(
    residuals: Callable[[float], FloatArray],
    value: float,
    series: RollingSeries,
    levers: FloatArray,
    sigma: FloatArray,
    h: float = 1e-4,
) -> float:
    """``sqrt(Var(sum_l j_l e_l)) / H`` (module docstring, step 4).

    ``series``: the nodes at ``value`` with their clean runs; ``levers``: ``g`` of every
    node; ``sigma``: the weight (m) of every series.  The score sum's variance is that of
    the yaw noise it carries (:func:`swpc_hw.calibration.mocap.yaw_noise.score_variance`).
    """
    e = residuals(value)
    j = (residuals(value + h) - residuals(value - h)) / (2 * h)
    H = float(j @ j)
    if H <= 0:
        return math.inf
    sig = sigma[series.ser[series.clean]]
    return math.sqrt(score_variance(series, levers, j / sig, e * sig)) / H
