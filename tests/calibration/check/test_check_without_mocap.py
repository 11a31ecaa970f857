"""A check without motion capture (swpc_hw.calibration.check.shape, imu_solver's
solve_imu_check): the robot's shape against the file's, docs/check.md."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from simulators.offline.datagen import ExperimentOptions
from simulators.offline.datagen_imu import ReferenceOptions, generate_imu_experiment
from swpc_hw.calibration.check.dataset_check import check_dataset
from swpc_hw.calibration.check.shape import compare_shape, gauge_directions, relative_map
from swpc_hw.calibration.check.verdict import CONSISTENT, DRIFTED, thresholds
from swpc_hw.errors import CalibrationError
from swpc_hw.files.dataset import Dataset
from swpc_hw.robot.frames import transform_parameters
from swpc_hw.robot.model import PARAM_NAMES, RobotParams
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED, PAPER_NOMINAL

IDS = [1, 2, 3, 4]
SD = np.array([1e-4, 1e-4, 2e-4, 5e-5, 2e-5])  # x_s, y_s, beta, b, r


def file_values(p: RobotParams = PAPER_CALIBRATED) -> np.ndarray:
    return np.array([[getattr(m, k) for k in PARAM_NAMES] for m in p.modules])


def cov(sd: np.ndarray = SD, n: int = 4) -> np.ndarray:
    return np.diag(np.tile(sd**2, n))


def test_the_five_unseen_directions_change_no_statistic() -> None:
    """Moved, turned, scaled (layout and radii), exactly (not only to first order): every
    module's change relative to the others is zero to the linearisation's error."""
    X = file_values()
    moved = transform_parameters(X, math.radians(2.0), [0.03, -0.02])
    moved[:, [0, 1, 3]] *= 1.002  # the layout's length scale (P_s and b)
    moved[:, 4] *= 0.997  # the radii's common scale
    v = compare_shape(moved, cov(), X, cov(), IDS)
    assert v.verdict == CONSISTENT
    assert max(m.chi2 for m in v.modules) < 0.1  # second-order terms of 2 deg and 0.3 %
    G = gauge_directions(X)
    for k in range(4):
        L = relative_map(G, np.ones(20), k, [a for a in range(4) if a != k])
        np.testing.assert_allclose(L @ G, 0.0, atol=1e-12)


def test_one_changed_module_is_named_alone_and_the_others_stay_clean() -> None:
    """A module swapped (its axis 2 mm away, b +1 mm) in a robot also moved and turned:
    the anchors drop it, so the other modules are judged against unchanged ones only
    (the check is fitted to the file: the frames differ little)."""
    X = file_values()
    robot = X.copy()
    robot[1, :2] += [1.4e-3, -1.4e-3]
    robot[1, 3] += 1e-3
    seen = transform_parameters(robot, math.radians(-0.1), [1e-3, 0.0])
    v = compare_shape(seen, cov(), X, cov(), IDS)
    assert v.verdict == DRIFTED and v.drifted == [2] and v.action == "recalibrate module 2"
    _, q, _ = thresholds(0.05, 4)
    assert all(m.chi2 < 0.01 * q for m in v.modules if m.id != 2), v.modules
    assert set(v.modules[1].parameters) == {"x_s", "y_s", "b"}
    row = {c.param: c.change for c in v.changes if c.module == 2}
    assert row["b"] == pytest.approx(1e-3, abs=1e-5)
    assert "shape" in v.notes[0]


def test_every_wheel_worn_alike_is_not_seen_and_two_modules_judge_each_other() -> None:
    X = file_values()
    worn = X.copy()
    worn[:, 4] -= 0.3e-3  # every wheel 0.3 mm smaller: the radii's common scale, almost
    v = compare_shape(worn, cov(), X, cov(), IDS)
    assert v.verdict == CONSISTENT  # what a check with the gyro cannot see (its note says)
    two = X[:2].copy()
    two[0, 4] -= 0.3e-3
    v = compare_shape(two, cov(n=2), X[:2], cov(n=2), [1, 2])
    assert v.drifted in ([1], [2], [1, 2]) and v.verdict == DRIFTED
    with pytest.raises(CalibrationError, match="two modules"):
        compare_shape(X[:1], cov(n=1), X[:1], cov(n=1), [1])
    with pytest.raises(CalibrationError, match="covariance is unknown"):
        compare_shape(X, np.full((20, 20), np.nan), X, cov(), IDS)


def test_unchanged_robots_raise_false_alarms_at_most_at_the_rate_asked() -> None:
    """Gaussian estimates with the stated covariances, 2000 robots: the sequential test
    keeps the robot's rate near Sidak's 5 % (it tests the largest statistic first).

    Its rate is 4.95 % (20 000 robots).  The bound, 5 % + 3 binomial std devs (6.46 %),
    fails a rate of 5 % with probability 0.18 % (over seeds; this seed passes) and catches
    one of 8 % with probability 99.5 %; the floor of 1 % catches a test that (almost)
    never fires (0.5 %) with probability 99.7 %: the trials that power needs."""
    rng = np.random.default_rng(3)
    X = file_values()
    C = cov()
    alarms = 0
    trials = 2000
    for _ in range(trials):
        noisy = X + rng.normal(size=(4, 5)) * SD * math.sqrt(2.0)
        alarms += compare_shape(noisy, C, X, C, IDS).verdict != CONSISTENT
    rate = alarms / trials
    assert rate <= 0.05 + 3 * math.sqrt(0.05 * 0.95 / trials), rate
    assert rate >= 0.01, rate  # not a test that never fires


CHECK = ExperimentOptions(
    angles=(math.radians(45.0),), spin_duration=math.radians(60.0) / 0.5, rest_time=1.0,
    counts_per_rev=2**17,
)  # fmt: skip
NO_REFERENCES = ReferenceOptions(axis_pairs=(), straight_drive=False)


def imu_check(truth: RobotParams, seed: int) -> Dataset:
    """The check's dataset as the robot records it: no poses."""
    opts = dataclasses.replace(CHECK, seed=seed)
    ds = generate_imu_experiment(truth, opts, references=NO_REFERENCES,
                                 nominal=PAPER_NOMINAL).experiment.dataset  # fmt: skip
    return dataclasses.replace(ds, poses=np.zeros((0, 4)))


