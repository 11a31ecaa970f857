"""The rolling observations: wheel encoders against the measured yaw at fixed pose nodes.

While the robot spins about the locked contact point ``C`` (in R), a free caster j rolls
``r_j dpsi_j = g_j dyaw`` with the lever ``g_j = (P_w,j - C) x u(theta_j)``
(:func:`swpc_hw.calibration.geometry.rolling_lever`).  Over a run of nodes
``t_0 < t_1 < ...`` the cumulative form is::

    r_j psi_j(t_l) - G_j(t_l) = c_run,     G_j(t_l) = sum_m (g_m + g_m+1) / 2 (yaw_m+1 - yaw_m)

The nodes are **poses** (inliers of the segment's fixed-point fit, ~``interval`` apart;
the joint solve takes each as the mean of the inlier poses within a few frames): their
yaw is used as measured, never interpolated between poses.  The encoders are smooth
functions of time (:class:`EncoderTrack`, cubic splines through the samples), evaluated
at the node times shifted by the clock offset.  So a change of the clock offset moves
the encoder values smoothly and never re-selects a sample: the cost is smooth in it.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from swpc_hw.calibration import geometry as geo
from swpc_hw.calibration.parameters import BETA, P_S, R
from swpc_hw.calibration.parameters import B as B_COL
from swpc_hw.files.dataset import Dataset

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]


@dataclass(frozen=True)
class EncoderTrack:
    """One module's reported steering and wheel angle as smooth functions of encoder time.

    Cubic splines through the samples (steering unwrapped first; duplicate stamps keep
    their first sample).  Valid on ``[t0, t1]`` (encoder clock).
    """

    t0: float
    t1: float
    steer_spline: Any
    wheel_spline: Any

    @classmethod
    def from_rows(cls, rows: FloatArray) -> EncoderTrack:
        """``rows``: (K, 3) ``t, steer, wheel`` sorted by t."""
        from scipy.interpolate import CubicSpline  # at first use: see swpc_hw.calibration

        t, first = np.unique(rows[:, 0], return_index=True)
        steer = np.unwrap(rows[first, 1])
        wheel = rows[first, 2]
        if t.size < 2:
            raise ValueError("an encoder track needs at least two distinct sample times")
        if t.size < 4:  # too few for a cubic: linear
            return cls(float(t[0]), float(t[-1]), _Linear(t, steer), _Linear(t, wheel))
        return cls(float(t[0]), float(t[-1]), CubicSpline(t, steer), CubicSpline(t, wheel))

    def steer(self, t: FloatArray) -> FloatArray:
        """Reported steering angle ``theta_hat`` (unwrapped, rad) at encoder times ``t``."""
        return np.asarray(self.steer_spline(t), dtype=float)

    def wheel(self, t: FloatArray) -> FloatArray:
        """Reported wheel angle ``psi`` (rad) at encoder times ``t``."""
        return np.asarray(self.wheel_spline(t), dtype=float)


@dataclass(frozen=True)
class _Linear:
    t: FloatArray
    y: FloatArray

    def __call__(self, x: FloatArray) -> FloatArray:
        return np.asarray(np.interp(x, self.t, self.y), dtype=float)


def encoder_tracks(ds: Dataset) -> dict[int, EncoderTrack]:
    """An :class:`EncoderTrack` for every module that has two or more encoder samples."""
    return {
        mid: EncoderTrack.from_rows(rows)
        for mid, rows in ds.encoders.items()
        if np.unique(rows[:, 0]).size >= 2
    }


def encoder_resolution(ds: Dataset, column: int = 1) -> float:
    """Quantization step of the encoders (rad; column 1 steering, 2 wheel): the smallest
    step between the distinct reported values of a module, the median over modules
    (1e-9 at least)."""
    steps = []
    for rows in ds.encoders.values():
        u = np.unique(rows[:, column])
        d = np.diff(u)
        d = d[d > 0]
        if d.size:
            steps.append(float(np.min(d)))
    return max(float(np.median(steps)) if steps else 0.0, 1e-9)


def decimate(t: FloatArray, interval: float) -> IntArray:
    """Indices of the samples nearest to the grid ``t_0 + k interval`` (each once).

    By time, not by count: dropped samples do not stretch the spacing.
    """
    if t.size < 2:
        return np.arange(t.size, dtype=np.int64)
    grid = np.arange(float(t[0]), float(t[-1]) + 0.5 * interval, interval)
    right = np.clip(np.searchsorted(t, grid), 1, t.size - 1)
    nearest = np.where(grid - t[right - 1] <= t[right] - grid, right - 1, right)
    return np.asarray(np.unique(nearest), dtype=np.int64)


@dataclass
class RollingSeries:
    """Nodes of every (segment, dynamic module) series, concatenated, ordered by series then time.

    ``seg``, ``mod`` (module index), ``ser`` (series number), ``bin`` (node number within
    its segment plus an offset per segment: nodes of different modules at the same pose
    share a bin), ``t`` (pose clock), ``yaw`` (as measured), ``psi``, ``theta`` (reported,
    at ``t`` + offset).  ``run``: clean run of every node (-1: cut out), set by
    :func:`cut_runs`; ``sigma``: noise std dev of every node (m).
    """

    seg: IntArray
    mod: IntArray
    ser: IntArray
    bin: IntArray
    t: FloatArray
    yaw: FloatArray
    psi: FloatArray
    theta: FloatArray
    run: IntArray = field(default_factory=lambda: np.zeros(0, np.int64))
    sigma: FloatArray = field(default_factory=lambda: np.zeros(0))

    @property
    def size(self) -> int:
        return int(self.ser.shape[0])

    def pairs(self) -> IntArray:
        """Index l of every increment (node l -> l+1) inside one series."""
        return np.flatnonzero(self.ser[1:] == self.ser[:-1])

    @property
    def clean(self) -> BoolArray:
        """Nodes in a clean run."""
        return np.asarray(self.run >= 0)


def build_rolling_series(
    tracks: Mapping[int, EncoderTrack],
    ids: list[int],
    static: list[int],
    node_poses: list[FloatArray],
    offset: float,
) -> RollingSeries:
    """The rolling series of every dynamic module of every segment.

    ``static[s]``: index of segment s's locked module; ``node_poses[s]``: (K, 4) pose rows
    ``t, x, y, yaw`` (yaw unwrapped) chosen as nodes.  A node enters a module's series
    if its encoder time ``t + offset`` is inside the module's track.
    """
    cols: list[list[Any]] = [[] for _ in range(8)]
    ser = 0
    bin0 = 0
    for s, (k, poses) in enumerate(zip(static, node_poses, strict=True)):
        for j, mid in enumerate(ids):
            if j == k or mid not in tracks:
                continue
            tr = tracks[mid]
            te = poses[:, 0] + offset
            inside = np.flatnonzero((te >= tr.t0) & (te <= tr.t1))
            if inside.size < 2:
                continue
            m = inside.size
            for c, v in zip(
                cols,
                (
                    np.full(m, s), np.full(m, j), np.full(m, ser), bin0 + inside,
                    poses[inside, 0], poses[inside, 3],
                    tr.wheel(te[inside]), tr.steer(te[inside]),
                ),
                strict=True,
            ):
                c.append(v)
            ser += 1
        bin0 += poses.shape[0]
    if not cols[0]:
        zi, z = np.zeros(0, np.int64), np.zeros(0)
        return RollingSeries(zi, zi, zi, zi, z, z, z, z)
    seg, mod, ser_, bins = (np.concatenate(c).astype(np.int64) for c in cols[:4])
    t, yaw, psi, theta = (np.concatenate(c).astype(float) for c in cols[4:])
    return RollingSeries(seg, mod, ser_, bins, t, yaw, psi, theta)


def rolling_levers(X: FloatArray, C: FloatArray, series: RollingSeries) -> FloatArray:
    """Lever ``g = (P_w - C) x u(theta_hat + beta)`` of every node (m)."""
    j = series.mod
    return geo.rolling_lever(X[j, P_S], X[j, B_COL], series.theta + X[j, BETA], C[series.seg])


def rolling_increments(
    X: FloatArray, C: FloatArray, series: RollingSeries
) -> tuple[IntArray, FloatArray, FloatArray]:
    """``(l, r dpsi - dG, dG)`` of every increment l -> l+1 within a series.

    ``dG = (g_l + g_l+1) / 2 (yaw_l+1 - yaw_l)`` (trapezoid).
    """
    g = rolling_levers(X, C, series)
    idx = series.pairs()
    dG = 0.5 * (g[idx] + g[idx + 1]) * (series.yaw[idx + 1] - series.yaw[idx])
    res = X[series.mod[idx], R] * (series.psi[idx + 1] - series.psi[idx]) - dG
    return idx, res, dG


def cumulative_rolling_residuals(
    X: FloatArray, C: FloatArray, series: RollingSeries
) -> FloatArray:
    """Centred cumulative residual ``r psi - G - c_run`` of every node in a clean run (m).

    ``c_run`` (the run's mean) is profiled out, so every node's yaw noise counts once
    (differencing would telescope away all but the end points).
    """
    sel = series.clean
    g = rolling_levers(X, C, series)[sel]
    e = centred_cumulative_sums(
        X[series.mod[sel], R] * series.psi[sel], g, series.yaw[sel], series.run[sel]
    )
    return np.asarray(e, dtype=float)


def centred_cumulative_sums(
    a: FloatArray, g: FloatArray, yaw: FloatArray, run: IntArray
) -> FloatArray:
    """``a - G - mean_run(a - G)`` with ``G_l = sum_{m < l} (g_m + g_m+1) / 2 (yaw_m+1 -
    yaw_m)`` summed within each run (``run``: contiguous run ids), column by column when
    ``a`` and ``g`` are (nodes, k): linear in ``(a, g)``, so the same sums give the
    residuals and their derivatives (:meth:`~swpc_hw.calibration.problem.JointProblem.jacobian`).
    """
    same = run[1:] == run[:-1]
    dyaw = (yaw[1:] - yaw[:-1]).reshape((-1,) + (1,) * (g.ndim - 1))
    keep = same.reshape(dyaw.shape)
    dG = np.zeros_like(g)
    dG[1:] = np.where(keep, 0.5 * (g[1:] + g[:-1]) * dyaw, 0.0)
    G = np.cumsum(dG, axis=0)
    starts = np.flatnonzero(np.concatenate([[True], ~same]))
    G = G - np.repeat(G[starts], np.diff(np.append(starts, run.size)), axis=0)
    e = a - G
    counts = np.maximum(np.bincount(run), 1)
    if e.ndim == 1:
        return np.asarray(e - (np.bincount(run, weights=e) / counts)[run], dtype=float)
    sums = np.zeros((counts.size, *e.shape[1:]))
    np.add.at(sums, run, e)
    return np.asarray(e - (sums / counts[:, None])[run], dtype=float)


def cut_runs(series: RollingSeries, slip: BoolArray, min_nodes: int = 3) -> IntArray:
    """Run id of every node after cutting the series at the slipping increments.

    ``slip``: one flag per increment (:meth:`RollingSeries.pairs`).  Runs shorter than
    ``min_nodes`` are dropped (-1).
    """
    idx = series.pairs()
    linked = np.zeros(series.size, dtype=bool)  # node l linked to node l+1
    linked[idx] = ~slip
    start = np.ones(series.size, dtype=bool)
    start[1:] = ~linked[:-1]
    run = np.cumsum(start) - 1
    counts = np.bincount(run) if run.size else np.zeros(0, np.int64)
    ok = counts[run] >= min_nodes
    _, dense = np.unique(run[ok], return_inverse=True)
    out = np.full(series.size, -1, dtype=np.int64)
    out[ok] = dense
    return out


def profiled_series_radius(
    X: FloatArray, C: FloatArray, series: RollingSeries
) -> tuple[FloatArray, FloatArray]:
    """Increment residuals with each series' radius profiled out by least squares.

    ``r_ser = sum dG dpsi / sum dpsi^2`` over the series' increments.  Returns
    ``(residual per increment, radius per series)``.
    """
    g = rolling_levers(X, C, series)
    idx = series.pairs()
    dG = 0.5 * (g[idx] + g[idx + 1]) * (series.yaw[idx + 1] - series.yaw[idx])
    dpsi = series.psi[idx + 1] - series.psi[idx]
    ser = series.ser[idx]
    nser = int(np.max(series.ser)) + 1 if series.size else 0
    num = np.bincount(ser, weights=dG * dpsi, minlength=nser)
    den = np.bincount(ser, weights=dpsi * dpsi, minlength=nser)
    r = np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)
    return r[ser] * dpsi - dG, r
