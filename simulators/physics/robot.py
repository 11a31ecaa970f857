"""Physics of the whole virtual robot under its drives (model of docs/model-and-frames.md).

:class:`RobotPhysics` holds the hidden *true* robot (``RobotParams``, default the paper's Table 4
calibrated values), the pose of R in W, and per module the true steering angle ``theta``
(relative to the body), the rolling wheel angle ``psi`` and the wheel angle its encoder
reads (``psi`` plus slip).  :meth:`RobotPhysics.step` advances it by ``dt`` under one
:class:`ModuleDrive` per module (what each axis' controller does, see ``simulators.virtual_robot``).

Constraint rows
---------------
With the body twist ``xi = (v_x, v_y, omega)`` in R, the no-slip constraint of module i
projected on ``u_i = u(theta_i)`` and ``n_i = n(theta_i)`` is linear in ``xi``::

    U_i . xi = r_i psi_dot_i,     U_i = (u_x, u_y, P_w,i x u_i)          (rolling)
    N_i . xi = b_i theta_dot_i,   N_i = (n_x, n_y, P_w,i x n_i)          (lateral)

(``a x b = a_x b_y - a_y b_x``).  Each axis is driven one of a few ways:

* wheel BRAKE (controller HOLD): ``U_i xi = 0`` is a **hard** row, and so is the module's
  lateral row if its steering is driven: a braked, steer-locked module pins its contact
  point to the floor (the seed's fixing tool) and the body can only pivot about it;
* wheel RATE (VELOCITY/POSITION): ``U_i xi = r psi_dot_cmd`` is a **soft** row, and so is
  the module's lateral row if its steering is driven: with every module driven, ``xi`` is
  the least-squares twist of the true model (:func:`swpc_hw.robot.model.forward_kinematics`);
  commands computed with wrong parameters leave residuals, i.e. slip and drift;
* wheel TORQUE or PASSIVE (FREE, disabled, fault): the wheel rolls without slip
  (``psi_dot = U_i xi / r_i``) and enters the body **dynamics** below;
* steering RATE (HOLD, POSITION, VELOCITY, homing): ``theta_dot`` is imposed; on a module
  whose wheel is not braked/driven, a mismatch ``N_i xi - b theta_dot`` scrubs the tyre
  sideways against a viscous lateral force;
* steering PASSIVE (FREE, disabled, fault): a free caster trails,
  ``b theta_dot = N_i xi`` (:func:`simulators.physics.core.caster_rates`).

Twist solution (:func:`prioritized_twist`): the hard rows are solved in least squares,
the soft rows in least squares within the null space of the hard ones, and the
directions still free (null space ``Z`` of both) follow a first-order dynamic with
inertia and viscous damping, integrated by implicit Euler (unconditionally stable)::

    M = M_body + sum_j J_w h_j h_j^T                      (h_j = U_j / r_j, rolling wheels)
    D(xi) = 1/2 sum_k c_k (g_k . xi - s_k)^2               (viscous rows)
    Z^T (M + dt C) Z z = Z^T M (xi_0 - xi_p) + dt Z^T (F - C xi_p + sum_k c_k s_k g_k)
    xi = xi_p + Z z,   C = sum_k c_k g_k g_k^T,   F = sum_j tau_j h_j + F_ext

with ``xi_0`` the previous twist and ``xi_p`` the hard/soft solution.  Viscous rows: each
rolling wheel (``g = U/r``, ``s = 0``, wheel damping), each steered but not held module's
tyre (``g = N``, ``s = b theta_dot``, lateral damping), each steered module's fork rotation
on the floor (``g = e_omega``, ``s = -theta_dot``, scrub damping) and the body (rolling
resistance).  ``F_ext`` is :attr:`RobotPhysics.push`, an external wrench on the body (someone
pushing the robot).  A constant wheel torque therefore gives a steady spin, and the rolling
wheels' encoder increments stay exactly those of rolling without slip:
``r dpsi = -D d(yaw)`` for a settled caster at distance ``D`` from the pivot.

Within a step the twist is constant (its rows are taken at the mid-step steering angle):
the pose advances by the exact SE(2) exponential (:func:`simulators.physics.se2_step`) and
the steering / wheel angles by classical RK4.
"""

