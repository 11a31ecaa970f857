"""Sequential stopping: a planned calibration's std devs forecast from the data so far.

The joint solver's covariance is the sandwich ``Cov = H^-1 M H^-1``
(:mod:`swpc_hw.calibration.mocap.covariance`), and both ``H = J^T J`` and ``M`` are sums over
the spins (segments) ``s``: every residual belongs to one spin, and so does every noise
correlation the middle holds (:func:`~swpc_hw.calibration.mocap.covariance.segment_terms`).
Spin ``s`` (about the locked module ``k`` at reported angle ``a_s``) adds::

    H_s = G_s^T Cov_s^-1 G_s + B_s + R_s(q_s)
    M_s = G_s^T Cov_s^-1 G_s + B_s + nu_s (R_s(q_s) + q_s^3 (R~_s - R_s))

with ``G_s = dC_s/dx`` (2, 5N) the Jacobian of its contact point
``C_s = P_s,k + b_k u(a_s + beta_k)``, ``Cov_s`` (2, 2) the covariance of its fixed point,
``B_s`` the information of its settled casters, ``R_s`` and ``R~_s`` its rolling rows'
shares of ``H`` and ``M`` at the planned sweep, ``q_s`` the sweep over the planned
sweep, ``R_s(q)`` the rolling rows' share at ``q`` (below; ``R_s(1) = R_s``) and
``nu_s = (sigma_s / sigma_plan,s)^2`` the poses' noise variance over the plan's (the
rolling rows keep the plan's weights, so a noisier yaw shows in the middle only).

The rolling residuals are cumulative, centred per series (:mod:`swpc_hw.calibration.rolling`):
a row's Jacobian grows with the wheel's travel since the series began, so a spin's
rolling information grows as the cube of its sweep, not in proportion (``sum_k (k -
mean k)^2 ~ K^3 / 12`` over ``K`` nodes; from the plan's prediction, exponent 2.8 between
60 and 360 deg).  ``R_s(q)`` for ``q < 1`` is the planned rows up to the sweep, centred
again over them (:meth:`SpinInformation.rolling_cut`), ``q^3 R_s`` beyond; what the
plan's middle holds beyond ``R_s`` (its cross terms with the fixed point, a correlation
the HAC found) scales as ``q^3``.  Scaled in proportion instead, a spin cut at a third
of its sweep was credited 9 times the radius information it holds, and sequential
stopping ended spins the final solve then found short of the requirement.

The **forecast** (:func:`forecast_covariance`) takes, for the spins done and the one in
progress, ``Cov_s`` from their own poses (the fixed point fitted to the poses so far,
:func:`~swpc_hw.calibration.fixed_point.fit_fixed_point`, whose HAC covariance carries
the noise as it really is), ``q_s`` from their sweep so far and ``nu_s`` from that
fit's residuals; for the spins to come, the plan's prediction (:class:`SpinInformation`,
from a simulated run of the plan: ``services.plan.predict``) at ``q = 1`` with ``Cov_s``
and ``nu`` times the plan's, ``nu`` the mean of the spins measured when above 1.
Everything else (``G_s``, ``B_s``, ``R_s``) is the plan's, linearised at the nominal
robot.

**The rule** (:meth:`Stopping.judge`): spin ``i`` ends once it has swept ``min_sweep``
and the forecast meets the requirement on what spin ``i`` informs: the locked module's
``x_s, y_s, beta, b``, every other module's ``r`` (it rolls), and the square path; or
once it has swept ``extension`` times its planned sweep.  A spin whose data are as
planned thus ends near its planned sweep, earlier when the poses are better than
assumed, later (up to the extension) when worse: the requirement is met by the data,
not by the assumption.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from swpc_hw.calibration.fixed_point import fit_fixed_point
from swpc_hw.calibration.mocap.covariance import segment_terms
from swpc_hw.calibration.mocap.solver import JointSolution
from swpc_hw.calibration.parameters import BETA, N_PARAMS, X_S, Y_S, B, R
from swpc_hw.calibration.plan.plan import Requirement, stddevs, worst_per_kind
from swpc_hw.calibration.prepare import prepare_segments
from swpc_hw.errors import CalibrationError
from swpc_hw.files.dataset import Dataset, Segment

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
IntArray = NDArray[np.int64]

JUDGE_STEP = math.radians(3.0)
"""rad of sweep between two judgements of a spin (a fit of its poses so far: a few ms)."""
MIN_SWEEP = math.radians(60.0)
"""rad: the least sweep a spin ends at.  A fixed point fitted to a shorter arc is
over-confident: against the truth, the RMS of its error over its std dev is 1.5 (offline
generator) to 1.8 (the in-process simulator) at 30 deg, 1.2-1.3 at 60 deg, 1.0-1.1 from
210 deg (docs/plan.md, 64 spins each)."""
EXTENSION = 2.0
"""The most a spin is extended: this times its planned sweep."""


@dataclass(frozen=True)
class SpinInformation:
    """One planned spin's share of the calibration's information (module docstring)."""

    module: int
    """Index of the locked module."""
    sweep: float
    """Planned sweep (rad)."""
    contact_jacobian: FloatArray
    """``G_s`` (2, 5N)."""
    fixed_covariance: FloatArray
    """The plan's ``Cov_s`` (2, 2)."""
    settled: FloatArray
    """``B_s`` (5N, 5N)."""
    rolling_h: FloatArray
    """``R_s`` (5N, 5N)."""
    rolling_m: FloatArray
    """``R~_s`` (5N, 5N)."""
    sigma: float
    """The plan's pose noise: its fixed-point fit's residual std dev (m)."""
    rolling_rows: FloatArray
    """``J_C,s`` (K, 5N): the spin's weighted rolling rows, centred over each series."""
    rolling_series: IntArray
    """(K,) the series (one per rolling module) of every row."""
    rolling_sweep: FloatArray
    """(K,) the sweep (rad) at every row's node, from the spin's first node."""

    def rolling_cut(self, sweep: float) -> FloatArray:
        """``R_s`` of the spin cut at ``sweep`` (rad): its rows up to it, each series
        centred again over what is kept (``J_k - mean_kept J``: the residuals of a run
        are centred over the run, and re-centring centred rows drops the old mean)."""
        keep = self.rolling_sweep <= sweep
        rows = self.rolling_rows[keep]
        ser = self.rolling_series[keep]
        out = np.zeros((rows.shape[1], rows.shape[1]))
        for k in np.unique(ser):
            r = rows[ser == k]
            r = r - r.mean(axis=0)
            out += r.T @ r
        return out

    @functools.cached_property
    def fixed_information(self) -> FloatArray:
        """``G_s^T Cov_s^-1 G_s`` at the plan's ``Cov_s``: the same for every forecast, so
        made once (a spin to come at ``nu`` times the plan's noise holds it over ``nu``)."""
        G = self.contact_jacobian
        return np.asarray(G.T @ np.linalg.solve(self.fixed_covariance, G), dtype=float)


