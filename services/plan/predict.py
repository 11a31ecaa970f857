"""The planner's prediction: a candidate protocol's std devs before the robot moves.

:func:`predicted_stddevs` plays the candidate on the robot the planner knows (the robot
config's nominal robot: the truth is unknown before calibrating) with the metrology's
noise (:class:`~swpc_hw.calibration.plan.plan.MocapNoise`), through the offline generator
(:mod:`simulators.datagen`), and solves it with the joint solver.  The solver's
covariance is ``H^-1 M H^-1`` with ``H = J^T J`` of its weighted residuals: the inverse
Fisher information of the design, the correlation of the noise included
(docs/solver-uncertainty.md).  Its std devs do not depend on the noise draw beyond the
estimate of the noise's size, so a few seeds' variances are averaged (``seeds``).

The solver runs with :data:`PREDICTION_OPTIONS`: its defaults without the test for slow
slip drifts.  The candidate's data carry no slip (the generator's defaults), and on the
default plan's candidates the test finds none: the covariance is the same bit for bit
(a test), at seven eighths of the CPU.  The test for slip bursts stays: on clean data
it finds a few false bursts, and the covariance depends on them by a few percent.

Without motion capture (``metrology: imu``, :func:`predicted_imu_covariance`) the
candidate's run with its rests and straight drive, the gyro and the tape's readings
(:mod:`simulators.offline.datagen_imu`), and the IMU solver's covariance in the ``design-fit``
frame.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from collections.abc import Sequence

import numpy as np

from simulators.offline.datagen import ExperimentOptions, generate_experiment
from simulators.offline.datagen_imu import IMU_PROTOCOL, ReferenceOptions, fisher_setup
from swpc_hw.calibration.gyro.covariance import imu_covariance
from swpc_hw.calibration.mocap.solver import JointSolution, solve_joint
from swpc_hw.calibration.options import SolverOptions
from swpc_hw.calibration.parameters import N_PARAMS
from swpc_hw.calibration.plan.forecast import SpinInformation, spin_information
from swpc_hw.calibration.plan.plan import Candidate, FloatArray, MocapNoise, PlanError, TimeModel
from swpc_hw.errors import CalibrationError
from swpc_hw.robot.model import RobotParams
from swpc_hw.sensors.gyro import GyroOptions

PREDICTION_OPTIONS = SolverOptions(drift_sigmas=math.inf)
"""The joint solver's options for a prediction (module docstring): no drift test."""


def spins_of(base: ExperimentOptions, c: Candidate, tm: TimeModel) -> ExperimentOptions:
    """``base`` spinning as candidate ``c``: its angles, a window of its sweep at the time
    model's yaw rate at its spin torque, its settle and align times."""
    return dataclasses.replace(
        base,
        angles=tuple(math.radians(a) for a in c.angles_deg),
        yaw_rate=tm.yaw_rate(c.spin_torque),
        spin_duration=tm.window(c),
        settle_time=c.settle_time,
        align_time=c.align_time,
    )


def experiment_options(
    c: Candidate, noise: MocapNoise, tm: TimeModel, seed: int = 0
) -> ExperimentOptions:
    """The offline experiment of candidate ``c``: its angles, a window of ``sweep`` at the
    time model's yaw rate at its spin torque, its settle and align times, the metrology's
    noise."""
    return dataclasses.replace(
        spins_of(ExperimentOptions(), c, tm),
        pose_rate=noise.rate,
        pose_sigma_xy=noise.sigma_xy,
        pose_sigma_yaw=noise.sigma_yaw,
        pose_noise_rho=noise.rho,
        seed=seed,
    )


def predicted_solution(
    robot: RobotParams, c: Candidate, noise: MocapNoise, tm: TimeModel, seed: int = 0
) -> JointSolution:
    """The joint solver's solve of a simulated run of candidate ``c`` on ``robot`` with
    the noise draw ``seed`` (module docstring).  A candidate the generator or the solver
    refuses on this robot: :class:`PlanError` with the reason."""
    try:
        ds = generate_experiment(robot, experiment_options(c, noise, tm, seed), robot).dataset
        return solve_joint(ds, PREDICTION_OPTIONS)
    except (ValueError, CalibrationError) as exc:  # casters never settle, data refused
        raise PlanError(f"{c.label()}: no prediction: {exc}") from exc


