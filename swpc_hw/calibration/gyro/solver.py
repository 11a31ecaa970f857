"""Calibration without motion capture: encoders, a gyro and tape-measure references.

Unknowns: every module's ``x_s, y_s, beta, b, r`` in the ``design-fit`` frame, the gyro's
scale ``s = 1 + eps`` and its bias at every rest window (:mod:`.problem`).  Stages:

1. **Checks**: clocks (:func:`.plausibility.check_dataset`), the segments
   (:func:`.prepare.prepare_segments`, the gyro's turn instead of the poses'), the
   references (refused when nothing fixes the radii or the length scale), rest windows
   before and after every segment.
2. **Build** (:mod:`.build`): noise levels, observations, the start.
3. **Units**: the gyro's yaw against the wheels' over every segment
   (:func:`.plausibility.check_gyro_ratio`: deg/s, a reversed axis, another sensor).
4. **Robust joint least squares** (:func:`fit_imu`): slip bursts found on the wheel
   increments against the gyro's (:func:`.slip.detect_slip`) cut the wheels' runs; each
   block's noise scale is re-estimated (both in :mod:`.weights`); a trust-region solve per
   iteration.
5. **The frame**: the three design-fit conditions are residuals of the problem (the data
   do not see a rigid motion of the frame, so they hold exactly at the optimum); the
   result is then aligned exactly (:func:`swpc_hw.robot.frames.design_fit_transform`).
6. **Covariance** in that frame (:func:`imu_covariance`, :mod:`.covariance`): the
   sandwich on the subspace the conditions leave,
   ``Z (Z^T H Z)^-1 Z^T M Z (Z^T H Z)^-1 Z^T``; the wheels' blocks with a HAC middle over
   their nodes.  Data that leave more than the frame free are refused, naming the
   directions.
7. **Plausibility after solving**: physical values near nominal, the gyro's scale, a
   straight drive whose wheels roll as one arc with the gyro's turn
   (:func:`check_drives_fit`) and that turned little enough for its first-order model
   (:func:`check_drives_straight`).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from swpc_hw.calibration import plausibility
from swpc_hw.calibration.gyro.assemble import assemble_imu_result
from swpc_hw.calibration.gyro.build import (
    ImuRun,
    NoiseLevels,
    build_imu_problem,
    check_references,
    initial_parameters,
)
from swpc_hw.calibration.gyro.covariance import imu_covariance
from swpc_hw.calibration.gyro.misfit import SpinMisfit, max_cut, spin_misfit
from swpc_hw.calibration.gyro.problem import ImuProblem
from swpc_hw.calibration.gyro.weights import (
    MAX_SLIP_FRACTION,
    cut_slip,
    initial_weights,
    set_gyro_sigma,
    spin_levers,
    update_scales,
)
from swpc_hw.calibration.options import SolverOptions
from swpc_hw.calibration.parameters import N_PARAMS, P_S, R, canonical_parameters
from swpc_hw.calibration.prepare import prepare_segments
from swpc_hw.calibration.result import CalibrationResult
from swpc_hw.errors import CalibrationError, ImplausibleDataError
from swpc_hw.files.dataset import Dataset, load_dataset
from swpc_hw.files.references import AxisDistance, Reference, WheelRadius
from swpc_hw.robot.frames import FILE_FIT, design_fit_transform, transform_parameters

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

COARSE_INTERVAL = 1.0
"""Node spacing (s) of the first, coarse solve."""


def fit_imu(
    run: ImuRun, x0: FloatArray, opts: SolverOptions, coarse: ImuRun | None = None
) -> tuple[FloatArray, list[int], list[SpinCut]]:
    """IRLS (:func:`irls`), then every spin's wheels tested against the geometry
    (:func:`.misfit.spin_misfit`): while spins do not fit, one is cut whole
    (:func:`trial_cut`; its wheel readings and its gyro chunks, its settled casters stay)
    and the IRLS runs again from there with fresh weights (``coarse``: the problem the
    trials run on).  More than :func:`.misfit.max_cut` spins not fitting is refused
    (:class:`ImplausibleDataError` naming them).  Returns the solution, the wheel
    increments left out in every rolling set (spins then drives: slip, or the whole spin)
    and the spins cut."""
    prob = run.problem
    floor = initial_weights(run, x0)
    valid = [rs.present.copy() for rs in [*prob.spins, *prob.drives]]
    x, cut = irls(run, x0, valid, opts, floor)
    cuts: list[SpinCut] = []
    while True:
        failing = misfits(prob, x, valid)
        gone = [c.segment for c in cuts]
        worst = trial_cut(coarse or run, x, failing, gone, prob) if failing else None
        if worst is None:
            for c in cuts:  # a spin cut whole: every increment it had is left out
                cut[c.segment] = int(np.sum(c.valid[1:] & c.valid[:-1]))
            check_drives_fit(run, x)
            return x, cut, cuts
        si, m = worst
        rs = prob.spins[si]
        cuts.append(
            SpinCut(
                si, prob.ids[int(prob.seg_static[si])], float(rs.t[0]), float(rs.t[-1]),
                m.z, m.ratio, valid[si].copy(),
            )
        )
        if len(cuts) > max_cut(len(prob.spins)):
            raise ImplausibleDataError(
                f"at least {len(cuts)} of {len(prob.spins)} spins have wheels that do not roll "
                "as one geometry says (a wheel slipping steadily, a caster not settled): "
                + "; ".join(c.describe() for c in cuts)
                + f"; at most {max_cut(len(prob.spins))} may be left out: repeat the run on a "
                "clean, even floor"
            )
        valid[si][:] = False
        floor = initial_weights(run, x)  # the weights the misfit inflated, reset
        x, cut = irls(run, x, valid, opts, floor)


def check_drives_fit(run: ImuRun, x: FloatArray) -> None:
    """Refuse a straight drive whose wheels do not roll as one arc
    (:func:`.misfit.spin_misfit` against the arc's levers: a wheel slipping while
    driving), or whose turn the gyro does not confirm: the wheels' ``kappa (Y_end -
    Y_start)`` against the gyro's beyond 5 std devs of its yaw over the drive (white
    noise ``v dt T``, the knots' bias error ``sigma_b T``) and 0.01 deg.  A drive cannot
    be cut: it is what fixes the radii."""
    prob = run.problem
    X, s, _ = prob.layout.split(x)
    nl = run.noise
    sigma_b = float(np.mean(prob.knot_sigma))
    for rs in prob.drives:
        levers, _, _, wheels_turn = prob.drive_arc(x, rs)
        m = spin_misfit(rs, levers / X[rs.mods, R])
        where = f"straight drive {rs.t[0]:g}-{rs.t[-1]:g} s"
        if not m.fits:
            raise ImplausibleDataError(
                f"{where}: its wheels do not roll as one arc (their ratios "
                f"{m.ratio * 100:.3f} % off, {m.z:.0f} std devs): a wheel slipped"
            )
        T = float(rs.t[-1] - rs.t[0])
        gyro_turn = prob.drive_turn(x, rs)
        sigma = math.sqrt(nl.gyro_var * nl.gyro_dt * T + (sigma_b * T) ** 2) / s
        if abs(gyro_turn - wheels_turn) > max(5.0 * sigma, math.radians(0.01)):
            raise ImplausibleDataError(
                f"{where}: the gyro says the robot turned {math.degrees(gyro_turn):.3f} deg, "
                f"the wheels {math.degrees(wheels_turn):.3f} deg: the gyro and the wheels "
                "disagree"
            )


TRIAL_CUTS = 4
"""How many of the worst spins :func:`trial_cut` tries leaving out."""


def misfits(
    prob: ImuProblem, x: FloatArray, valid: list[BoolArray]
) -> list[tuple[int, SpinMisfit]]:
    """The spins (index, misfit) that do not fit at ``x``, worst first."""
    X, _, _ = prob.layout.split(x)
    out = []
    for si, (rs, g) in enumerate(zip(prob.spins, spin_levers(prob, x), strict=True)):
        if not valid[si].any():
            continue
        m = spin_misfit(rs, g / X[rs.mods, R])
        if not m.fits:
            out.append((si, m))
    return sorted(out, key=lambda e: -e[1].z)


def trial_cut(
    run: ImuRun,
    x: FloatArray,
    failing: list[tuple[int, SpinMisfit]],
    gone: list[int],
    judge: ImuProblem | None = None,
) -> tuple[int, SpinMisfit]:
    """Which of the failing spins to cut: the worst by ``z`` unless a fit bent by a large
    slip puts the worst ``z`` elsewhere.  On ``run`` (the coarse problem: a tenth of the
    cost), without the spins ``gone`` already cut, each of the :data:`TRIAL_CUTS` worst
    is left out in turn for one solve from ``x`` (fresh weights); the one after whose
    removal the fewest spins fail, then the smallest sum of their ``z^2`` (judged on
    ``judge``'s spins, the fine problem's: a coarse spin's few nodes blur ``z``), is cut.
    The problem's samples are put back as they were."""
    if len(failing) == 1:
        return failing[0]
    from scipy.optimize import least_squares  # at first use: see swpc_hw.calibration

    prob = run.problem
    kept = [(rs.present.copy(), rs.run.copy(), list(rs.chunks)) for rs in prob.spins]

    def drop(si: int) -> None:
        prob.spins[si].present = np.zeros_like(prob.spins[si].present)
        prob.spins[si].chunks = []

    best: tuple[tuple[int, float], int] | None = None
    for k, (si, _) in enumerate(failing[:TRIAL_CUTS]):
        for g in [*gone, si]:
            drop(g)
        prob.restack()
        initial_weights(run, x)
        sol = least_squares(
            prob.residuals, x, jac=prob.jacobian, method="lm", x_scale="jac",
            xtol=1e-10, ftol=1e-10, gtol=1e-10, max_nfev=50,
        )
        jp = judge or prob
        valid = [
            rs.present if i not in (*gone, si) else np.zeros_like(rs.present)
            for i, rs in enumerate(jp.spins)
        ]
        rest = misfits(jp, np.asarray(sol.x, dtype=float), valid)
        score = (len(rest), float(sum(m.z**2 for _, m in rest)))
        if best is None or score < best[0]:
            best = (score, k)
        for rs, (present, run_, chunks) in zip(prob.spins, kept, strict=True):
            rs.present, rs.run, rs.chunks = present.copy(), run_.copy(), list(chunks)
        prob.restack()
    assert best is not None
    return failing[best[1]]


@dataclasses.dataclass(frozen=True, eq=False)
class SpinCut:
    """A spin cut whole because its wheels' ratios do not fit (:mod:`.misfit`):
    its index, the locked module, its window (s), the misfit in std devs and the ratios'
    relative RMS change.  (Which wheel slips is not said: a fit bent by the slip spreads
    it over the spin's wheels.)"""

    segment: int
    static_module: int
    start: float
    end: float
    z: float
    ratio: float
    valid: BoolArray
    """Its usable samples before the cut."""

    def describe(self) -> str:
        return (
            f"spin about module {self.static_module} {self.start:.2f}-{self.end:.2f} s "
            f"(its wheels' ratios {self.ratio * 100:.3f} % off, {self.z:.0f} std devs)"
        )


def irls(
    run: ImuRun, x0: FloatArray, valid: list[BoolArray], opts: SolverOptions, floor: float
) -> tuple[FloatArray, list[int]]:
    """IRLS: slip and noise scales alternate with the least-squares solve; at least two
    iterations, at most ``opts.irls_iterations``, done when the cuts are the same as the
    last iteration's and no noise scale moved by 1 %.  ``valid``: every rolling set's
    usable samples.  Returns the solution and the wheel increments cut as slip in every
    rolling set (spins, then drives)."""
    from scipy.optimize import least_squares  # at first use: see swpc_hw.calibration

    prob = run.problem
    n = prob.layout.n
    st = prob.settled
    x = x0.copy()
    cut: list[int] = []
    before: list[BoolArray] = []
    for it in range(max(2, opts.irls_iterations)):
        r_mean = float(np.mean(x[R : N_PARAMS * n : N_PARAMS]))
        cut = cut_slip(prob, valid, x, opts, r_mean * floor * math.sqrt(2.0))
        total = sum(int(np.sum(v[1:] & v[:-1])) for v in valid)
        if sum(cut) > MAX_SLIP_FRACTION * total:
            raise ImplausibleDataError(
                f"{sum(cut)} of {total} wheel increments disagree with the gyro: not slip but "
                "data that do not fit the robot (robot.yaml, the segments' windows, the "
                "gyro's axis or units)"
            )
        scales = np.array([rs.sigma for rs in [*prob.spins, *prob.drives]])
        masks = [rs.present.copy() for rs in [*prob.spins, *prob.drives]]
        if it > 0:
            update_scales(prob, x, floor)
            moved = np.abs(np.array([rs.sigma for rs in [*prob.spins, *prob.drives]]) / scales - 1)
            same = all(
                np.array_equal(m, rs.present) for m, rs in zip(
                    before, [*prob.spins, *prob.drives], strict=True
                )
            )
            if it > 1 and same and float(moved.max(initial=0.0)) < 0.01:
                break
        before = masks
        set_gyro_sigma(prob, run, x)
        sol = least_squares(
            prob.residuals, x, jac=prob.jacobian, method="lm", x_scale="jac",
            xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=100,
        )
        x = sol.x.copy()
        X = canonical_parameters(x[: N_PARAMS * n].reshape(n, N_PARAMS))
        x[: N_PARAMS * n] = X.ravel()
        zb = prob.blocks(x)["settled"]
        rms_b = math.sqrt(float(np.mean(zb**2))) if zb.size else 1.0
        if rms_b > 1.0:  # settled block noisier than its prior: inflate (never deflate)
            st.sigma = st.sigma * rms_b
    update_scales(prob, x, floor)
    set_gyro_sigma(prob, run, x)
    return x, cut


def coarse_fit(run: ImuRun, x0: FloatArray, opts: SolverOptions) -> FloatArray:
    """One solve of a problem with sparse nodes, from the nominal start: it brings a far
    start (a robot 30 % off its design) near the optimum at a tenth of the cost.  Slip
    bursts are cut first (against the gyro with the start's levers, each wheel's scale
    fitted: :func:`wheel_increments`): least squares would bend everything to them."""
    from scipy.optimize import least_squares  # at first use: see swpc_hw.calibration

    prob = run.problem
    n = prob.layout.n
    floor = initial_weights(run, x0)
    valid = [rs.present.copy() for rs in [*prob.spins, *prob.drives]]
    r_mean = float(np.mean(x0[R : N_PARAMS * n : N_PARAMS]))
    cut_slip(prob, valid, x0, opts, r_mean * floor * math.sqrt(2.0), pooled=True)
    sol = least_squares(
        prob.residuals, x0, jac=prob.jacobian, method="lm", x_scale="jac",
        xtol=1e-8, ftol=1e-8, gtol=1e-8, max_nfev=100,
    )
    x = np.asarray(sol.x, dtype=float).copy()
    x[: N_PARAMS * n] = canonical_parameters(x[: N_PARAMS * n].reshape(n, N_PARAMS)).ravel()
    return x


def align_design_fit(prob: ImuProblem, x: FloatArray) -> FloatArray:
    """``x`` with its modules moved exactly into the design-fit frame."""
    n = prob.layout.n
    X = x[: N_PARAMS * n].reshape(n, N_PARAMS)
    phi, t = design_fit_transform(X[:, P_S], prob.P_nom)
    out = x.copy()
    out[: N_PARAMS * n] = transform_parameters(X, phi, t).ravel()
    return out


# ------------------------------------------------------------------ the solve


def solve_imu(
    ds: Dataset,
    options: SolverOptions | None = None,
    source: str = "dataset",
    noise: NoiseLevels | None = None,
) -> CalibrationResult:
    """Calibrate all modules from a dataset without poses (module docstring)."""
    return _solve(ds, options, source, noise, None)


def solve_imu_check(
    ds: Dataset,
    reference: FloatArray,
    options: SolverOptions | None = None,
    source: str = "dataset",
    noise: NoiseLevels | None = None,
) -> CalibrationResult:
    """A check's estimate from a dataset without poses and without references, started
    from the file's parameters ``reference`` (N, 5; the dataset's module order).

    The robot's own sensors fix everything but a planar rigid motion and two scales (the
    layout's and the radii's, docs/imu.md): five gauge conditions fit the estimate to the
    file (its centroid, its rotation, its length scale, the sum of its radii; the
    ``gauge`` block), so that the frame of the result, ``file-fit``, is the file's
    own up to the changes the check measures.  What it determines is the shape: every
    parameter relative to the others.  The covariance is on the subspace the five
    conditions leave (:func:`imu_covariance`); comparing with the file
    (:func:`swpc_hw.calibration.check.shape.compare_shape`) removes the same five
    directions again, per module."""
    X = np.asarray(reference, dtype=float)
    if X.shape != (len(ds.robot.ids), N_PARAMS) or not np.all(np.isfinite(X)):
        raise CalibrationError(
            f"{source}: the file's parameters must be ({len(ds.robot.ids)}, {N_PARAMS}), finite"
        )
    result = _solve(ds, options, source, noise, X)
    result.params = result.params.model_copy(update={"frame": FILE_FIT})
    return result


def _solve(
    ds: Dataset,
    options: SolverOptions | None,
    source: str,
    noise: NoiseLevels | None,
    reference: FloatArray | None,
) -> CalibrationResult:
    opts = options or SolverOptions()
    if opts.time_offset != 0.0:
        raise CalibrationError(
            "without motion capture the encoders and the gyro share one clock: no time "
            "offset (given or auto) applies"
        )
    if ds.imu is None:
        raise CalibrationError(f"{source}: no imu.csv: not an IMU dataset")
    plausibility.check_dataset(ds, source)
    # a check starts from the file: one steering angle per module is enough
    segs = prepare_segments(ds, 0.0, source, calibration=reference is None)
    if reference is None:
        check_references(ds, source)
    coarse = build_imu_problem(
        ds, segs, dataclasses.replace(opts, increment_interval=COARSE_INTERVAL), source, noise,
        reference,
    )  # fmt: skip
    x0 = initial_parameters(coarse, ds, start=reference)
    plausibility.check_gyro_ratio(gyro_ratio(coarse.problem, x0), source)
    check_drives_straight(coarse, x0, plausibility.robot_size(ds.robot), source)
    x0 = coarse_fit(coarse, x0, opts)
    run = build_imu_problem(ds, segs, opts, source, noise, reference)
    x, cut, spin_cuts = fit_imu(run, x0, opts, coarse)
    x = align_design_fit(run.problem, x)
    X = x[: N_PARAMS * run.problem.layout.n].reshape(-1, N_PARAMS)
    plausibility.check_result(X, ds.robot)
    plausibility.check_gyro_scale(float(x[run.problem.layout.scale]) - 1.0)
    check_drives_straight(run, x, plausibility.robot_size(ds.robot), source)  # at the optimum
    cov, J, f = imu_covariance(run.problem, x)
    return assemble_imu_result(
        run, ds, segs, x, cov, J, f, cut, [c.describe() for c in spin_cuts]
    )


def check_drives_straight(run: ImuRun, x: FloatArray, size: float, source: str) -> None:
    """Refuse a straight drive that turned more than its first-order arc covers.

    The drive's model (:mod:`.problem`, ``drive``) takes the gyro's turn ``dyaw`` to
    first order; what it leaves out is of second order: the chord of an arc of length
    ``L`` against its along-track length, ``~dyaw^2 L / 8``, and the rotation of a point
    ``|P| <= size`` from the origin, ``~dyaw^2 size / 2``.  Refused when those exceed a
    quarter of the reference's std dev (0.8 deg over 4 m, with a 0.5 mm tape)."""
    prob = run.problem
    for ref, rs in zip(run.drive_refs, prob.drives, strict=True):
        dyaw = prob.drive_turn(x, rs)
        second = dyaw * dyaw * (ref.value / 8.0 + size / 2.0)
        if second > 0.25 * ref.stddev:
            raise ImplausibleDataError(
                f"{source}/references.yaml: straight_drive {ref.start:g}-{ref.end:g} s: the "
                f"gyro says the robot turned {math.degrees(dyaw):.3f} deg: too far from a "
                f"straight line (the arc's second-order terms {second * 1e3:.3f} mm, a "
                f"quarter of the reference's std dev {ref.stddev * 1e3:.2f} mm): steer the "
                "wheels parallel (the spins' betas) and drive on a level floor"
            )


def gyro_ratio(prob: ImuProblem, x: FloatArray) -> float:
    """Median over the segments of the gyro's turn over the wheels' (1 when right)."""
    X, s, knots = prob.layout.split(x)
    out = []
    for rs, g in zip(prob.spins, spin_levers(prob, x), strict=True):
        _, Y = prob.rolled(X, rs, g)
        if not rs.chunks:
            continue
        la, lb = rs.chunks[0]
        wheels = float(Y[lb] - Y[la])
        gy = float(rs.gyro_yaw(s, knots, np.array([la]), np.array([lb]))[0])
        if abs(wheels) > 0:
            out.append(gy / wheels)
    return float(np.median(out)) if out else 1.0


LOOSE_LENGTH = 0.05
"""Std dev (m) of the stand-in axis distance :func:`solve_spins` gives when none is known."""
LOOSE_RADIUS = 1e-4
"""Std dev (m) of its stand-in wheel radius.  Without a straight drive the radii's scale
and the gyro's are one unknown (``r dpsi = D s dyaw``): the stand-in is all that holds
it, and moves no ``beta``.  Its std dev sets only how well the problem is conditioned:
at 5 mm the scaled information's smallest eigenvalue fell under ``1e-12`` of its largest
on every run (the encoders fix the radii's ratios to microns), and the spins were
refused as "not determined", the drive steered by the nominal ``beta`` and refused for
turning; at 0.1 mm and 0.01 mm the differences of ``beta`` are the same to 1e-4 deg
(``tests/calibration/gyro/test_spins_alone.py``)."""


def solve_spins(
    ds: Dataset, options: SolverOptions | None = None, source: str = "dataset"
) -> CalibrationResult:
    """The spins alone, before any straight drive: what steers the drive.

    The encoders fix the differences of ``beta`` by themselves (docs/imu.md, the Fisher
    table: 0.5 mdeg), not the two scales (the layout's length, the wheels' radii).  The
    dataset's own axis distances and wheel radii are used; a scale nothing fixes is held
    loosely at the nominal robot's by a stand-in reference: the distance between the first
    two steering axes (std dev :data:`LOOSE_LENGTH`), the first wheel's radius
    (:data:`LOOSE_RADIUS`).  Neither moves a difference of ``beta``.  A straight drive in
    the dataset is left out.  The result's lengths are not a calibration: only its
    ``beta`` (design-fit frame) is meant to be used.
    """
    refs: list[Reference] = [
        r for r in ds.references if isinstance(r, AxisDistance | WheelRadius)
    ]
    a = ds.robot.arrays()
    ids = ds.robot.ids
    if not any(isinstance(r, AxisDistance) for r in refs):
        d = float(np.linalg.norm(a.P_s[0] - a.P_s[1]))
        refs.append(AxisDistance((ids[0], ids[1]), d, LOOSE_LENGTH))
    if not any(isinstance(r, WheelRadius) for r in refs):
        refs.append(WheelRadius(ids[0], float(a.r[0]), LOOSE_RADIUS))
    return solve_imu(dataclasses.replace(ds, references=refs), options, source)


def solve_imu_directory(
    path: str | Path, options: SolverOptions | None = None
) -> CalibrationResult:
    """Load a dataset directory without poses.csv and solve it."""
    return solve_imu(load_dataset(path), options, source=str(path))
