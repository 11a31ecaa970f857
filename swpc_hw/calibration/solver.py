"""Joint robust calibration solver.

Unknowns: for every module i, ``x_s, y_s, beta, b, r`` (5N).  Observations, for every
segment s (spin about the locked module k at reported steering ``a_s``):

A. **Fixed point** — every pose in the window satisfies ``p + R(yaw) C_R,s = C_W,s``
   with ``C_R,s = P_s,k + b_k u(a_s + beta_k)``.  Each segment is first solved in closed
   form (:func:`geometry.fixed_point`) with iterative outlier rejection; since the model
   is linear in ``(C_R, C_W)``, its information on ``C_R,s`` after profiling out
   ``C_W,s`` is exactly ``I_s / sigma_s^2`` (isotropic), so the whole pose stream enters
   the joint problem as two residuals ``sqrt(I_s)/sigma_s (C_R,s(theta) - C_R,s_hat)``.
B. **Settled free casters** — every dynamic module j satisfies
   ``(P_s,j - C_R,s) . u(theta_hat_j + beta_j) + b_j = 0`` (its contact point lies on
   the perpendicular through the pivot).  This ties beta_j, P_s,j and b_j to the fixed
   points of the *other* modules: 2(N-1) constraints per module.
C. **Rolling** — for every dynamic module ``r_j dpsi_j = g_j dyaw`` with
   ``g_j = (P_w,j - C_R,s) x u(theta_j)``.  At encoder nodes ~0.1 s apart (yaw
   interpolated from the inlier poses, only nodes inside the pose time span) the
   cumulative form ``r_j psi_j(t_l) - G_j(t_l) = c_run`` holds, with
   ``G_j(t_l) = sum_m (g_m + g_m+1)/2 (yaw_m+1 - yaw_m)`` (measured steering, so caster
   transients are modelled exactly).  The intercept ``c_run`` is profiled out (residuals
   centred per run), so every node's yaw noise counts once — differencing would
   telescope away all but the end points.  Wheel-slip bursts are found on the short
   increments ``r dpsi - g dyaw`` (beyond ``slip_sigmas`` robust sigmas, dilated by one
   interval) and cut the series into clean runs.

Solution: closed-form initialisation (paper geometry generalised to M >= 2 angles,
:func:`geometry.steering_circle_fit`), then Gauss-Newton/trust-region
(:func:`scipy.optimize.least_squares`) in an IRLS loop that re-estimates the Cauchy
weights of block C and the noise scale of every block (variance components).  The
covariance is ``s^2 (J^T W J)^-1`` at the solution.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares, minimize_scalar

from swpc_hw.calibration import geometry as geo
from swpc_hw.calibration.prepare import (
    SegmentData,
    encoders_in_window,
    prepare_segments,
)
from swpc_hw.dataset import Dataset, load_dataset
from swpc_hw.errors import CalibrationError
from swpc_hw.model import ModuleStddev, RobotParams

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

PARAM_NAMES = ("x_s", "y_s", "beta", "b", "r")
MIN_SLIP_INCREMENTS = 8
"""Series with fewer wheel increments are not screened for slip (too little statistics)."""


@dataclass
class SolverOptions:
    """Tuning of the joint solver (defaults suit 100 Hz mocap and 200 Hz encoders)."""

    time_offset: float | Literal["auto"] = 0.0
    """Encoder clock minus pose clock (s), or ``"auto"`` to estimate it."""
    offset_bounds: tuple[float, float] = (-0.25, 0.25)
    increment_interval: float = 0.1
    """Length (s) of the wheel-encoder intervals of block C."""
    steer_sigma_floor: float = 2e-5
    """Floor of a settled steering angle's standard deviation (rad): encoder resolution."""
    outlier_sigmas: float = 4.0
    """Poses whose fixed-point residual exceeds this many sigmas are rejected."""
    cauchy_c: float = 2.385
    """Cauchy constant (in sigmas) of the clock-offset search."""
    slip_sigmas: float = 4.0
    """Wheel increments beyond this many robust sigmas are slip and cut the rolling runs."""
    irls_iterations: int = 4


