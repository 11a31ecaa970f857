"""Calibration of SWPC robots: closed-form geometry, the paper's baseline and the joint solver."""

from swpc_hw.calibration.mocap.solver import (
    CalibrationResult,
    SolverOptions,
    solve,
    solve_directory,
)

__all__ = ["CalibrationResult", "SolverOptions", "solve", "solve_directory"]
