"""The joint problem's analytic Jacobian (swpc_hw/calibration/problem.py) against scipy's
own finite differences, on a noisy run with slip cut out and on a three-module robot."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import approx_fprime

from simulators.offline.datagen import ExperimentOptions, generate_experiment
from swpc_hw.calibration.mocap.solver import solve_joint
from swpc_hw.robot.model import RobotParams
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED

NOISY = ExperimentOptions(
    spin_duration=4.0, pose_sigma_xy=0.5e-3, pose_sigma_yaw=0.002, slip_burst_rate=0.05, seed=3
)


@pytest.mark.parametrize("modules", [4, 3])
def test_the_analytic_jacobian_is_scipys_finite_differences(modules: int) -> None:
    truth = RobotParams(modules=PAPER_CALIBRATED.modules[:modules])
    sol = solve_joint(generate_experiment(truth, NOISY).dataset)
    prob = sol.problem
    assert prob.block_sizes()[1] > 0 and prob.block_sizes()[2] > 100  # every block is there
    rng = np.random.default_rng(0)
    # at the solution and away from it (beta and b moved by mrad and mm)
    for x in (sol.x, sol.x + 2e-3 * rng.standard_normal(sol.x.size)):
        analytic = prob.jacobian(x)
        numeric = approx_fprime(x, prob.residuals, 1e-7)
        assert analytic.shape == numeric.shape == (sum(prob.block_sizes()), 5 * modules)
        scale = np.abs(numeric).max(axis=0)
        assert np.all(scale > 0)  # every parameter moves some residual
        # forward differences of step 1e-7: their own error is ~1e-7 of the scale
        assert np.max(np.abs(analytic - numeric) / scale) < 1e-5
