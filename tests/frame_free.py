"""Frame-free figures of a calibration: what does not depend on the frame it is written in.

A calibration without motion capture writes its parameters in the ``design-fit`` frame,
the truth of a simulation is in R: compare what a planar rigid motion of the frame leaves
unchanged, with std devs from the result's covariance (first order)::

    distance between steering axes i, j   |P_s,i - P_s,j|
    beta difference                       beta_j - beta_first
    b_j, r_j
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from swpc_hw.robot.model import PARAM_NAMES, RobotParams

NAMES = PARAM_NAMES


@dataclass(frozen=True)
class Figure:
    name: str
    unit: str
    error: float
    """estimate minus truth (m or rad)"""
    stddev: float

    @property
    def z(self) -> float:
        return self.error / self.stddev if self.stddev > 0 else math.inf

    def __str__(self) -> str:
        f = 180 / math.pi if self.unit == "deg" else 1e3
        return (
            f"{self.name}: {self.error * f:+.4f} {self.unit if self.unit == 'deg' else 'mm'} "
            f"(std {self.stddev * f:.4f}, z {self.z:+.2f})"
        )


def frame_free(est: RobotParams, cov: np.ndarray, truth: RobotParams) -> list[Figure]:
    """The frame-free figures of ``est`` (with its parameters' covariance ``cov``, 5 per
    module in :data:`NAMES` order) against ``truth``."""
    E, T = est.arrays(), truth.arrays()
    n = len(est.ids)
    out = []

    def sd(grad: np.ndarray) -> float:
        return float(math.sqrt(max(float(grad @ cov @ grad), 0.0)))

    for i, j in itertools.combinations(range(n), 2):
        d = E.P_s[i] - E.P_s[j]
        dist = float(np.linalg.norm(d))
        g = np.zeros(5 * n)
        g[5 * i : 5 * i + 2], g[5 * j : 5 * j + 2] = d / dist, -d / dist
        true = float(np.linalg.norm(T.P_s[i] - T.P_s[j]))
        out.append(Figure(f"axis distance {est.ids[i]}-{est.ids[j]}", "mm", dist - true, sd(g)))
    for j in range(1, n):
        g = np.zeros(5 * n)
        g[5 * j + 2], g[2] = 1.0, -1.0
        err = (E.beta[j] - E.beta[0]) - (T.beta[j] - T.beta[0])
        out.append(Figure(f"beta {est.ids[j]} - beta {est.ids[0]}", "deg", float(err), sd(g)))
    for j in range(n):
        for k, name in ((3, "b"), (4, "r")):
            g = np.zeros(5 * n)
            g[5 * j + k] = 1.0
            err = float((E.b if k == 3 else E.r)[j] - (T.b if k == 3 else T.r)[j])
            out.append(Figure(f"{name} {est.ids[j]}", "mm", err, sd(g)))
    return out
