"""A fixed point fitted to a short arc is read at its error (issue 44): sequential stopping
ends spins at 60 deg (``MIN_SWEEP``), and there the long-run covariance's window, fitted to
white noise's chance correlation, read the fixed point's variance a third low."""

from __future__ import annotations

import math

import numpy as np
import pytest

from swpc_hw.calibration.fixed_point import fit_fixed_point
from swpc_hw.robot.model import rot


def arc(rng: np.random.Generator, sweep_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """Poses at 100 Hz of a robot spinning at 1.01 rad/s about a contact point ``C_R``
    (0.3 m, 0.2 m in R) fixed in the world, white noise of 0.5 mm and 0.05 deg (the
    planner's motion capture): ``(poses t, x, y, yaw; C_R)``."""
    C_R, C_W = np.array([0.3, 0.2]), np.array([1.0, -0.5])
    t = np.arange(0.0, math.radians(sweep_deg) / 1.01, 0.01)
    yaw = 0.4 + 1.01 * t
    p = C_W - np.einsum("kij,j->ki", rot(yaw), C_R)
    noisy = np.column_stack([
        t, p + rng.normal(0.0, 0.5e-3, p.shape), yaw + rng.normal(0.0, math.radians(0.05), t.size)
    ])  # fmt: skip
    return noisy, C_R


@pytest.mark.parametrize("sweep_deg", [60.0, 120.0])
def test_a_short_arcs_fixed_point_is_as_uncertain_as_its_covariance_says(
    sweep_deg: float,
) -> None:
    rng = np.random.default_rng(60)
    z2 = []
    for _ in range(600):
        poses, C_R = arc(rng, sweep_deg)
        fit = fit_fixed_point(poses)
        e = fit.C_R - C_R
        z2.append(float(e @ np.linalg.solve(fit.covariance, e)) / 2.0)
    mean = float(np.mean(z2))  # chi2(2) / 2: 1 when honest, std error 0.04 over 600
    print(f"\n{sweep_deg:g} deg: mean z^2 {mean:.3f}")
    assert 0.85 < mean < 1.2, mean