@dataclass
class SegmentQuality:
    """Quality figures of one segment."""

    row: int
    static_module: int
    angle: float
    poses_used: int
    poses_rejected: int
    fixed_point_rms: float
    """RMS of the pose residuals ``|p + R C_R - C_W|`` of inliers (m)."""
    fixed_point: tuple[float, float]
    fixed_point_std: float
    increments_used: int = 0
    increments_rejected: int = 0
    rolling_rms: float = 0.0
    """RMS of ``r dpsi - g dyaw`` over the inlier increments (m)."""
    settled_rms: float = 0.0
    """RMS of the settled-caster residuals of the dynamic modules (m)."""


@dataclass
class CalibrationResult:
    """Calibrated parameters (with std devs in ``params``) and quality figures."""

    params: RobotParams
    nominal: RobotParams
    segments: list[SegmentQuality]
    time_offset: float
    time_offset_std: float | None
    time_offset_mode: str
    poses_used: int
    poses_rejected: int
    increments_used: int
    increments_rejected: int
    reduced_chi2: float
    method: str = "joint"
    extra: dict[str, float] = field(default_factory=dict)

    def stddev_array(self) -> FloatArray:
        """(N, 5) standard deviations in the order x_s, y_s, beta, b, r."""
        rows = []
        for m in self.params.modules:
            s = m.stddev
            rows.append([math.nan] * 5 if s is None else [getattr(s, k) for k in PARAM_NAMES])
        return np.array(rows, dtype=float)

    def quality_document(self) -> dict[str, object]:
        """Plain-data quality figures (for the kinematic file's provenance and the API)."""
        return {
            "method": self.method,
            "time_offset": float(self.time_offset),
            "time_offset_std": None
            if self.time_offset_std is None
            else float(self.time_offset_std),
            "time_offset_mode": self.time_offset_mode,
            "poses_used": self.poses_used,
            "poses_rejected": self.poses_rejected,
            "increments_used": self.increments_used,
            "increments_rejected": self.increments_rejected,
            "reduced_chi2": float(self.reduced_chi2),
            "segments": [
                {
                    "static_module": q.static_module,
                    "angle": float(q.angle),
                    "poses_used": q.poses_used,
                    "poses_rejected": q.poses_rejected,
                    "fixed_point_rms": float(q.fixed_point_rms),
                    "rolling_rms": float(q.rolling_rms),
                    "settled_rms": float(q.settled_rms),
                    "increments_used": q.increments_used,
                    "increments_rejected": q.increments_rejected,
                }
                for q in self.segments
            ],
        }


# --------------------------------------------------------------------- stage 1: segments


def robust_fixed_point(
    poses: FloatArray, outlier_sigmas: float = 4.0, max_iter: int = 20
) -> tuple[FloatArray, FloatArray, NDArray[np.bool_], float]:
    """Fixed point of one segment with iterative outlier rejection.

    Residual norms of a 2-D Gaussian are Rayleigh distributed: ``sigma = median|e| /
    sqrt(2 ln 2)``; poses with ``|e| > outlier_sigmas * sigma`` are rejected and the
    closed form re-solved until the inlier set is stable.  ``poses``: (K, 3) (x, y, yaw).
    Returns ``(C_R, C_W, inliers, sigma)`` with ``sigma`` the per-coordinate noise of the
    inliers.
    """
    mask = np.ones(poses.shape[0], dtype=bool)
    C_R, C_W = geo.fixed_point(poses)
    for _ in range(max_iter):
        e = np.linalg.norm(geo.fixed_point_residuals(poses, C_R, C_W), axis=-1)
        scale = float(np.median(e[mask])) / math.sqrt(2.0 * math.log(2.0))
        new = e <= max(outlier_sigmas * scale, 1e-12)
        if new.sum() < 5:
            new = np.ones_like(mask)
        if np.array_equal(new, mask):
            break
        mask = new
        C_R, C_W = geo.fixed_point(poses[mask])
    e = geo.fixed_point_residuals(poses[mask], C_R, C_W)
    dof = max(2 * int(mask.sum()) - 4, 1)
    sigma = math.sqrt(float(np.sum(e**2)) / dof)
    return C_R, C_W, mask, sigma


