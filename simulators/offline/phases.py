"""The offline generator's motion as phases (:mod:`simulators.offline.datagen`): each a
closed-form piece of the timeline, a rotation about a fixed body point (a spin, a
re-steer), a steering alignment or a straight translation, evaluated at any times."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from simulators.physics.core import (
    FloatArray,
    pose_about_pivot,
    smooth_step,
    spin_angle,
    trailing_about_pivot,
)
from swpc_hw.robot.model import rot


@dataclass
class Phase:
    """A piece of the timeline: rotation about a fixed body point, or steering alignment."""

    t0: float
    t1: float
    pose0: FloatArray
    theta0: FloatArray
    psi0: FloatArray
    kind: str  # "rotate" | "align" | "translate"
    pivot: FloatArray = field(default_factory=lambda: np.zeros(2))  # translate: direction
    free: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, dtype=bool))
    fork: int = -1  # index of a module whose fork keeps its world orientation
    profile: tuple[str, float, float, float] = ("spin", 0.0, 0.0, 0.0)
    theta1: FloatArray = field(default_factory=lambda: np.zeros(0))

    def phi(self, tau: FloatArray) -> FloatArray:
        kind, a, b_, c = self.profile
        if kind == "spin":
            return spin_angle(tau, a, b_, c)
        return a * smooth_step(tau / b_)  # "resteer": total angle a over b_ seconds

    def evaluate(
        self, t: FloatArray, P_s: FloatArray, b: FloatArray, r: FloatArray
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Poses (K, 3) (yaw not wrapped), true theta (K, N), psi (K, N) at times ``t``."""
        tau = np.asarray(t, dtype=float) - self.t0
        K, n = tau.shape[0], self.theta0.shape[0]
        theta = np.broadcast_to(self.theta0, (K, n)).copy()
        psi = np.broadcast_to(self.psi0, (K, n)).copy()
        if self.kind == "align":
            s = smooth_step(tau / (self.t1 - self.t0))[:, None]
            theta = self.theta0 + (self.theta1 - self.theta0) * s
            pose = np.broadcast_to(self.pose0, (K, 3)).copy()
            return pose, theta, psi
        ph = self.phi(tau)
        if self.kind == "translate":  # distance ph along the body direction self.pivot
            pose = np.broadcast_to(self.pose0, (K, 3)).copy()
            pose[:, :2] += ph[:, None] * (rot(self.pose0[2]) @ self.pivot)[None, :]
            along = np.cos(self.theta0) * self.pivot[0] + np.sin(self.theta0) * self.pivot[1]
            return pose, theta, psi + ph[:, None] * (along / r)[None, :]
        pose = pose_about_pivot(self.pose0, self.pivot, ph)
        idx = np.flatnonzero(self.free)
        if idx.size:
            th, dpsi = trailing_about_pivot(
                P_s[idx], b[idx], r[idx], self.pivot, self.theta0[idx], ph[:, None]
            )
            theta[:, idx] = th
            psi[:, idx] = self.psi0[idx] + dpsi
        if self.fork >= 0:
            theta[:, self.fork] = self.theta0[self.fork] - ph
        return pose, theta, psi


def evaluate_phases(
    phases: list[Phase], t: FloatArray, P_s: FloatArray, b: FloatArray, r: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Poses (K, 3) (yaw not wrapped), true theta (K, N), psi (K, N) at times ``t``, each
    from the phase it falls in (after the last one's end: its end)."""
    n = P_s.shape[0]
    K = t.shape[0]
    pose = np.zeros((K, 3))
    theta = np.zeros((K, n))
    psi = np.zeros((K, n))
    starts = np.array([p.t0 for p in phases])
    which = np.clip(np.searchsorted(starts, t, side="right") - 1, 0, len(phases) - 1)
    for i, ph in enumerate(phases):
        sel = np.flatnonzero(which == i)
        if sel.size:
            tt = np.minimum(t[sel], ph.t1)
            pose[sel], theta[sel], psi[sel] = ph.evaluate(tt, P_s, b, r)
    return pose, theta, psi
