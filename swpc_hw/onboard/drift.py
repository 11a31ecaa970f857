"""Calibration suspect: drift of the wheel radii and homing errors seen while the robot works.

A passive observer of the onboard odometry (:mod:`swpc_hw.onboard.odometry`): from the readings of
normal driving it keeps a running estimate, per module, of how far the robot's true wheel
radius ``r`` and homing error ``beta`` are from the kinematic file's, and raises a
*calibration suspect* when one is both significant and large enough to matter.

Signature of a parameter error.  The odometry's residual of module i is
``e_i = v + omega x Q_i - g_i`` (m/s, docs of :mod:`swpc_hw.onboard.odometry`).  With the true
twist, a file whose radius is short of the truth by ``dr_i = r_true - r_file`` and whose
homing error is short by ``dbeta_i = beta_true - beta_file`` leaves, to first order::

    e_i h = dr_i * (dpsi_i / s_i) u_i  +  dbeta_i * rot90(c_i) h
          = dr_i * phi_r,i  +  dbeta_i * phi_beta,i                       (m)

with ``u_i`` the mid-step rolling direction, ``c_i = v + omega x P_s,i`` the velocity of
the steering axis and ``rot90(x, y) = (-y, x)``: a radius error lies along the rolling
direction, proportional to the wheel's turn; a homing error across the steering axis's
velocity, proportional to its travel.  (The beta term: moving the direction by ``dbeta``
moves ``g`` by ``dbeta (a n - b theta_dot u)`` and the contact point ``Q`` by
``b dbeta n``; together ``dbeta ((c . n) u - (c . u) n) = dbeta rot90(c)``.)

The twist is not the truth: the odometry solved it by weighted least squares over all
modules, the faulty one included, so the stacked residual (2N) is the regressors seen
through the weighted residual maker ``I - H`` (``H = A (A^T W A)^-1 A^T W`` the hat matrix
of the rigid-twist fit, weights the odometry's IRLS weights)::

    y = sum_steps e h = (I - H) Phi p + noise,     p = (dr_1, dbeta_1, ..., dr_N, dbeta_N)

Regressing ``e`` on ``Phi`` alone would pull the estimate towards zero (the twist has
absorbed part of the error); regressing on ``M = (I - H) Phi`` does not.  ``(I - H) x`` is
``x`` minus the rigid field ``v + omega x Q`` fitted to it with the same weights
(:func:`residual_maker`).

Blocks.  Steps are summed into blocks of about ``block_length`` metres of mean wheel
travel (or ``block_turn`` rad of steering): the encoder quantization, which differentiates
into large per-step residuals, telescopes in the sum; ``H`` is taken at the block's mean
contact points and weights.  A block in which the odometry saw a wheel slip (an IRLS
weight below ``slip_weight``) is dropped.

Estimate (recursive least squares with exponential forgetting in metres driven,
``lambda = exp(-d / window)`` for a block of ``d`` metres)::

    L <- lambda L + M^T M,   eta <- lambda eta + M^T y,   Y <- lambda Y + y^T y,
    k <- lambda k + 1                                              (effective blocks)
    p = T q,   q = (T^T L T + L0)^-1 T^T eta
    s^2 = (Y - 2 p^T eta + p^T L p) / (k (2N - 3) - (2N - 1)),   Cov p = s^2 T (T^T L T + L0)^-1 T^T

(``L0`` a ridge of 1e-9 of the diagonal, for the directions no motion observes; the noise
scale ``s^2`` is measured from the residuals, not assumed.)

Observability.  Every radius scaled by the same factor (``dr_i = t r_i``: the direction
``G``) is, for settled casters, the rigid motion scaled: the odometry cannot see it (only
the reference measurements of a check run can).  Worse, ``t = -1`` (every radius zero)
"explains" any residual, since ``M G ~ (I - H) sum g h = -y``: the estimate is kept out of
that direction (``T``: an orthonormal basis of the complement of ``G``).  Radii are
reported relative to the modules' median: ``e_i = dr_i / r_i``,
``r-estimate_i = r_i (e_i - median_j e_j)``, a linear
contrast ``c_i^T p`` given the order of the ``e_j`` (the median is one of them, or the mean
of the middle two), with std ``sqrt(c_i^T Cov c_i)``; one wheel off shows on that wheel
alone.  The homing errors are reported as they are: a common shift of all betas shows only
when the robot turns, and until it has turned enough their std stays large and nothing is
flagged.

Detector.  A parameter of a module is *suspect* while ``|estimate| > z_on * std`` and
``|estimate| > min_r`` (or ``min_beta``); it is raised after ``hold`` metres suspect in a
row and cleared after ``hold`` metres with ``|estimate| < z_off * std`` or below the size.
Nothing is judged before ``min_blocks`` effective blocks.  The evidence
(:class:`Suspect`): module id, parameter, estimate, its std, metres driven since the
estimate started.

Pure numpy / floats; no clock: distance, not time, drives it.
"""