# ------------------------------------------------------------------- stage 2: the problem


@dataclass
class _Series:
    """Encoder nodes of every (segment, dynamic module) pair, concatenated by series.

    Node arrays are ordered by series then time; ``ser`` numbers the series.
    """

    seg: IntArray
    mod: IntArray
    ser: IntArray
    psi: FloatArray
    th: FloatArray
    yaw: FloatArray

    @property
    def size(self) -> int:
        return int(self.ser.shape[0])

    def pairs(self) -> IntArray:
        """Index l of every increment (node l -> l+1) inside one series."""
        return np.flatnonzero(self.ser[1:] == self.ser[:-1])


@dataclass
class _Problem:
    n: int
    seg_static: IntArray
    seg_angle: FloatArray
    C_hat: FloatArray  # (S, 2)
    C_weight: FloatArray  # (S,) sqrt(I)/sigma
    pair_seg: IntArray
    pair_mod: IntArray
    pair_theta: FloatArray
    pair_sigma_theta: FloatArray
    nodes: _Series
    pair_sigma: FloatArray = field(default_factory=lambda: np.zeros(0))
    run: IntArray = field(default_factory=lambda: np.zeros(0, np.int64))
    """Run id of every node (-1: not in a clean run)."""
    node_sigma: FloatArray = field(default_factory=lambda: np.zeros(0))

    def contact_points(self, X: FloatArray) -> FloatArray:
        k = self.seg_static
        return geo.contact_point_of(X[k, :2], X[k, 3], self.seg_angle + X[k, 2])

    def levers(self, X: FloatArray, C: FloatArray) -> FloatArray:
        nd = self.nodes
        j = nd.mod
        return geo.rolling_lever(X[j, :2], X[j, 3], nd.th + X[j, 2], C[nd.seg])

    def increments(self, X: FloatArray, C: FloatArray) -> tuple[IntArray, FloatArray, FloatArray]:
        """``(l, r dpsi - g dyaw, g dyaw)`` of every increment l -> l+1 within a series."""
        nd = self.nodes
        g = self.levers(X, C)
        idx = nd.pairs()
        dG = 0.5 * (g[idx] + g[idx + 1]) * (nd.yaw[idx + 1] - nd.yaw[idx])
        res = X[nd.mod[idx], 4] * (nd.psi[idx + 1] - nd.psi[idx]) - dG
        return idx, res, dG

    def rolling(self, X: FloatArray, C: FloatArray) -> FloatArray:
        """Centred cumulative rolling residual ``r psi - G`` of every node in a clean run."""
        nd = self.nodes
        sel = self.run >= 0
        run = self.run[sel]
        g = self.levers(X, C)[sel]
        yaw, psi = nd.yaw[sel], nd.psi[sel]
        dG = np.zeros_like(g)
        same = run[1:] == run[:-1]
        dG[1:] = np.where(same, 0.5 * (g[1:] + g[:-1]) * (yaw[1:] - yaw[:-1]), 0.0)
        G = np.cumsum(dG)
        starts = np.flatnonzero(np.concatenate([[True], ~same]))
        G = G - np.repeat(G[starts], np.diff(np.append(starts, run.size)))
        e = X[nd.mod[sel], 4] * psi - G
        counts = np.bincount(run)
        mean = np.bincount(run, weights=e) / np.maximum(counts, 1)
        return np.asarray(e - mean[run], dtype=float)

    def blocks(self, x: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Raw residual blocks A (S,2) [m], B (Q,) [m], C (clean nodes,) [m]."""
        X = x.reshape(self.n, 5)
        C = self.contact_points(X)
        A = C - self.C_hat
        j, s = self.pair_mod, self.pair_seg
        B = geo.settled_residual(X[j, :2], X[j, 3], self.pair_theta + X[j, 2], C[s])
        return A, B, self.rolling(X, C)

    def residuals(self, x: FloatArray) -> FloatArray:
        A, B, R = self.blocks(x)
        return np.concatenate(
            [
                (A * self.C_weight[:, None]).ravel(),
                B / self.pair_sigma,
                R / self.node_sigma[self.run >= 0],
            ]
        )

    def cut_runs(self, slip: NDArray[np.bool_]) -> None:
        """Split the series into clean runs at the slipping increments (``slip`` per pair)."""
        nd = self.nodes
        idx = nd.pairs()
        linked = np.zeros(nd.size, dtype=bool)  # node l linked to node l+1
        linked[idx] = ~slip
        # a new run starts at every node not linked from its predecessor
        start = np.ones(nd.size, dtype=bool)
        start[1:] = ~linked[:-1]
        run = np.cumsum(start) - 1
        counts = np.bincount(run)
        ok = counts[run] >= 3
        _, dense = np.unique(run[ok], return_inverse=True)
        self.run = np.full(nd.size, -1, dtype=np.int64)
        self.run[ok] = dense


def _build_series(
    ds: Dataset,
    segs: list[SegmentData],
    offset: float,
    interval: float,
    windows: list[tuple[float, float]] | None = None,
    pose_sets: list[FloatArray] | None = None,
) -> _Series:
    """Encoder nodes of every dynamic module in every segment.

    Nodes are encoder samples spaced ~``interval`` apart, inside the segment window and
    inside the time span of the segment's inlier poses; yaw is linearly interpolated
    from the inlier poses at the nodes (pose clock = encoder stamp - offset).
    """
    ids = ds.robot.ids
    parts: list[tuple[int, int, FloatArray, FloatArray]] = []
    for si, sd in enumerate(segs):
        poses = sd.poses[sd.inliers] if pose_sets is None else pose_sets[si]
        t_p, yaw_p = poses[:, 0], poses[:, 3]
        start, end = (sd.segment.start, sd.segment.end) if windows is None else windows[si]
        lo, hi = max(start, float(t_p[0])), min(end, float(t_p[-1]))
        for j, mid in enumerate(ids):
            if j == sd.static:
                continue
            enc = encoders_in_window(ds, mid, lo, hi, offset)
            if enc.shape[0] < 2:
                continue
            dt = float(np.median(np.diff(enc[:, 0])))
            step = max(1, round(interval / max(dt, 1e-9)))
            nodes = enc[::step]
            if nodes.shape[0] < 2:
                continue
            parts.append((si, j, nodes, np.interp(nodes[:, 0], t_p, yaw_p)))
    if not parts:
        z = np.zeros(0)
        zi = np.zeros(0, np.int64)
        return _Series(zi, zi, zi, z, z, z)
    return _Series(
        seg=np.concatenate([np.full(p[2].shape[0], p[0], dtype=np.int64) for p in parts]),
        mod=np.concatenate([np.full(p[2].shape[0], p[1], dtype=np.int64) for p in parts]),
        ser=np.concatenate(
            [np.full(p[2].shape[0], k, dtype=np.int64) for k, p in enumerate(parts)]
        ),
        psi=np.concatenate([p[2][:, 2] for p in parts]),
        th=np.concatenate([p[2][:, 1] for p in parts]),
        yaw=np.concatenate([p[3] for p in parts]),
    )


def _mad_sigma(x: FloatArray) -> float:
    if x.size == 0:
        return 0.0
    return 1.4826 * float(np.median(np.abs(x - np.median(x))))


def closed_form_geometry(segs: list[SegmentData], n: int) -> FloatArray:
    """Initial (N, 5) parameters from the fixed points (generalised eq. 1-3); r = nan."""
    X = np.full((n, 5), np.nan)
    for i in range(n):
        mine = [s for s in segs if s.static == i]
        pts = np.array([_fp(s) for s in mine])
        angles = np.array([s.angle for s in mine])
        P_s, b, beta = geo.steering_circle_fit(pts, angles)
        X[i, :2], X[i, 2], X[i, 3] = P_s, beta, b
    return X


def canonical_parameters(X: FloatArray) -> FloatArray:
    """The representative with ``b >= 0`` of every module's mirror pair.

    The model only sees ``b u(theta + beta)`` and ``r dpsi``, and
    ``u(theta + beta + pi) = -u(theta + beta)``, so

        (x_s, y_s, beta, b, r)  and  (x_s, y_s, beta + pi, -b, -r)

    give identical residuals in all three blocks (A: ``C_R = P_s + b u(a + beta)``;
    B: ``(P_s - C_R) . u(theta + beta) + b`` changes sign; C: the lever
    ``g = (P_w - C) x u(theta)`` and ``r`` both change sign).  The trust-region step can
    cross ``b = 0`` into the mirror; this maps such a module back, ``beta`` wrapped to
    ``[-pi, pi)``.  ``X``: (N, 5) rows ``x_s, y_s, beta, b, r``; returns a copy.
    """
    Y = np.array(X, dtype=float, copy=True)
    mirror = Y[:, 3] < 0
    Y[mirror, 2] += np.pi
    Y[mirror, 3:5] *= -1.0
    Y[:, 2] = (Y[:, 2] + np.pi) % (2 * np.pi) - np.pi
    return Y


def _check_physical(X: FloatArray, ids: list[int]) -> None:
    """Refuse a solution no robot can have, naming every offending parameter."""
    bad = []
    for mid, row in zip(ids, X, strict=True):
        bad += [
            f"module {mid} {name} = {v}"
            for name, v in zip(PARAM_NAMES, row, strict=True)
            if not math.isfinite(v)
        ]
        b, r = float(row[3]), float(row[4])
        if math.isfinite(b) and math.isfinite(r) and (b <= 0 or r <= 0):
            bad.append(f"module {mid} b = {b:.6g} m, r = {r:.6g} m")
    if bad:
        raise CalibrationError(
            "the solver did not converge to a physical solution: " + "; ".join(bad)
        )


def _fp(s: SegmentData) -> FloatArray:
    C_R, _ = geo.fixed_point(s.poses[s.inliers][:, 1:])
    return C_R


def _profiled_radius_residuals(
    nodes: _Series, X: FloatArray, C: FloatArray, n: int
) -> tuple[FloatArray, FloatArray]:
    """Increment residuals with the radius of each series profiled out by least squares.

    Returns ``(residuals per increment, radius per series)``.
    """
    j = nodes.mod
    g = geo.rolling_lever(X[j, :2], X[j, 3], nodes.th + X[j, 2], C[nodes.seg])
    idx = nodes.pairs()
    dG = 0.5 * (g[idx] + g[idx + 1]) * (nodes.yaw[idx + 1] - nodes.yaw[idx])
    dpsi = nodes.psi[idx + 1] - nodes.psi[idx]
    ser = nodes.ser[idx]
    nser = int(nodes.ser.max()) + 1 if nodes.size else 0
    num = np.bincount(ser, weights=dG * dpsi, minlength=nser)
    den = np.bincount(ser, weights=dpsi * dpsi, minlength=nser)
    r = np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)
    return r[ser] * dpsi - dG, r


def _radius_init(prob: _Problem, X: FloatArray) -> FloatArray:
    """Per-module median over its series of the least-squares ratio ``r = g dyaw / dpsi``."""
    C = prob.contact_points(X)
    _, r_ser = _profiled_radius_residuals(prob.nodes, X, C, prob.n)
    nd = prob.nodes
    r = np.full(prob.n, np.nan)
    for j in range(prob.n):
        sers = np.unique(nd.ser[nd.mod == j])
        if sers.size == 0:
            raise CalibrationError(
                f"module index {j}: no wheel-encoder data while another module was locked"
            )
        r[j] = abs(float(np.median(r_ser[sers])))
    return r


def _estimate_offset(
    ds: Dataset, segs: list[SegmentData], X: FloatArray, opts: SolverOptions
) -> tuple[float, float | None]:
    """Clock offset (encoder - pose, s) maximising the rolling consistency (block C).

    For a trial offset the wheel increments of the whole *hold* period of every
    segment (the static module's steering within 0.2 deg of its angle; ramps included,
    which is where timing is observable) are compared with ``g dyaw``; per (segment,
    module) the radius is profiled out by least squares; the cost is a Cauchy sum in
    units of the residual scale at zero offset.  A grid search then a bounded Brent
    refinement; the std dev is ``1 / sqrt(cost'')``.
    """
    windows = []
    pose_sets = []
    for sd in segs:
        a, b = _hold_window(ds, sd)
        sel = (ds.poses[:, 0] >= a) & (ds.poses[:, 0] <= b)
        poses = ds.poses[sel].copy()
        poses[:, 3] = np.unwrap(poses[:, 3])
        _, _, mask, _ = robust_fixed_point(poses[:, 1:], opts.outlier_sigmas)
        windows.append((a, b))
        pose_sets.append(poses[mask])
    n = ds.robot.arrays().n
    k = np.array([s.static for s in segs])
    C = geo.contact_point_of(X[k, :2], X[k, 3], np.array([s.angle for s in segs]) + X[k, 2])

    def residual(offset: float) -> FloatArray:
        nodes = _build_series(ds, segs, offset, opts.increment_interval, windows, pose_sets)
        return _profiled_radius_residuals(nodes, X, C, n)[0]

    scale = max(_mad_sigma(residual(0.0)), 1e-12)

    def cost(offset: float) -> float:
        z = residual(offset) / scale
        return float(0.5 * np.sum(opts.cauchy_c**2 * np.log1p((z / opts.cauchy_c) ** 2)))

    lo, hi = opts.offset_bounds
    grid = np.linspace(lo, hi, 51)
    costs = np.array([cost(float(t)) for t in grid])
    i = int(np.argmin(costs))
    step = grid[1] - grid[0]
    res = minimize_scalar(
        cost,
        bounds=(max(lo, grid[i] - step), min(hi, grid[i] + step)),
        method="bounded",
        options={"xatol": 1e-5},
    )
    best = float(res.x)
    h = 2e-3
    curv = (cost(best + h) - 2 * cost(best) + cost(best - h)) / h**2
    std = 1.0 / math.sqrt(curv) if curv > 0 else None
    return best, std


def _hold_window(
    ds: Dataset, sd: SegmentData, tol: float = math.radians(0.2)
) -> tuple[float, float]:
    """Largest interval around the segment in which the static module stays at its angle."""
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
    return float(min(t[lo], sd.segment.start)), float(max(t[hi], sd.segment.end))


def solve(
    ds: Dataset, options: SolverOptions | None = None, source: str = "dataset"
) -> CalibrationResult:
    """Calibrate all modules from a dataset (see the module docstring for the method)."""
    opts = options or SolverOptions()
    ids = ds.robot.ids
    n = len(ids)
    offset = 0.0 if opts.time_offset == "auto" else float(opts.time_offset)
    segs = prepare_segments(ds, offset, source)
    # stage 1: robust fixed point of every segment
    C_hat, C_w, sig = [], [], []
    for sd in segs:
        C_R, _, mask, sigma = robust_fixed_point(sd.poses[:, 1:], opts.outlier_sigmas)
        sd.inliers = mask
        info = float(geo.fixed_point_information(sd.poses[mask][:, 1:]))
        C_hat.append(C_R)
        sig.append(max(sigma, 1e-9))
        C_w.append(math.sqrt(info) / max(sigma, 1e-9))
    X0 = closed_form_geometry(segs, n)
    offset_std: float | None = None
    mode = "given"
    if opts.time_offset == "auto":
        offset, offset_std = _estimate_offset(ds, segs, np.nan_to_num(X0), opts)
        mode = "estimated"
    # settled steering of the dynamic modules: one robust value per (segment, module)
    pair_seg, pair_mod, pair_theta, pair_sig = [], [], [], []
    for si, sd in enumerate(segs):
        for j, mid in enumerate(ids):
            if j == sd.static:
                continue
            enc = encoders_in_window(ds, mid, sd.segment.start, sd.segment.end, offset)
            th = enc[:, 1]
            pair_seg.append(si)
            pair_mod.append(j)
            pair_theta.append(float(np.median(th)))
            pair_sig.append(max(_mad_sigma(th), opts.steer_sigma_floor))
    nodes = _build_series(ds, segs, offset, opts.increment_interval)
    prob = _Problem(
        n=n,
        seg_static=np.array([s.static for s in segs], dtype=np.int64),
        seg_angle=np.array([s.angle for s in segs]),
        C_hat=np.array(C_hat),
        C_weight=np.array(C_w),
        pair_seg=np.array(pair_seg, dtype=np.int64),
        pair_mod=np.array(pair_mod, dtype=np.int64),
        pair_theta=np.array(pair_theta),
        pair_sigma_theta=np.array(pair_sig),
        nodes=nodes,
    )
    X0[:, 4] = _radius_init(prob, X0)
    x = X0.ravel().copy()
    # initial scale of block B from the closed-form start
    C0 = prob.contact_points(X0)
    lever = np.abs(
        geo.rolling_lever(
            X0[prob.pair_mod, :2],
            X0[prob.pair_mod, 3],
            prob.pair_theta + X0[prob.pair_mod, 2],
            C0[prob.pair_seg],
        )
    )
    prob.pair_sigma = np.maximum(lever, 0.05) * prob.pair_sigma_theta
    # stage 2: alternate slip detection / noise scales with the trust-region solve
    slip = np.zeros(nodes.pairs().size, dtype=bool)
    sol = None
    for _ in range(max(1, opts.irls_iterations)):
        X = x.reshape(n, 5)
        C = prob.contact_points(X)
        idx, inc_res, _ = prob.increments(X, C)
        ser = nodes.ser[idx]
        # robust scale per series, floored by half the pooled scale of all series so that
        # a short series (few increments) cannot produce a tiny, over-rejecting scale
        inc_sig = np.zeros(inc_res.size)
        dev = inc_res - _series_median(inc_res, ser)
        pooled = 0.5 * _mad_sigma(dev) if dev.size else 0.0
        enough = np.zeros(inc_res.size, dtype=bool)
        for k in np.unique(ser):
            sel = ser == k
            inc_sig[sel] = max(_mad_sigma(inc_res[sel]), pooled, 1e-12)
            enough[sel] = int(sel.sum()) >= MIN_SLIP_INCREMENTS
        bad = enough & (np.abs(dev) > opts.slip_sigmas * inc_sig)
        slip = bad.copy()  # dilate by one increment within the series
        same_prev = np.zeros_like(bad)
        same_prev[1:] = ser[1:] == ser[:-1]
        slip[1:] |= bad[:-1] & same_prev[1:]
        slip[:-1] |= bad[1:] & same_prev[1:]
        prob.cut_runs(slip)
        R = prob.rolling(X, C)
        runs = prob.run[prob.run >= 0]
        ser_nodes = nodes.ser[prob.run >= 0]
        prob.node_sigma = np.full(nodes.size, 1.0)
        clean_sigma = np.zeros(R.size)
        for k in np.unique(ser_nodes):
            sel = ser_nodes == k
            nruns = np.unique(runs[sel]).size
            dof = max(int(sel.sum()) - nruns, 1)
            clean_sigma[sel] = max(math.sqrt(float(np.sum(R[sel] ** 2)) / dof), 1e-12)
        prob.node_sigma[prob.run >= 0] = clean_sigma
        sol = least_squares(
            prob.residuals,
            x,
            method="trf",
            x_scale="jac",
            xtol=1e-15,
            ftol=1e-15,
            gtol=1e-15,
            max_nfev=200,
        )
        x = canonical_parameters(sol.x.reshape(n, 5)).ravel()
        _, B, _ = prob.blocks(x)
        zb = B / prob.pair_sigma
        rms_b = math.sqrt(float(np.mean(zb**2))) if zb.size else 1.0
        if rms_b > 1.0:  # block B noisier than its prior: inflate (never deflate)
            prob.pair_sigma = prob.pair_sigma * rms_b
    assert sol is not None
    X = x.reshape(n, 5)
    _check_physical(X, ids)
    # covariance from the weighted Jacobian (central differences)
    J = _jacobian(prob.residuals, x)
    f = prob.residuals(x)
    dof = max(f.size - x.size, 1)
    s2 = float(f @ f) / dof
    std = parameter_stddev(J, s2).reshape(n, 5)
    params = RobotParams.from_arrays(
        ids,
        X[:, :2],
        X[:, 2],
        X[:, 3],
        X[:, 4],
        robot=ds.robot.robot,
        frame=ds.robot.frame,
    )
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
    quality = _quality(prob, segs, x, ids, np.array(sig), slip)
    inc_rej = int(slip.sum())
    return CalibrationResult(
        params=params,
        nominal=ds.robot,
        segments=quality,
        time_offset=offset,
        time_offset_std=offset_std,
        time_offset_mode=mode,
        poses_used=int(sum(int(s.inliers.sum()) for s in segs)),
        poses_rejected=int(sum(int((~s.inliers).sum()) for s in segs)),
        increments_used=int(slip.size) - inc_rej,
        increments_rejected=inc_rej,
        reduced_chi2=s2,
    )


def parameter_stddev(J: FloatArray, s2: float) -> FloatArray:
    """Standard deviations ``sqrt(diag(s2 (J^T J)^-1))`` computed stably.

    The columns are first scaled to unit norm (Jacobi preconditioning: parameters in
    metres and radians with weights spanning many decades make ``J^T J`` numerically
    singular otherwise), then inverted by SVD.  A parameter the data do not determine
    (zero singular value, or a non-finite/non-positive variance) gets NaN — unknown,
    never 0.
    """
    norms = np.linalg.norm(J, axis=0)
    out = np.full(J.shape[1], np.nan)
    ok = norms > 0
    if not ok.any():
        return out
    Js = J[:, ok] / norms[ok]
    _, sv, Vt = np.linalg.svd(Js, full_matrices=False)
    if sv.size == 0 or sv[-1] <= sv[0] * 1e-12:
        return out
    cov_s = (Vt.T / sv**2) @ Vt
    var = np.diag(cov_s) * max(s2, 1e-30) / norms[ok] ** 2
    good = np.isfinite(var) & (var > 0)
    sub = np.full(var.shape, np.nan)
    sub[good] = np.sqrt(var[good])
    out[ok] = sub
    return out


def _jacobian(f: Callable[[FloatArray], FloatArray], x: FloatArray) -> FloatArray:
    """Central-difference Jacobian of ``f`` at ``x``."""
    cols = []
    for i in range(x.size):
        h = 1e-7 * max(1.0, abs(float(x[i])))
        xp, xm = x.copy(), x.copy()
        xp[i] += h
        xm[i] -= h
        cols.append((f(xp) - f(xm)) / (2 * h))
    return np.column_stack(cols)


def _series_median(values: FloatArray, ser: IntArray) -> FloatArray:
    """Median of ``values`` within each series, broadcast back to the elements."""
    out = np.zeros_like(values)
    for k in np.unique(ser):
        sel = ser == k
        out[sel] = np.median(values[sel])
    return out


def _quality(
    prob: _Problem,
    segs: list[SegmentData],
    x: FloatArray,
    ids: list[int],
    sig: FloatArray,
    slip: NDArray[np.bool_],
) -> list[SegmentQuality]:
    _, B, R = prob.blocks(x)
    X = x.reshape(prob.n, 5)
    C = prob.contact_points(X)
    node_seg = prob.nodes.seg[prob.run >= 0]
    inc_seg = prob.nodes.seg[prob.nodes.pairs()]
    out = []
    for si, sd in enumerate(segs):
        seln = node_seg == si
        seli = inc_seg == si
        selb = prob.pair_seg == si
        out.append(
            SegmentQuality(
                row=sd.row,
                static_module=ids[sd.static],
                angle=sd.angle,
                poses_used=int(sd.inliers.sum()),
                poses_rejected=int((~sd.inliers).sum()),
                fixed_point_rms=float(sig[si]) * math.sqrt(2.0),
                fixed_point=(float(C[si, 0]), float(C[si, 1])),
                fixed_point_std=float(1.0 / prob.C_weight[si]),
                increments_used=int((seli & ~slip).sum()),
                increments_rejected=int((seli & slip).sum()),
                rolling_rms=float(np.sqrt(np.mean(R[seln] ** 2))) if seln.any() else 0.0,
                settled_rms=float(np.sqrt(np.mean(B[selb] ** 2))) if selb.any() else 0.0,
            )
        )
    return out


def solve_directory(path: str | Path, options: SolverOptions | None = None) -> CalibrationResult:
    """Load a dataset directory and solve it."""
    return solve(load_dataset(path), options, source=str(path))