def mean_covariance(c: Candidate, solutions: Sequence[JointSolution]) -> FloatArray:
    """(5N, 5N) the mean of the ``solutions``' covariances (of candidate ``c``'s runs);
    :class:`PlanError` when a solve gives none."""
    covs = []
    for sol in solutions:
        if sol.result.covariance is None:
            raise PlanError(f"{c.label()}: the solver gives no covariance")
        covs.append(sol.result.covariance)
    return np.asarray(np.mean(covs, axis=0), dtype=float)


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
    return mean_covariance(c, [predicted_solution(robot, c, noise, tm, s) for s in seeds])


def spins_of_solution(c: Candidate, solution: JointSolution) -> list[SpinInformation]:
    """Every spin's share of the information of candidate ``c`` from a solve of a
    simulated run of it (:func:`predicted_solution`), in the run's order
    (:func:`swpc_hw.calibration.plan.forecast.spin_information`)."""
    return spin_information(solution, math.radians(c.sweep_deg))


def predicted_spins(
    robot: RobotParams, c: Candidate, noise: MocapNoise, tm: TimeModel, seed: int = 0
) -> list[SpinInformation]:
    """Every spin's share of the information of candidate ``c`` on ``robot``, in the run's
    order (:func:`swpc_hw.calibration.plan.forecast.spin_information`): what sequential
    stopping forecasts the spins to come with.  The solve of seed 0 is that of
    :func:`predicted_covariance`'s first seed (the planner keeps it for the plan's
    candidate, :mod:`services.plan.planner`).  :class:`PlanError` as
    :func:`predicted_covariance`."""
    return spins_of_solution(c, predicted_solution(robot, c, noise, tm, seed))


# ------------------------------------------------------------------ without motion capture


TAPE_READINGS = 2
"""Tape readings per pair of steering axes the prediction assumes (docs/imu-operation.md)."""


def imu_experiment_options(c: Candidate, tm: TimeModel) -> ExperimentOptions:
    """The offline experiment of candidate ``c`` without motion capture: as
    :func:`experiment_options` (no poses needed), with its rests (``rest_time``) and its
    straight drive (``drive_length`` at the time model's ``drive_speed``)."""
    if c.rest_time is None or c.drive_length is None:
        raise PlanError(f"{c.label()}: a candidate without motion capture has a rest and a drive")
    return dataclasses.replace(
        spins_of(IMU_PROTOCOL, c, tm),
        rest_time=c.rest_time,
        drive_length=c.drive_length,
        drive_speed=tm.drive_speed,
    )


def tape_readings(ids: Sequence[int], readings: int = TAPE_READINGS) -> ReferenceOptions:
    """The tape's references of a run: ``readings`` per pair of modules (the operator's
    procedure, docs/imu-operation.md: every pair read twice), the straight drive, 0.5 mm."""
    pairs = tuple(p for p in itertools.combinations(ids, 2) for _ in range(readings))
    return ReferenceOptions(axis_pairs=pairs)


def predicted_imu_covariance(
    robot: RobotParams,
    c: Candidate,
    gyro: GyroOptions,
    tm: TimeModel,
    references: ReferenceOptions | None = None,
) -> FloatArray:
    """(5N, 5N) covariance of candidate ``c`` without motion capture on ``robot`` (modules
    in its order), in the ``design-fit`` frame the run's result reports: the IMU
    solver's covariance (:func:`swpc_hw.calibration.gyro.covariance.imu_covariance`) at the
    truth of the candidate's noiseless run (:func:`simulators.datagen_imu.fisher_setup`:
    the gyro's white noise and walk, the encoders' quantization and the tape's std dev as
    weights).  A solve of a noisy run gives the same std devs within 0.5 %
    (docs/plan.md) at three times the CPU, and needs no seed.  :class:`PlanError` as
    :func:`predicted_covariance`."""
    refs = references or tape_readings(robot.ids)
    n = N_PARAMS * len(robot.ids)
    try:
        run, x = fisher_setup(robot, imu_experiment_options(c, tm), gyro, refs, robot)
        cov = imu_covariance(run.problem, x)[0]
    except (ValueError, CalibrationError) as exc:
        raise PlanError(f"{c.label()}: no prediction: {exc}") from exc
    return np.asarray(cov[:n, :n], dtype=float)
