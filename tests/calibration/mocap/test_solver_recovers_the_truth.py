"""Calibration solver: recovers the truth from generator data; bad data is a clear error."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from services.cli import main as swpc_main
from simulators.offline.datagen import ExperimentOptions, generate_experiment
from swpc_hw.calibration import geometry as geo
from swpc_hw.calibration.mocap.baseline import solve_paper
from swpc_hw.calibration.mocap.solver import SolverOptions, canonical_parameters, solve
from swpc_hw.files.dataset import load_dataset
from swpc_hw.files.kinematic_file import load_kinematics
from swpc_hw.robot.model import PARAM_NAMES, RobotParams, contact_point
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED, PAPER_NOMINAL

NAMES = PARAM_NAMES
NOISELESS = ExperimentOptions(counts_per_rev=None, spin_duration=6.0)


def as_array(p: RobotParams) -> np.ndarray:
    return np.array([[getattr(m, k) for k in NAMES] for m in p.modules])


def ring_robot(n: int, seed: int) -> RobotParams:
    """n modules on a ring (radius ~0.25 m) with random errors."""
    rng = np.random.default_rng(seed)
    ang = np.arange(n) * 2 * np.pi / n + np.pi / n + rng.uniform(-0.1, 0.1, n)
    rad = 0.25 * (1 + rng.uniform(-0.1, 0.1, n))
    P = np.column_stack([rad * np.cos(ang), rad * np.sin(ang)])
    return RobotParams.from_arrays(
        [10 + i for i in range(n)], P, rng.uniform(-0.3, 0.3, n),
        0.02 * (1 + rng.uniform(-0.1, 0.1, n)), 0.055 * (1 + rng.uniform(-0.1, 0.1, n)),
    )


@pytest.mark.parametrize("n", [2, 3, 4, 6])
def test_noiseless_recovery_for_any_number_of_modules(n: int) -> None:
    truth = ring_robot(n, seed=n)
    ds = generate_experiment(truth, NOISELESS).dataset
    res = solve(ds)
    err = np.abs(as_array(res.params) - as_array(truth))
    assert err.max() < 1e-9, err
    assert [m.id for m in res.params.modules] == truth.ids


def test_noiseless_recovery_with_three_steering_angles() -> None:
    opts = dataclasses.replace(NOISELESS, angles=tuple(math.radians(a) for a in (30, 120, 250)))
    ds = generate_experiment(PAPER_CALIBRATED, opts).dataset
    assert len(ds.segments) == 12
    res = solve(ds)
    assert np.abs(as_array(res.params) - as_array(PAPER_CALIBRATED)).max() < 1e-9


def test_paper_baseline_is_exact_without_noise() -> None:
    ds = generate_experiment(PAPER_CALIBRATED, NOISELESS).dataset
    res = solve_paper(ds)
    assert np.abs(as_array(res.params) - as_array(PAPER_CALIBRATED)).max() < 1e-9


def test_paper_equations_match_the_generalised_fit() -> None:
    rng = np.random.default_rng(7)
    P_s, b, beta = rng.normal(size=2) * 0.2, 0.021, 0.4
    a = np.array([0.8, 2.9])
    pts = P_s + b * np.column_stack([np.cos(a + beta), np.sin(a + beta)])
    bb = geo.offset_from_chord(pts[0], pts[1], a[1] - a[0])
    ps = geo.steering_axis_from_chord(pts[0], pts[1], bb, a[1] - a[0])
    np.testing.assert_allclose([bb, *ps, geo.homing_error(pts[0], ps, a[0])], [b, *P_s, beta])
    ps2, b2, beta2 = geo.steering_circle_fit(pts, a)
    np.testing.assert_allclose([b2, *ps2, beta2], [b, *P_s, beta])


def test_a_module_in_its_mirror_parametrisation_is_mapped_back() -> None:
    P_s, beta, b, r = np.array([0.21, -0.12]), 3.0, 0.021, 0.055
    theta, C = np.array([0.4, 1.9, -2.2]), np.array([0.5, 0.1])  # steering angles, a point
    mirror = (beta + np.pi, -b, -r)
    # every observation block is blind to the mirror: A equal, B and C change sign
    np.testing.assert_allclose(
        contact_point(P_s, np.array(-b), theta + mirror[0]),
        contact_point(P_s, np.array(b), theta + beta),
        atol=1e-15,
    )
    np.testing.assert_allclose(
        geo.settled_residual(P_s, np.array(-b), theta + mirror[0], C),
        -geo.settled_residual(P_s, np.array(b), theta + beta, C),
        atol=1e-15,
    )
    g = geo.rolling_lever(P_s, np.array(b), theta + beta, C)
    g_m = geo.rolling_lever(P_s, np.array(-b), theta + mirror[0], C)
    np.testing.assert_allclose(g_m / mirror[2], g / r, rtol=1e-12)  # same dpsi per dyaw
    X = np.array([[*P_s, mirror[0], mirror[1], mirror[2]], [0.0, 0.2, -0.5, 0.02, 0.056]])
    Y = canonical_parameters(X)
    np.testing.assert_allclose(Y[0], [*P_s, beta, b, r], atol=1e-15)
    np.testing.assert_array_equal(Y[1], X[1])  # b > 0: left alone
    assert X[0, 3] < 0  # a copy: the input is untouched


def test_noisy_result_is_within_its_reported_uncertainty() -> None:
    opts = ExperimentOptions(pose_sigma_xy=0.5e-3, pose_sigma_yaw=math.radians(0.05), seed=3)
    ds = generate_experiment(PAPER_CALIBRATED, opts).dataset
    res = solve(ds)
    err = as_array(res.params) - as_array(PAPER_CALIBRATED)
    std = res.stddev_array()
    assert np.all(std > 0)
    assert np.abs(err / std).max() < 5.0
    assert np.abs(err[:, [0, 1, 3, 4]]).max() < 0.05e-3  # 50 micrometres
    assert np.abs(err[:, 2]).max() < math.radians(0.01)
    assert res.poses_rejected <= 0.001 * res.poses_used  # Rayleigh tail beyond 4 sigma: 3e-4


def test_outliers_and_slip_are_rejected_and_counted() -> None:
    opts = ExperimentOptions(
        pose_sigma_xy=0.5e-3, pose_sigma_yaw=math.radians(0.05), dropout_fraction=0.2,
        outlier_fraction=0.01, outlier_magnitude=0.05, slip_burst_rate=0.3, seed=5,
    )
    exp = generate_experiment(PAPER_CALIBRATED, opts)
    res = solve(exp.dataset)
    err = as_array(res.params) - as_array(PAPER_CALIBRATED)
    assert res.poses_rejected >= 0.5 * len(exp.outlier_times)
    assert res.increments_rejected > 0
    assert np.abs(err[:, 4]).max() < 0.02e-3  # r within 20 micrometres despite slip
    paper = solve_paper(exp.dataset)
    err_p = as_array(paper.params) - as_array(PAPER_CALIBRATED)
    assert np.abs(err_p[:, 4]).max() > 5 * np.abs(err[:, 4]).max()


def test_a_given_clock_offset_is_honoured_exactly() -> None:
    opts = ExperimentOptions(clock_offset=-0.05, counts_per_rev=None, spin_duration=6.0)
    ds = generate_experiment(PAPER_CALIBRATED, opts).dataset
    given = solve(ds, SolverOptions(time_offset=-0.05))
    assert given.time_offset_mode == "given"
    assert np.abs(as_array(given.params) - as_array(PAPER_CALIBRATED)).max() < 1e-8
    paper = solve_paper(ds, -0.05)
    assert np.abs(as_array(paper.params) - as_array(PAPER_CALIBRATED)).max() < 1e-9


# ------------------------------------------------------------------ CLI and bad data


@pytest.fixture(scope="module")
def dataset_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("run")
    opts = ExperimentOptions(pose_sigma_xy=0.5e-3, pose_sigma_yaw=math.radians(0.05), seed=11)
    generate_experiment(PAPER_CALIBRATED, opts).save(d)
    return d


def test_cli_writes_a_loadable_file_and_prints_the_table(
    dataset_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "kinematics.yaml"
    assert swpc_main(["solve", str(dataset_dir), "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert "nominal" in text and "std dev" in text and str(out) in text
    assert "215.000" in text  # nominal x_s of module 1 in mm
    k = load_kinematics(out)
    err = as_array(k.params) - as_array(PAPER_CALIBRATED)
    assert np.abs(err[:, [0, 1, 3, 4]]).max() < 0.05e-3
    assert all(m.stddev is not None for m in k.params.modules)
    assert k.extra["quality"]["poses_used"] > 5000
    # the full covariance: 20 x 20, its diagonal the stddevs; the modules' betas are
    # correlated (each beta leans on the others' fixed points through the settled casters)
    cov = np.array(k.covariance)
    assert cov.shape == (20, 20)
    std = np.array([[getattr(m.stddev, n) for n in NAMES] for m in k.params.modules])
    np.testing.assert_allclose(np.sqrt(np.diag(cov)), std.ravel(), rtol=1e-12)
    beta = [5 * i + 2 for i in range(4)]
    corr = cov[np.ix_(beta, beta)] / np.outer(std[:, 2], std[:, 2])
    assert np.abs(corr[~np.eye(4, dtype=bool)]).max() > 0.2


def _copy(src: Path, dst: Path) -> Path:
    dst.mkdir()
    for f in src.iterdir():
        (dst / f.name).write_bytes(f.read_bytes())
    return dst


def _rewrite(path: Path, keep: object) -> None:
    lines = path.read_text().splitlines()
    path.write_text("\n".join([lines[0], *[ln for ln in lines[1:] if keep(ln)]]) + "\n")


BAD_CASES = {
    "missing file": (lambda d: (d / "poses.csv").unlink(), "poses.csv: missing file"),
    "missing column": (
        lambda d: (d / "encoders.csv").write_text(
            (d / "encoders.csv").read_text().replace("t,module,steer,wheel", "t,module,steer", 1)
        ),
        "encoders.csv: missing column(s) wheel",
    ),
    "module never locked": (
        lambda d: _rewrite(d / "segments.csv", lambda ln: not ln.startswith("3,")),
        "module 3 is never locked",
    ),
    "one steering angle": (
        lambda d: _rewrite(
            d / "segments.csv",
            lambda ln: ln != (d / "segments.csv").read_text().splitlines()[4],
        ),
        "module 2 has 1 distinct steering angle",
    ),
    "no rotation": (
        lambda d: (d / "segments.csv").write_text(
            (d / "segments.csv").read_text() + "1,0.0,0.5\n"
        ),
        "no rotation",
    ),
    "too few samples": (
        lambda d: (d / "segments.csv").write_text(
            (d / "segments.csv").read_text() + "1,1000.0,1000.05\n"
        ),
        "too few pose samples",
    ),
    "bad robot.yaml": (
        lambda d: (d / "robot.yaml").write_text(
            (d / "robot.yaml").read_text().replace("r: 0.055", "r: -0.055", 1)
        ),
        "robot.yaml: modules[0].r: must be within [0.001, 1] (got -0.055)",
    ),
    "not a number": (
        lambda d: (d / "poses.csv").write_text((d / "poses.csv").read_text() + "1.0,abc,2,3\n"),
        "poses.csv: unreadable row",
    ),
}


@pytest.mark.parametrize("case", sorted(BAD_CASES))
def test_bad_data_is_a_one_line_error_exit_2_and_no_output(
    case: str, dataset_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    mutate, message = BAD_CASES[case]
    d = _copy(dataset_dir, tmp_path / "ds")
    mutate(d)
    out = tmp_path / "k.yaml"
    assert swpc_main(["solve", str(d), "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err
    assert message in err
    assert str(d) in err
    assert not out.exists()


def test_dataset_round_trip(dataset_dir: Path, tmp_path: Path) -> None:
    from swpc_hw.files.dataset import save_dataset

    ds = load_dataset(dataset_dir)
    save_dataset(tmp_path / "copy", ds)
    again = load_dataset(tmp_path / "copy")
    np.testing.assert_allclose(again.poses, ds.poses, atol=1e-9)
    assert again.segments == ds.segments
    for mid in ds.robot.ids:
        np.testing.assert_allclose(again.encoders[mid], ds.encoders[mid], atol=1e-9)


def test_the_paper_method_table_has_no_nan_and_one_turn_angles() -> None:
    from swpc_hw.calibration.mocap.solver import CalibrationResult, SegmentQuality
    from swpc_hw.calibration.report import format_table

    seg = SegmentQuality(0, 1, math.radians(405.0), 100, 0, math.nan, (0.0, 0.0), math.nan)
    res = CalibrationResult(
        params=PAPER_NOMINAL, nominal=PAPER_NOMINAL, segments=[seg], time_offset=0.0,
        time_offset_std=None, time_offset_mode="given", poses_used=100, poses_rejected=0,
        increments_used=0, increments_rejected=0, reduced_chi2=math.nan, method="paper",
    )  # fmt: skip
    text = format_table(res)
    assert "nan" not in text.lower() and "at   45.00 deg" in text, text
