"""The solver tells the truth about itself: correlated noise, clock offset, slow slip, bad data.

One run each (statistics over many seeds are in ``python -m benchmarks solver``).
"""

from __future__ import annotations

import dataclasses
import math
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from services.cli import main as swpc_main
from simulators.offline.datagen import (
    ExperimentOptions,
    PartialSlip,
    ar1_noise,
    generate_experiment,
)
from swpc_hw.calibration.fixed_point import fit_fixed_point
from swpc_hw.calibration.mocap.baseline import solve_paper, widest_pair
from swpc_hw.calibration.mocap.clock_offset import jackknife_std
from swpc_hw.calibration.mocap.solver import (
    SolverOptions,
    check_rolling_left,
    solve,
    solve_joint,
)
from swpc_hw.calibration.mocap.yaw_noise import score_variance
from swpc_hw.calibration.plausibility import check_dataset, check_result, jitter_sigma
from swpc_hw.calibration.prepare import prepare_segments
from swpc_hw.calibration.rolling import RollingSeries
from swpc_hw.calibration.uncertainty import ar1_quadratic_form, long_run_covariance
from swpc_hw.errors import CalibrationError, ImplausibleDataError, ImplausibleResultError
from swpc_hw.files.dataset import Dataset, save_dataset
from swpc_hw.robot.model import PARAM_NAMES, RobotParams, wrap_angle
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED, PAPER_NOMINAL

NAMES = PARAM_NAMES
MOCAP = ExperimentOptions(
    pose_sigma_xy=0.5e-3, pose_sigma_yaw=math.radians(0.05), spin_duration=4.0, seed=21
)


def as_array(p: RobotParams) -> np.ndarray:
    return np.array([[getattr(m, k) for k in NAMES] for m in p.modules])


def z_scores(res: object) -> np.ndarray:
    r = res
    return (as_array(r.params) - as_array(PAPER_CALIBRATED)) / r.stddev_array()  # type: ignore[attr-defined]


# ------------------------------------------------------------------ correlated noise


def test_long_run_variance_of_ar1_noise_with_gaps() -> None:
    """Var(sum) of AR(1) noise is (1 + rho) / (1 - rho) times the white value; 20 % gaps."""
    rng = np.random.default_rng(1)
    rho, T = 0.8, 40_000
    w = rng.normal(size=T)
    x = np.empty(T)
    x[0] = w[0]
    for t in range(1, T):
        x[t] = rho * x[t - 1] + math.sqrt(1 - rho * rho) * w[t]
    present = rng.uniform(size=T) > 0.2
    S = np.where(present, x, 0.0)[:, None]
    omega, rho_hat, _ = long_run_covariance(S, present)
    assert rho_hat == pytest.approx(rho, abs=0.02)
    # Var(sum of the present samples) = sum_{i,j present} rho^|i-j| = sum_k c_k rho^|k|
    p = present.astype(float)
    pairs = [float(p[: T - k] @ p[k:]) for k in range(150)]
    expected = pairs[0] + 2 * sum(c * rho**k for k, c in enumerate(pairs) if k > 0)
    assert expected < 0.85 * present.sum() * (1 + rho) / (1 - rho)  # the gaps matter
    assert omega[0, 0] == pytest.approx(expected, rel=0.1)
    white, rho_w, _ = long_run_covariance(w[:, None], np.ones(T, dtype=bool))
    assert white[0, 0] == pytest.approx(T, rel=0.05)
    assert abs(rho_w) < 0.02


def test_correlated_mocap_noise_inflates_the_std_devs_and_says_so() -> None:
    white = solve(generate_experiment(PAPER_CALIBRATED, MOCAP).dataset)
    ar1 = solve(
        generate_experiment(
            PAPER_CALIBRATED, dataclasses.replace(MOCAP, pose_noise_rho=0.8)
        ).dataset
    )
    ratio = ar1.stddev_array() / white.stddev_array()
    # AR(1) with rho 0.8: sqrt((1 + rho) / (1 - rho)) = 3 on what the poses determine
    assert np.median(ratio[:, [0, 1, 4]]) == pytest.approx(3.0, rel=0.25)
    # per segment (4 s of poses each: a noisy estimate of a ratio that is 3 and 1)
    assert all(2.0 < s.noise_inflation < 4.0 for s in ar1.segments)  # type: ignore[operator]
    assert all(0.75 < s.noise_inflation < 1.25 for s in white.segments)  # type: ignore[operator]
    for res in (white, ar1):
        assert np.abs(z_scores(res)).max() < 4.0


