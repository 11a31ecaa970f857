"""Force-based planar dynamics of an SWPC robot with tyre contact (issue 44: other physics).

Independent of :mod:`simulators.physics.robot` and :mod:`simulators.physics.core`: no
no-slip constraint anywhere.  The body, each module's fork and each wheel are rigid bodies
with inertia; they move only under forces: the tyres' contact forces, the drives' torques
and the joints' friction.  The robot's geometry is the model's (docs/model-and-frames.md)
with the *true* parameters.  One robot per :class:`Plant`; the step is plain Python over
floats, a loop over the modules (numpy's per-call overhead on arrays of four is several
times the arithmetic: 130 us a step against ~20 us).

State
-----
Body: the CoM ``c`` (in R, default the centroid of the steering axes) at ``p_c`` in W,
yaw ``phi``; its velocity ``v_c`` (expressed in R) and yaw rate ``w``.  Module ``i``: true steering
angle ``theta_i`` (relative to the body) and rate; wheel angle ``psi_i`` (the encoder's
convention: ``psi_dot > 0`` moves the body along ``+u``) and rate; the tyre's deflection
``delta_i = (delta_x, delta_y)`` in the wheel frame ``(u, e)``, ``u = u(theta)``,
``e = (-sin theta, cos theta)``; the integrators of the drives' position loops.

Kinematics (vectors in R)
-------------------------
The hub (the fork's point over the contact) is at ``P_w = P_s + b u``; its velocity over
the floor, and the slip velocity of the wheel's material at the contact::

    v_H = v_c + w z x (P_w - c) + b theta_dot e
    s_x = v_H . u - r psi_dot,    s_y = v_H . e

(no slip, ``s = 0``, is exactly the model's constraint ``v + w x P_w = r psi_dot u + b
theta_dot n``).

Tyre: brush with relaxation (LuGre-like, a regularised Coulomb law)
-------------------------------------------------------------------
The deflection is the hub's offset from the tread's point stuck to the floor; it grows
with the slip, turns with the wheel frame (``Omega = w + theta_dot``), relaxes as the
tread rolls out of the patch (relaxation length ``L``) and slides where the force reaches
``mu N`` (``N = m g / n_modules``)::

    d delta/dt = s - Omega z x delta - (|r psi_dot| / L) delta - |s| (K o delta) / (mu N)
    f = -(K o delta + c_d o d delta/dt)          (force of the floor on the wheel, (u, e))

``K = (K_x, K_y)`` the longitudinal and lateral stiffnesses (N/m), ``c_d`` the tread's
damping, ``2 zeta sqrt(K m_eq)`` with ``m_eq`` the wheel's ``J_w / r^2`` (x) and the
fork's ``J_s / b^2`` (y).  Small slip: linear (a rolling wheel's slip stiffness ``K L``
per unit slip ratio or slip angle, a still wheel a spring ``K``); steady sliding: ``|f| =
mu N`` against ``s``.  No spin (bore) torque at the patch.

Dynamics
--------
The forks' mass is the body's; their yaw inertia ``J_s`` about the steering axis is their
own.  With ``F_i = f_x u + f_y e`` (R) and ``T_i`` the steering joint's torque on the fork
(drive plus friction, its reaction on the body)::

    m (dv_c/dt + w z x v_c) = sum F_i                  (v_c in R)
    I dw/dt         = sum (P_s,i - c) x F_i - sum T_i
    J_s (dw/dt + theta_ddot_i) = b f_y,i + T_i
    J_w psi_ddot_i  = tau_i - c_w psi_dot_i - c_rr N r tanh(psi_dot / eps) - r f_x,i
    T_i = T_drive,i - c_s theta_dot_i - T_c tanh(theta_dot_i / eps)

The tanh regularises Coulomb friction: no stiction, so a free caster creeps all the way
to its trailing angle (a real joint's dead band is not modelled).  Caster shimmy is: at
``c_s = 0.02`` N m s the free casters of the default tyres oscillate at +-2 rad/s during a
spin; the default 0.3 (a geared steering drive's own drag) damps it; with tyres 10x
stiffer the Coulomb term then makes a slowly growing shimmy (none without it).

``T_drive``: a PID position loop on the steering (hold) or 0 (free); ``tau``: the wheel's
torque command, or a PID on the wheel angle (brake), saturated at the drive's torque.

Integration: semi-implicit (symplectic) Euler at a fixed step ``dt`` (0.5 ms): the
velocities from the forces of the current state (``v_c`` turned by ``R(-w dt)``, exact
for the frame's rotation), then the angles, the deflection and the pose from the new
velocities, the pose by the SE(2) exponential of the constant twist (a point still in
the body's rotation stays exactly still: Euler's tangent steps spiral outwards, which
moved the locked contact point 35 um per turn, in the data and not in the tyre), the
deflection's relaxation and sliding terms implicitly (``delta' = (delta + dt (s - Omega
z x delta)) / (1 + dt (|r psi_dot| / L + |s| K / mu N))``, unconditionally stable).
Why: one force evaluation per step (RK4 costs four) with the energy of the tyre springs
bounded (explicit Euler lets it grow); stable while ``omega_n dt < 2`` for the fastest
mode, the wheel on its tyre (``sqrt(K_x r^2 / J_w)``: 250 rad/s at the defaults, 0.12
per step; the results do not move at dt = 0.1 ms).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import NamedTuple

from swpc_hw.robot.model import RobotParams


@dataclass(frozen=True)
class Gains:
    """A drive's position loop: ``T = kp e + ki int(e) - kd rate``, ``|T| <= limit``
    (the integral clamped to ``|ki int(e)| <= limit``)."""

    kp: float
    ki: float
    kd: float
    limit: float


@dataclass(frozen=True)
class TyreOptions:
    """The physics' constants (SI).  Defaults: a robot of the paper's class (60 kg, four
    modules) on polyurethane caster wheels."""

    mass: float = 60.0  # kg, the whole robot
    yaw_inertia: float = 4.0  # kg m^2, about the CoM, forks excluded
    com: tuple[float, float] | None = None  # in R; None: the centroid of the steering axes
    steer_inertia: float = 0.01  # kg m^2, fork and wheel about the steering axis
    steer_viscous: float = 0.3  # N m s/rad, steering joint (0.02: the casters shimmy)
    steer_coulomb: float = 0.05  # N m, steering joint
    wheel_inertia: float = 0.005  # kg m^2, wheel (and reflected rotor) about its axle
    wheel_viscous: float = 0.15  # N m s/rad, gearbox and bearings
    rolling_resistance: float = 0.01  # c_rr: torque c_rr N r against rolling
    mu: float = 0.8
    gravity: float = 9.81
    stiffness_x: float = 1.0e5  # N/m, longitudinal
    stiffness_y: float = 1.0e5  # N/m, lateral
    relaxation_length: float = 0.01  # m
    damping_ratio: float = 0.3  # of the tread's damping c_d
    smoothing: float = 0.01  # rad/s, the tanh of Coulomb friction
    steer_gains: Gains = Gains(200.0, 2000.0, 2.0, 20.0)
    brake_gains: Gains = Gains(100.0, 1000.0, 1.0, 10.0)
    dt: float = 5e-4  # s

    def stiffer(self, factor: float) -> TyreOptions:
        """These options with both tyre stiffnesses ``factor`` times higher and ``dt``
        divided by ``ceil(sqrt(factor) / 4)`` (the wheel's mode keeps ``omega_n dt`` below
        0.5; an integer divisor keeps the sample times on the grid)."""
        return replace(
            self, stiffness_x=self.stiffness_x * factor, stiffness_y=self.stiffness_y * factor,
            dt=self.dt / max(1, math.ceil(math.sqrt(factor) / 4.0 - 1e-9)),
        )  # fmt: skip

    def describe(self) -> str:
        """One line of the constants that shape the contact."""
        return (
            f"m {self.mass:g} kg, I {self.yaw_inertia:g} kg m^2, K_x {self.stiffness_x:.3g} "
            f"N/m, K_y {self.stiffness_y:.3g} N/m, L {self.relaxation_length * 1e3:g} mm "
            f"(slip stiffness K L: {self.stiffness_x * self.relaxation_length:.0f} N, "
            f"cornering {self.stiffness_y * self.relaxation_length:.0f} N/rad), mu "
            f"{self.mu:g}, zeta {self.damping_ratio:g}, J_s {self.steer_inertia:g}, steering "
            f"friction {self.steer_viscous:g} N m s + {self.steer_coulomb:g} N m, J_w "
            f"{self.wheel_inertia:g}, wheel losses {self.wheel_viscous:g} N m s + c_rr "
            f"{self.rolling_resistance:g}, dt {self.dt * 1e3:g} ms"
        )


class ModuleConst(NamedTuple):
    """One module's true geometry and derived constants."""

    lx: float  # P_s - c, in R
    ly: float
    b: float
    r: float
    beta: float  # only for the encoders: theta_hat = theta - beta
    cd_x: float  # tread damping, N s/m
    cd_y: float