from __future__ import annotations

import enum
import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from simulators.physics.core import FloatArray, se2_step
from swpc_hw.robot.model import (
    RobotArrays,
    RobotParams,
    contact_point,
)
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED


class WheelDrive(enum.Enum):
    PASSIVE = "passive"  # free / disabled / fault: rolls with the floor, wheel damping only
    BRAKE = "brake"  # HOLD: the wheel does not turn
    RATE = "rate"  # VELOCITY / POSITION: the motor imposes psi_dot
    TORQUE = "torque"  # TORQUE: the motor applies a torque, the wheel rolls


class SteerDrive(enum.Enum):
    PASSIVE = "passive"  # free / disabled / fault: the caster trails
    RATE = "rate"  # HOLD / POSITION / VELOCITY / homing: theta_dot imposed


@dataclass(frozen=True)
class ModuleDrive:
    """What one module's controller does during a step (SI units)."""

    steer: SteerDrive = SteerDrive.PASSIVE
    steer_rate: float = 0.0  # rad/s, for SteerDrive.RATE
    wheel: WheelDrive = WheelDrive.PASSIVE
    wheel_value: float = 0.0  # rad/s for RATE, N.m for TORQUE


FREE_MODULE = ModuleDrive()


@dataclass(frozen=True)
class PhysicsOptions:
    """Physical constants of the virtual robot (SI units) and slip-burst injection.

    Defaults: with the paper's robot locked on one module, ``-0.6 N.m`` on the three other
    wheels spins it at about 0.5 rad/s and reaches steady state within about a second.
    """

    body_mass: float = 30.0  # kg
    body_inertia: float = 1.5  # kg m^2 about z at the origin of R
    body_damping: float = 2.0  # N s/m, floor resistance to translation
    body_rot_damping: float = 0.2  # N m s/rad, to rotation
    wheel_inertia: float = 0.002  # kg m^2, wheel + reflected rotor, about the axle
    wheel_damping: float = 0.1  # N m s/rad, rolling resistance + drivetrain
    lateral_damping: float = 300.0  # N s/m, tyre scrubbed sideways by a steered module
    scrub_damping: float = 5.0  # N m s/rad, wheel of a steered module pivoting on the floor
    slip_burst_rate: float = 0.0  # bursts per second per rolling wheel
    slip_duration: tuple[float, float] = (0.2, 0.5)  # s, uniform
    slip_factor: tuple[float, float] = (0.3, 1.0)  # extra encoder rotation / rolling rotation
    seed: int = 0


# --------------------------------------------------------------------------- pure maths