# ------------------------------------------------------------------ clock offset


@pytest.mark.parametrize("offset", [0.0, 0.03, 0.2])
def test_clock_offset_estimate_and_its_std_dev_with_mocap_noise(offset: float) -> None:
    """No offset, a small one and a large one (the old estimate stuck at
    +-15 ms, a multiple of half the encoder period, on 0 and -30 ms)."""
    opts = dataclasses.replace(MOCAP, clock_offset=offset)
    ds = generate_experiment(PAPER_CALIBRATED, opts).dataset
    res = solve(ds, SolverOptions(time_offset="auto"))
    assert res.time_offset_mode == "estimated"
    assert res.time_offset_std is not None and 2e-5 < res.time_offset_std < 1e-3
    err = res.time_offset - offset
    assert abs(err) < 1e-3
    assert abs(err) < 3.0 * res.time_offset_std
    assert np.abs(z_scores(res)).max() < 4.0


def test_a_steady_slip_widens_the_clock_offsets_std_dev_to_cover_it() -> None:
    """Issue 30: wheel 2 slipping 0.54 % through both spins about module 1 pulls the
    estimate on a true 0 by many sandwich std devs (-0.44 ms here, 4 s spins; -1.28 ms
    with 12 s spins, z 17).  The modules' leave-one-out spread now is its std dev."""
    slips = tuple(PartialSlip(2, m, 0.09, 1.0, -0.0054) for m in range(2))
    opts = dataclasses.replace(
        MOCAP, partial_slips=slips, rest_time=2.0, drive_length=4.0, seed=9000
    )
    res = solve(generate_experiment(PAPER_CALIBRATED, opts).dataset,
                SolverOptions(time_offset="auto"))  # fmt: skip
    assert res.time_offset_mode == "estimated" and res.time_offset_std is not None
    assert abs(res.time_offset) > 0.3e-3  # the slip's pull, as before
    assert abs(res.time_offset) < 2.0 * res.time_offset_std  # now covered
    clean = dataclasses.replace(opts, partial_slips=())
    ref = solve(generate_experiment(PAPER_CALIBRATED, clean).dataset,
                SolverOptions(time_offset="auto"))  # fmt: skip
    assert ref.time_offset_std is not None and ref.time_offset_std < 0.2e-3
    assert res.time_offset_std > 4.0 * ref.time_offset_std  # 0.41 ms against 0.083 ms


def test_jackknife_std_of_groups() -> None:
    assert jackknife_std([1.0]) == 0.0
    # (G - 1) / G sum (v - mean)^2 = 3/4 (3 x 0.25^2 + 0.75^2) = 0.5625
    assert jackknife_std([0.0, 0.0, 0.0, 1.0]) == pytest.approx(0.75)


def test_ar1_quadratic_form_is_the_matrix_product() -> None:
    rng = np.random.default_rng(4)
    c = rng.normal(size=40)
    present = rng.uniform(size=40) > 0.3
    k = np.arange(40)
    R = 0.7 ** np.abs(k[:, None] - k[None, :])
    x = np.where(present, c, 0.0)
    assert ar1_quadratic_form(c, present, 0.7) == pytest.approx(float(x @ R @ x), rel=1e-12)