@dataclass(frozen=True)
class Plant:
    """One robot's truth as the physics uses it."""

    modules: tuple[ModuleConst, ...]
    com: tuple[float, float]  # in R
    load: float  # N, normal load per wheel


def plant(truth: RobotParams, opt: TyreOptions) -> Plant:
    """The plant of robot ``truth`` (module docstring: ``c_d``, ``N``)."""
    a = truth.arrays()
    com = (
        (float(a.P_s[:, 0].mean()), float(a.P_s[:, 1].mean())) if opt.com is None else opt.com
    )
    z = 2.0 * opt.damping_ratio
    mods = tuple(
        ModuleConst(
            float(a.P_s[i, 0] - com[0]), float(a.P_s[i, 1] - com[1]), float(a.b[i]),
            float(a.r[i]), float(a.beta[i]),
            z * math.sqrt(opt.stiffness_x * opt.wheel_inertia) / float(a.r[i]),
            z * math.sqrt(opt.stiffness_y * opt.steer_inertia) / float(a.b[i]),
        )
        for i in range(a.n)
    )
    return Plant(mods, com, opt.mass * opt.gravity / a.n)


class ModuleState(NamedTuple):
    theta: float  # true steering angle, relative to the body
    theta_dot: float
    psi: float  # wheel angle
    psi_dot: float
    dx: float  # tyre deflection along u
    dy: float  # tyre deflection along e
    i_steer: float  # integral of the steering loop's error
    i_wheel: float  # integral of the brake's error


