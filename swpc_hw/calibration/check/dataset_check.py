"""A check's dataset solved from the file in force and judged: with motion capture by the
test of :mod:`swpc_hw.calibration.check.verdict`, without by the shape of
:mod:`swpc_hw.calibration.check.shape`.  What ``swpc check --offline`` and a check run both
do."""

from __future__ import annotations

from typing import Any

from swpc_hw.calibration.check.shape import compare_shape
from swpc_hw.calibration.check.verdict import (
    CheckVerdict,
    check_estimates,
    file_notes,
    in_order,
    stated_covariance,
)
from swpc_hw.calibration.gyro.solver import solve_imu_check
from swpc_hw.calibration.mocap.solver import SolverOptions, solve
from swpc_hw.errors import CalibrationError
from swpc_hw.robot.model import RobotParams


def check_dataset(
    ds: Any,
    file: RobotParams,
    file_covariance: Any,
    *,
    false_alarm: float = 0.05,
    whole_robot: float = 0.5,
    repeatability: Any = None,
    source: str = "dataset",
) -> tuple[Any, CheckVerdict]:
    """Solve a check's dataset from the file's parameters and judge it:
    ``(CalibrationResult, CheckVerdict)``.  What ``swpc check --offline`` and a check run
    both do.  With motion capture (``poses.csv``) the file must be in the dataset's frame
    (R); without (``imu.csv``), :func:`check_dataset_imu`."""
    test: dict[str, Any] = dict(
        false_alarm=false_alarm, whole_robot=whole_robot, repeatability=repeatability
    )
    if not ds.has_poses:
        return check_dataset_imu(ds, file, file_covariance, source, test)
    if file.frame != ds.robot.frame:
        raise CalibrationError(
            f"the file is in frame {file.frame!r}, the check measures in {ds.robot.frame!r} "
            "(the motion capture's rigid body): they cannot be compared; calibrate with "
            "motion capture first, or check without motion capture (metrology imu)"
        )
    X, _ = in_order(file, None, ds.robot.ids)
    start = RobotParams.from_matrix(ds.robot.ids, X, robot=ds.robot.robot, frame=ds.robot.frame)
    result = solve(ds, SolverOptions(time_offset=0.0), source=source, start=start)
    return result, check_estimates(result.params, result.covariance, file, file_covariance, **test)


def check_dataset_imu(
    ds: Any, file: RobotParams, file_covariance: Any, source: str, test: dict[str, Any]
) -> tuple[Any, CheckVerdict]:
    """A check without motion capture (the gyro and the encoders, no references): the
    dataset solved fitted to the file (:func:`~swpc_hw.calibration.gyro.solver.solve_imu_check`,
    frame ``file-fit``) and judged on the robot's shape
    (:func:`~swpc_hw.calibration.check.shape.compare_shape` with the keywords ``test``).
    The file may be in any frame: the comparison does not depend on it."""
    if ds.imu is None:
        raise CalibrationError(
            f"{source}: neither poses.csv nor imu.csv: a check measures with motion capture "
            "or the gyro"
        )
    ids = ds.robot.ids
    X, _ = in_order(file, None, ids)
    result = solve_imu_check(ds, X, source=source)
    if result.covariance is None:
        raise CalibrationError(f"{source}: the check's data do not determine its covariance")
    X_check, _ = in_order(result.params, None, ids)
    C_file = stated_covariance(file, file_covariance, ids)
    verdict = compare_shape(X_check, result.covariance, X, C_file, ids, **test)
    verdict.notes += file_notes(file, file_covariance, ids)
    return result, verdict
