"""A fake robot for the calibration state machine: kinematics on a virtual clock, no CAN.

:class:`FakeRobot` implements :class:`swpc_hw.drives.robot_io.RobotIO` over a kinematic world
that moves only when the state machine sleeps on its :class:`swpc_hw.clock.VirtualClock`
(``on_sleep``), in steps of ``dt``:

* a module whose steering is position-held and whose wheel is braked pins its contact
  point ``C = P_s + b u(theta)``; with it and a driven wheel the body spins about C at
  ``spin_rate`` (counter-clockwise for a negative wheel torque, as the protocol drives, or
  a negative wheel velocity, as the probes roll): ``v = -omega x C``;
* every free caster trails exactly (:func:`swpc_hw.robot.model.trailing_steering_angle`) and
  every rolling wheel turns ``dpsi = (v + omega x P_w) . u / r dt``;
* a position-held steering moves to its target at ``steer_rate``;
* the encoders report the angles quantised to ``counts`` per turn (2**17, the simulator's);
* poses (seeded noise) go to a real :class:`services.sensors.mocap.MocapIngest` every
  ``pose_every`` steps, stamped with the clock's wall time (clock mode ``wall``);
* with every steering position-held and every wheel under torque (the straight drive of
  a run without motion capture) the body translates at ``drive_speed`` along the wheels'
  mean direction, and every wheel rolls;
* a gyro (``imu``: a real :class:`services.sensors.gyro.GyroIngest`) reads the yaw rate
  every step with a scale error, a bias and seeded white noise.

So the real solver recovers the fake robot's true parameters from a run.  Faults, stuck
axes, a silent mocap, a drifting robot and homing are knobs of the world; every command
and ``stop_all`` is logged with its time.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from services.sensors.gyro import GyroIngest
from services.sensors.mocap import MocapIngest
from simulators.physics.core import se2_step
from swpc_hw.clock import VirtualClock
from swpc_hw.robot.model import FloatArray, RobotParams, nearest_turn, trailing_steering_angle
from swpc_hw.sensors.gyro import GyroSample, encode_imu
from swpc_hw.sensors.mocap import PoseSample, encode_native

_TWO_PI = 2.0 * math.pi


@dataclass
class FakeModule:
    theta_hat: float
    psi: float = 0.0
    steer: str = "disabled"  # disabled | free | position
    target: float = 0.0
    wheel: str = "disabled"  # disabled | free | hold | torque
    torque: float = 0.0
    homed: bool = True
    homing_until: float | None = None


@dataclass
class FakeRobot:
    """:class:`swpc_hw.drives.robot_io.RobotIO` on a kinematic world (module docstring)."""

    truth: RobotParams
    clock: VirtualClock
    mocap: MocapIngest
    spin_rate: float = 0.5
    steer_rate: float = 3.0
    dt: float = 0.005
    pose_every: int = 2
    pose_sigma: float = 1e-4
    homed: bool = True
    homing_time: float = 0.3
    seed: int = 3
    # knobs
    faults: list[str] = field(default_factory=list)
    stuck: set[int] = field(default_factory=set)
    mocap_on: bool = True
    drift: float = 0.0
    """yaw rate (rad/s) of a robot pushed by someone, whatever its wheels do"""
    node_problems: list[str] = field(default_factory=list)
    stamp_offset: float = 0.0
    """added to every pose's stamp (a mocap clock off this host's)"""
    pose_latency: float = 0.0
    """poses arrive this long after they were sampled (a slow mocap network)"""
    imu: GyroIngest | None = None
    """the robot's gyro goes here every step (rad/s: scale, bias and noise below)"""
    gyro_bias: float = 0.002
    gyro_scale_error: float = 0.003
    gyro_sigma: float = 1e-4
    gyro_on: bool = True
    drive_speed: float = 0.4
    """m/s of a straight drive: every wheel under torque, every steering held"""
    counts: int = 2**17
    """encoder counts per turn of the reported angles (0: exact)"""
    ramp_time: float = 0.2
    """s: a spin or a drive reaches its rate linearly over this long"""
    # what happened
    log: list[tuple[float, str, int | None]] = field(default_factory=list)
    stop_all_times: list[float] = field(default_factory=list)
    closed: bool = False

    def __post_init__(self) -> None:
        self.arrays = self.truth.arrays()
        self.ids = list(self.truth.ids)
        rng = np.random.default_rng(self.seed)
        self._rng = rng
        self.mods = {
            m: FakeModule(theta_hat=float(rng.uniform(-3, 3)), homed=self.homed) for m in self.ids
        }
        self.rows: dict[int, list[tuple[float, float, float]]] = {m: [] for m in self.ids}
        self.pose = np.zeros(3)
        self.t = self.clock.now()
        self.pose_log: list[tuple[float, float, float, float]] = [(self.t, 0.0, 0.0, 0.0)]
        self._moving_since: float | None = None
        self._steps = 0
        self._trail: dict[tuple[float, float, float, bool], FloatArray] = {}
        a = self.arrays  # per module, as floats: P_s (x, y), b, beta, r
        self._geometry = tuple(
            [float(x) for x in col]
            for col in (a.P_s[:, 0], a.P_s[:, 1], a.b, a.beta, a.r)
        )
        self._in_flight: deque[tuple[float, bytes]] = deque()
        self.clock.on_sleep.append(self.advance_to)
        self._feed_pose()

    # ------------------------------------------------------------------ the world
    def advance_to(self, t: float) -> None:
        while self.t + self.dt <= t + 1e-12:
            self._step(self.dt)

    def _index(self, m: int) -> int:
        return self.ids.index(m)

    def _step(self, dt: float) -> None:
        # scalar maths (math, not 2-element numpy arrays): the same operations in the same
        # order, so the same numbers, at a fraction of the CPU (this runs every 10 ms of
        # every run)
        t = self.t + dt
        A = self.arrays
        for m, md in self.mods.items():
            if md.homing_until is not None and t >= md.homing_until:
                md.homed, md.homing_until = True, None
                md.theta_hat = 0.0
            if md.steer == "position" and m not in self.stuck:
                step = self.steer_rate * dt
                md.theta_hat += max(-step, min(step, md.target - md.theta_hat))
        locked = [m for m, md in self.mods.items() if md.steer == "position" and md.wheel == "hold"]
        driving = [md for md in self.mods.values() if md.wheel == "torque" and md.torque != 0.0]
        omega, vx, vy = self.drift, 0.0, 0.0
        held = all(md.steer == "position" for md in self.mods.values())
        Psx, Psy, bs, betas, rs = self._geometry
        if len(locked) == 1 and driving:
            k = self._index(locked[0])
            theta_k = self.mods[locked[0]].theta_hat + betas[k]
            Cx = Psx[k] + bs[k] * math.cos(theta_k)
            Cy = Psy[k] + bs[k] * math.sin(theta_k)
            omega = self.spin_rate * (1.0 if driving[0].torque < 0 else -1.0) + self.drift
            vx, vy = omega * Cy, omega * -Cx  # v = -omega x C: C stays put
        elif not locked and held and len(driving) == len(self.mods):
            # the straight drive: a translation along the wheels' mean direction, away from
            # it for a negative torque (the wheels roll backwards)
            th = np.array([md.theta_hat for md in self.mods.values()]) + A.beta
            u = np.array([np.cos(th).sum(), np.sin(th).sum()])
            sign = -1.0 if driving[0].torque < 0 else 1.0
            vx, vy = (float(c) for c in sign * self.drive_speed * u / np.linalg.norm(u))
        moving = omega != 0.0 or vx != 0.0 or vy != 0.0
        if moving and self._moving_since is None:
            self._moving_since = t - dt
        elif not moving:
            self._moving_since = None
        if moving and self.ramp_time > 0:
            assert self._moving_since is not None
            f = min(1.0, (t - self._moving_since) / self.ramp_time)
            omega, vx, vy = omega * f, vx * f, vy * f
        if moving:
            translating = float(vx != 0.0 or vy != 0.0)
            # the turn's sign too: about the same point the other way round, the casters
            # trail the other way
            key = (vx / (omega or 1.0), vy / (omega or 1.0), translating, omega > 0.0)
            trail = self._trail.get(key)
            if trail is None and not held:  # constant for a whole spin
                trail = self._trail[key] = trailing_steering_angle(A, np.array([vx, vy]), omega)
            for i, m in enumerate(self.ids):
                md = self.mods[m]
                if md.steer in ("free", "disabled") and m not in locked and trail is not None:
                    # nearest_turn(theta_hat, trail[i]), in floats (% is numpy's mod)
                    c = md.theta_hat
                    md.theta_hat = c + (math.pi - (math.pi - (float(trail[i]) - c)) % _TWO_PI)
                th = md.theta_hat + betas[i]
                ux, uy = math.cos(th), math.sin(th)
                Pwx, Pwy = Psx[i] + bs[i] * ux, Psy[i] + bs[i] * uy
                velx, vely = vx + omega * -Pwy, vy + omega * Pwx
                if md.wheel in ("free", "torque", "disabled"):
                    md.psi += (velx * ux + vely * uy) / rs[i] * dt
            self.pose = se2_step(self.pose, (vx, vy), omega, dt)
        self.t = t
        self.pose_log.append((t, *self.pose.tolist()))
        if self.imu is not None and self.gyro_on:
            wz = (1 + self.gyro_scale_error) * omega + self.gyro_bias
            wz += float(self._rng.normal(0.0, self.gyro_sigma))
            self.imu.feed(encode_imu(GyroSample(self.clock.to_wall(t), wz)), t_recv=t)
        q = 2 * math.pi / self.counts if self.counts else 0.0
        for m, md in self.mods.items():
            th, psi = md.theta_hat, md.psi
            if q:
                th, psi = round(th / q) * q, round(psi / q) * q
            self.rows[m].append((t, th, psi))
        self._steps += 1
        if self._steps % self.pose_every == 0:
            self._feed_pose()

    def _feed_pose(self) -> None:
        if self.mocap_on:
            x, y, yaw = self.pose + self._rng.normal(0.0, self.pose_sigma, 3) * [1, 1, 0.1]
            stamp = self.clock.wall() - self.clock.now() + self.t + self.stamp_offset
            payload = encode_native(PoseSample.planar(stamp, x, y, yaw))
            self._in_flight.append((self.t + self.pose_latency, payload))
        while self._in_flight and self._in_flight[0][0] <= self.t + 1e-12:
            t_recv, payload = self._in_flight.popleft()
            self.mocap.feed(payload, t_recv=t_recv)

    def _cmd(self, what: str, module: int | None = None) -> None:
        self.log.append((self.clock.now(), what, module))

    def stopped_for_good_after(self, t: float) -> bool:
        """stop_all() came at or after clock time ``t`` and no command that moves anything
        followed it in the log (same-instant commands included: the log is ordered)."""
        i = next((k for k, c in enumerate(self.log) if c[0] >= t and c[1] == "stop_all"), None)
        return i is not None and all(c[1] in ("stop_all", "release") for c in self.log[i:])

    # ------------------------------------------------------------------ RobotIO
    @property
    def module_ids(self) -> list[int]:
        return list(self.ids)

    def problems(self) -> list[str]:
        out = list(self.node_problems)
        out += [f"module {m}: steering not homed" for m in self.unhomed()]
        return out

    def activate(self) -> None:
        self._cmd("activate")
        for md in self.mods.values():
            md.steer, md.wheel = "free", "free"

    def unhomed(self) -> list[int]:
        return [m for m, md in self.mods.items() if not md.homed]

    def start_homing(self, module: int) -> None:
        self._cmd("start_homing", module)
        self.mods[module].homing_until = self.clock.now() + self.homing_time

    def lock(self, module: int, steer: float) -> None:
        self._cmd("lock", module)
        md = self.mods[module]
        md.steer, md.target = "position", float(nearest_turn(md.theta_hat, steer))
        md.wheel, md.torque = "hold", 0.0

    def steer_to(self, module: int, steer: float) -> None:
        self._cmd("steer_to", module)
        md = self.mods[module]
        md.steer, md.target = "position", float(nearest_turn(md.theta_hat, steer))

    def free_steer(self, module: int) -> None:
        self._cmd("free_steer", module)
        self.mods[module].steer = "free"

    def wheel_torque(self, module: int, torque: float) -> None:
        self._cmd("wheel_torque", module)
        self.mods[module].wheel, self.mods[module].torque = "torque", torque

    def wheel_velocity(self, module: int, velocity: float) -> None:
        """A wheel rolled at ``velocity`` drives like a torque of its sign (the probes: a
        negative roll turns the robot counter-clockwise about the locked module)."""
        self._cmd("wheel_velocity", module)
        self.mods[module].wheel, self.mods[module].torque = "torque", velocity

    def spins_by_torque(self, module: int) -> bool:
        return True

    def wheel_hold(self, module: int) -> None:
        self._cmd("wheel_hold", module)
        self.mods[module].wheel, self.mods[module].torque = "hold", 0.0

    def wheel_free(self, module: int) -> None:
        self._cmd("wheel_free", module)
        self.mods[module].wheel, self.mods[module].torque = "free", 0.0

    def steering(self, module: int) -> float:
        return self.mods[module].theta_hat

    def stop_all(self) -> None:
        self._cmd("stop_all")
        self.stop_all_times.append(self.clock.now())
        for md in self.mods.values():
            md.steer, md.wheel, md.torque = "disabled", "disabled", 0.0

    def release(self) -> None:
        self._cmd("release")

    def encoders(self, module: int, since: float) -> FloatArray:
        a = np.array(self.rows[module], dtype=float).reshape(-1, 3)
        return a[a[:, 0] >= since]

    def encoder_rows(self, module: int, cursor: int, since: float) -> tuple[FloatArray, int]:
        rows = self.rows[module]
        a = np.array(rows[cursor:], dtype=float).reshape(-1, 3)
        return a[a[:, 0] >= since], len(rows)

    def pose_at(self, t: float) -> FloatArray:
        """The true pose ``(x, y, yaw)`` at the step nearest ``t``."""
        k = min(range(len(self.pose_log)), key=lambda i: abs(self.pose_log[i][0] - t))
        return np.array(self.pose_log[k][1:])

    def take_faults(self) -> list[str]:
        out, self.faults = self.faults, []
        return out

    def close(self) -> None:
        self.closed = True
