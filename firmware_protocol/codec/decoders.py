"""Decoding: the typed record of each message (:data:`Decoded`) and :func:`parse`, which
checks a received frame's id, DLC and signal ranges against the DBC and builds its record."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cantools
from cantools.database.can import Message

from firmware_protocol.codec.dbc import _messages_by_id
from firmware_protocol.codec.enums import Axis, AxisState, ControlMode, HomingState
from firmware_protocol.codec.exceptions import (
    FrameLengthError,
    ProtocolError,
    SignalRangeError,
    UnknownFrameError,
)
from firmware_protocol.codec.ids import Command, split_id
from firmware_protocol.codec.layout import frame_layout, unpack_frame

# ---------------------------------------------------------------- decoded frames


@dataclass(frozen=True)
class Sync:
    node: int
    counter: int


@dataclass(frozen=True)
class SetAxisState:
    node: int
    axis: Axis
    enabled: bool


@dataclass(frozen=True)
class SetControl:
    node: int
    axis: Axis
    mode: ControlMode
    setpoint: float


@dataclass(frozen=True)
class ClearErrors:
    node: int
    axis_mask: int


@dataclass(frozen=True)
class SetLimits:
    node: int
    axis: Axis
    max_torque: float
    max_velocity: float


@dataclass(frozen=True)
class SetWatchdog:
    node: int
    timeout_ms: int


@dataclass(frozen=True)
class SetFeedback:
    node: int
    rate_hz: int
    sync_mode: bool


@dataclass(frozen=True)
class StartHoming:
    node: int
    axis: Axis


@dataclass(frozen=True)
class Heartbeat:
    node: int
    states: tuple[AxisState, AxisState]
    modes: tuple[ControlMode, ControlMode]
    errors: tuple[int, int]
    homed: bool
    sync_mode: bool
    counter: int


@dataclass(frozen=True)
class FeedbackPosition:
    node: int
    steer: float
    wheel: float
    counter: int


@dataclass(frozen=True)
class FeedbackVelocityTorque:
    node: int
    steer_velocity: float
    wheel_velocity: float
    steer_torque: float
    wheel_torque: float
    counter: int


@dataclass(frozen=True)
class FaultReport:
    node: int
    axis: Axis
    new_errors: int
    active_errors: int
    state: AxisState


@dataclass(frozen=True)
class HomingStatus:
    node: int
    axis: Axis
    status: HomingState
    sensor_position: float


Decoded = (
    Sync
    | SetAxisState
    | SetControl
    | ClearErrors
    | SetLimits
    | SetWatchdog
    | SetFeedback
    | StartHoming
    | Heartbeat
    | FeedbackPosition
    | FeedbackVelocityTorque
    | FaultReport
    | HomingStatus
)


# ---------------------------------------------------------------- parsing


def _decode_values(msg: Message, node: int, data: bytes) -> dict[str, Any]:
    if len(data) != msg.length:
        raise FrameLengthError(
            f"node {node} {msg.name}: DLC {len(data)}, the DBC says {msg.length}"
        )
    layout = frame_layout(msg.frame_id)
    if layout is not None:
        values = unpack_frame(layout, data)
        ranges = [(s.name, s.minimum, s.maximum) for s in layout if s.name in values]
    else:
        try:
            values = msg.decode(data, decode_choices=False, scaling=True)  # type: ignore[assignment]
        except cantools.database.DecodeError as exc:
            raise ProtocolError(f"node {node} {msg.name}: {exc}") from exc
        sigs = [msg.get_signal_by_name(n) for n in values]
        ranges = [(str(s.name), s.minimum, s.maximum) for s in sigs]
    for name, lo, hi in ranges:
        value = values[name]
        v = float(value)
        if (lo is not None and v < lo - 1e-9 * abs(lo)) or (
            hi is not None and v > hi + 1e-9 * abs(hi)
        ):
            raise SignalRangeError(
                f'node {node} {msg.name}: signal "{name}" = {value} outside [{lo}, {hi}]', name
            )
    return values


def parse(arbitration_id: int, data: bytes) -> Decoded:
    """Decode one frame into its typed record.

    Raises :class:`UnknownFrameError` (id not in the DBC), :class:`FrameLengthError`
    (DLC differs from the DBC), :class:`SignalRangeError` (a value outside the DBC range,
    naming the signal) or :class:`ProtocolError`.
    """
    msg = _messages_by_id().get(arbitration_id)
    node, cmd = split_id(arbitration_id)
    if msg is None:
        raise UnknownFrameError(f"unknown frame id 0x{arbitration_id:03x} (node {node})")
    v = _decode_values(msg, node, data)
    command = Command(cmd)
    try:
        return _build(command, node, v)
    except ValueError as exc:  # an enum value the DBC range allows but the enum lacks
        raise ProtocolError(f"node {node} {msg.name}: {exc}") from exc


def _build(command: Command, node: int, v: dict[str, Any]) -> Decoded:
    if command == Command.FEEDBACK_POSITION:
        return FeedbackPosition(
            node, float(v["SteerPosition"]), float(v["WheelPosition"]), int(v["Counter"])
        )
    if command == Command.FEEDBACK_VELOCITY_TORQUE:
        return FeedbackVelocityTorque(
            node,
            float(v["SteerVelocity"]),
            float(v["WheelVelocity"]),
            float(v["SteerTorque"]),
            float(v["WheelTorque"]),
            int(v["Counter"]),
        )
    if command == Command.HEARTBEAT:
        return Heartbeat(
            node,
            (AxisState(int(v["SteerState"])), AxisState(int(v["WheelState"]))),
            (ControlMode(int(v["SteerMode"])), ControlMode(int(v["WheelMode"]))),
            (int(v["SteerErrors"]), int(v["WheelErrors"])),
            bool(v["Homed"]),
            bool(v["SyncMode"]),
            int(v["Counter"]),
        )
    if command == Command.SYNC:
        return Sync(node, int(v["SyncCounter"]))
    if command == Command.SET_AXIS_STATE:
        return SetAxisState(node, Axis(int(v["Axis"])), int(v["RequestedState"]) == 1)
    if command == Command.SET_CONTROL:
        mode = ControlMode(int(v["Mode"]))
        setpoint = float(
            v.get("PositionSetpoint", v.get("VelocitySetpoint", v.get("TorqueSetpoint", 0.0)))
        )
        return SetControl(node, Axis(int(v["Axis"])), mode, setpoint)
    if command == Command.CLEAR_ERRORS:
        return ClearErrors(node, int(v["AxisMask"]))
    if command == Command.SET_LIMITS:
        return SetLimits(node, Axis(int(v["Axis"])), float(v["MaxTorque"]), float(v["MaxVelocity"]))
    if command == Command.SET_WATCHDOG:
        return SetWatchdog(node, int(v["TimeoutMs"]))
    if command == Command.SET_FEEDBACK:
        return SetFeedback(node, int(v["RateHz"]), bool(v["SyncMode"]))
    if command == Command.START_HOMING:
        return StartHoming(node, Axis(int(v["Axis"])))
    if command == Command.FAULT_REPORT:
        return FaultReport(
            node,
            Axis(int(v["Axis"])),
            int(v["NewErrors"]),
            int(v["ActiveErrors"]),
            AxisState(int(v["AxisState"])),
        )
    if command == Command.HOMING_STATUS:
        return HomingStatus(
            node,
            Axis(int(v["Axis"])),
            HomingState(int(v["Status"])),
            float(v["SensorPosition"]),
        )
    raise UnknownFrameError(f"node {node}: no decoder for {command.name}")  # pragma: no cover
