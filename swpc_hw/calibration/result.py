"""What a calibration returns: parameters with std devs and covariance, and quality figures."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from swpc_hw.calibration.parameters import N_PARAMS
from swpc_hw.robot.model import RobotParams

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
    """RMS of the cumulative rolling residuals ``r psi - G`` of the clean runs (m); of the
    wheels' profiled residuals (rad) in an IMU calibration (NaN for a spin cut whole)."""
    settled_rms: float | None = None
    """RMS of the settled-caster residuals of the dynamic modules (m)."""
    noise_inflation: float | None = None
    """Std dev of the fixed point over what white noise of the same size would give."""
    noise_rho: float | None = None
    """Lag-1 autocorrelation of the fixed-point scores (frame to frame).

    None: not computed by the method."""


@dataclass
class ReferenceResidual:
    """One reference at the solution: what it says, what the calibration gives."""

    label: str
    kind: str
    value: float
    stddev: float
    predicted: float
    predicted_std: float | None = None
    """Std dev of ``predicted`` from the calibration's covariance (the reference included)."""

    @property
    def residual(self) -> float:
        return self.predicted - self.value


@dataclass
class BiasKnot:
    """The gyro's bias at a rest window: time (s), value and std dev (rad/s)."""

    t: float
    bias: float
    std: float | None


@dataclass
class ImuQuality:
    """What a calibration without motion capture adds to the quality figures."""

    gyro_scale_error: float
    """``eps`` of ``wz = (1 + eps) omega + bias``."""
    gyro_scale_error_std: float | None
    bias: list[BiasKnot]
    gyro_noise_density: float
    """White noise of the gyro, rad/s/sqrt(Hz), from the rests' scatter."""
    bias_walk: float
    """Random walk of the bias, rad/s/sqrt(s), from the knots (0: not seen)."""
    references: list[ReferenceResidual]
    block_chi2: dict[str, float] = field(default_factory=dict)
    """Reduced chi^2 of every residual block (1 when its noise model is right)."""
    notes: list[str] = field(default_factory=list)
    """Warnings for the reader (a reference that pins something only weakly)."""

    def document(self) -> dict[str, object]:
        return {
            "gyro_scale_error": float(self.gyro_scale_error),
            "gyro_scale_error_std": _opt(self.gyro_scale_error_std),
            "gyro_noise_density": float(self.gyro_noise_density),
            "bias_walk": float(self.bias_walk),
            "bias": [{"t": k.t, "bias": k.bias, "std": _opt(k.std)} for k in self.bias],
            "references": [
                {
                    "reference": r.label,
                    "value": r.value,
                    "stddev": r.stddev,
                    "predicted": r.predicted,
                    "predicted_std": _opt(r.predicted_std),
                    "residual": r.residual,
                }
                for r in self.references
            ],
            "block_chi2": {k: float(v) for k, v in self.block_chi2.items()},
            "notes": list(self.notes),
        }


@dataclass
class CalibrationResult:
    """Calibrated parameters (with std devs in ``params``) and quality figures.

    ``covariance``: (5N, 5N) covariance of all parameters, modules in ``params`` order and
    ``x_s, y_s, beta, b, r`` within a module (SI units), or None when unknown.
    ``time_offset_mode``: ``given``, ``estimated`` or ``not observable`` (then
    ``time_offset`` is the value assumed, 0).  ``reduced_chi2`` is None for a method
    without a noise model.  ``mode``: ``mocap`` (poses) or ``imu`` (gyro and
    references, ``imu`` set, parameters in the design-fit frame).
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
    mode: str = "mocap"
    imu: ImuQuality | None = None

    def stddev_array(self) -> FloatArray:
        """(N, 5) standard deviations in the order x_s, y_s, beta, b, r."""
        rows = []
        for m in self.params.modules:
            s = m.stddev
            rows.append([math.nan] * N_PARAMS if s is None else list(s.values()))
        return np.array(rows, dtype=float)

    def quality_document(self) -> dict[str, object]:
        """Plain-data quality figures (for the kinematic file's provenance and the API)."""
        doc: dict[str, object] = {
            "method": self.method,
            "mode": self.mode,
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
        if self.imu is not None:
            doc["imu"] = self.imu.document()
        return doc


def _opt(value: float | None) -> float | None:
    return None if value is None else float(value)