from __future__ import annotations

import functools
import math
from array import array
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from swpc_hw.errors import SwpcError
from swpc_hw.onboard.odometry import (
    Odometry,
    OdometryError,
    OdometryStep,
    _contact_velocities,
    _Geometry,
)
from swpc_hw.robot.model import RobotParams

FloatArray = NDArray[np.float64]
Parameter = Literal["r", "beta"]
Rows = Sequence[tuple[float, float, float, float, float, float]]

_PI = math.pi
_TWO_PI = 2.0 * math.pi


class DriftError(SwpcError, ValueError):
    """Drift options out of range, or readings that do not match the monitored robot."""


@dataclass(frozen=True)
class DriftOptions:
    """Knobs of the drift estimate and its detector (SI units; module docstring).

    ``min_r`` 0.15 mm and ``min_beta`` 0.15 deg: what one module's error costs the odometry
    (docs/odometry.md, "Calibration suspect"); ``z_on`` 5 sigmas to raise, ``z_off`` 3 to
    clear; ``hold`` metres in a row before either.
    """

    block_length: float = 0.25
    block_turn: float = 0.1
    window: float = 300.0
    slip_weight: float = 0.5
    z_on: float = 5.0
    z_off: float = 3.0
    min_r: float = 0.15e-3
    min_beta: float = math.radians(0.15)
    hold: float = 10.0
    min_blocks: float = 100.0

    def __post_init__(self) -> None:
        if not (
            self.block_length > 0.0 and self.block_turn > 0.0 and self.window > 0.0
            and 0.0 <= self.slip_weight <= 1.0 and self.z_on >= self.z_off > 0.0
            and self.min_r >= 0.0 and self.min_beta >= 0.0 and self.hold >= 0.0
            and self.min_blocks >= 1.0
        ):
            raise DriftError(
                "drift: need block_length, block_turn, window > 0, slip_weight in [0, 1], "
                "z_on >= z_off > 0, min_r, min_beta, hold >= 0, min_blocks >= 1"
            )


@dataclass(frozen=True)
class DriftEstimate:
    """One module's running estimate: ``r`` (m, relative to the modules' median) and
    ``beta`` (rad), truth minus file, with their std."""

    module: int
    r: float
    r_std: float
    beta: float
    beta_std: float


@dataclass(frozen=True)
class Suspect:
    """The evidence of a calibration suspect (SI units)."""

    module: int
    parameter: Parameter
    estimate: float
    std: float
    metres: float  # driven since the estimate started

    def fields(self) -> dict[str, object]:
        """The log line's fields, in millimetres and degrees (human-facing)."""
        scale, unit = (1e3, "mm") if self.parameter == "r" else (180.0 / math.pi, "deg")
        return {
            "module": self.module,
            "parameter": self.parameter,
            f"estimate_{unit}": round(self.estimate * scale, 4),
            f"std_{unit}": round(self.std * scale, 4),
            "metres": round(self.metres, 1),
        }


@dataclass(frozen=True)
class SuspectChange:
    """A suspect raised (``raised=True``) or cleared, with its evidence at that moment."""

    raised: bool
    suspect: Suspect


