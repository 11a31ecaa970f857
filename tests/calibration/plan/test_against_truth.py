"""A result against a known truth (:func:`swpc_hw.calibration.plan.square_error.against_truth`):
the figures a simulator's run is judged by, and by which the covariance is judged honest."""

from __future__ import annotations

import math

import numpy as np
import pytest

from swpc_hw.calibration.plan.square_error import (
    against_truth,
    square_path_error,
    square_path_sd,
    square_path_sensitivity,
)
from swpc_hw.robot.model import PARAM_NAMES, RobotParams
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED, PAPER_NOMINAL

TRUTH = PAPER_CALIBRATED
N = 5 * len(TRUTH.modules)


def moved(p: RobotParams, e: np.ndarray) -> RobotParams:
    """``p`` with every parameter moved by ``e`` (N, 5)."""
    a = np.array([[getattr(m, k) for k in PARAM_NAMES] for m in p.modules]) + e
    return RobotParams.from_arrays(p.ids, a[:, :2], a[:, 2], a[:, 3], a[:, 4])


def test_the_figures_are_those_of_the_error_and_the_covariance() -> None:
    sd = np.tile([10e-6, 12e-6, math.radians(0.002), 8e-6, 2e-6], len(TRUTH.modules))
    C = np.diag(sd**2)
    e = np.zeros((4, 5))
    e[1, 0], e[2, 2], e[3, 4] = 30e-6, math.radians(-0.004), 4e-6  # 3, -2 and 2 sd
    got = against_truth(moved(TRUTH, e), C, TRUTH, PAPER_NOMINAL)
    assert got.dof == N and got.nees == pytest.approx((9 + 4 + 4) / N, rel=1e-9)
    assert got.largest == pytest.approx(
        {"position": 30e-6, "beta": math.radians(0.004), "radius": 4e-6}, rel=1e-6
    )
    assert got.rms_z["radius"] == pytest.approx(2 / math.sqrt(4), rel=1e-6)
    assert got.rms_z["position"] == pytest.approx(3 / math.sqrt(12), rel=1e-6)
    S = square_path_sensitivity(PAPER_NOMINAL)
    assert got.square == pytest.approx(square_path_error(S, e.ravel()), rel=1e-6)
    assert got.square_forecast == square_path_sd(S, C)
    assert got.square[0] > 0 and got.square[1] > 0
    exact = against_truth(TRUTH, C, TRUTH, PAPER_NOMINAL)
    assert exact.nees == 0 and exact.square == (0.0, 0.0)


def test_errors_drawn_from_the_covariance_have_a_nees_of_one() -> None:
    """Over 400 draws ``e ~ N(0, C)`` of a full (correlated) covariance the mean NEES is 1
    within its sampling error (sd ``sqrt(2 / 20 / 400)`` = 0.016); the same errors
    against a covariance half as large: 2."""
    rng = np.random.default_rng(44)
    A = rng.normal(size=(N, N)) * 1e-5
    C = A @ A.T + np.eye(N) * 1e-12
    draws = rng.multivariate_normal(np.zeros(N), C, size=400)
    S = square_path_sensitivity(PAPER_NOMINAL)

    def nees(d: np.ndarray, C: np.ndarray) -> float:
        return against_truth(moved(TRUTH, d.reshape(4, 5)), C, TRUTH, PAPER_NOMINAL, S).nees

    assert abs(float(np.mean([nees(d, C) for d in draws])) - 1.0) < 0.06
    half = [nees(d, C / 2) for d in draws[:100]]
    assert 1.7 < float(np.mean(half)) < 2.3


def test_a_gauge_the_covariance_lacks_leaves_its_rank() -> None:
    """A design-fit covariance has three directions it does not hold (the frame's): NEES
    is over the 17 it does."""
    rng = np.random.default_rng(3)
    A = rng.normal(size=(N, N - 3)) * 1e-5
    C = A @ A.T
    e = (A @ rng.normal(size=N - 3)).reshape(4, 5)
    got = against_truth(moved(TRUTH, e), C, TRUTH, PAPER_NOMINAL)
    assert got.dof == N - 3 and 0 < got.nees < 10


def test_other_modules_or_a_wrong_covariance_are_refused() -> None:
    three = RobotParams(robot=TRUTH.robot, frame=TRUTH.frame, modules=TRUTH.modules[:3])
    with pytest.raises(ValueError, match="modules"):
        against_truth(three, np.eye(15), TRUTH, PAPER_NOMINAL)
    with pytest.raises(ValueError, match=r"covariance \(15, 15\)"):
        against_truth(TRUTH, np.eye(15), TRUTH, PAPER_NOMINAL)