@pytest.mark.parametrize("rho", [0.0, 0.64])
def test_the_variance_of_a_score_sum_while_the_casters_swing_round(rho: float) -> None:
    """Three casters turning round one after the other while the yaw noise is summed into
    the cumulative residual: the variance of ``sum a e`` over 200 noise draws against
    what :func:`score_variance` says from each draw's residuals.  Scores per node with a
    Bartlett sum (what the clock offset used) read half of it."""
    K, M = 600, 3
    t = np.arange(K) * 0.02
    swing = [np.tanh((t - 0.8 * (i + 1)) / 0.3) for i in range(M)]
    g = np.concatenate([0.3 * (1 + 0.3 * i) * swing[i] for i in range(M)])
    ramp = np.exp(-(((t - 1.0) / 0.5) ** 2)) - np.exp(-(((t - 10.0) / 0.5) ** 2))
    a = np.concatenate([(1 + 0.5 * i) * (ramp - ramp.mean()) for i in range(M)])
    i0 = np.zeros(K * M, dtype=np.int64)
    z = np.zeros(K * M)
    mod = np.repeat(np.arange(M), K)
    series = RollingSeries(i0, mod, mod, np.tile(np.arange(K), M), np.tile(t, M), z, z, z, run=mod)
    rng = np.random.default_rng(3)
    sums, said, per_node = [], [], []
    for _ in range(200):
        n = ar1_noise(rng.normal(size=K), rho)
        G = [np.cumsum(np.r_[0.0, 0.5 * (gi[1:] + gi[:-1]) * np.diff(n)]) for gi in np.split(g, M)]
        e = -np.concatenate([Gi - Gi.mean() for Gi in G])  # the run's intercept profiled
        sums.append(float(a @ e))
        said.append(score_variance(series, g, a, e))
        per_node.append(long_run_covariance((a * e).reshape(M, K).sum(0)[:, None], t >= 0)[0])
    var = float(np.var(sums))
    assert float(np.mean(said)) == pytest.approx(var, rel=0.2)
    assert float(np.mean(per_node)) < 0.7 * var


def test_a_clock_offset_steady_spins_cannot_show_is_reported_not_observable() -> None:
    """Poses and encoders only inside the segments (steady spins): no information."""
    exp = generate_experiment(PAPER_CALIBRATED, dataclasses.replace(MOCAP, clock_offset=-0.1))
    ds = exp.dataset

    def inside(t: np.ndarray) -> np.ndarray:
        return np.any([(t >= s.start) & (t <= s.end) for s in ds.segments], axis=0)

    only = Dataset(
        ds.robot,
        ds.poses[inside(ds.poses[:, 0])],
        {m: e[inside(e[:, 0] + 0.1)] for m, e in ds.encoders.items()},
        ds.segments,
    )
    res = solve(only, SolverOptions(time_offset="auto"))
    assert res.time_offset_mode == "not observable"
    assert (res.time_offset, res.time_offset_std) == (0.0, None)
    assert np.abs(z_scores(res)).max() < 4.0  # and harmless: the parameters are right


# ------------------------------------------------------------------ slow slip


def test_a_wheel_slipping_0_4_percent_over_part_of_two_segments_is_cut_out() -> None:
    slips = (PartialSlip(2, 0, 0.5, 1.0, 0.004), PartialSlip(2, 4, 0.0, 0.5, 0.004))
    opts = dataclasses.replace(MOCAP, partial_slips=slips, spin_duration=8.0, seed=3001)
    res = solve(generate_experiment(PAPER_CALIBRATED, opts).dataset)
    rejected = {q.row: q.increments_rejected for q in res.segments}
    assert rejected[0] >= 15 and rejected[4] >= 15  # ~2 s and more of each 4 s slip
    assert sum(rejected.values()) - rejected[0] - rejected[4] <= 10
    assert np.abs(z_scores(res)).max() < 3.5


# ------------------------------------------------------------------ bad data


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("run")
    generate_experiment(PAPER_CALIBRATED, MOCAP).save(d)
    return d


def _copy(src: Path, dst: Path) -> Path:
    dst.mkdir()
    for f in src.iterdir():
        (dst / f.name).write_bytes(f.read_bytes())
    return dst


def _map_poses(path: Path, f: object) -> None:
    lines = path.read_text().splitlines()
    rows = [[float(v) for v in ln.split(",")] for ln in lines[1:]]
    rows = [f(r) for r in rows]  # type: ignore[operator]
    path.write_text("\n".join([lines[0], *(",".join(f"{v:.9f}" for v in r) for r in rows)]) + "\n")


def _jump_back(path: Path) -> None:
    lines = path.read_text().splitlines()
    half = len(lines) // 2
    moved = [f"{float(ln.split(',', 1)[0]) - 5.0:.6f},{ln.split(',', 1)[1]}" for ln in lines[half:]]
    path.write_text("\n".join(lines[:half] + moved) + "\n")


