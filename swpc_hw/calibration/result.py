"""What a calibration returns: parameters with std devs and covariance, and quality figures."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from swpc_hw.calibration.parameters import PARAM_NAMES
from swpc_hw.model import RobotParams

FloatArray = NDArray[np.float64]


@dataclass
class SegmentQuality:
    """Quality figures of one segment."""

    row: int
    static_module: int
    angle: float
    poses_used: int
    poses_rejected: int
    fixed_point_rms: float
    """RMS length of the pose residuals ``|p + R C_R - C_W|`` of inliers (m)."""
    fixed_point: tuple[float, float]
    fixed_point_std: float | None = None
    """Std dev of the fixed point per coordinate (m), correlated noise included."""
    increments_used: int = 0
    increments_rejected: int = 0
    rolling_rms: float | None = None
    """RMS of the cumulative rolling residuals ``r psi - G`` of the clean runs (m)."""
    settled_rms: float | None = None
    """RMS of the settled-caster residuals of the dynamic modules (m)."""
    noise_inflation: float | None = None
    """Std dev of the fixed point over what white noise of the same size would give."""
    noise_rho: float | None = None
    """Lag-1 autocorrelation of the fixed-point scores (frame to frame).

    None: not computed by the method."""


@dataclass
class CalibrationResult:
    """Calibrated parameters (with std devs in ``params``) and quality figures.

    ``covariance``: (5N, 5N) covariance of all parameters, modules in ``params`` order and
    ``x_s, y_s, beta, b, r`` within a module (SI units), or None when unknown.
    ``time_offset_mode``: ``given``, ``estimated`` or ``not observable`` (then
    ``time_offset`` is the value assumed, 0).  ``reduced_chi2`` is None for a method
    without a noise model.
    """

    params: RobotParams
    nominal: RobotParams
    segments: list[SegmentQuality]
    time_offset: float
    time_offset_std: float | None
    time_offset_mode: str
    poses_used: int
    poses_rejected: int
    increments_used: int
    increments_rejected: int
    reduced_chi2: float | None
    method: str = "joint"
    covariance: FloatArray | None = None
    extra: dict[str, float] = field(default_factory=dict)

    def stddev_array(self) -> FloatArray:
        """(N, 5) standard deviations in the order x_s, y_s, beta, b, r."""
        rows = []
        for m in self.params.modules:
            s = m.stddev
            rows.append([math.nan] * 5 if s is None else [getattr(s, k) for k in PARAM_NAMES])
        return np.array(rows, dtype=float)

    def quality_document(self) -> dict[str, object]:
        """Plain-data quality figures (for the kinematic file's provenance and the API)."""
        return {
            "method": self.method,
            "time_offset": float(self.time_offset),
            "time_offset_std": _opt(self.time_offset_std),
            "time_offset_mode": self.time_offset_mode,
            "poses_used": self.poses_used,
            "poses_rejected": self.poses_rejected,
            "increments_used": self.increments_used,
            "increments_rejected": self.increments_rejected,
            "reduced_chi2": _opt(self.reduced_chi2),
            "segments": [
                {
                    "static_module": q.static_module,
                    "angle": float(q.angle),
                    "poses_used": q.poses_used,
                    "poses_rejected": q.poses_rejected,
                    "fixed_point_rms": float(q.fixed_point_rms),
                    "fixed_point_std": _opt(q.fixed_point_std),
                    "noise_inflation": _opt(q.noise_inflation),
                    "noise_rho": _opt(q.noise_rho),
                    "rolling_rms": _opt(q.rolling_rms),
                    "settled_rms": _opt(q.settled_rms),
                    "increments_used": q.increments_used,
                    "increments_rejected": q.increments_rejected,
                }
                for q in self.segments
            ],
        }


def _opt(value: float | None) -> float | None:
    return None if value is None else float(value)