def test_a_gyro_check_finds_a_re_homed_axis_against_a_file_in_any_frame() -> None:
    """Offline, the datagen's gyro and encoders (one spin about each module at 45 deg,
    60 deg sweeps, 1 s rests, no references): the file in force in design-fit (turned and
    shifted from R) with no uncertainty; module 4 re-homed by +0.3 deg."""
    rep = [0.05e-3, 0.05e-3, math.radians(0.02), 0.05e-3, 0.02e-3]
    file = PAPER_CALIBRATED.model_copy(update={"frame": "design-fit"})
    X = transform_parameters(file_values(), math.radians(5.0), [0.1, -0.05])
    file = RobotParams.from_arrays(IDS, X[:, :2], X[:, 2], X[:, 3], X[:, 4], frame="design-fit")
    res, same = check_dataset(imu_check(PAPER_CALIBRATED, 11), file, None, repeatability=rep)
    assert same.verdict == CONSISTENT, same.summary
    assert res.params.frame == "file-fit" and res.mode == "imu"
    m4 = PAPER_CALIBRATED.module(4)
    rehomed = PAPER_CALIBRATED.model_copy(update={"modules": [
        m.model_copy(update={"beta": m4.beta + math.radians(0.3)}) if m.id == 4 else m
        for m in PAPER_CALIBRATED.modules
    ]})  # fmt: skip
    _, out = check_dataset(imu_check(rehomed, 12), file, None, repeatability=rep)
    assert out.drifted == [4] and out.modules[3].parameters == ["beta"], out.summary
    row = next(c for c in out.changes if c.module == 4 and c.param == "beta")
    assert math.degrees(row.change) == pytest.approx(0.3, abs=0.03)


def test_a_gyro_check_of_a_file_from_a_calibration_without_motion_capture() -> None:
    """The file from the IMU calibration (design-fit, its covariance singular along the
    frame's three rigid directions): each module's relative change has a determined
    covariance all the same; unchanged consistent, a worn wheel named alone."""
    from swpc_hw.calibration.gyro.solver import solve_imu

    exp = generate_imu_experiment(PAPER_CALIBRATED, nominal=PAPER_NOMINAL)
    cal = solve_imu(dataclasses.replace(exp.experiment.dataset, poses=np.zeros((0, 4))))
    assert cal.params.frame == "design-fit" and cal.covariance is not None
    rep = [0.05e-3, 0.05e-3, math.radians(0.02), 0.05e-3, 0.02e-3]
    _, same = check_dataset(imu_check(PAPER_CALIBRATED, 31), cal.params, cal.covariance,
                            repeatability=rep)  # fmt: skip
    assert same.verdict == CONSISTENT, same.summary
    worn = PAPER_CALIBRATED.model_copy(update={"modules": [
        m.model_copy(update={"r": m.r - 0.3e-3}) if m.id == 3 else m
        for m in PAPER_CALIBRATED.modules
    ]})  # fmt: skip
    _, out = check_dataset(imu_check(worn, 31), cal.params, cal.covariance, repeatability=rep)
    assert out.drifted == [3] and out.modules[2].parameters == ["r"], out.summary
