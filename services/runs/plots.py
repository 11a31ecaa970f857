"""Calibration plot (matplotlib, Agg): pivot circles, fitted fixed points, residuals; each
module in its colour (:data:`services.runs.mcap.MODULE_COLOURS`)."""

from __future__ import annotations

import io

import numpy as np

from services.runs.mcap import module_colour
from swpc_hw.calibration import geometry as geo
from swpc_hw.calibration.mocap.solver import CalibrationResult
from swpc_hw.files.dataset import Dataset


def calibration_plot(ds: Dataset, result: CalibrationResult) -> bytes:
    """PNG with three panels:

    1. the robot origin's trajectory in W during every spin (the pivot circles);
    2. the robot frame: nominal and calibrated steering axes, the calibrated caster
       circles ``|P - P_s| = b`` and the fitted fixed points of every segment;
    3. the fixed-point residuals ``|p + R C_R - C_W|`` of every pose, by segment.

    Without poses (a calibration without motion capture) panel 2 alone, its axes and
    circles: panels 1 and 3 and the fixed points need the poses.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    posed = ds.poses.shape[0] > 0
    if posed:
        fig, (ax0, ax1, ax2) = plt.subplots(1, 3, figsize=(16, 5.2))
    else:
        fig, ax1 = plt.subplots(1, 1, figsize=(6.4, 5.2))
    for s_idx, seg in enumerate(ds.segments if posed else []):
        sel = (ds.poses[:, 0] >= seg.start) & (ds.poses[:, 0] <= seg.end)
        P = ds.poses[sel]
        if P.shape[0] < 3:
            continue
        c = module_colour(seg.static_module)
        ax0.plot(P[:, 1], P[:, 2], ".", ms=1.5, color=c)
        pp = P[:, 1:].copy()
        pp[:, 2] = np.unwrap(pp[:, 2])
        C_R, C_W = geo.fixed_point(pp)
        ax0.plot(*C_W, "k+", ms=8)
        res = np.linalg.norm(geo.fixed_point_residuals(pp, C_R, C_W), axis=-1) * 1e3
        ax2.plot(
            np.full(res.shape, s_idx + 1)
            + np.random.default_rng(s_idx).uniform(-0.3, 0.3, res.size),
            res,
            ".",
            ms=1,
            color=c,
        )
        ax1.plot(C_R[0] * 1e3, C_R[1] * 1e3, "x", color=c, ms=7)
    if posed:
        ax0.set_title("origin of R during each spin (W)")
        ax0.set_xlabel("x (m)")
        ax0.set_ylabel("y (m)")
        ax0.axis("equal")
        ax2.set_title("fixed-point residual per pose")
        ax2.set_xlabel("segment")
        ax2.set_ylabel("|p + R C_R - C_W| (mm)")
    t = np.linspace(0, 2 * np.pi, 200)
    for m in result.params.modules:
        c = module_colour(m.id)
        nom = ds.robot.module(m.id)
        ax1.plot(nom.x_s * 1e3, nom.y_s * 1e3, "s", mfc="none", color=c, ms=8)
        ax1.plot(m.x_s * 1e3, m.y_s * 1e3, "o", color=c, ms=5, label=f"module {m.id}")
        ax1.plot(
            (m.x_s + m.b * np.cos(t)) * 1e3, (m.y_s + m.b * np.sin(t)) * 1e3, "-", color=c, lw=0.8
        )
    ax1.set_title(
        f"{result.params.frame}: nominal (square), calibrated (dot)"
        + (", fixed points (x)" if posed else "")
    )
    ax1.set_xlabel("x (mm)")
    ax1.set_ylabel("y (mm)")
    ax1.axis("equal")
    ax1.legend(fontsize=7)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    plt.close(fig)
    return buf.getvalue()
