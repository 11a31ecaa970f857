"""What the virtual drives of every kind share: the interface the virtual robot drives them
through (:class:`VirtualDrive`), one axis' state (:class:`AxisModel`), what that state does to
the physics (:func:`axis_drive`: a drive of :class:`simulators.physics.robot.RobotPhysics`)
and encoder quantisation."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Protocol

import can

from firmware_protocol.codec import Axis, AxisState, ControlMode, ErrorFlag, Frame
from simulators.physics.robot import ModuleDrive, SteerDrive, WheelDrive


@dataclass
class AxisModel:
    """State of one axis of a virtual controller (SI units)."""

    state: AxisState = AxisState.DISABLED
    mode: ControlMode = ControlMode.FREE
    setpoint: float = 0.0
    errors: int = 0
    position: float = 0.0
    velocity: float = 0.0
    torque: float = 0.0
    max_torque: float = 5.0
    max_velocity: float = 40.0
    inertia: float = 0.01
    friction: float = 0.02
    hold_target: float = 0.0


HOMING_SPEED = 0.5
"""Steering speed while homing (rad/s), as the virtual controller's own axis model."""


def _clamp(x: float, limit: float) -> float:
    return max(-limit, min(limit, x))


def axis_drive(
    ax: AxisModel, axis: Axis, position: float, dt: float, position_tau: float
) -> tuple[str, float]:
    """What one controller axis does to the physics during the next ``dt``.

    Returns ``(kind, value)`` with kind ``"passive"``, ``"rate"`` (rad/s), ``"brake"``
    or ``"torque"`` (N.m, wheel only).  POSITION is the first-order loop
    ``rate = clamp((setpoint - position) / max(position_tau, dt), max_velocity)``.  A
    steering torque becomes a rate through ``J dv/dt = tau - c v`` (exact over ``dt``).
    """
    if ax.state == AxisState.HOMING:
        return "rate", HOMING_SPEED
    if ax.state != AxisState.ENABLED or ax.mode == ControlMode.FREE:
        return "passive", 0.0
    if ax.mode == ControlMode.HOLD:
        return ("brake", 0.0) if axis == Axis.WHEEL else ("rate", 0.0)
    if ax.mode == ControlMode.POSITION:
        rate = (ax.setpoint - position) / max(position_tau, dt)
        return "rate", _clamp(rate, ax.max_velocity)
    if ax.mode == ControlMode.VELOCITY:
        return "rate", _clamp(ax.setpoint, ax.max_velocity)
    tau = _clamp(ax.setpoint, ax.max_torque)  # TORQUE
    if axis == Axis.WHEEL:
        return "torque", tau
    v_inf = tau / ax.friction
    return "rate", v_inf + (ax.velocity - v_inf) * math.exp(-dt * ax.friction / ax.inertia)


def module_drive(steer: tuple[str, float], wheel: tuple[str, float]) -> ModuleDrive:
    """Combine the two axes' :func:`axis_drive` into the physics' :class:`ModuleDrive`."""
    sk, sv = steer
    wk, wv = wheel
    s = SteerDrive.RATE if sk == "rate" else SteerDrive.PASSIVE
    w = {
        "passive": WheelDrive.PASSIVE,
        "brake": WheelDrive.BRAKE,
        "rate": WheelDrive.RATE,
        "torque": WheelDrive.TORQUE,
    }[wk]
    return ModuleDrive(s, sv if s is SteerDrive.RATE else 0.0, w, wv)


def quantize(x: float, counts: int) -> float:
    """``round(x / q) * q`` with ``q = 2 pi / counts`` (``counts = 0``: unchanged)."""
    if counts <= 0:
        return x
    q = 2.0 * math.pi / counts
    return round(x / q) * q


class VirtualDrive(Protocol):
    """One module's drives (steering and wheel) on the bus."""

    @property
    def homed(self) -> bool:
        """The steering has been homed (its reported angle is ``theta - beta``)."""
        ...

    muted: bool
    """Heartbeat loss: the drives send nothing while muted."""

    @property
    def sensor_position(self) -> float:
        """The steering's power-up coordinate of the homing reference (rad)."""
        ...

    heartbeats: int
    feedback_frames: int
    """Heartbeats and feedback frames sent (counters)."""

    def receive(self, msg: can.Message, now: float) -> list[can.Message]:
        """A frame from the bus (every frame: the drive keeps what is its own) at simulated
        time ``now``; the frames it answers with."""
        ...

    def step(self, now: float) -> list[can.Message]:
        """The drives' own logic at ``now`` (watchdogs, homing, heartbeats, feedback)."""
        ...

    def next_due(self) -> float:
        """The next simulated time :meth:`step` has something to do."""
        ...

    def feedback_rate(self) -> float:
        """The rate of its free-running feedback (Hz; 0: none, or on SYNC): the virtual
        robot's tick is never longer than its period."""
        ...

    def drive(
        self, axis: Axis, position: float, dt: float, position_tau: float
    ) -> tuple[str, float]:
        """What ``axis`` does to the physics over the next ``dt`` (``position``: where it
        is now): :func:`simulators.drives.base.axis_drive`'s ``(kind, value)``."""
        ...

    def sense(
        self, axis: Axis, position: float, velocity: float, torque: float | None
    ) -> None:
        """The encoder's reading after a tick; ``torque``: the torque applied (0 passive or
        braked), None for an axis in a rate loop (the drive estimates its own)."""
        ...

    def inject_fault(self, axis: Axis, error: ErrorFlag) -> list[can.Message]:
        """Latch a hardware error on ``axis`` (as the drive reports it on its bus)."""
        ...

    def params(self) -> dict[str, Any]:
        """What the truth document says of these drives (kind, nodes)."""
        ...


def message(frame: Frame) -> can.Message:
    """A classic 11-bit data frame."""
    return can.Message(arbitration_id=frame.arbitration_id, data=frame.data, is_extended_id=False)