@dataclass(frozen=True)
class SpinSoFar:
    """What one spin's own poses gave so far: its sweep (rad), its fixed point's
    covariance (2, 2) and residual std dev (m) (a
    :class:`~swpc_hw.calibration.fixed_point.FixedPointFit`'s ``covariance``, ``sigma``)."""

    sweep: float
    fixed_covariance: FloatArray
    sigma: float


def spin_information(solution: JointSolution, sweep: float) -> list[SpinInformation]:
    """Every spin's :class:`SpinInformation` from a solve of a run of the plan (all at
    the planned ``sweep``, rad), in the run's order."""
    prob, x = solution.problem, solution.x
    J, _, terms = segment_terms(prob, x, solution.fits)
    nA, nB, _ = prob.block_sizes()
    clean = prob.rolling.clean
    rows_c, seg_c = J[nA + nB :], prob.rolling.seg[clean]
    ser_c, yaw_c, t_c = prob.rolling.ser[clean], prob.rolling.yaw[clean], prob.rolling.t[clean]
    out = []
    for s, t in enumerate(terms):
        W = prob.fixed.whiten[s]
        mine = seg_c == s
        yaw = yaw_c[mine]
        first = yaw[np.argmin(t_c[mine])] if yaw.size else 0.0
        out.append(
            SpinInformation(
                module=int(prob.fixed.static[s]),
                sweep=sweep,
                contact_jacobian=np.linalg.solve(W, t.fixed_rows),
                fixed_covariance=np.asarray(prob.fixed.covariance[s], dtype=float),
                settled=t.settled_h,
                rolling_h=t.rolling_h,
                rolling_m=t.rolling_m,
                sigma=solution.fits[s].sigma,
                rolling_rows=rows_c[mine],
                rolling_series=ser_c[mine],
                rolling_sweep=np.abs(yaw - first),
            )
        )
    return out


