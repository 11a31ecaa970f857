"""Onboard odometry: integrate steering and wheel encoders of all modules into the robot pose.

Model (docs/model-and-frames.md), per module i with true steering ``theta = theta_hat + beta``,
``u = (cos theta, sin theta)``, ``n = (sin theta, -cos theta)``, ``c = v + omega x P_s``::

    v + omega x P_w = r psi_dot u + b theta_dot n          (P_w = P_s + b u)
    <=>   c . u = r psi_dot,      c . n = b (theta_dot + omega)

Discrete step.  Between two readings (``t0 -> t1``, ``h = t1 - t0``) we know only the
increments ``dtheta = theta_hat1 - theta_hat0`` (wrapped to (-pi, pi]) and
``dpsi = psi1 - psi0``.  For a twist that is constant over the step the constraints
integrate exactly to::

    h c . M = r dpsi,      h c . M_perp = b (dtheta + omega h),
    M = (1/h) int u(theta(t)) dt   (mean rolling direction),  M_perp = (M_y, -M_x)

and with constant twist the steering obeys ``b theta_ddot = r psi_dot theta_dot``.  The
mean direction is therefore, to fourth order in the step,
``M = s u(theta_e)`` with::

    s       = sinc(dtheta / 2) = sin(dtheta / 2) / (dtheta / 2)
    theta_e = theta_hat0 + dtheta / 2 + beta - r dpsi dtheta / (12 b)

(the midpoint angle, corrected by the steering curvature).  Dividing by ``s`` gives the
model of docs/model-and-frames.md at an *effective* contact point ``Q``::

    v + omega x Q_i = g_i,     Q_i = P_s,i + (b_i / s_i) u(theta_e,i),
                               g_i = (r_i dpsi_i u(theta_e,i) + b_i dtheta_i n(theta_e,i)) / (s_i h)

which reduces to ``forward_kinematics`` at the midpoint angle when ``dtheta -> 0``.

Least squares over all modules with per-module weights ``w_i`` (normal equations solved in
closed form; ``W = sum w``, ``X = sum w Q_x``, ``Y = sum w Q_y``, ``S = sum w |Q|^2``,
``G = sum w g``, ``T = sum w (Q x g)``)::

    omega = (T + (Y G_x - X G_y) / W) / (S - (X^2 + Y^2) / W)
    v_x   = (G_x + omega Y) / W,        v_y = (G_y - omega X) / W

Residual of module i (m/s): ``e_i = v + omega x Q_i - g_i``.  Iteratively reweighted (IRLS)
so that one slipping wheel does not drag the estimate: the weights come from the low-passed
residual vectors ``f_i = alpha e_i + (1 - alpha) f_i,prev`` (``alpha = 1 - exp(-h / tau)``,
tau = ``slip_time_constant``; |f_i| is the reported slip indicator) through the Geman-McClure
weight ``w = 1 / (1 + z^2)^2``, ``z = |f_i| / sigma`` (or Cauchy ``1 / (1 + z^2)``, Huber
``min(1, 1 / z)``), ``sigma = scale_abs + scale_rel * rms_i |g_i|``.  Filtering matters:
encoder quantization differentiates into large zero-mean per-step residuals; weights that
followed them would break the telescoping of quantization errors and bias the pose, while a
slipping wheel's residual persists.

Pose: exact SE(2) exponential of the step twist (not Euler on yaw)::

    dyaw = omega h
    [dx, dy]_R = h [[A, -B], [B, A]] [v_x, v_y],   A = sin(dyaw) / dyaw,  B = (1 - cos dyaw) / dyaw
    p_W += R(yaw) [dx, dy]_R,  yaw += dyaw            (yaw continuous, not wrapped)

The update hot path uses plain Python floats (4 modules: 8-17 us per update on one core,
``python -m benchmarks odometry``).

Importing this module pulls numpy, yaml and pydantic (through :mod:`swpc_hw.robot.model`), never
FastAPI, zenoh or scipy.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, NamedTuple

import numpy as np
from numpy.typing import NDArray

from swpc_hw.errors import SwpcError
from swpc_hw.files.kinematic_file import load_kinematics
from swpc_hw.robot.model import RobotParams

FloatArray = NDArray[np.float64]
Robust = Literal["cauchy", "geman", "huber", "none"]

_PI = math.pi
_TWO_PI = 2.0 * math.pi


class OdometryError(SwpcError, ValueError):
    """Odometry input is inconsistent (wrong module count, non-finite value, time not increasing),
    or a reloaded kinematic file does not match the running robot."""


class Pose(NamedTuple):
    """Planar pose of R in W (m, m, rad); yaw is continuous (not wrapped)."""

    x: float
    y: float
    yaw: float


@dataclass(frozen=True)
class OdometryStep:
    """Diagnostics of the last update.

    ``twist``: (v_x, v_y, omega) in R (m/s, m/s, rad/s); ``residuals``: per-module |e_i| of
    this step (m/s); ``filtered_residuals``: their low-passed norms |f_i| (m/s, the slip
    indicator); ``weights``: final IRLS weights (1 = trusted, -> 0 = slipping);
    ``sigma``: the residual scale used (m/s); ``iterations``: least-squares solves.
    """

    t: float
    dt: float
    twist: tuple[float, float, float]
    residuals: tuple[float, ...]
    filtered_residuals: tuple[float, ...]
    weights: tuple[float, ...]
    sigma: float
    iterations: int


Row = tuple[float, float, float, float, float, float]
"""One module for the hot path: ``x_s, y_s, beta, b, r`` and ``r / (12 b)``."""


def geometry_row(x_s: float, y_s: float, beta: float, b: float, r: float) -> Row:
    """A module's :data:`Row`: its five parameters and the steering curvature's factor
    ``r / (12 b)`` of ``theta_e`` (module docstring)."""
    return (x_s, y_s, beta, b, r, r / (12.0 * b))


@dataclass(frozen=True)
class _Geometry:
    """Parameters as plain float tuples, in module (file) order, for the hot path."""

    params: RobotParams
    ids: tuple[int, ...]
    rows: tuple[Row, ...]

    @classmethod
    def of(cls, params: RobotParams) -> _Geometry:
        rows = tuple(
            geometry_row(float(m.x_s), float(m.y_s), float(m.beta), float(m.b), float(m.r))
            for m in params.modules
        )
        return cls(params=params, ids=tuple(params.ids), rows=rows)


# --------------------------------------------------------------------------- pure maths


def se2_exp_step(pose: tuple[float, float, float], vx: float, vy: float, omega: float,
                 dt: float) -> Pose:
    """Compose ``pose`` with the exact SE(2) motion of the body twist (v_x, v_y, omega) over dt.

    ``dyaw = omega dt``; body displacement ``dt [[A, -B], [B, A]] v`` with
    ``A = sin(dyaw)/dyaw``, ``B = (1 - cos dyaw)/dyaw`` (series below 1e-4 rad); world
    ``p += R(yaw) d``, ``yaw += dyaw``.
    """
    x, y, yaw = pose
    phi = omega * dt
    if abs(phi) < 1e-4:
        p2 = phi * phi
        A = 1.0 - p2 / 6.0 + p2 * p2 / 120.0
        B = phi * (0.5 - p2 / 24.0)
    else:
        A = math.sin(phi) / phi
        B = (1.0 - math.cos(phi)) / phi
    dxb = (A * vx - B * vy) * dt
    dyb = (B * vx + A * vy) * dt
    c, s = math.cos(yaw), math.sin(yaw)
    return Pose(x + c * dxb - s * dyb, y + s * dxb + c * dyb, yaw + phi)


class StepSolution(NamedTuple):
    """Result of :func:`step_twist`."""

    twist: tuple[float, float, float]  # (v_x, v_y, omega) in R
    residuals: list[float]  # per-module |e_i| of this step, m/s
    filtered: list[float]  # low-passed residual vectors, flat (ex_0, ey_0, ex_1, ...), m/s
    weights: list[float]  # IRLS weights that produced ``twist``
    sigma: float  # residual scale, m/s
    iterations: int  # least-squares solves
    contacts: tuple[list[float], list[float], list[float], list[float]] = ([], [], [], [])
    """``(Qx, Qy, gx, gy)`` of the step (:func:`_contact_velocities`), for the observers
    of the odometry (drift monitor) not to compute them again."""


def _contact_velocities(
    rows: Sequence[tuple[float, float, float, float, float, float]],
    dt: float,
    theta_hat0: Sequence[float] | FloatArray,
    theta_hat1: Sequence[float] | FloatArray,
    psi0: Sequence[float] | FloatArray,
    psi1: Sequence[float] | FloatArray,
) -> tuple[list[float], list[float], list[float], list[float], float]:
    """Each wheel's mid-step contact point ``Q_i`` and the velocity ``g_i`` its encoders say
    it had (module docstring): ``(Qx, Qy, gx, gy, sum |g_i|^2)``."""
    n = len(rows)
    Qx = [0.0] * n
    Qy = [0.0] * n
    gx = [0.0] * n
    gy = [0.0] * n
    inv_dt = 1.0 / dt
    g2 = 0.0
    for i in range(n):
        x_s, y_s, beta, b, r, k12 = rows[i]
        th0 = theta_hat0[i]
        dth = theta_hat1[i] - th0
        if dth > _PI:
            dth -= _TWO_PI
        elif dth <= -_PI:
            dth += _TWO_PI
        dps = psi1[i] - psi0[i]
        half = 0.5 * dth
        s = 1.0 - half * half / 6.0 if abs(half) < 1e-4 else math.sin(half) / half
        th = th0 + half + beta - k12 * dps * dth
        cu = math.cos(th)
        su = math.sin(th)
        bs = b / s
        Qx[i] = x_s + bs * cu
        Qy[i] = y_s + bs * su
        a = r * dps * inv_dt / s
        c = bs * dth * inv_dt
        # g = a u + c n,  n = (sin, -cos)
        gxi = a * cu + c * su
        gyi = a * su - c * cu
        gx[i] = gxi
        gy[i] = gyi
        g2 += gxi * gxi + gyi * gyi
    return Qx, Qy, gx, gy, g2


def _weighted_twist(
    w: Sequence[float], Qx: list[float], Qy: list[float], gx: list[float], gy: list[float]
) -> tuple[float, float, float]:
    """The twist ``(vx, vy, omega)`` of weighted least squares over the contact points:
    ``min sum w_i |v + omega x Q_i - g_i|^2`` in closed form."""
    W = X = Y = S = Gx = Gy = T = 0.0
    for i in range(len(w)):
        wi = w[i]
        qx = Qx[i]
        qy = Qy[i]
        W += wi
        X += wi * qx
        Y += wi * qy
        S += wi * (qx * qx + qy * qy)
        Gx += wi * gx[i]
        Gy += wi * gy[i]
        T += wi * (qx * gy[i] - qy * gx[i])
    D = S - (X * X + Y * Y) / W
    if not D > 1e-12 * S:
        raise OdometryError("odometry: the weighted contact points are degenerate")
    om = (T + (Y * Gx - X * Gy) / W) / D
    return (Gx + om * Y) / W, (Gy - om * X) / W, om


def robust_weight(robust: Robust, z2: float) -> float:
    """The IRLS weight of a residual of squared size ``z2`` (in sigmas^2)."""
    if robust == "geman":
        wn = 1.0 / (1.0 + z2)
        return wn * wn
    if robust == "cauchy":
        return 1.0 / (1.0 + z2)
    if robust == "huber":  # threshold 1 sigma
        return 1.0 if z2 <= 1.0 else 1.0 / math.sqrt(z2)
    return 1.0


def step_twist(
    rows: Sequence[tuple[float, float, float, float, float, float]],
    dt: float,
    theta_hat0: Sequence[float] | FloatArray,
    theta_hat1: Sequence[float] | FloatArray,
    psi0: Sequence[float] | FloatArray,
    psi1: Sequence[float] | FloatArray,
    *,
    robust: Robust = "geman",
    scale_abs: float = 0.003,
    scale_rel: float = 0.02,
    max_iterations: int = 8,
    alpha: float = 1.0,
    filtered: Sequence[float] | None = None,
) -> StepSolution:
    """Robust least-squares twist of one step (equations in the module docstring).

    ``rows[i] = (x_s, y_s, beta, b, r, r / (12 b))``.  The IRLS weights are computed from the
    low-passed residual vectors ``f_i = alpha e_i + (1 - alpha) f_i,prev`` (``filtered`` holds
    ``f_prev``; ``alpha = 1``: this step's residuals only), so that encoder quantization noise,
    which differentiates into large but zero-mean per-step residuals, does not modulate the
    weights while a persistent slip does.
    """
    n = len(rows)
    Qx, Qy, gx, gy, g2 = _contact_velocities(rows, dt, theta_hat0, theta_hat1, psi0, psi1)
    sigma = scale_abs + scale_rel * math.sqrt(g2 / n)
    inv_sigma = 1.0 / sigma
    keep = 1.0 - alpha
    prev = filtered if filtered is not None else [0.0] * (2 * n)
    filt = [0.0] * (2 * n)
    w = [1.0] * n
    wn_all = [1.0] * n
    res = [0.0] * n
    iterations = 0
    plain = robust == "none"
    geman = robust == "geman"
    sqrt = math.sqrt
    while True:
        iterations += 1
        vx, vy, om = _weighted_twist(w, Qx, Qy, gx, gy)
        change = 0.0
        for i in range(n):
            ex = vx - om * Qy[i] - gx[i]
            ey = vy + om * Qx[i] - gy[i]
            res[i] = sqrt(ex * ex + ey * ey)
            fx = alpha * ex + keep * prev[2 * i]
            fy = alpha * ey + keep * prev[2 * i + 1]
            filt[2 * i] = fx
            filt[2 * i + 1] = fy
            if plain:
                continue
            z2 = (fx * fx + fy * fy) * inv_sigma * inv_sigma
            if geman:  # robust_weight("geman", z2), inline on the hot path
                wn = 1.0 / (1.0 + z2)
                wn = wn * wn
            else:
                wn = robust_weight(robust, z2)
            d = abs(wn - w[i])
            if d > change:
                change = d
            wn_all[i] = wn
        if plain or change < 1e-4 or iterations >= max_iterations:
            break  # ``w`` (reported) are the weights that produced the twist
        w, wn_all = wn_all, w
    return StepSolution((vx, vy, om), res, filt, w, sigma, iterations, (Qx, Qy, gx, gy))


# --------------------------------------------------------------------------- runtime object


def file_signature(path: Path) -> tuple[int, int, int] | None:
    """``(mtime ns, size, inode)`` of a file, None if it cannot be read: a new kinematic
    file installed by an atomic rename changes the inode."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return (st.st_mtime_ns, st.st_size, st.st_ino)


@dataclass(frozen=True)
class OdometryOptions:
    """Tuning of the robust step solve (defaults suit 4 modules at 100-1000 Hz feedback).

    ``robust``: weight function of the filtered residual ``z = |f_i| / sigma`` — ``geman``
    (Geman-McClure, ``1/(1+z^2)^2``, default: a slipping wheel's pull vanishes), ``cauchy``
    (``1/(1+z^2)``), ``huber`` (``min(1, 1/z)``) or ``none`` (plain least squares).
    ``sigma = scale_abs + scale_rel * rms_i |g_i|`` (m/s).  ``slip_time_constant`` (s): time
    constant of the first-order low-pass on the residual vectors that drive the weights
    (``alpha = 1 - exp(-dt / tau)``; 0 = per-step residuals).
    """

    robust: Robust = "geman"
    scale_abs: float = 0.003
    scale_rel: float = 0.02
    max_iterations: int = 8
    slip_time_constant: float = 0.05

    def __post_init__(self) -> None:
        if self.robust not in ("cauchy", "geman", "huber", "none"):
            raise OdometryError(
                f"odometry: robust must be geman, cauchy, huber or none (got {self.robust!r})"
            )
        if not (
            self.scale_abs > 0.0
            and self.scale_rel >= 0.0
            and self.max_iterations >= 1
            and self.slip_time_constant >= 0.0
        ):
            raise OdometryError(
                "odometry: need scale_abs > 0, scale_rel >= 0, max_iterations >= 1, "
                "slip_time_constant >= 0"
            )


class Odometry:
    """Integrates timestamped steering/wheel readings of all modules into the pose of R in W.

    Readings are given in module order (the order of ``params.modules``, i.e. the file
    order; see :attr:`ids`): ``theta_hat`` reported steering (rad, relative to homing; wrapped
    or not) and ``psi`` cumulative wheel angle (rad).  The first :meth:`update` only stores
    the readings.  :meth:`reload` swaps the parameters atomically while running.
    """

    def __init__(
        self,
        params: RobotParams,
        *,
        pose: tuple[float, float, float] = (0.0, 0.0, 0.0),
        options: OdometryOptions | None = None,
        source: str | os.PathLike[str] | None = None,
    ) -> None:
        self._geom = _Geometry.of(params)
        self.options = options if options is not None else OdometryOptions()
        self._pose = Pose(*(float(p) for p in pose))
        self._t: float | None = None
        self._th: list[float] = []
        self._ps: list[float] = []
        self._filtered: list[float] | None = None
        self._last: tuple[float, float, StepSolution] | None = None
        self._source: Path | None = Path(source) if source is not None else None
        self._signature = file_signature(self._source) if self._source is not None else None

    # ------------------------------------------------------------------ construction / reload

    @classmethod
    def from_file(
        cls,
        path: str | os.PathLike[str],
        *,
        pose: tuple[float, float, float] = (0.0, 0.0, 0.0),
        options: OdometryOptions | None = None,
    ) -> Odometry:
        """Odometry on the parameters of a kinematic file (``swpc-kinematics/1``)."""
        params = load_kinematics(path).params
        return cls(params, pose=pose, options=options, source=path)

    def reload(self, path: str | os.PathLike[str] | None = None) -> RobotParams:
        """Load a kinematic file and swap the parameters in atomically (between two updates).

        ``path`` defaults to the file the odometry was loaded from.  The new file must describe
        the same module ids in the same order.  On any error (missing, malformed, mismatched)
        raises :class:`KinematicFileError` / :class:`OdometryError` and keeps the old
        parameters.  Returns the new parameters.
        """
        p = Path(path) if path is not None else self._source
        if p is None:
            raise OdometryError("odometry: reload() needs a path (not loaded from a file)")
        sig = file_signature(p)
        params = load_kinematics(p).params
        self.set_params(params)
        self._source = p
        self._signature = sig
        return params

    def reload_if_changed(self) -> bool:
        """Reload the source file if its mtime/size/inode changed since the last (attempted) load.

        Cheap enough to call at a few Hz from the runtime loop.  A bad new file raises once
        (and the old parameters stay); the same bad file is not retried until it changes again.
        """
        if self._source is None:
            return False
        sig = file_signature(self._source)
        if sig is None or sig == self._signature:
            return False
        self._signature = sig
        params = load_kinematics(self._source).params
        self.set_params(params)
        return True

    def set_params(self, params: RobotParams) -> None:
        """Swap in new parameters (same module ids, same order); the pose is kept."""
        geom = _Geometry.of(params)
        if geom.ids != self._geom.ids:
            raise OdometryError(
                f"odometry: new parameters have module ids {list(geom.ids)}, "
                f"running robot has {list(self._geom.ids)}"
            )
        self._geom = geom  # single reference assignment: atomic for a concurrent update()

    # ------------------------------------------------------------------ state

    @property
    def params(self) -> RobotParams:
        return self._geom.params

    @property
    def ids(self) -> tuple[int, ...]:
        """Module ids in the order readings are expected."""
        return self._geom.ids

    @property
    def rows(self) -> tuple[Row, ...]:
        """The parameters of the hot path (:data:`Row`, module order), as of the last
        :meth:`set_params`."""
        return self._geom.rows

    @property
    def source(self) -> Path | None:
        return self._source

    @property
    def pose(self) -> Pose:
        return self._pose

    @property
    def t(self) -> float | None:
        """Timestamp of the last reading (None before the first)."""
        return self._t

    def reset(self, pose: tuple[float, float, float] = (0.0, 0.0, 0.0), *,
              clear_readings: bool = False) -> None:
        """Set the pose.  The last readings are kept (integration continues from the new pose)
        unless ``clear_readings`` (then the next update only stores readings, e.g. after a gap,
        and the slip filter restarts)."""
        self._pose = Pose(*(float(p) for p in pose))
        if clear_readings:
            self._t = None
            self._filtered = None
            self._last = None

    @property
    def last(self) -> OdometryStep | None:
        """Diagnostics of the last integrating update (twist, residuals, IRLS weights)."""
        if self._last is None:
            return None
        t, dt, sol = self._last
        f = sol.filtered
        return OdometryStep(
            t=t, dt=dt, twist=sol.twist, residuals=tuple(sol.residuals),
            filtered_residuals=tuple(math.hypot(f[2 * i], f[2 * i + 1])
                                     for i in range(len(sol.residuals))),
            weights=tuple(sol.weights), sigma=sol.sigma, iterations=sol.iterations,
        )

    def slipping(self, threshold: float = 0.5) -> tuple[int, ...]:
        """Ids of modules whose last IRLS weight is below ``threshold`` (likely slipping)."""
        if self._last is None:
            return ()
        w = self._last[2].weights
        return tuple(mid for mid, wi in zip(self._geom.ids, w, strict=True) if wi < threshold)

    # ------------------------------------------------------------------ update

    def update_by_id(self, t: float, readings: Mapping[int, tuple[float, float]]) -> Pose:
        """Like :meth:`update` with readings keyed by module id: ``{id: (theta_hat, psi)}``
        (e.g. one feedback frame per module from the driver, collected for one cycle)."""
        try:
            pairs = [readings[mid] for mid in self._geom.ids]
        except KeyError as exc:
            missing = exc.args[0]
            raise OdometryError(f"odometry: no reading for module {missing} at t={t!r}") from exc
        return self.update(t, [p[0] for p in pairs], [p[1] for p in pairs])

    def update(self, t: float, theta_hat: Sequence[float] | FloatArray,
               psi: Sequence[float] | FloatArray) -> Pose:
        """Consume one reading of all modules at time ``t`` (s); returns the new pose."""
        geom = self._geom
        n = len(geom.rows)
        if len(theta_hat) != n or len(psi) != n:
            raise OdometryError(
                f"odometry: expected {n} steering and wheel readings "
                f"(got {len(theta_hat)}, {len(psi)})"
            )
        th = list(map(float, theta_hat))
        ps = list(map(float, psi))
        t = float(t)
        if not (math.isfinite(t) and math.isfinite(math.fsum(th)) and math.isfinite(math.fsum(ps))):
            raise OdometryError(f"odometry: non-finite reading at t={t!r}")
        t0 = self._t
        if t0 is None:
            self._t, self._th, self._ps = t, th, ps
            return self._pose
        dt = t - t0
        if not dt > 0.0:
            raise OdometryError(f"odometry: time must increase (t={t!r} after {t0!r})")
        o = self.options
        tau = o.slip_time_constant
        sol = step_twist(
            geom.rows, dt, self._th, th, self._ps, ps, robust=o.robust,
            scale_abs=o.scale_abs, scale_rel=o.scale_rel, max_iterations=o.max_iterations,
            alpha=1.0 - math.exp(-dt / tau) if tau > 0.0 else 1.0, filtered=self._filtered,
        )
        vx, vy, om = sol.twist
        self._pose = se2_exp_step(self._pose, vx, vy, om, dt)
        self._t, self._th, self._ps = t, th, ps
        self._filtered = sol.filtered
        self._last = (t, dt, sol)
        return self._pose


__all__ = [
    "Odometry",
    "OdometryError",
    "OdometryOptions",
    "OdometryStep",
    "Pose",
    "StepSolution",
    "se2_exp_step",
    "step_twist",
]