class State(NamedTuple):
    """The body (CoM ``x, y`` in W, ``yaw``; the CoM's velocity in R and the yaw rate)
    and every module's state."""

    x: float
    y: float
    yaw: float
    vx: float  # the CoM's velocity, in R
    vy: float
    w: float
    modules: tuple[ModuleState, ...]

    def pose(self, p: Plant) -> tuple[float, float, float]:
        """The pose of R in W: ``p_R = p_c - R(yaw) c``."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        cx, cy = p.com
        return (self.x - (c * cx - s * cy), self.y - (s * cx + c * cy), self.yaw)


def rest_state(
    p: Plant, pose: tuple[float, float, float] = (0.0, 0.0, 0.0), theta_hat: float = 0.0
) -> State:
    """Everything still, tyres undeflected, every module at ``theta_hat``, R at ``pose``."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    cx, cy = p.com
    mods = tuple(ModuleState(m.beta + theta_hat, 0, 0, 0, 0, 0, 0, 0) for m in p.modules)
    return State(pose[0] + c * cx - s * cy, pose[1] + s * cx + c * cy, pose[2], 0, 0, 0, mods)


class ModuleCommand(NamedTuple):
    """What one module's drives do in a step.  Steering: held at the true angle
    ``steer_target`` when ``steer_hold``, else free.  Wheel: held at ``brake_target`` when
    ``brake``, else the torque ``torque`` (0: free)."""

    steer_hold: bool
    steer_target: float
    brake: bool
    brake_target: float
    torque: float