# --------------------------------------------------------------------------- pure maths


def residual_maker(
    Qx: Sequence[float], Qy: Sequence[float], w: Sequence[float], columns: FloatArray
) -> FloatArray:
    """``(I - H) X`` for each column of ``X`` (2N x K, rows x_0, y_0, x_1, ...): the column
    minus the rigid field ``v + omega x Q_i`` fitted to it by weighted least squares.

    All columns at once, in the closed form of the odometry's weighted solve
    (:mod:`swpc_hw.onboard.odometry`: ``W = sum w``, ``X = sum w Q_x``, ``Y = sum w Q_y``,
    ``S = sum w |Q|^2``, per column ``G = sum w c``, ``T = sum w (Q x c)``)::

        omega = (T + (Y G_x - X G_y) / W) / (S - (X^2 + Y^2) / W)
        v_x   = (G_x + omega Y) / W,        v_y = (G_y - omega X) / W
    """
    out = np.array(columns, dtype=np.float64)
    W = X = Y = S = 0.0
    for wi, qx, qy in zip(w, Qx, Qy, strict=True):
        W += wi
        X += wi * qx
        Y += wi * qy
        S += wi * (qx * qx + qy * qy)
    D = S - (X * X + Y * Y) / W
    if not D > 1e-12 * S:
        raise OdometryError("odometry: the weighted contact points are degenerate")
    wv = np.asarray(w, dtype=np.float64)[:, None]
    qx_ = np.asarray(Qx, dtype=np.float64)[:, None]
    qy_ = np.asarray(Qy, dtype=np.float64)[:, None]
    cx, cy = out[0::2], out[1::2]  # (N, K) views
    Gx = (wv * cx).sum(axis=0)
    Gy = (wv * cy).sum(axis=0)
    T = (wv * (qx_ * cy - qy_ * cx)).sum(axis=0)
    om = (T + (Y * Gx - X * Gy) / W) / D
    vx = (Gx + om * Y) / W
    vy = (Gy - om * X) / W
    cx -= vx - om * qy_
    cy -= vy + om * qx_
    return out


def median_contrast(eps: FloatArray, i: int) -> FloatArray:
    """Weights ``c`` with ``c . eps = eps_i - median(eps)`` for this order of ``eps``."""
    c = -_median_weights(eps)
    c[i] += 1.0
    return c


