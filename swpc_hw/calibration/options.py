"""The joint solver's settings (:class:`SolverOptions`), shared by its stages."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal


@dataclass
class SolverOptions:
    """Tuning of the joint solver (defaults suit 100 Hz mocap and 200 Hz encoders)."""

    time_offset: float | Literal["auto"] = 0.0
    """Encoder clock minus pose clock (s), or ``"auto"`` to estimate it."""
    offset_bounds: tuple[float, float] = (-0.25, 0.25)
    """Search range of the clock offset (s)."""
    offset_grid_step: float = 0.01
    """Coarse grid step of the clock-offset search (s); the cost is smooth, its basin
    tens of milliseconds wide (the ramps last a second)."""
    offset_node_interval: float = 0.02
    """Spacing of the pose nodes of the clock-offset cost (s)."""
    offset_max_std: float = 0.005
    """A clock offset with a larger std dev (s) is reported as not observable."""
    increment_interval: float = 0.1
    """Spacing (s) of the pose nodes of the rolling block."""
    node_half_width: float = 0.025
    """A rolling node is the mean of the inlier poses within this (s) of its grid time."""
    steer_sigma_floor: float | None = None
    """Floor of a settled steering angle's std dev (rad); None: the encoders' quantization
    step over sqrt(12) (:func:`swpc_hw.calibration.rolling.encoder_resolution`)."""
    outlier_sigmas: float = 4.0
    """Poses whose fixed-point residual exceeds this many sigmas are rejected."""
    cauchy_c: float = 2.385
    """Cauchy constant (in sigmas) of the coarse clock-offset search."""
    slip_sigmas: float = 4.0
    """Wheel increments beyond this many robust sigmas are a slip burst."""
    drift_chunk: float = 2.0
    """Length (s) of the chunks of a rolling series tested for a slow slip drift."""
    drift_sigmas: float = 5.0
    """A chunk whose cumulative rolling residual drifts beyond this many sigmas slips."""
    irls_iterations: int = 4
