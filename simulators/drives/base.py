"""What one controller axis does to the physics: the virtual controller's state and mode
turned into a drive of :class:`simulators.physics.robot.RobotPhysics`, and encoder quantisation."""

from __future__ import annotations

import math

from firmware_protocol.codec import Axis, AxisState, ControlMode
from simulators.drives.swpc import AxisModel
from simulators.physics.robot import ModuleDrive, SteerDrive, WheelDrive

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