BAD_DATA = {
    "poses in millimetres": (
        lambda d: _map_poses(d / "poses.csv", lambda r: [r[0], r[1] * 1e3, r[2] * 1e3, r[3]]),
        ["poses look like millimetres"],
    ),
    "yaw in degrees": (
        lambda d: _map_poses(d / "poses.csv", lambda r: [*r[:3], math.degrees(r[3])]),
        ["yaw looks like degrees"],
    ),
    "pose clock jumps back 5 s": (
        lambda d: _jump_back(d / "poses.csv"),
        ["poses.csv: t: the clock jumps back 4.990 s", "not one monotonic clock"],
    ),
    "header-only poses": (
        lambda d: (d / "poses.csv").write_text("t,x,y,yaw\n"),
        ["poses.csv: no data rows"],
    ),
    "paper method with an automatic clock offset": (
        lambda d: None,
        ["--time-offset auto is not available with --method paper"],
    ),
}


@pytest.mark.parametrize("case", sorted(BAD_DATA))
def test_bad_data_is_refused_with_a_one_line_reason(
    case: str, run_dir: Path, tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    mutate, messages = BAD_DATA[case]
    d = _copy(run_dir, tmp_path / "ds")
    mutate(d)
    out = tmp_path / "k.yaml"
    extra = ["--method", "paper", "--time-offset", "auto"] if "paper" in case else []
    assert swpc_main(["solve", str(d), "-o", str(out), *extra]) == 2
    captured = capfd.readouterr()
    err = captured.err.strip()
    assert "\n" not in err and "Warning" not in err  # one line, no numpy warnings
    for m in messages:
        assert m in err
    assert not out.exists()


def test_a_sorted_file_of_a_jumped_clock_is_refused_by_its_fixed_points() -> None:
    """Sorted, the two overlapping streams interleave: their segments are no fixed point.

    (Refused before the joint solve: cheap.)"""
    long_spins = dataclasses.replace(MOCAP, spin_duration=12.0)
    ds = generate_experiment(PAPER_CALIBRATED, long_spins).dataset
    jump = ds.poses.shape[0] // 2
    jumped = ds.poses.copy()
    jumped[jump:, 0] -= 5.003  # back 5 s, off the 100 Hz grid
    jumped = jumped[np.argsort(jumped[:, 0], kind="stable")]
    with pytest.raises(ImplausibleDataError, match="did not turn about one point"):
        solve(Dataset(ds.robot, jumped, ds.encoders, ds.segments))
    dup = ds.poses.copy()
    dup[jump:, 0] -= 5.0  # on the 100 Hz grid: timestamps carry two poses
    dup = dup[np.argsort(dup[:, 0], kind="stable")]
    with pytest.raises(ImplausibleDataError, match="carry two different poses"):
        check_dataset(Dataset(ds.robot, dup, ds.encoders, ds.segments))


def test_jitter_measures_the_white_pose_noise(run_dir: Path) -> None:
    from swpc_hw.files.dataset import load_dataset

    sd = prepare_segments(load_dataset(run_dir))[0]
    assert jitter_sigma(sd.poses[:, 0], sd.poses[:, 1]) == pytest.approx(0.5e-3, rel=0.15)
    assert fit_fixed_point(sd.poses).rms == pytest.approx(
        math.sqrt(2 * 0.5e-3**2 + 0.3**2 * math.radians(0.05) ** 2), rel=0.15
    )


def test_piping_into_a_reader_that_stops_is_not_an_error(run_dir: Path, tmp_path: Path) -> None:
    """``swpc solve ... | head -1``: the reader is gone before the table is printed."""
    out = tmp_path / "k.yaml"
    cmd = [sys.executable, "-m", "services.cli", "solve", str(run_dir), "-o", str(out)]
    proc = subprocess.Popen(
        [*cmd, "--method", "paper"], stdout=subprocess.PIPE, stderr=subprocess.PIPE
    )
    assert proc.stdout is not None and proc.stderr is not None
    proc.stdout.close()  # before the child has solved anything
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=60) == 0, err
    assert "Traceback" not in err and "BrokenPipe" not in err
    assert out.exists()


# ------------------------------------------------------------------ the paper's baseline


