"""Human-facing tables of calibration results (millimetres and degrees)."""

from __future__ import annotations

import math
from typing import TypeGuard

from swpc_hw.calibration.result import CalibrationResult
from swpc_hw.robot.model import ModuleParams, RobotParams

#: name, attribute, factor to display unit, unit
COLUMNS = (
    ("x_s", "x_s", 1e3, "mm"),
    ("y_s", "y_s", 1e3, "mm"),
    ("beta", "beta", 180.0 / math.pi, "deg"),
    ("b", "b", 1e3, "mm"),
    ("r", "r", 1e3, "mm"),
)
DISPLAY: dict[str, tuple[str, float]] = {name: (unit, f) for name, _, f, unit in COLUMNS}
"""Each parameter's display unit and its factor from SI."""


def _fmt(value: float, unit: str) -> str:
    return f"{value:.4f}" if unit == "deg" else f"{value:.3f}"


def result_rows(result: CalibrationResult, truth: RobotParams | None = None) -> list[list[str]]:
    """Rows: module, parameter, unit, nominal, estimate, std dev[, truth, error]."""
    rows: list[list[str]] = []
    for m in result.params.modules:
        nominal: ModuleParams | None = (
            result.nominal.module(m.id) if m.id in result.nominal.ids else None
        )
        for name, attr, f, unit in COLUMNS:
            est = getattr(m, attr) * f
            std = getattr(m.stddev, attr) * f if m.stddev is not None else math.nan
            row = [
                str(m.id),
                name,
                unit,
                _fmt(getattr(nominal, attr) * f, unit) if nominal else "-",
                _fmt(est, unit),
                _fmt(std, unit) if math.isfinite(std) else "-",
            ]
            if truth is not None:
                t = getattr(truth.module(m.id), attr) * f
                row += [_fmt(t, unit), f"{est - t:+.4f}"]
            rows.append(row)
    return rows


def format_table(result: CalibrationResult, truth: RobotParams | None = None) -> str:
    """Plain-text table: nominal, estimate and std dev (and truth/error when given)."""
    header = ["module", "param", "unit", "nominal", "estimate", "std dev"]
    if truth is not None:
        header += ["truth", "error"]
    rows = [header, *result_rows(result, truth)]
    widths = [max(len(r[i]) for r in rows) for i in range(len(header))]
    lines = []
    for k, r in enumerate(rows):
        lines.append("  ".join(c.rjust(w) for c, w in zip(r, widths, strict=True)))
        if k == 0:
            lines.append("  ".join("-" * w for w in widths))
    q = result
    lines.append("")
    chi2 = f"{q.reduced_chi2:.3g}" if _known(q.reduced_chi2) else "n/a (no noise model)"
    if q.imu is not None:
        lines += imu_lines(q)
        lines.append(
            f"wheel increments used {q.increments_used} (left out {q.increments_rejected}: "
            f"slip, spins cut whole); reduced chi2 {chi2}"
        )
    else:
        lines.append(
            f"poses used {q.poses_used} (rejected {q.poses_rejected}); wheel increments used "
            f"{q.increments_used} (rejected {q.increments_rejected}); {offset_text(q)}; "
            f"reduced chi2 {chi2}"
        )
    if q.method == "paper":
        lines.append("  (the paper's procedure computes no rolling or settled residuals)")
    for s in q.segments:
        # the reported steering angle of the locked module, on one turn: [0, 360) deg
        angle = math.degrees(s.angle) % 360.0
        figures = [
            f"{name} {value * 1e3:.4f} mm"
            for name, value in (
                ("fixed-point RMS", s.fixed_point_rms),
                ("rolling RMS", None if q.imu is not None else s.rolling_rms),
                ("settled RMS", s.settled_rms),
            )
            if _known(value)
        ]
        if q.imu is not None:  # the wheels' residuals are angles there (rad)
            if _known(s.rolling_rms):
                figures.insert(0, f"rolling RMS {s.rolling_rms * 1e6:.2f} urad")
            figures.append(
                f"increments {s.increments_used}/{s.increments_used + s.increments_rejected}"
            )
        if _known(s.noise_inflation):
            figures.append(f"noise correlation x{s.noise_inflation:.2f}")
        if q.imu is None:
            figures.append(f"poses {s.poses_used}/{s.poses_used + s.poses_rejected}")
        lines.append(
            f"  segment {s.row + 1}: module {s.static_module} at {angle:7.2f} deg: "
            + ", ".join(figures)
        )
    inflation = [f for f in (s.noise_inflation for s in q.segments) if _known(f)]
    if inflation and max(inflation) > 1.2:
        lines.append(
            f"  the pose noise is correlated from frame to frame: std devs are up to "
            f"{max(inflation):.2f}x what white noise of its size would give (included above)"
        )
    return "\n".join(lines)


def imu_lines(q: CalibrationResult) -> list[str]:
    """The mode, the gyro's estimates and every reference's residual (mm, deg/s, %)."""
    m = q.imu
    if m is None:
        return []
    deg = 180.0 / math.pi
    eps_std = m.gyro_scale_error_std
    lines = [
        f"mode: imu (encoders, gyro and references; frame {q.params.frame}: the rigid "
        "transform that best aligns the steering axes with robot.yaml's)",
        f"gyro: scale error {m.gyro_scale_error * 100:+.4f} %"
        + (f" (std {eps_std * 100:.4f} %)" if eps_std is not None else "")
        + f", white noise {m.gyro_noise_density * deg:.4g} deg/s/sqrt(Hz), bias walk "
        f"{m.bias_walk * deg:.3g} deg/s/sqrt(s)",
        "gyro bias at the rest windows (deg/s): "
        + ", ".join(
            f"{k.t:.1f} s {k.bias * deg:+.5f}" + (f" ({k.std * deg:.5f})" if k.std else "")
            for k in m.bias
        ),
        "references (value, calibrated, residual, residual / stddev):",
    ]
    for r in m.references:
        f, unit = (1e3, "mm")
        std = f" (std {r.predicted_std * f:.4f})" if r.predicted_std is not None else ""
        lines.append(
            f"  {r.label}: {r.value * f:.4f} {unit}, {r.predicted * f:.4f}{std}, "
            f"{r.residual * f:+.4f} {unit}, {r.residual / r.stddev:+.2f}"
        )
    lines += [f"  note: {n}" for n in m.notes]
    return lines


def _known(value: float | None) -> TypeGuard[float]:
    """A figure the method computed: not None and finite (never printed as ``nan``)."""
    return value is not None and math.isfinite(value)


def offset_text(q: CalibrationResult) -> str:
    """The clock offset in words: value, how it was obtained, std dev."""
    if q.time_offset_mode == "not observable":
        return (
            "time offset not observable from these data (no acceleration in the "
            f"recorded spins): {q.time_offset * 1e3:.2f} ms assumed, harmless for that reason"
        )
    std = f", std {q.time_offset_std * 1e3:.3f} ms" if q.time_offset_std is not None else ""
    return f"time offset {q.time_offset * 1e3:.3f} ms ({q.time_offset_mode}{std})"
