"""CAN driver of the caster-module controllers (python-can + the DBC in firmware_protocol)."""

from __future__ import annotations

from firmware_protocol.codec import Axis, AxisState, ControlMode, ErrorFlag, HomingState
from swpc_hw.can.config import CanConfig
from swpc_hw.can.driver import CanDriver
from swpc_hw.can.errors import (
    CanBusError,
    CanCommandError,
    CanConfigError,
    CanError,
    LifecycleError,
    NodeError,
    NodeTimeoutError,
)
from swpc_hw.can.types import (
    DriverEvent,
    DriverStats,
    EventKind,
    FeedbackSample,
    Lifecycle,
    ModuleState,
    Severity,
)

__all__ = [
    "Axis",
    "AxisState",
    "CanBusError",
    "CanCommandError",
    "CanConfig",
    "CanConfigError",
    "CanDriver",
    "CanError",
    "ControlMode",
    "DriverEvent",
    "DriverStats",
    "ErrorFlag",
    "EventKind",
    "FeedbackSample",
    "HomingState",
    "Lifecycle",
    "LifecycleError",
    "ModuleState",
    "NodeError",
    "NodeTimeoutError",
    "Severity",
]