def pid(g: Gains, error: float, integral: float, rate: float) -> float:
    return max(-g.limit, min(g.limit, g.kp * error + g.ki * integral - g.kd * rate))


def slip(
    vrx: float, vry: float, w: float, m: ModuleState, k: ModuleConst, opt: TyreOptions,
    load: float,
) -> tuple[float, float, float, float, float, float]:  # fmt: skip
    """One tyre at the body velocity ``(vrx, vry)`` (of the CoM, in R) and yaw rate ``w``:
    ``(cos theta, sin theta, e_x, e_y, k_x, k_y)`` with ``e = s - Omega z x delta`` and
    ``k = |r psi_dot| / L + |s| K / (mu N)`` per axis, so that ``d delta/dt = e - k delta``
    (module docstring)."""
    cu, su = math.cos(m.theta), math.sin(m.theta)
    bt = k.b * m.theta_dot
    hx = vrx - w * (k.ly + k.b * su) - bt * su
    hy = vry + w * (k.lx + k.b * cu) + bt * cu
    sx = hx * cu + hy * su - k.r * m.psi_dot
    sy = -hx * su + hy * cu
    om = w + m.theta_dot
    smag = math.hypot(sx, sy) / (opt.mu * load)
    roll = abs(k.r * m.psi_dot) / opt.relaxation_length
    return (cu, su, sx + om * m.dy, sy - om * m.dx,
            roll + smag * opt.stiffness_x, roll + smag * opt.stiffness_y)  # fmt: skip


class Forces(NamedTuple):
    """One module's tyre force (floor on wheel, wheel frame), joint torque on the fork and
    drive torque on the wheel."""

    fx: float
    fy: float
    steer: float
    wheel: float


def module_forces(
    m: ModuleState, c: ModuleCommand, k: ModuleConst, opt: TyreOptions, e_x: float, e_y: float,
    k_x: float, k_y: float, load: float,
) -> Forces:  # fmt: skip
    """``f = -(K o delta + c_d o d delta/dt)``, the joint's ``T`` and the wheel's ``tau``
    (module docstring)."""
    fx = -(opt.stiffness_x * m.dx + k.cd_x * (e_x - k_x * m.dx))
    fy = -(opt.stiffness_y * m.dy + k.cd_y * (e_y - k_y * m.dy))
    eps = opt.smoothing
    t = 0.0
    if c.steer_hold:
        t = pid(opt.steer_gains, c.steer_target - m.theta, m.i_steer, m.theta_dot)
    t -= opt.steer_viscous * m.theta_dot + opt.steer_coulomb * math.tanh(m.theta_dot / eps)
    tau = c.torque
    if c.brake:
        tau = pid(opt.brake_gains, c.brake_target - m.psi, m.i_wheel, m.psi_dot)
    tau -= opt.wheel_viscous * m.psi_dot + opt.rolling_resistance * load * k.r * math.tanh(
        m.psi_dot / eps
    )
    return Forces(fx, fy, t, tau)


def _clamp_integral(g: Gains, v: float) -> float:
    lim = g.limit / g.ki if g.ki > 0 else 0.0
    return max(-lim, min(lim, v))


