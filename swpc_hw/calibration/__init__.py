"""Calibration of SWPC robots: closed-form geometry, the paper's baseline and the joint solver.

The solver's names are imported on first use (PEP 562): a module of this package that
needs no solver (the gyro problem's builder, the options) does not pay scipy.optimize's
import (0.65 s on the development VM, 20x that under the test VM's emulation) for it.
Likewise every module here imports scipy inside the function that uses it: the service
starts without scipy (a third of its imports) and pays for it at its first solve.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from swpc_hw.calibration.mocap.solver import (
        CalibrationResult,
        SolverOptions,
        solve,
        solve_directory,
    )

__all__ = ["CalibrationResult", "SolverOptions", "solve", "solve_directory"]


def __getattr__(name: str) -> object:
    if name in __all__:
        from swpc_hw.calibration.mocap import solver

        return getattr(solver, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
