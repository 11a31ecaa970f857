"""The signals' enumerations: the axis, its state and control mode, the homing state and
the latched error bits (:class:`ErrorFlag`, named by :func:`error_names`)."""

from __future__ import annotations

import enum


class Axis(enum.IntEnum):
    STEER = 0
    WHEEL = 1


class AxisState(enum.IntEnum):
    DISABLED = 0
    ENABLED = 1
    HOMING = 2
    FAULT = 3


class ControlMode(enum.IntEnum):
    FREE = 0
    HOLD = 1
    POSITION = 2
    VELOCITY = 3
    TORQUE = 4


class HomingState(enum.IntEnum):
    NOT_HOMED = 0
    IN_PROGRESS = 1
    DONE = 2
    FAILED = 3


class ErrorFlag(enum.IntFlag):
    """Latched per-axis error bits (Heartbeat ``SteerErrors``/``WheelErrors``)."""

    NONE = 0
    WATCHDOG_TIMEOUT = 1 << 0
    OVER_SPEED = 1 << 1
    OVER_TORQUE = 1 << 2
    HOMING_FAILED = 1 << 3
    NOT_HOMED = 1 << 4
    INVALID_COMMAND = 1 << 5
    ENCODER = 1 << 6
    OVER_TEMPERATURE = 1 << 7
    UNDER_VOLTAGE = 1 << 8
    MOTOR = 1 << 9


def error_names(bits: int) -> str:
    """``"WATCHDOG_TIMEOUT|OVER_SPEED"`` for an error word, ``"-"`` for 0."""
    names = [f.name for f in ErrorFlag if f and bits & f and f.name]
    unknown = bits & ~sum(int(f) for f in ErrorFlag)
    if unknown:
        names.append(f"0x{unknown:04x}")
    return "|".join(names) if names else "-"