def step(s: State, cmds: Sequence[ModuleCommand], p: Plant, opt: TyreOptions) -> State:
    """One semi-implicit Euler step of ``opt.dt`` (module docstring)."""
    dt, load = opt.dt, p.load
    Fx = Fy = Mz = 0.0
    per: list[tuple[float, float, Forces]] = []
    for m, c, k in zip(s.modules, cmds, p.modules, strict=True):
        cu, su, ex, ey, kx, ky = slip(s.vx, s.vy, s.w, m, k, opt, load)
        f = module_forces(m, c, k, opt, ex, ey, kx, ky, load)
        gx, gy = f.fx * cu - f.fy * su, f.fx * su + f.fy * cu  # in R
        Fx += gx
        Fy += gy
        Mz += k.lx * gy - k.ly * gx - f.steer
        per.append((cu, su, f))
    w_dot = Mz / opt.yaw_inertia
    w = s.w + dt * w_dot
    a = w * dt
    ca, sa = math.cos(a), math.sin(a)
    tx, ty = s.vx + dt * Fx / opt.mass, s.vy + dt * Fy / opt.mass
    vx, vy = ca * tx + sa * ty, -sa * tx + ca * ty  # R(-w dt): the world's velocity in R
    mods = []
    for m, c, k, (_, _, f) in zip(s.modules, cmds, p.modules, per, strict=True):
        thd = m.theta_dot + dt * ((k.b * f.fy + f.steer) / opt.steer_inertia - w_dot)
        psd = m.psi_dot + dt * (f.wheel - k.r * f.fx) / opt.wheel_inertia
        moved = m._replace(theta_dot=thd, psi_dot=psd)
        _, _, ex, ey, kx, ky = slip(vx, vy, w, moved, k, opt, load)
        i_s = i_w = 0.0
        if c.steer_hold:
            i_s = _clamp_integral(opt.steer_gains, m.i_steer + dt * (c.steer_target - m.theta))
        if c.brake:
            i_w = _clamp_integral(opt.brake_gains, m.i_wheel + dt * (c.brake_target - m.psi))
        mods.append(ModuleState(
            m.theta + dt * thd, thd, m.psi + dt * psd, psd,
            (m.dx + dt * ex) / (1.0 + dt * kx), (m.dy + dt * ey) / (1.0 + dt * ky), i_s, i_w,
        ))  # fmt: skip
    # the pose by the SE(2) exponential of the constant twist (vx, vy, w) over dt
    fs, fc = (1.0, 0.5 * a) if abs(a) < 1e-9 else (sa / a, (1.0 - ca) / a)
    px, py = (fs * vx - fc * vy) * dt, (fc * vx + fs * vy) * dt
    cy, sy = math.cos(s.yaw), math.sin(s.yaw)
    return State(s.x + cy * px - sy * py, s.y + sy * px + cy * py, s.yaw + a, vx, vy, w,
                 tuple(mods))  # fmt: skip


def energy(s: State, opt: TyreOptions) -> float:
    """Kinetic energy of body, forks and wheels plus the tyres' elastic energy (J)::

        E = m |v_c|^2 / 2 + I w^2 / 2 + sum J_s (w + theta_dot)^2 / 2 + J_w psi_dot^2 / 2
            + (K_x delta_x^2 + K_y delta_y^2) / 2
    """
    e = 0.5 * opt.mass * (s.vx**2 + s.vy**2) + 0.5 * opt.yaw_inertia * s.w**2
    for m in s.modules:
        e += 0.5 * opt.steer_inertia * (s.w + m.theta_dot) ** 2
        e += 0.5 * opt.wheel_inertia * m.psi_dot**2
        e += 0.5 * (opt.stiffness_x * m.dx**2 + opt.stiffness_y * m.dy**2)
    return e


def tread_points(s: State, p: Plant) -> list[tuple[float, float]]:
    """Every module's tread point stuck to the floor, ``hub - delta``, in W."""
    x0, y0, yaw = s.pose(p)
    c, sn = math.cos(yaw), math.sin(yaw)
    out = []
    for m, k in zip(s.modules, p.modules, strict=True):
        cu, su = math.cos(m.theta), math.sin(m.theta)
        px = k.lx + p.com[0] + k.b * cu - (m.dx * cu - m.dy * su)
        py = k.ly + p.com[1] + k.b * su - (m.dx * su + m.dy * cu)
        out.append((x0 + c * px - sn * py, y0 + sn * px + c * py))
    return out