def test_the_paper_takes_the_widest_pair_of_angles() -> None:
    rad = [math.radians(a) for a in (30.0, 90.0, 250.0)]
    assert widest_pair(rad) == (rad[1], rad[2])  # 160 deg apart, the others 60 and 140
    assert widest_pair(rad[:2]) == (rad[0], rad[1])
    # on a run with the three angles: exactly what the widest pair's segments alone give
    opts = dataclasses.replace(MOCAP, angles=tuple(rad), spin_duration=3.5)
    ds = generate_experiment(PAPER_CALIBRATED, opts).dataset
    angle = [sd.angle for sd in prepare_segments(ds)]

    def only(keep: tuple[float, float]) -> Dataset:
        segs = [
            s
            for s, a in zip(ds.segments, angle, strict=True)
            if min(abs(float(wrap_angle(a - k))) for k in keep) < 1e-3
        ]
        assert len(segs) == 8
        return Dataset(ds.robot, ds.poses, ds.encoders, segs)

    full = as_array(solve_paper(ds).params)
    np.testing.assert_array_equal(full, as_array(solve_paper(only((rad[1], rad[2]))).params))
    first_two = as_array(solve_paper(only((rad[0], rad[1]))).params)
    assert np.all(full != first_two)


def test_the_paper_report_has_no_nan_and_refuses_short_spins(
    run_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "k.yaml"
    assert swpc_main(["solve", str(run_dir), "-o", str(out), "--method", "paper"]) == 0
    text = capsys.readouterr().out
    assert "nan" not in text.lower() and "reduced chi2 n/a" in text
    short = dataclasses.replace(MOCAP, spin_duration=0.7)  # 20 deg per segment
    ds = generate_experiment(PAPER_CALIBRATED, short).dataset
    refused = r"turned (19|20)\.\d deg: the paper.s circle fit"
    with pytest.raises(ImplausibleDataError, match=refused):
        solve_paper(ds)
    res = solve(ds)  # the joint solver says what such data are worth
    assert np.abs(z_scores(res)).max() < 4.0
    save_dataset(tmp_path / "short", ds)
    capsys.readouterr()
    out = tmp_path / "short.yaml"
    assert swpc_main(["solve", str(tmp_path / "short"), "-o", str(out), "--method", "paper"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and re.search(refused, err), err
    assert not out.exists()


def test_a_result_no_robot_can_have_or_far_from_nominal_is_refused() -> None:
    """The gate after solving, on the nominal robot's own parameters, one fault at a time."""
    X = as_array(PAPER_NOMINAL)
    check_result(X, PAPER_NOMINAL)  # the nominal robot itself passes
    cases = {
        "nan": ((1, 0), math.nan, "did not converge to a physical solution: module 2 x_s = nan"),
        "b <= 0": ((2, 3), -0.002, "module 3 b = -0.002 m, r = 0.055 m"),
        "r <= 0": ((0, 4), 0.0, "module 1 b = 0.02 m, r = 0 m"),
        "moved": ((3, 1), X[3, 1] + 0.3, "module 4 P_s 0.3 m from nominal"),
        "radius": ((1, 4), 0.2, "module 2 r = 0.2 m against 0.055 m nominal"),
        "mm": ((slice(None), 4), 55.0, "(poses look like millimetres)"),
    }
    for name, (where, value, message) in cases.items():
        Y = X.copy()
        Y[where] = value
        with pytest.raises(ImplausibleResultError) as exc:
            check_result(Y, PAPER_NOMINAL)
        assert message in str(exc.value), (name, str(exc.value))
        assert "\n" not in str(exc.value)


def test_a_wheel_with_every_increment_cut_as_slip_is_refused_naming_it() -> None:
    """A wheel slipping through every spin leaves no rolling increment after the slip
    cuts, and its radius unmeasured (8e7 m on the soft-tyred physics of
    ``bench_other_physics``): refused naming the module, not passed on to the
    plausibility gate as a robot far from the nominal."""
    ex = generate_experiment(PAPER_CALIBRATED, ExperimentOptions(seed=3), PAPER_NOMINAL)
    sol = solve_joint(ex.dataset)
    series = sol.problem.rolling
    mods = series.mod[series.pairs()]
    ids = PAPER_NOMINAL.ids
    check_rolling_left(sol.problem, np.zeros(mods.size, dtype=bool), ids, "run")  # all kept
    slip = mods == 1  # module 2's increments, every one cut
    check_rolling_left(sol.problem, slip & (np.arange(mods.size) % 2 == 0), ids, "run")
    with pytest.raises(CalibrationError, match=r"run: module 2's wheel: all (\d+) of its"):
        check_rolling_left(sol.problem, slip, ids, "run")
    assert int(slip.sum()) > 100  # 6 spins of 360 deg at 0.1 s nodes