def constraint_rows(arrays: RobotArrays, theta: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Rolling and lateral constraint rows ``U`` and ``N`` (N, 3) at true steering ``theta``.

    ``U_i = (u_x, u_y, P_w,i x u_i)``, ``N_i = (n_x, n_y, P_w,i x n_i)`` so that
    ``U_i . xi = (v + omega x P_w,i) . u_i`` and likewise for ``n``; with
    ``P_w = P_s + b u`` (:func:`swpc_hw.robot.model.contact_point`), ``u = (cos, sin)``,
    ``n = (sin, -cos)`` written out (this runs every physics step).
    """
    th = np.asarray(theta, dtype=float)
    c = np.cos(th)
    s = np.sin(th)
    px = arrays.P_s[:, 0] + arrays.b * c
    py = arrays.P_s[:, 1] + arrays.b * s
    U = np.empty((th.shape[0], 3))
    N = np.empty((th.shape[0], 3))
    U[:, 0] = c
    U[:, 1] = s
    U[:, 2] = px * s - py * c
    N[:, 0] = s
    N[:, 1] = -c
    N[:, 2] = -px * c - py * s
    return U, N


def _lsq_null(
    A: FloatArray, t: FloatArray, basis: FloatArray, tol: float = 1e-10
) -> tuple[FloatArray, FloatArray]:
    """Least squares within ``span(basis)`` and what is left free, from one SVD.

    With ``A basis = W S V^T`` (numerical rank ``k``): ``y = V_k S_k^-1 W_k^T t`` (the
    minimum-norm least-squares solution of ``A basis y = t``) and the orthonormal basis
    ``basis V_{k:}`` of ``{basis y : A basis y = 0}``.  Returns ``(basis @ y, null basis)``
    (read-only arrays).

    Remembered for the same inputs, bit for bit (:func:`_lsq_null_of`): a pinned module's
    rows stay the same through a whole spin, and the SVD was a third of a physics step.
    """
    A = np.ascontiguousarray(A, dtype=float)
    t = np.ascontiguousarray(t, dtype=float)
    basis = np.ascontiguousarray(basis, dtype=float)
    return _lsq_null_of(
        A.tobytes(), A.shape, t.tobytes(), basis.tobytes(), basis.shape, float(tol)
    )


@functools.lru_cache(maxsize=64)
def _lsq_null_of(
    a: bytes,
    a_shape: tuple[int, ...],
    t: bytes,
    basis: bytes,
    basis_shape: tuple[int, ...],
    tol: float,
) -> tuple[FloatArray, FloatArray]:
    """:func:`_lsq_null` on its inputs' bytes."""
    A = np.frombuffer(a).reshape(a_shape)
    B = np.frombuffer(basis).reshape(basis_shape)
    W, sv, Vt = np.linalg.svd(A @ B)
    rank = int(np.sum(sv > tol * max(float(sv[0]) if sv.size else 0.0, 1.0)))
    y = Vt[:rank].T @ ((W[:, :rank].T @ np.frombuffer(t)) / sv[:rank])
    x = np.asarray(B @ y, dtype=float)
    Z = np.asarray(B @ Vt[rank:].T, dtype=float)
    x.flags.writeable = False
    Z.flags.writeable = False
    return x, Z


def prioritized_twist(
    hard: tuple[FloatArray, FloatArray],
    soft: tuple[FloatArray, FloatArray],
    damping: tuple[FloatArray, FloatArray],
    mass: FloatArray,
    force: FloatArray,
    twist0: FloatArray,
    dt: float,
) -> FloatArray:
    """Body twist after one step: hard rows, then soft rows, then the damped dynamics.

    ``hard = (A_h, t_h)`` and ``soft = (A_s, t_s)`` are rows ``A xi = t``;
    ``damping = (C, d)`` with ``C = sum_k c_k g_k g_k^T`` and ``d = sum_k c_k s_k g_k`` (the
    viscous rows); ``mass`` (3, 3), ``force`` (3,), ``twist0`` the previous twist.
    Implicit Euler in the remaining null space ``Z`` (see the module docstring)::

        Z^T (M + dt C) Z z = Z^T M (xi_0 - xi_p) + dt Z^T (F - C xi_p + d)
    """
    A_h, t_h = hard
    A_s, t_s = soft
    C, d = damping
    Z = np.eye(3)
    xi: FloatArray = np.zeros(3)
    if A_h.shape[0]:
        xi, Z = _lsq_null(A_h, t_h, Z)
    if A_s.shape[0] and Z.shape[1]:
        dxi, Z = _lsq_null(A_s, t_s - A_s @ xi, Z)
        xi = xi + dxi
    if Z.shape[1] == 0:
        return xi
    lhs = Z.T @ (mass + dt * C) @ Z
    rhs = Z.T @ (mass @ (twist0 - xi) + dt * (force - C @ xi + d))
    z = np.linalg.solve(lhs, rhs)
    return np.asarray(xi + Z @ z, dtype=float)


@dataclass(frozen=True)
class DriveArrays:
    """Per-module drives as arrays (what the vectorised rates need)."""

    steer_driven: NDArray[np.bool_]
    steer_rate: FloatArray  # 0 where not driven
    brake: NDArray[np.bool_]
    rate: NDArray[np.bool_]
    torque: FloatArray  # N.m, 0 where not TORQUE
    wheel_rate: FloatArray  # rad/s, 0 where not RATE

    @property
    def wheel_driven(self) -> NDArray[np.bool_]:
        return self.brake | self.rate

    @classmethod
    def of(cls, drives: Sequence[ModuleDrive]) -> DriveArrays:
        sd = np.array([d.steer is SteerDrive.RATE for d in drives])
        sr = np.array([d.steer_rate if d.steer is SteerDrive.RATE else 0.0 for d in drives])
        brake = np.array([d.wheel is WheelDrive.BRAKE for d in drives])
        rate = np.array([d.wheel is WheelDrive.RATE for d in drives])
        tq = np.array([d.wheel_value if d.wheel is WheelDrive.TORQUE else 0.0 for d in drives])
        wr = np.array([d.wheel_value if d.wheel is WheelDrive.RATE else 0.0 for d in drives])
        return cls(sd, sr, brake, rate, tq, wr)

    def __post_init__(self) -> None:
        st = self.steer_driven
        dyn = ~(self.brake | self.rate)
        # row selections used every step (index arrays: cheaper than boolean masks)
        idx = np.flatnonzero
        object.__setattr__(self, "i_brake", idx(self.brake))
        object.__setattr__(self, "i_brake_st", idx(self.brake & st))
        object.__setattr__(self, "i_rate", idx(self.rate))
        object.__setattr__(self, "i_rate_st", idx(self.rate & st))
        object.__setattr__(self, "i_dyn", idx(dyn))
        object.__setattr__(self, "i_dyn_st", idx(dyn & st))
        object.__setattr__(self, "n_steered", int(st.sum()))
        wd = self.brake | self.rate
        object.__setattr__(self, "steer_imposed", tuple(
            float(v) if on else None for on, v in zip(st, self.steer_rate, strict=True)))
        object.__setattr__(self, "wheel_imposed", tuple(
            float(v) if on else None for on, v in zip(wd, self.wheel_rate, strict=True)))
        object.__setattr__(self, "steer_rate_sum", float(self.steer_rate.sum()))

    i_brake: NDArray[np.intp] = field(init=False)
    i_brake_st: NDArray[np.intp] = field(init=False)
    i_rate: NDArray[np.intp] = field(init=False)
    i_rate_st: NDArray[np.intp] = field(init=False)
    i_dyn: NDArray[np.intp] = field(init=False)
    i_dyn_st: NDArray[np.intp] = field(init=False)
    n_steered: int = field(init=False)
    steer_imposed: tuple[float | None, ...] = field(init=False)
    """Per module the imposed steering rate (rad/s), None where the caster trails."""
    wheel_imposed: tuple[float | None, ...] = field(init=False)
    """Per module the imposed wheel rate (rad/s, 0 braked), None where the wheel rolls."""
    steer_rate_sum: float = field(init=False)


def module_rate(
    consts: tuple[float, float, float, float],
    twist: tuple[float, float, float],
    theta: float,
    steer_rate: float | None = None,
    wheel_rate: float | None = None,
) -> tuple[float, float]:
    """``(theta_dot, psi_dot)`` of one module under the body twist ``twist = (v_x, v_y,
    omega)``, ``consts = (x_s, y_s, b, r)``.

    A passive steering trails and a passive / torque wheel rolls, exactly as
    :func:`simulators.physics.core.caster_rates` (written out in floats: four modules
    are cheaper so than as arrays, and this runs four times per module and physics step;
    the tests check both agree)::

        P_w = P_s + b (cos theta, sin theta),   w = v + omega x P_w
        b theta_dot = w . n(theta),   r psi_dot = w . u(theta)

    An imposed ``steer_rate`` / ``wheel_rate`` (rad/s: a driven axis; 0 a braked wheel)
    replaces the rolling rate.
    """
    xs, ys, b, r = consts
    vx0, vy0, om = twist
    c = math.cos(theta)
    s = math.sin(theta)
    vx = vx0 - om * (ys + b * s)
    vy = vy0 + om * (xs + b * c)
    td = steer_rate if steer_rate is not None else (vx * s - vy * c) / b
    pd = wheel_rate if wheel_rate is not None else (vx * c + vy * s) / r
    return td, pd


def rk4_module(
    consts: tuple[float, float, float, float],
    twist: tuple[float, float, float],
    theta: float,
    steer_rate: float | None,
    wheel_rate: float | None,
    dt: float,
) -> tuple[float, float]:
    """``(dtheta, dpsi)`` of one module over ``dt`` under a constant body twist: classical
    RK4 on :func:`module_rate` (arguments as there)."""

    def f(th: float) -> tuple[float, float]:
        return module_rate(consts, twist, th, steer_rate, wheel_rate)

    k1t, k1p = f(theta)
    k2t, k2p = f(theta + 0.5 * dt * k1t)
    k3t, k3p = f(theta + 0.5 * dt * k2t)
    k4t, k4p = f(theta + dt * k3t)
    return dt / 6.0 * (k1t + 2 * k2t + 2 * k3t + k4t), dt / 6.0 * (k1p + 2 * k2p + 2 * k3p + k4p)


# --------------------------------------------------------------------------- state


@dataclass
class _SlipBurst:
    end: float
    factor: float


@dataclass
class RobotPhysics:
    """The true robot's state and its physics step (see the module docstring)."""

    truth: RobotParams = PAPER_CALIBRATED
    options: PhysicsOptions = field(default_factory=PhysicsOptions)
    pose0: tuple[float, float, float] = (0.0, 0.0, 0.0)
    theta0: Sequence[float] | None = None
    """Initial true steering angles (default 0 for every module)."""

    def __post_init__(self) -> None:
        self.arrays = self.truth.arrays()
        n = self.arrays.n
        self.t = 0.0
        self.pose = np.array(self.pose0, dtype=float)
        self.theta = np.zeros(n) if self.theta0 is None else np.array(self.theta0, dtype=float)
        if self.theta.shape != (n,):
            raise ValueError(f"theta0 needs {n} values")
        self.psi = np.zeros(n)
        self.psi_encoder = np.zeros(n)
        self.twist = np.zeros(3)
        self.push = np.zeros(3)
        """External wrench on the body in R: ``(f_x, f_y, tau_z)`` in N, N and N m, the
        torque about R's origin (a person pushing the robot; zero by default)."""
        self.theta_dot = np.zeros(n)
        self.psi_dot = np.zeros(n)
        self.steps = 0
        self.slip_bursts: list[tuple[int, float, float, float]] = []
        """(module index, start, end, factor) of every slip burst so far."""
        self._rng = np.random.default_rng(self.options.seed)
        self._slip: list[_SlipBurst | None] = [None] * n
        o = self.options
        self._mass = np.diag([o.body_mass, o.body_mass, o.body_inertia])
        self._damping = np.diag([o.body_damping, o.body_damping, o.body_rot_damping])
        self._drives: tuple[ModuleDrive, ...] = ()
        a = self.arrays
        self._module_consts = [
            (float(p[0]), float(p[1]), float(b), float(r))
            for p, b, r in zip(a.P_s, a.b, a.r, strict=True)
        ]
        self._drive_arrays: DriveArrays | None = None

    @property
    def n(self) -> int:
        return self.arrays.n

    def contact_points(self) -> FloatArray:
        """True contact points ``P_w = P_s + b u(theta)`` in R, (N, 2)."""
        return contact_point(self.arrays.P_s, self.arrays.b, self.theta)

    def contact_points_world(self) -> FloatArray:
        """True contact points in W, (N, 2)."""
        c, s = math.cos(self.pose[2]), math.sin(self.pose[2])
        P = self.contact_points()
        return np.column_stack(
            [self.pose[0] + c * P[:, 0] - s * P[:, 1], self.pose[1] + s * P[:, 0] + c * P[:, 1]]
        )

    # ------------------------------------------------------------------ twist
    def solve_twist(self, drives: DriveArrays, dt: float) -> FloatArray:
        """The body twist for the coming step (rows and dynamics of the module docstring)."""
        A = self.arrays
        o = self.options
        st = drives.steer_driven
        # rows at the mid-step steering angle (second order in dt for a re-steered pin)
        theta_mid = self.theta + 0.5 * dt * np.where(st, drives.steer_rate, self.theta_dot)
        U, N = constraint_rows(A, theta_mid)
        lat = A.b * drives.steer_rate
        ib, ibs, ir, irs = drives.i_brake, drives.i_brake_st, drives.i_rate, drives.i_rate_st
        hard = (
            np.concatenate([U[ib], N[ibs]]),
            np.concatenate([np.zeros(ib.size), lat[ibs]]),
        )
        soft = (
            np.concatenate([U[ir], N[irs]]),
            np.concatenate([A.r[ir] * drives.wheel_rate[ir], lat[irs]]),
        )
        idn, ids = drives.i_dyn, drives.i_dyn_st
        H = U[idn] / A.r[idn, None]
        Lr = N[ids]
        HtH = H.T @ H
        C = o.wheel_damping * HtH + o.lateral_damping * (Lr.T @ Lr) + self._damping
        C[2, 2] += o.scrub_damping * drives.n_steered
        d = o.lateral_damping * (Lr.T @ lat[ids])
        d[2] -= o.scrub_damping * drives.steer_rate_sum
        mass = self._mass + o.wheel_inertia * HtH
        force = H.T @ drives.torque[idn] + self.push
        return prioritized_twist(hard, soft, (C, d), mass, force, self.twist, dt)

    # ------------------------------------------------------------------ step
    def step(self, dt: float, drives: Sequence[ModuleDrive]) -> None:
        """Advance by ``dt`` (s) with every module's drive held constant."""
        if dt <= 0.0:
            return
        if len(drives) != self.n:
            raise ValueError(f"{len(drives)} drives for {self.n} modules")
        key = tuple(drives)
        if self._drive_arrays is None or key != self._drives:
            self._drives, self._drive_arrays = key, DriveArrays.of(drives)
        da = self._drive_arrays
        xi = self.solve_twist(da, dt)
        twist = (float(xi[0]), float(xi[1]), float(xi[2]))
        steps = [
            rk4_module(consts, twist, th, steer, wheel, dt)
            for consts, th, steer, wheel in zip(
                self._module_consts, self.theta.tolist(), da.steer_imposed, da.wheel_imposed,
                strict=True,
            )
        ]
        dtheta = np.array([d[0] for d in steps])
        dpsi = np.array([d[1] for d in steps])
        self.pose = se2_step(self.pose, xi[:2], float(xi[2]), dt)
        self.theta = self.theta + dtheta
        self.psi = self.psi + dpsi
        self.psi_encoder = self.psi_encoder + dpsi + self._slip_extra(dpsi, dt)
        self.twist = xi
        self.theta_dot = dtheta / dt
        self.psi_dot = dpsi / dt
        self.t += dt
        self.steps += 1

    def _slip_extra(self, dpsi: FloatArray, dt: float) -> FloatArray:
        """Encoder over-rotation of wheels inside a slip burst: ``factor * dpsi``."""
        o = self.options
        extra = np.zeros(self.n)
        if o.slip_burst_rate <= 0.0:
            return extra
        for j in range(self.n):
            burst = self._slip[j]
            if burst is not None and self.t >= burst.end:
                burst = self._slip[j] = None
            rolling = abs(dpsi[j]) > 1e-12
            if burst is None and rolling and self._rng.random() < o.slip_burst_rate * dt:
                dur = float(self._rng.uniform(*o.slip_duration))
                fac = float(self._rng.uniform(*o.slip_factor))
                burst = self._slip[j] = _SlipBurst(self.t + dur, fac)
                self.slip_bursts.append((j, self.t, self.t + dur, fac))
            if burst is not None:
                extra[j] = burst.factor * dpsi[j]
        return extra