def _sandwich(H: FloatArray, M: FloatArray) -> FloatArray:
    """``H^-1 M H^-1`` with ``H`` scaled to a unit diagonal first; NaN when ``H`` is
    singular (a parameter no spin informs)."""
    d = np.sqrt(np.clip(np.diag(H), 0.0, None))
    p = H.shape[0]
    if not np.all(d > 0) or not np.all(np.isfinite(H)):
        return np.full((p, p), np.nan)
    Hs = H / np.outer(d, d)
    w, V = np.linalg.eigh(Hs)
    if w[0] <= w[-1] * 1e-12:
        return np.full((p, p), np.nan)
    Hi = (V / w) @ V.T
    cov = (Hi @ (M / np.outer(d, d)) @ Hi) / np.outer(d, d)
    return np.asarray(0.5 * (cov + cov.T), dtype=float)


def forecast_covariance(
    spins: Sequence[SpinInformation], so_far: Sequence[SpinSoFar]
) -> FloatArray:
    """The forecast ``Cov = H^-1 M H^-1`` (5N, 5N) (module docstring): ``so_far[s]`` for
    the first ``len(so_far)`` spins, the plan for the others, at the poses' noise seen so
    far: the mean ``nu`` of the spins measured (the motion capture's noise is the
    system's, not a spin's), the fixed points' information over it and the rolling
    middle times it.  As planned at the plan's noise, a run whose poses are worse than
    assumed ended its first spins early on the promise of the later ones, which then ran
    out of extension."""
    if len(so_far) > len(spins):
        raise CalibrationError(f"{len(so_far)} spins measured, the plan has {len(spins)}")
    p = spins[0].contact_jacobian.shape[1]
    H, M = np.zeros((p, p)), np.zeros((p, p))
    nus = [(got.sigma / info.sigma) ** 2 if info.sigma > 0 else 1.0
           for info, got in zip(spins, so_far, strict=False)]  # fmt: skip
    seen = max(float(np.mean(nus)), 1.0) if nus else 1.0
    for s, info in enumerate(spins):
        if s >= len(so_far):  # to come: as planned, at the noise seen
            fixed = info.fixed_information / seen
            H += fixed + info.settled + info.rolling_h
            M += fixed + info.settled + seen * info.rolling_m
            continue
        got = so_far[s]
        cov, q = got.fixed_covariance, got.sweep / info.sweep
        nu = nus[s]
        G = info.contact_jacobian
        fixed = G.T @ np.linalg.solve(cov, G)
        if q >= 1.0:
            rh, rm = q**3 * info.rolling_h, q**3 * info.rolling_m
        else:
            rh = info.rolling_cut(got.sweep)
            rm = rh + q**3 * (info.rolling_m - info.rolling_h)
        H += fixed + info.settled + rh
        M += fixed + info.settled + nu * rm
    return _sandwich(H, M)


def informed(spin: SpinInformation, n: int) -> BoolArray:
    """(N, 5) the parameters a spin informs (module docstring): its locked module's
    ``x_s, y_s, beta, b`` and every other module's ``r``."""
    mask = np.zeros((n, N_PARAMS), dtype=bool)
    mask[spin.module, [X_S, Y_S, BETA, B]] = True
    mask[:, R] = True
    mask[spin.module, R] = False
    return mask


@dataclass(frozen=True)
class Judgement:
    """A spin judged at a moment: the forecast, its ratio to the requirement (on what the
    spin informs, <= 1: met) and whether the spin ends now."""

    covariance: FloatArray
    ratio: float
    stop: bool
    why: str = ""
    """Why the spin ends: ``met`` (the forecast meets the requirement), ``most sweep``
    (``extension`` times its planned sweep), ``spin time`` (the time it may take is up);
    empty while it goes on."""

    def document(self, requirement: Requirement) -> dict[str, float | None]:
        """The forecast's worst std dev per kind, the square path's end error that the
        requirement's share of runs stay within (mm, deg), and the ratio: what the run's
        status shows."""
        sd = stddevs(self.covariance)
        worst = worst_per_kind(sd) if np.all(np.isfinite(sd)) else {}
        sq = requirement.square_bound(self.covariance)

        def mm(v: float | None) -> float | None:
            return None if v is None or not math.isfinite(v) else v * 1e3

        def deg(v: float | None) -> float | None:
            return None if v is None or not math.isfinite(v) else math.degrees(v)

        return {
            "position_mm": mm(worst.get("position")),
            "beta_deg": deg(worst.get("beta")),
            "radius_mm": mm(worst.get("radius")),
            "square_position_mm": mm(None if sq is None else sq[0]),
            "square_heading_deg": deg(None if sq is None else sq[1]),
            "ratio": self.ratio if math.isfinite(self.ratio) else None,
        }


