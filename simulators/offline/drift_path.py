"""A mixed path of normal driving, as the drives' encoders read it (for the drift observer).

Segments of constant body twist, drawn at random: straights forward and back, strafes in
any direction, arcs, spins on the spot and stops, at several speeds
(:func:`mixed_segments`).  :func:`drive_readings` turns them into the readings of every
module at the feedback rate, on a *true* robot that may differ from the kinematic file the
odometry loads:

* per module the exact no-slip caster model of docs/model-and-frames.md,
  ``b (theta_dot + omega) = c . n(theta)``, ``r psi_dot = c . u(theta)``
  (``c = v + omega x P_s``), integrated with DOP853 (rtol 1e-10) through each segment
  (the casters swivel to each new twist as the kinematics say);
* small slips: each wheel's increments multiplied by ``1 + eps(t)``, ``eps`` a zero-mean
  first-order (Ornstein-Uhlenbeck) process, std ``slip_std``, time constant ``slip_tau``,
  plus slip bursts (one wheel ``burst`` faster or slower, at random, for
  ``burst_duration``) at a mean rate of ``bursts_per_minute``;
* reported steering ``theta_hat = theta - beta``; both encoders quantized to ``counts``
  per turn; sample times jittered by ``+-jitter / rate``.

Plain numpy and scipy; deterministic for a seed.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.integrate import solve_ivp
from scipy.signal import lfilter

from swpc_hw.onboard.drift import DriftMonitor, DriftOptions, SuspectChange
from swpc_hw.onboard.odometry import Odometry
from swpc_hw.onboard.twist_controller import settled_steering
from swpc_hw.robot.model import RobotParams

FloatArray = NDArray[np.float64]
Twist = tuple[float, float, float]


@dataclass(frozen=True)
class PathNoise:
    """Encoder and floor imperfections of :func:`drive_readings` (module docstring)."""

    counts: int = 2**17
    slip_std: float = 0.002
    slip_tau: float = 1.0
    bursts_per_minute: float = 1.0
    burst: float = 0.05
    burst_duration: float = 0.3
    jitter: float = 0.1


def mixed_segments(duration: float, seed: int) -> list[tuple[float, Twist]]:
    """``(seconds, (v_x, v_y, omega))`` segments of normal driving, ``duration`` s in all:
    straights 40 % (0.1-0.6 m/s, a quarter of them backwards), arcs 20 %, strafes 15 %
    (any direction, 0.1-0.4 m/s), spins 10 % (0.3-1.0 rad/s), stops 15 %; 1-8 s each."""
    rng = np.random.default_rng(seed)
    out: list[tuple[float, Twist]] = []
    total = 0.0
    while total < duration:
        kind = rng.choice(5, p=[0.4, 0.2, 0.15, 0.1, 0.15])
        dur = float(rng.uniform(1.0, 8.0))
        sign = 1.0 if rng.random() < 0.5 else -1.0
        tw: Twist
        if kind == 0:
            v = float(rng.uniform(0.1, 0.6))
            tw = (-v if rng.random() < 0.25 else v, 0.0, 0.0)
        elif kind == 1:
            tw = (float(rng.uniform(0.1, 0.5)), 0.0, sign * float(rng.uniform(0.1, 0.6)))
        elif kind == 2:
            a = float(rng.uniform(-math.pi, math.pi))
            v = float(rng.uniform(0.1, 0.4))
            tw = (v * math.cos(a), v * math.sin(a), 0.0)
        elif kind == 3:
            tw = (0.0, 0.0, sign * float(rng.uniform(0.3, 1.0)))
        else:
            tw = (0.0, 0.0, 0.0)
        dur = min(dur, duration - total) if duration - total > 0.5 else dur
        out.append((dur, tw))
        total += dur
    return out


def caster_rates(
    truth: RobotParams, twist: Twist
) -> Callable[[float, FloatArray], FloatArray]:
    """The casters' kinematics under a constant body twist ``(v_x, v_y, omega)``: ``f(t,
    z)`` with ``z = (theta (N), psi (N))`` the true steering and rolling angles, for
    ``scipy.integrate.solve_ivp``.  Each contact point rolls without slip: with the
    steering axis' velocity ``c = (v_x - omega y_s, v_y + omega x_s)``::

        dtheta/dt = (c_x sin theta - c_y cos theta) / b - omega
        dpsi/dt   = (c_x cos theta + c_y sin theta) / r
    """
    a = truth.arrays()
    n = a.n
    vx, vy, om = twist
    cx = vx - om * a.P_s[:, 1]
    cy = vy + om * a.P_s[:, 0]

    def f(_t: float, z: FloatArray) -> FloatArray:
        q = z[:n]
        return np.concatenate([
            (cx * np.sin(q) - cy * np.cos(q)) / a.b - om,
            (cx * np.cos(q) + cy * np.sin(q)) / a.r,
        ])  # fmt: skip

    return f


def drive_readings(
    truth: RobotParams,
    segments: list[tuple[float, Twist]],
    *,
    rate: float = 200.0,
    noise: PathNoise | None = None,
    seed: int = 0,
) -> Iterator[tuple[FloatArray, FloatArray, FloatArray]]:
    """The readings ``(t (T,), theta_hat (T, N), psi (T, N))`` of each segment in turn
    (the first chunk starts with the reading at t = 0)."""
    nz = noise if noise is not None else PathNoise()
    a = truth.arrays()
    n = a.n
    rng = np.random.default_rng(seed)
    q = 2.0 * math.pi / nz.counts if nz.counts else 0.0
    first = next((tw for _, tw in segments if tw != (0.0, 0.0, 0.0)), (1.0, 0.0, 0.0))
    th = settled_steering(a, first) + a.beta
    ps = np.zeros(n)  # true rolling angle
    meas = np.zeros(n)  # what the wheel encoder counts (rolling + slip)
    eps_state = np.zeros(n)
    alpha = math.exp(-1.0 / (rate * nz.slip_tau))
    burst_p = nz.bursts_per_minute / 60.0 / rate
    burst_left = np.zeros(n)
    burst_level = np.zeros(n)

    def quant(x: FloatArray) -> FloatArray:
        return np.round(x / q) * q if q else x

    t0 = 0.0
    yield np.array([0.0]), quant(th - a.beta)[None, :], quant(meas)[None, :]
    for dur, tw in segments:
        k = max(1, round(dur * rate))
        ts = np.linspace(0.0, dur, k + 1)[1:]
        ts[:-1] += rng.uniform(-nz.jitter, nz.jitter, k - 1) / rate
        sol = solve_ivp(caster_rates(truth, tw), (0.0, dur), np.concatenate([th, ps]),
                        method="DOP853", t_eval=ts,
                        rtol=1e-10, atol=1e-12)
        if not sol.success:
            raise RuntimeError(f"drive_readings: {sol.message}")
        TH = sol.y[:n].T
        PS = sol.y[n:].T
        dps = np.diff(np.vstack([ps, PS]), axis=0)
        # slip: OU relative speed error, plus bursts
        white = rng.normal(0.0, nz.slip_std * math.sqrt(1.0 - alpha * alpha), (k, n))
        eps, zf = lfilter([1.0], [1.0, -alpha], white, axis=0, zi=(alpha * eps_state)[None, :])
        eps_state = zf[0] / alpha if alpha else eps[-1]
        start = rng.random((k, n)) < burst_p
        signs = np.where(rng.random((k, n)) < 0.5, -nz.burst, nz.burst)
        bursts = np.zeros((k, n))
        for j in range(n):
            left, level = burst_left[j], burst_level[j]
            for s in range(k):
                if start[s, j]:
                    left, level = nz.burst_duration * rate, signs[s, j]
                if left > 0:
                    bursts[s, j] = level
                    left -= 1
            burst_left[j], burst_level[j] = left, level
        meas_seg = meas + np.cumsum(dps * (1.0 + eps + bursts), axis=0)
        yield t0 + ts, quant(TH - a.beta), quant(meas_seg)
        th, ps, meas = sol.y[:n, -1], sol.y[n:, -1], meas_seg[-1]
        t0 += dur


def with_error(params: RobotParams, module: int, *, dr: float = 0.0,
               dbeta: float = 0.0) -> RobotParams:
    """``params`` with module ``module``'s wheel radius ``+dr`` (m) and homing error
    ``+dbeta`` (rad): a true robot that has drifted from its file."""
    mods = [m.model_copy(update={"r": m.r + dr, "beta": m.beta + dbeta}) if m.id == module
            else m for m in params.modules]
    return params.model_copy(update={"modules": mods})


@dataclass(frozen=True)
class DriftRun:
    """What a :class:`~swpc_hw.onboard.drift.DriftMonitor` made of a drive: every suspect change,
    the metres and hours driven, and the monitor at the end."""

    changes: list[SuspectChange]
    metres: float
    seconds: float
    monitor: DriftMonitor


def observe_drive(
    truth: RobotParams,
    file: RobotParams,
    segments: list[tuple[float, Twist]],
    *,
    rate: float = 200.0,
    noise: PathNoise | None = None,
    seed: int = 0,
    options: DriftOptions | None = None,
    stop_at_first: bool = False,
) -> DriftRun:
    """Drive ``truth`` along ``segments`` (:func:`drive_readings`) with the odometry and the
    drift monitor on ``file``; stop at the first suspect raised if ``stop_at_first``."""
    odo = Odometry(file)
    mon = DriftMonitor(file, options)
    changes: list[SuspectChange] = []
    t_end = 0.0
    for t, th, ps in drive_readings(truth, segments, rate=rate, noise=noise, seed=seed):
        thl, psl = th.tolist(), ps.tolist()
        for k in range(t.size):
            odo.update(float(t[k]), thl[k], psl[k])
            got = mon.feed(odo, thl[k], psl[k])
            if got:
                changes.extend(got)
                if stop_at_first and any(c.raised for c in got):
                    return DriftRun(changes, mon.metres, float(t[k]), mon)
        t_end = float(t[-1])
    return DriftRun(changes, mon.metres, t_end, mon)


__all__ = [
    "DriftRun",
    "PathNoise",
    "drive_readings",
    "mixed_segments",
    "observe_drive",
    "with_error",
]
