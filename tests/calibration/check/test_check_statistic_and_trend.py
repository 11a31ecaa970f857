"""A check's test statistic and a parameter's trend (swpc_hw.calibration.check.verdict, .trend),
and a check solved offline from the file in force (docs/check.md)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from simulators.offline.datagen import ExperimentOptions, generate_experiment
from swpc_hw.calibration.check.dataset_check import check_dataset
from swpc_hw.calibration.check.trend import linear_trend
from swpc_hw.calibration.check.verdict import (
    CONSISTENT,
    DRIFTED,
    WHOLE_ROBOT,
    check_estimates,
    compare,
    sidak,
    stated_covariance,
    thresholds,
)
from swpc_hw.errors import CalibrationError
from swpc_hw.robot.model import PARAM_NAMES, ModuleStddev
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED, PAPER_NOMINAL

IDS = [1, 2, 3, 4]
SD = np.array([1e-4, 1e-4, 2e-4, 5e-5, 2e-5])  # x_s, y_s, beta, b, r


def diag(n: int = 4, sd: np.ndarray = SD) -> np.ndarray:
    return np.diag(np.tile(sd**2, n))


def file_values() -> np.ndarray:
    return np.array([[getattr(m, k) for k in PARAM_NAMES] for m in PAPER_CALIBRATED.modules])


def test_sidak_gives_the_robot_its_false_alarm_rate() -> None:
    a = sidak(0.05, 4)
    assert 1 - (1 - a) ** 4 == pytest.approx(0.05)
    alpha_m, q, z = thresholds(0.05, 4)
    assert alpha_m == pytest.approx(a)
    from scipy.stats import chi2, norm

    assert chi2.sf(q, 5) == pytest.approx(a) and 2 * norm.sf(z) * 5 == pytest.approx(a)


def test_an_unchanged_robot_raises_a_false_alarm_at_the_rate_asked() -> None:
    """Monte Carlo of the statistic itself: Gaussian estimates with the stated covariances
    (a correlated one for the check), 4000 robots; Sidak over 4 modules keeps 5 %.

    The band, 5 % +- 3 binomial std devs (3.97-6.03 %), fails a statistic whose rate is
    5 % with probability 0.26 % (over seeds; this seed passes), and one whose rate is 7 %
    or 3 % with probability 99 % (C_file left out of the change's covariance: 8.3 %):
    the trials that power needs (1000 would catch 7 % one time in two)."""
    rng = np.random.default_rng(7)
    X = file_values()
    A = rng.normal(size=(20, 20)) * 0.3 + np.eye(20)
    S = np.diag(np.tile(SD, 4))
    C_check = S @ (A @ A.T / 20 + np.eye(20) * 0.5) @ S
    C_file = diag(sd=SD / 4)
    L = np.linalg.cholesky(C_check + C_file)
    alarms = 0
    trials = 4000
    for _ in range(trials):
        noisy = X + (L @ rng.normal(size=20)).reshape(4, 5)
        alarms += compare(noisy, C_check, X, C_file, IDS).verdict != CONSISTENT
    rate = alarms / trials
    assert abs(rate - 0.05) < 3 * math.sqrt(0.05 * 0.95 / trials), rate


def test_a_worn_wheel_is_named_with_its_parameter() -> None:
    X = file_values()
    chk = X.copy()
    chk[1, 4] -= 0.3e-3  # module 2's r, 15 std devs of the change
    out = compare(chk, diag(), X, diag(), IDS)
    assert out.verdict == DRIFTED and out.drifted == [2]
    assert out.action == "recalibrate module 2"
    m2 = out.modules[1]
    assert m2.drifted and m2.parameters == ["r"] and m2.chi2 > out.threshold
    row = next(c for c in out.changes if c.module == 2 and c.param == "r")
    assert row.drifted and row.change == pytest.approx(-0.3e-3)
    assert row.z == pytest.approx(-0.3e-3 / math.sqrt(2 * SD[4] ** 2))
    assert "module 2 r -0.300 mm" in out.summary
    doc = out.document()
    assert doc["drifted_modules"] == [2] and len(doc["table"]) == 20
    assert next(r for r in doc["table"] if r["module"] == 2 and r["param"] == "r")["unit"] == "mm"


def test_half_the_modules_drifted_is_the_whole_robot_and_beta_wraps() -> None:
    X = file_values()
    chk = X.copy()
    chk[0, 2] += math.radians(0.3)
    chk[2, 0] += 2e-3
    out = compare(chk, diag(), X, diag(), IDS)
    assert out.drifted == [1, 3] and out.action == WHOLE_ROBOT
    # one module alone: that module; with whole_robot 0.25 the whole robot again
    chk[2, 0] -= 2e-3
    assert compare(chk, diag(), X, diag(), IDS).action == "recalibrate module 1"
    assert compare(chk, diag(), X, diag(), IDS, whole_robot=0.25).action == WHOLE_ROBOT
    # beta across +-pi: a change of 0.1 mrad, not of 2 pi
    Xw, Cw = X.copy(), X.copy()
    Xw[:, 2], Cw[:, 2] = math.pi - 0.5e-4, -math.pi + 0.5e-4
    assert compare(Cw, diag(), Xw, diag(), IDS).verdict == CONSISTENT


def test_repeatability_widens_the_change_and_unknown_covariance_refuses() -> None:
    X = file_values()
    chk = X.copy()
    chk[3, 4] += 0.15e-3  # 5.3 combined std devs of the bare change: flagged
    assert compare(chk, diag(), X, diag(), IDS).drifted == [4]
    rep = [0, 0, 0, 0, 0.05e-3]
    assert compare(chk, diag(), X, diag(), IDS, repeatability=rep).verdict == CONSISTENT
    bad = diag()
    bad[0, 0] = math.nan
    with pytest.raises(CalibrationError, match="do not determine every parameter"):
        compare(chk, bad, X, diag(), IDS)


def test_the_file_is_judged_in_its_own_frame_and_order() -> None:
    # the file lists its modules in another order; its covariance follows them
    rev = PAPER_CALIBRATED.model_copy(update={"modules": PAPER_CALIBRATED.modules[::-1]})
    C = np.diag(np.arange(1, 21, dtype=float)) * 1e-10
    C_in_order = stated_covariance(rev, C, IDS)
    assert C_in_order[0, 0] == pytest.approx(16e-10) and C_in_order[19, 19] == pytest.approx(5e-10)
    out = check_estimates(PAPER_CALIBRATED, diag(), rev, C)
    assert out.verdict == CONSISTENT and out.notes == []
    # no covariance: its std devs, else exact, and said so
    sd = ModuleStddev(**dict(zip(PARAM_NAMES, SD, strict=True)))
    with_sd = rev.model_copy(update={"modules": [m.model_copy(update={"stddev": sd})
                                                 for m in rev.modules]})  # fmt: skip
    assert np.allclose(np.diag(stated_covariance(with_sd, None, IDS)), np.tile(SD**2, 4))
    assert "uncorrelated" in check_estimates(PAPER_CALIBRATED, diag(), with_sd, None).notes[0]
    assert "exact" in check_estimates(PAPER_CALIBRATED, diag(), rev, None).notes[0]
    other = PAPER_CALIBRATED.model_copy(update={"frame": "design-fit"})
    with pytest.raises(CalibrationError, match="two frames"):
        check_estimates(PAPER_CALIBRATED, diag(), other, None)


def test_trend_recovers_a_line_and_the_day_it_leaves_its_tolerance() -> None:
    day = 86400.0
    t = np.arange(6) * 7 * day
    y = 55.0 - 0.01 * t / (7 * day)  # mm: 0.01 mm a week
    tr = linear_trend(t, y, np.full(6, 0.002), reference=55.0, tolerance=0.2, now=t[-1])
    assert tr is not None and tr.significant and not tr.outside
    assert tr.slope * 7 * day == pytest.approx(-0.01)
    assert tr.leaves_at == pytest.approx(20 * 7 * day)  # 0.2 mm at 0.01 mm a week
    assert tr.birge == pytest.approx(1.0)
    # a slope within its noise: not significant, no date
    flat = linear_trend(t, 55 + np.array([0.01, -0.01] * 3), np.full(6, 0.01),
                        reference=55.0, tolerance=0.2, now=t[-1])  # fmt: skip
    assert flat is not None and not flat.significant and flat.leaves_at is None
    # scatter beyond the std devs widens the slope's std dev (Birge's ratio)
    wide = linear_trend(t, y + np.array([0.05, -0.05] * 3), np.full(6, 0.002),
                        reference=55.0, tolerance=0.2, now=t[-1])  # fmt: skip
    assert wide is not None and wide.birge > 100 and wide.slope_std > 10 * tr.slope_std
    assert linear_trend([0.0], [1.0], [0.1], reference=1, tolerance=1, now=0) is None
    assert linear_trend([1.0, 1.0], [1.0, 2.0], [0.1, 0.1], reference=1, tolerance=1, now=0) is None


NOISE = ExperimentOptions(pose_sigma_xy=0.5e-3, pose_sigma_yaw=math.radians(0.05))


def test_a_check_solved_from_the_file_finds_a_worn_wheel_and_only_it() -> None:
    """Offline, the check's shape (every module locked once at 45 deg, 90 deg sweeps): the
    file in force a calibration of the truth, the robot's module 3 wheel 0.3 mm smaller."""
    from swpc_hw.calibration.mocap.solver import solve

    cal = solve(generate_experiment(PAPER_CALIBRATED, dataclasses.replace(NOISE, seed=5),
                                    PAPER_NOMINAL).dataset)  # fmt: skip
    check = dataclasses.replace(
        NOISE, angles=(math.radians(45.0),), spin_duration=math.pi / 2 / NOISE.yaw_rate, seed=6
    )
    exp = generate_experiment(PAPER_CALIBRATED, check, PAPER_NOMINAL)
    assert len(exp.dataset.segments) == 4  # one spin about each module
    rep = [0.05e-3, 0.05e-3, math.radians(0.02), 0.05e-3, 0.02e-3]
    res, same = check_dataset(exp.dataset, cal.params, cal.covariance, repeatability=rep)
    assert same.verdict == CONSISTENT, same.summary
    assert res.params.frame == "R" and np.all(np.isfinite(res.stddev_array()))
    m3 = PAPER_CALIBRATED.module(3)
    worn = PAPER_CALIBRATED.model_copy(update={"modules": [
        m.model_copy(update={"r": m3.r - 0.3e-3}) if m.id == 3 else m
        for m in PAPER_CALIBRATED.modules
    ]})  # fmt: skip
    exp = generate_experiment(worn, check, PAPER_NOMINAL)
    _, out = check_dataset(exp.dataset, cal.params, cal.covariance, repeatability=rep)
    assert out.drifted == [3] and out.modules[2].parameters == ["r"], out.summary
    row = next(c for c in out.changes if c.module == 3 and c.param == "r")
    assert row.change == pytest.approx(-0.3e-3, abs=0.05e-3)


def test_a_check_without_any_metrology_or_in_another_frame_is_refused() -> None:
    check = dataclasses.replace(NOISE, angles=(math.radians(45.0),), spin_duration=2.0)
    ds = generate_experiment(PAPER_CALIBRATED, check, PAPER_NOMINAL).dataset
    other = PAPER_CALIBRATED.model_copy(update={"frame": "design-fit"})
    with pytest.raises(CalibrationError, match="cannot be compared"):
        check_dataset(ds, other, None)
    no_poses = dataclasses.replace(ds, poses=np.zeros((0, 4)))
    with pytest.raises(CalibrationError, match=r"neither poses\.csv nor imu\.csv"):
        check_dataset(no_poses, PAPER_CALIBRATED, None)


def test_the_calibration_still_needs_two_angles_and_every_module() -> None:
    from swpc_hw.calibration.mocap.solver import solve
    from swpc_hw.errors import DatasetError

    one = dataclasses.replace(NOISE, angles=(math.radians(45.0),), spin_duration=2.0)
    ds = generate_experiment(PAPER_CALIBRATED, one, PAPER_NOMINAL).dataset
    with pytest.raises(DatasetError, match="need >= 2"):
        solve(ds)
    some = dataclasses.replace(NOISE, modules=(1, 3), spin_duration=2.0)
    ds = generate_experiment(PAPER_CALIBRATED, some, PAPER_NOMINAL).dataset
    assert [s.static_module for s in ds.segments] == [1, 1, 3, 3]
    with pytest.raises(DatasetError, match="module 2 is never locked"):
        solve(ds)
    with pytest.raises(ValueError, match="not all module ids"):
        generate_experiment(PAPER_CALIBRATED, dataclasses.replace(one, modules=(9,)))
