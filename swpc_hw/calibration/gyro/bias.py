"""The gyro without motion capture: rest windows, bias knots, integrals and their noise.

A z gyro fixed to R reads ``wz = s omega + bias(t) + n`` (``s = 1 + eps``: its unknown
scale, ``bias`` unknown and slowly drifting, ``n`` white).  The yaw the robot turned
between two times is then::

    dyaw(t_a, t_b) = (int_{t_a}^{t_b} wz dt - int_{t_a}^{t_b} bias dt) / s

* **Bias knots**: while every encoder shows the robot still (:func:`rest_windows`),
  ``omega = 0`` and the mean of ``wz`` over the window observes the bias at its mean time
  ``tau_i``.  The bias is a parameter per knot, linear in between and constant beyond the
  ends: ``bias(t) = sum_i b_i phi_i(t)`` with the hat functions ``phi_i``
  (:func:`linear_basis`).  So both integrals above are linear in the data and the knots:
  :func:`cumulative_trapezoid_at` of ``wz`` and of the basis.
* **Noise**: white noise of per-sample variance ``v`` (from the rests' scatter,
  :func:`white_variance`) gives an integral over ``T`` seconds the variance
  ``v dt T`` (``dt`` the sample period; a density ``N`` in rad/s/sqrt(Hz) sampled at
  ``f`` has ``v = N^2 f``, so ``N^2 T``).  A knot mean over ``n`` samples: ``v / n``.
* **Bias walk**: a random walk of intensity ``q^2`` (rad^2/s^3) leaves, between two
  knots ``T`` apart, a Brownian bridge about the straight line; the variance of its
  integral over ``[a, b]`` is :func:`bridge_integral_variance`.  ``q^2`` comes from the
  knots themselves (:func:`bias_walk_intensity`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from swpc_hw.files.dataset import Dataset

FloatArray = NDArray[np.float64]

MIN_REST = 0.5
"""A rest window lasts at least this long (s) after trimming."""
REST_TRIM = 0.1
"""Seconds cut from both ends of a still interval (the motion's last and first samples)."""
STILL_COUNTS = 2.5
"""An axis that moves by more than this many encoder steps between samples is moving."""
MAX_GAP = 0.1
"""Encoder samples further apart than this (s) leave the time in between unknown."""


@dataclass(frozen=True)
class CumulativeIntegral:
    """``int_{t_0}^{tq} y dt`` of the piecewise-linear interpolant of samples ``(t, y)``.

    Exact for a signal linear between samples (the trapezoid rule, with the partial last
    interval).  ``y``: (K,) or (K, p); the running sums are computed once
    (:meth:`of`), then :meth:`at` answers any times (clipped to ``[t_0, t_-1]``).
    """

    t: FloatArray
    y: FloatArray
    cum: FloatArray

    @classmethod
    def of(cls, t: FloatArray, y: FloatArray) -> CumulativeIntegral:
        Y = np.asarray(y, dtype=float).reshape(t.size, -1)
        steps = 0.5 * np.diff(t)[:, None] * (Y[1:] + Y[:-1])
        cum = np.vstack([np.zeros((1, Y.shape[1])), np.cumsum(steps, axis=0)])
        return cls(np.asarray(t, dtype=float), Y, cum)

    def at(self, tq: FloatArray) -> FloatArray:
        """(Q, p) integrals from ``t_0`` to every ``tq``."""
        t, Y = self.t, self.y
        q = np.clip(np.asarray(tq, dtype=float), t[0], t[-1])
        i = np.clip(np.searchsorted(t, q, side="right") - 1, 0, t.size - 2)
        h = (q - t[i])[:, None]
        slope = (Y[i + 1] - Y[i]) / (t[i + 1] - t[i])[:, None]
        return np.asarray(self.cum[i] + h * (Y[i] + 0.5 * slope * h), dtype=float)


def cumulative_trapezoid_at(t: FloatArray, y: FloatArray, tq: FloatArray) -> FloatArray:
    """:class:`CumulativeIntegral` of ``(t, y)`` at ``tq``: (Q,) for 1-D ``y``, else (Q, p)."""
    out = CumulativeIntegral.of(t, y).at(tq)
    return out[:, 0] if np.ndim(y) == 1 else out


def linear_basis(knots: FloatArray, t: FloatArray) -> FloatArray:
    """Hat functions ``phi_i(t)`` (T, K) of linear interpolation through ``knots`` (sorted),
    constant beyond the first and last knot (``sum_i phi_i = 1``)."""
    K = knots.size
    tt = np.asarray(t, dtype=float)
    out = np.zeros((tt.size, K))
    if K == 1:
        out[:, 0] = 1.0
        return out
    q = np.clip(tt, knots[0], knots[-1])
    i = np.clip(np.searchsorted(knots, q, side="right") - 1, 0, K - 2)
    w = (q - knots[i]) / (knots[i + 1] - knots[i])
    rows = np.arange(tt.size)
    out[rows, i] = 1.0 - w
    out[rows, i + 1] += w
    return out


def rest_windows(ds: Dataset, resolution: float) -> list[tuple[float, float]]:
    """Windows (s) in which every module's steering and wheel encoder is still.

    An axis moves between two consecutive samples when its reading changes by more than
    :data:`STILL_COUNTS` encoder steps (``resolution``, rad); samples more than
    :data:`MAX_GAP` apart leave the time between them unknown.  The still intervals,
    common to all modules, are trimmed by :data:`REST_TRIM` at both ends and kept when
    :data:`MIN_REST` long at least.
    """
    tol = STILL_COUNTS * resolution
    starts, ends = [], []
    lo, hi = -math.inf, math.inf
    for rows in ds.encoders.values():
        t = rows[:, 0]
        lo, hi = max(lo, float(t[0])), min(hi, float(t[-1]))
        d = np.abs(np.diff(rows[:, 1:], axis=0)).max(axis=1)
        moving = np.flatnonzero((d > tol) | (np.diff(t) > MAX_GAP))
        starts.append(t[moving])
        ends.append(t[moving + 1])
    a = np.concatenate([*starts, [hi]])
    b = np.concatenate([*ends, [hi]])
    order = np.argsort(a, kind="stable")
    a, b = a[order], b[order]
    reach = np.maximum.accumulate(np.concatenate([[lo], b]))[:-1]  # busy up to here before
    w0, w1 = reach + REST_TRIM, np.minimum(a, hi) - REST_TRIM
    keep = (a > reach) & (w1 - w0 >= MIN_REST)
    return [(float(x), float(y)) for x, y in zip(w0[keep], w1[keep], strict=True)]


@dataclass(frozen=True)
class BiasKnots:
    """Bias observations of the rest windows: knot time ``tau`` (mean sample time), the
    mean ``wz`` over the window, its sample count ``n`` and duration ``T`` (s)."""

    tau: FloatArray
    mean: FloatArray
    n: NDArray[np.int64]
    T: FloatArray
    windows: list[tuple[float, float]]

    @property
    def size(self) -> int:
        return int(self.tau.size)


def bias_knots(
    imu: FloatArray, windows: list[tuple[float, float]], min_samples: int = 10
) -> BiasKnots:
    """One knot per rest window with at least ``min_samples`` gyro samples."""
    tau, mean, n, T, kept = [], [], [], [], []
    for a, b in windows:
        sel = (imu[:, 0] >= a) & (imu[:, 0] <= b)
        if int(sel.sum()) < min_samples:
            continue
        tau.append(float(imu[sel, 0].mean()))
        mean.append(float(imu[sel, 1].mean()))
        n.append(int(sel.sum()))
        T.append(b - a)
        kept.append((a, b))
    return BiasKnots(np.array(tau), np.array(mean), np.array(n, dtype=np.int64), np.array(T), kept)


def white_variance(imu: FloatArray, knots: BiasKnots) -> float:
    """Per-sample variance of the gyro's white noise: the scatter about each rest's mean,
    pooled (``sum (wz - mean_i)^2 / sum (n_i - 1)``); 0 without rests."""
    ss, dof = 0.0, 0
    for (a, b), m in zip(knots.windows, knots.mean, strict=True):
        sel = (imu[:, 0] >= a) & (imu[:, 0] <= b)
        ss += float(np.sum((imu[sel, 1] - m) ** 2))
        dof += int(sel.sum()) - 1
    return ss / dof if dof > 0 else 0.0


def bias_walk_intensity(knots: BiasKnots, knot_var: FloatArray) -> float:
    """``q^2`` (rad^2/s^3) of the bias random walk from consecutive knots::

        E[(m_i+1 - m_i)^2] = v_i + v_i+1 + q^2 (tau_i+1 - tau_i)

    ``q^2 = max(0, sum (d_i^2 - v_i - v_i+1) / sum (tau_i+1 - tau_i))``; 0 with < 2 knots.
    """
    if knots.size < 2:
        return 0.0
    d = np.diff(knots.mean)
    excess = float(np.sum(d**2 - knot_var[1:] - knot_var[:-1]))
    return max(excess / float(np.sum(np.diff(knots.tau))), 0.0)


def bridge_integral_variance(T: float, a: float, b: float, q2: float) -> float:
    """Variance of ``int_a^b B(t) dt`` for a Brownian bridge ``B`` of intensity ``q2`` on
    ``[0, T]`` (``Cov(B(s), B(t)) = q2 s (T - t) / T`` for ``s <= t``), ``0 <= a <= b <= T``::

        V = (q2 / T) int_a^b (T - t)(t^2 - a^2) dt
          = (q2 / T) [T (b^3 - a^3) / 3 - (b^4 - a^4) / 4 - T a^2 (b - a) + a^2 (b^2 - a^2) / 2]
    """
    if T <= 0 or q2 <= 0:
        return 0.0
    val = (
        T * (b**3 - a**3) / 3.0
        - (b**4 - a**4) / 4.0
        - T * a * a * (b - a)
        + a * a * (b * b - a * a) / 2.0
    )
    return max(q2 * val / T, 0.0)


def walk_variance(knots: BiasKnots, q2: float, t_a: float, t_b: float) -> float:
    """Variance (rad^2) of ``int_{t_a}^{t_b}`` of the bias walk about the knots' line.

    Inside the knots: the bridges of the knot intervals that ``[t_a, t_b]`` overlaps
    (independent).  Beyond an end knot the walk grows from it: with ``u`` the distance
    to that knot, ``Var int_{u0}^{u1} W = (u1^3 - u0^3) / 3 - u0^2 (u1 - u0)``.
    """
    if q2 <= 0 or knots.size == 0:
        return 0.0
    tau = knots.tau
    var = 0.0
    for i in range(tau.size - 1):
        a, b = max(t_a, tau[i]), min(t_b, tau[i + 1])
        if b > a:
            var += bridge_integral_variance(tau[i + 1] - tau[i], a - tau[i], b - tau[i], q2)
    for edge, lo, hi in ((tau[0], t_a, min(t_b, tau[0])), (tau[-1], max(t_a, tau[-1]), t_b)):
        if hi > lo:
            u0, u1 = sorted((abs(lo - edge), abs(hi - edge)))
            var += q2 * ((u1**3 - u0**3) / 3.0 - u0 * u0 * (u1 - u0))
    return var
