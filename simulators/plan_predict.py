"""The planner's prediction: a candidate protocol's std devs before the robot moves.

:func:`predicted_stddevs` plays the candidate on the robot the planner knows (the robot
config's nominal robot: the truth is unknown before calibrating) with the metrology's
noise (:class:`~swpc_hw.calibration.plan.MocapNoise`), through the offline generator
(:mod:`simulators.datagen`), and solves it with the joint solver.  The solver's
covariance is ``H^-1 M H^-1`` with ``H = J^T J`` of its weighted residuals: the inverse
Fisher information of the design, the correlation of the noise included
(docs/solver-uncertainty.md).  Its std devs do not depend on the noise draw beyond the
estimate of the noise's size, so a few seeds' variances are averaged (``seeds``).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np

from simulators.datagen import ExperimentOptions, generate_experiment
from swpc_hw.calibration.forecast import SpinInformation, spin_information
from swpc_hw.calibration.plan import Candidate, FloatArray, MocapNoise, PlanError, TimeModel
from swpc_hw.calibration.solver import solve, solve_joint
from swpc_hw.errors import CalibrationError
from swpc_hw.model import RobotParams


def experiment_options(
    c: Candidate, noise: MocapNoise, tm: TimeModel, seed: int = 0
) -> ExperimentOptions:
    """The offline experiment of candidate ``c``: its angles, a window of ``sweep`` at the
    time model's yaw rate at its spin torque, its settle and align times, the metrology's
    noise."""
    return dataclasses.replace(
        ExperimentOptions(),
        angles=tuple(math.radians(a) for a in c.angles_deg),
        yaw_rate=tm.yaw_rate(c.spin_torque),
        spin_duration=tm.window(c),
        settle_time=c.settle_time,
        align_time=c.align_time,
        pose_rate=noise.rate,
        pose_sigma_xy=noise.sigma_xy,
        pose_sigma_yaw=noise.sigma_yaw,
        pose_noise_rho=noise.rho,
        seed=seed,
    )


def predicted_covariance(
    robot: RobotParams,
    c: Candidate,
    noise: MocapNoise,
    tm: TimeModel,
    seeds: Sequence[int] = (0, 1),
) -> FloatArray:
    """(5N, 5N) covariance of candidate ``c`` on ``robot`` (modules in its order): the
    mean over ``seeds`` of the solver's covariances (module docstring).  A candidate the
    generator or the solver refuses on this robot: :class:`PlanError` with the reason."""
    covs = []
    for s in seeds:
        try:
            ds = generate_experiment(robot, experiment_options(c, noise, tm, s), robot).dataset
            cov = solve(ds).covariance
        except (ValueError, CalibrationError) as exc:  # casters never settle, data refused
            raise PlanError(f"{c.label()}: no prediction: {exc}") from exc
        if cov is None:
            raise PlanError(f"{c.label()}: the solver gives no covariance")
        covs.append(cov)
    return np.asarray(np.mean(covs, axis=0), dtype=float)


def predicted_spins(
    robot: RobotParams, c: Candidate, noise: MocapNoise, tm: TimeModel, seed: int = 0
) -> list[SpinInformation]:
    """Every spin's share of the information of candidate ``c`` on ``robot``, in the run's
    order (:func:`swpc_hw.calibration.forecast.spin_information`): what sequential
    stopping forecasts the spins to come with.  :class:`PlanError` as
    :func:`predicted_covariance`."""
    try:
        ds = generate_experiment(robot, experiment_options(c, noise, tm, seed), robot).dataset
        solution = solve_joint(ds)
    except (ValueError, CalibrationError) as exc:
        raise PlanError(f"{c.label()}: no prediction: {exc}") from exc
    return spin_information(solution, math.radians(c.sweep_deg))