@dataclass(frozen=True)
class Stopping:
    """Sequential stopping of a planned run (module docstring): the plan's spins, in the
    run's order, and its requirement."""

    spins: tuple[SpinInformation, ...]
    requirement: Requirement
    min_sweep: float = MIN_SWEEP
    extension: float = EXTENSION

    def __post_init__(self) -> None:
        if not self.spins:
            raise CalibrationError("sequential stopping needs the plan's spins")
        if not (self.min_sweep > 0 and self.extension >= 1.0):
            raise CalibrationError("sequential stopping: min_sweep > 0, extension >= 1")

    @property
    def n(self) -> int:
        return int(self.spins[0].contact_jacobian.shape[1]) // N_PARAMS

    def max_sweep(self, i: int) -> float:
        """The most spin ``i`` sweeps (rad)."""
        return self.extension * self.spins[i].sweep

    def ratio(self, covariance: FloatArray, mask: BoolArray | None = None) -> float:
        """:meth:`Requirement.ratio` on the parameters of ``mask`` (all: None)."""
        return self.requirement.ratio(covariance, mask)

    def before(self) -> Judgement:
        """The plan's own forecast, before any spin."""
        cov = forecast_covariance(self.spins, [])
        return Judgement(cov, self.ratio(cov), False)

    def judge(
        self, so_far: Sequence[SpinSoFar], spin_time: float = 0.0, max_spin_time: float = math.inf
    ) -> Judgement:
        """Judge the spin in progress, ``so_far[-1]`` (the ones before it done), which has
        lasted ``spin_time`` of the ``max_spin_time`` it may (s; the run's step timeout
        with a margin: the spin ends before the run would fail)."""
        i = len(so_far) - 1
        if i < 0:
            raise CalibrationError("judge: no spin in progress")
        cov = forecast_covariance(self.spins, so_far)
        ratio = self.ratio(cov, informed(self.spins[i], self.n))
        sweep = so_far[-1].sweep
        why = ""
        if sweep >= self.min_sweep and ratio <= 1.0:
            why = "met"
        elif sweep >= self.max_sweep(i):
            why = "most sweep"
        elif spin_time >= max_spin_time:
            why = "spin time"
        return Judgement(cov, ratio, bool(why), why)


def so_far(poses: FloatArray, sweep: float) -> SpinSoFar:
    """What a spin's poses so far give: ``poses`` (K, 4) ``t, x, y, yaw`` (yaw unwrapped)
    fitted (:func:`~swpc_hw.calibration.fixed_point.fit_fixed_point`)."""
    fit = fit_fixed_point(poses)
    return SpinSoFar(sweep, fit.covariance, fit.sigma)


def replay(
    ds: Dataset, stopping: Stopping, step: float = JUDGE_STEP
) -> tuple[list[Segment], list[SpinSoFar]]:
    """A recorded run's spins cut where sequential stopping ends them, judged every
    ``step`` of sweep as a run judges them: the segments (their windows ended there) and
    what each gave.  A spin recorded shorter than the rule wants ends with its
    recording.  For benchmarks and tests: the same rule on recorded data (a judgement
    before the spin may end, below ``min_sweep`` and its most sweep, is not made: it
    cannot end it)."""
    segs = prepare_segments(ds, 0.0, "replay", True)
    if len(segs) != len(stopping.spins):
        raise CalibrationError(f"replay: {len(segs)} spins recorded, the plan has "
                               f"{len(stopping.spins)}")  # fmt: skip
    done: list[SpinSoFar] = []
    cut: list[Segment] = []
    for i, sd in enumerate(segs):
        P = sd.poses
        swept = np.abs(P[:, 3] - P[0, 3])
        end, judged, now = P.shape[0] - 1, -math.inf, None
        for k in range(10, P.shape[0]):
            if swept[k] - judged < step:
                continue
            judged = float(swept[k])
            if judged < min(stopping.min_sweep, stopping.max_sweep(i)):
                continue  # the spin cannot end yet, whatever the forecast: not fitted
            now = so_far(P[: k + 1], judged)
            if stopping.judge([*done, now]).stop:
                end = k
                break
        if now is None or end == P.shape[0] - 1:
            now = so_far(P, float(swept[-1]))
        done.append(now)
        cut.append(Segment(sd.segment.static_module, sd.segment.start, float(P[end, 0])))
    return cut, done