def _median_weights(eps: FloatArray) -> FloatArray:
    """Weights ``m`` with ``m . eps = median(eps)`` for this order of ``eps``."""
    n = eps.size
    order = np.argsort(eps, kind="stable")
    m = np.zeros(n)
    if n % 2:
        m[order[n // 2]] = 1.0
    else:
        m[order[n // 2 - 1]] = 0.5
        m[order[n // 2]] = 0.5
    return m


def gauge_complement(radii: Sequence[float]) -> FloatArray:
    """``T`` (2N x 2N-1): an orthonormal basis of the parameters orthogonal to the common
    radius scale ``G`` (``G_r,i = r_i``, ``G_beta,i = 0``)."""
    return _gauge_complement(tuple(float(r) for r in radii)).copy()


@functools.lru_cache(maxsize=16)
def _gauge_complement(radii: tuple[float, ...]) -> FloatArray:
    """:func:`gauge_complement`, made once per set of radii (read-only)."""
    m = 2 * len(radii)
    G = np.zeros(m)
    G[0::2] = radii
    Q, _ = np.linalg.qr(np.column_stack([G / np.linalg.norm(G), np.eye(m)]))
    T = np.ascontiguousarray(Q[:, 1:m], dtype=np.float64)
    T.setflags(write=False)
    return T


def drift_estimates(
    ids: Sequence[int], radii: Sequence[float], L: FloatArray, eta: FloatArray, Y: float,
    k: float,
) -> tuple[list[DriftEstimate], float]:
    """The estimates of all modules from the accumulated information (module docstring),
    and the noise scale ``s^2`` (m^2 per block component)."""
    n = len(ids)
    m = 2 * n
    T = _gauge_complement(tuple(float(r) for r in radii))
    Lq = T.T @ L @ T
    A = Lq + np.diag(1e-9 * np.diag(Lq) + 1e-300)
    Ainv = np.linalg.inv(A)
    p = T @ (Ainv @ (T.T @ eta))
    dof = k * (m - 3) - (m - 1)
    rss = max(Y - 2.0 * float(p @ eta) + float(p @ L @ p), 0.0)
    s2 = rss / dof if dof > 0.0 else math.inf
    cov = s2 * (T @ Ainv @ T.T)
    r = np.asarray(radii, dtype=np.float64)
    eps = p[0::2] / r
    # row i: the contrast of module i (median_contrast) on p, r_i (dr_j / r_j) c_j
    C = np.zeros((n, m))
    C[:, 0::2] = (np.eye(n) - _median_weights(eps)) * (r[:, None] / r)
    est_r = C @ p
    var_r = ((C @ cov) * C).sum(axis=1)
    var_b = np.diagonal(cov)[1::2]
    out = [
        DriftEstimate(
            module=int(ids[i]), r=float(est_r[i]), r_std=math.sqrt(max(float(var_r[i]), 0.0)),
            beta=float(p[2 * i + 1]), beta_std=math.sqrt(max(float(var_b[i]), 0.0)),
        )
        for i in range(n)
    ]  # fmt: skip
    return out, s2


# --------------------------------------------------------------------------- runtime object


class DriftMonitor:
    """The running drift estimate and detector of one robot (module docstring).

    Feed it every odometry step: :meth:`feed` after each ``Odometry.update`` with the same
    readings, or :meth:`observe` with the step's readings and the odometry's
    :class:`~swpc_hw.onboard.odometry.OdometryStep`.  It changes nothing in the odometry.
    """

    def __init__(self, params: RobotParams, options: DriftOptions | None = None) -> None:
        self.options = options if options is not None else DriftOptions()
        geom = _Geometry.of(params)
        self.ids = geom.ids
        self._radii = tuple(row[4] for row in geom.rows)
        self._prev: tuple[float | None, list[float], list[float]] | None = None
        self.restart()

    def restart(self) -> None:
        """Forget everything (after a new kinematic file: the estimate is of the file's
        errors)."""
        n = len(self.ids)
        m = 2 * n
        self.L = np.zeros((m, m))
        self.eta = np.zeros(m)
        self.Y = 0.0
        self.k = 0.0
        self.metres = 0.0
        self.blocks = 0
        self.dropped = 0
        self.estimates: list[DriftEstimate] = []
        self.noise = math.inf
        self.suspects: dict[tuple[int, Parameter], Suspect] = {}
        self._run: dict[tuple[int, Parameter], float] = {}  # metres in a row of the other state
        self._new_block()

    def _new_block(self) -> None:
        # the block's steps, flat in step order: dt and the twist (v_x, v_y, omega) of
        # each, and per module its contact point, encoder velocity, weight and rows
        self._dt = array("d")
        self._tw = array("d")
        self._qx = array("d")
        self._qy = array("d")
        self._gx = array("d")
        self._gy = array("d")
        self._w = array("d")
        self._rows: list[Rows] = []
        self._travel = 0.0
        self._turn = 0.0
        self._slip = False

    # ------------------------------------------------------------------ feeding

    def feed(self, odometry: Odometry, theta_hat: Sequence[float] | FloatArray,
             psi: Sequence[float] | FloatArray) -> list[SuspectChange]:
        """After ``odometry.update(t, theta_hat, psi)``: observe that step (the first
        reading only stores).  Returns the suspects raised or cleared by it."""
        last = odometry._last
        th = list(map(float, theta_hat))
        ps = list(map(float, psi))
        prev = self._prev
        self._prev = (odometry.t, th, ps)
        if (last is None or prev is None or prev[0] is None or last[0] != odometry.t
                or not math.isclose(last[0] - last[1], prev[0], rel_tol=0.0, abs_tol=1e-9)):
            return []  # the odometry only stored this reading, or we missed the last one
        _t, dt, sol = last
        rows = odometry.rows
        n = len(self.ids)
        if len(rows) != n or len(sol.weights) != n:
            raise DriftError(f"drift: expected {n} modules (got {len(rows)})")
        Qx, Qy, gx, gy = sol.contacts  # the odometry's own, of these readings
        if len(Qx) != n:
            Qx, Qy, gx, gy, _ = _contact_velocities(rows, dt, prev[1], th, prev[2], ps)
        return self._step(rows, dt, prev[1], th, Qx, Qy, gx, gy, sol.twist, sol.weights)

    def observe(self, rows: Rows, theta_hat0: Sequence[float], theta_hat1: Sequence[float],
                psi0: Sequence[float], psi1: Sequence[float],
                step: OdometryStep) -> list[SuspectChange]:
        """One odometry step: its readings before and after and the odometry's result."""
        n = len(self.ids)
        if len(rows) != n or len(step.weights) != n:
            raise DriftError(f"drift: expected {n} modules (got {len(rows)})")
        Qx, Qy, gx, gy, _ = _contact_velocities(
            rows, step.dt, theta_hat0, theta_hat1, psi0, psi1)
        return self._step(rows, step.dt, theta_hat0, theta_hat1, Qx, Qy, gx, gy, step.twist,
                          step.weights)

    def _step(self, rows: Rows, dt: float, theta_hat0: Sequence[float],
              theta_hat1: Sequence[float], Qx: Sequence[float], Qy: Sequence[float],
              gx: Sequence[float], gy: Sequence[float], twist: Sequence[float],
              weights: Sequence[float]) -> list[SuspectChange]:
        """Take one step into the block: kept as it is (the block's sums are made when it
        closes, :meth:`_close_block`); here only what decides the block's end, the mean
        wheel travel ``mean_i |g_i| h`` and the largest steering turn, and the slip."""
        n = len(Qx)
        travel = 0.0
        turn = 0.0
        hypot = math.hypot
        for gxi, gyi, th1, th0 in zip(gx, gy, theta_hat1, theta_hat0, strict=False):
            travel += hypot(gxi, gyi) * dt
            dth = th1 - th0
            if dth > _PI:
                dth -= _TWO_PI
            elif dth <= -_PI:
                dth += _TWO_PI
            if dth < 0.0:
                dth = -dth
            if dth > turn:
                turn = dth
        if min(weights) < self.options.slip_weight:
            self._slip = True
        self._dt.append(dt)
        self._tw.extend(twist)
        self._qx.extend(Qx)
        self._qy.extend(Qy)
        self._gx.extend(gx)
        self._gy.extend(gy)
        self._w.extend(weights)
        self._rows.append(rows)
        self._travel += travel / n
        self._turn += turn
        if self._travel < self.options.block_length and self._turn < self.options.block_turn:
            return []
        return self._close_block()

    # ------------------------------------------------------------------ blocks

    def _block_sums(self) -> tuple[FloatArray, FloatArray, FloatArray, list[float],
                                   list[float], list[float]]:
        """The block's sums over its ``K`` steps (module docstring; per module i, step
        ``h``, twist ``(v, omega)``, contact point ``Q``, encoder velocity ``g``)::

            y_i      = sum (v + omega x Q_i - g_i) h                (the residual, m)
            phi_r,i  = sum (g_i . u_i) h / r_i  u_i,   u_i = (Q_i - P_s,i) / |Q_i - P_s,i|
            phi_b,i  = sum rot90(v + omega x P_s,i) h

        as flat vectors (x_0, y_0, x_1, ...), and the mean contact points and weights."""
        k = len(self._dt)
        n = len(self.ids)
        h = np.frombuffer(self._dt)[:, None]
        tw = np.frombuffer(self._tw).reshape(k, 3)
        vx, vy, om = tw[:, 0:1], tw[:, 1:2], tw[:, 2:3]
        qx, qy, gx, gy, w = (
            np.frombuffer(a).reshape(k, n) for a in (self._qx, self._qy, self._gx, self._gy,
                                                     self._w))
        first = self._rows[0]
        same = all(r is first for r in self._rows)
        R = np.array(first if same else self._rows, dtype=np.float64)  # (N, 6) or (K, N, 6)
        xs, ys, r = R[..., 0], R[..., 1], R[..., 4]
        y = np.empty(2 * n)
        y[0::2] = ((vx - om * qy - gx) * h).sum(axis=0)
        y[1::2] = ((vy + om * qx - gy) * h).sum(axis=0)
        ux = qx - xs
        uy = qy - ys
        nu = np.hypot(ux, uy)
        ux /= nu
        uy /= nu
        rho = (gx * ux + gy * uy) * h / r  # dpsi / s
        fr = np.empty(2 * n)
        fr[0::2] = (rho * ux).sum(axis=0)
        fr[1::2] = (rho * uy).sum(axis=0)
        fb = np.empty(2 * n)  # rot90(c) h, c = v + omega x P_s
        fb[0::2] = -((vy + om * xs) * h).sum(axis=0)
        fb[1::2] = ((vx - om * ys) * h).sum(axis=0)
        Qx = (qx.sum(axis=0) / k).tolist()
        Qy = (qy.sum(axis=0) / k).tolist()
        wm = (w.sum(axis=0) / k).tolist()
        return y, fr, fb, Qx, Qy, wm

    def _close_block(self) -> list[SuspectChange]:
        o = self.options
        n = len(self.ids)
        d = self._travel
        self.metres += d
        if self._slip:
            self.dropped += 1
            self._new_block()
            return self._judge(d)
        yv, fr, fb, Qx, Qy, w = self._block_sums()
        Phi = np.zeros((2 * n, 2 * n))
        for i in range(n):
            Phi[2 * i:2 * i + 2, 2 * i] = fr[2 * i:2 * i + 2]
            Phi[2 * i:2 * i + 2, 2 * i + 1] = fb[2 * i:2 * i + 2]
        M = residual_maker(Qx, Qy, w, Phi)
        lam = math.exp(-d / o.window)
        self.L = lam * self.L + M.T @ M
        self.eta = lam * self.eta + M.T @ yv
        self.Y = lam * self.Y + float(yv @ yv)
        self.k = lam * self.k + 1.0
        self.blocks += 1
        self._new_block()
        if self.k >= o.min_blocks:
            self.estimates, self.noise = drift_estimates(
                self.ids, self._radii, self.L, self.eta, self.Y, self.k)
        return self._judge(d)

    def _judge(self, d: float) -> list[SuspectChange]:
        """Advance the detector by a block of ``d`` metres (module docstring)."""
        o = self.options
        changes: list[SuspectChange] = []
        for e in self.estimates:
            checks: tuple[tuple[Parameter, float, float, float], ...] = (
                ("r", e.r, e.r_std, o.min_r), ("beta", e.beta, e.beta_std, o.min_beta))
            for par, est, std, size in checks:
                key = (e.module, par)
                ev = Suspect(e.module, par, est, std, self.metres)
                raised = key in self.suspects
                if raised:
                    other = abs(est) < o.z_off * std or abs(est) < size
                else:
                    other = abs(est) > o.z_on * std and abs(est) > size
                run = self._run.get(key, 0.0) + d if other else 0.0
                if other and run >= o.hold:
                    run = 0.0
                    if raised:
                        del self.suspects[key]
                    else:
                        self.suspects[key] = ev
                    changes.append(SuspectChange(not raised, ev))
                elif raised:
                    self.suspects[key] = ev  # the latest evidence
                self._run[key] = run
        return changes


__all__ = [
    "DriftError",
    "DriftEstimate",
    "DriftMonitor",
    "DriftOptions",
    "Suspect",
    "SuspectChange",
    "drift_estimates",
    "gauge_complement",
    "median_contrast",
    "residual_maker",
]
