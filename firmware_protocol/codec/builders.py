"""The frame builders: pure ``make_*`` functions, one a message (host -> node, then
node -> host), each returning the :class:`~firmware_protocol.codec.ids.Frame` to send.

Values go through the compiled layout when they certainly encode, else through cantools'
strict encoding, whose errors name the offending signal (:class:`SignalRangeError`).
"""

from __future__ import annotations

from typing import Any

import cantools
from cantools.database.can import Message

from firmware_protocol.codec.dbc import message_for, wrap
from firmware_protocol.codec.enums import Axis, AxisState, ControlMode, HomingState
from firmware_protocol.codec.exceptions import ProtocolError, SignalRangeError
from firmware_protocol.codec.ids import Command, Frame
from firmware_protocol.codec.layout import frame_layout, pack_frame


def _encode(node: int, command: Command, values: dict[str, Any]) -> Frame:
    msg = message_for(node, command)
    layout = frame_layout(msg.frame_id)
    if layout is not None:
        bits = pack_frame(layout, values)
        if bits is not None:
            return Frame(msg.frame_id, bits.to_bytes(msg.length, "little"))
    try:  # strict: cantools names the offending signal
        data = msg.encode(values, scaling=True, padding=False, strict=True)
    except cantools.database.EncodeError as exc:
        signal = _signal_in(str(exc), msg)
        raise SignalRangeError(f"node {node} {msg.name}: {exc}", signal) from exc
    except (KeyError, ValueError, TypeError) as exc:
        raise ProtocolError(f"node {node} {msg.name}: cannot encode {values}: {exc}") from exc
    return Frame(msg.frame_id, bytes(data))


def _signal_in(text: str, msg: Message) -> str:
    for sig in msg.signals:
        if f'"{sig.name}"' in text:
            return str(sig.name)
    return ""


# ---------------------------------------------------------------- builders (host -> node)


def make_sync(counter: int) -> Frame:
    """Broadcast SYNC (id 0x000): every controller in sync mode samples now."""
    return _encode(0, Command.SYNC, {"SyncCounter": counter})


def make_set_axis_state(node: int, axis: Axis, enabled: bool) -> Frame:
    return _encode(
        node,
        Command.SET_AXIS_STATE,
        {"Axis": int(axis), "RequestedState": int(AxisState.ENABLED if enabled else 0)},
    )


def make_set_control(node: int, axis: Axis, mode: ControlMode, setpoint: float = 0.0) -> Frame:
    """Mode and setpoint (rad, rad/s or N.m by mode; ignored for FREE and HOLD)."""
    values: dict[str, Any] = {"Axis": int(axis), "Mode": int(mode)}
    if mode == ControlMode.POSITION:
        values["PositionSetpoint"] = setpoint
    elif mode == ControlMode.VELOCITY:
        values["VelocitySetpoint"] = setpoint
    elif mode == ControlMode.TORQUE:
        values["TorqueSetpoint"] = setpoint
    return _encode(node, Command.SET_CONTROL, values)


def make_clear_errors(node: int, axis_mask: int = 0b11) -> Frame:
    """Clear the latched errors of the axes in ``axis_mask`` (bit 0 steer, bit 1 wheel)."""
    return _encode(node, Command.CLEAR_ERRORS, {"AxisMask": axis_mask})


def make_set_limits(node: int, axis: Axis, max_torque: float, max_velocity: float) -> Frame:
    return _encode(
        node,
        Command.SET_LIMITS,
        {"Axis": int(axis), "MaxTorque": max_torque, "MaxVelocity": max_velocity},
    )


def make_set_watchdog(node: int, timeout_ms: int) -> Frame:
    """Command watchdog timeout in ms (0 disables it)."""
    return _encode(node, Command.SET_WATCHDOG, {"TimeoutMs": timeout_ms})


def make_set_feedback(node: int, rate_hz: int, sync_mode: bool = False) -> Frame:
    """Feedback stream rate (0 = off, up to 500 Hz) or one sample per SYNC."""
    return _encode(node, Command.SET_FEEDBACK, {"RateHz": rate_hz, "SyncMode": int(sync_mode)})


def make_start_homing(node: int, axis: Axis = Axis.STEER) -> Frame:
    return _encode(node, Command.START_HOMING, {"Axis": int(axis)})


# ---------------------------------------------------------------- builders (node -> host)


def make_heartbeat(
    node: int,
    states: tuple[AxisState, AxisState],
    modes: tuple[ControlMode, ControlMode],
    errors: tuple[int, int],
    homed: bool,
    sync_mode: bool,
    counter: int,
) -> Frame:
    return _encode(
        node,
        Command.HEARTBEAT,
        {
            "SteerState": int(states[0]),
            "SteerMode": int(modes[0]),
            "WheelState": int(states[1]),
            "WheelMode": int(modes[1]),
            "SteerErrors": int(errors[0]),
            "WheelErrors": int(errors[1]),
            "Homed": int(homed),
            "SyncMode": int(sync_mode),
            "Counter": counter,
        },
    )


def make_feedback_position(node: int, steer: float, wheel: float, counter: int) -> Frame:
    """Positions in rad; both wrap like the controller's fixed-point counters."""
    return _encode(
        node,
        Command.FEEDBACK_POSITION,
        {
            "SteerPosition": wrap(steer, "SteerPosition"),
            "WheelPosition": wrap(wheel, "WheelPosition"),
            "Counter": counter,
        },
    )


def make_feedback_velocity_torque(
    node: int,
    steer_velocity: float,
    wheel_velocity: float,
    steer_torque: float,
    wheel_torque: float,
    counter: int,
) -> Frame:
    return _encode(
        node,
        Command.FEEDBACK_VELOCITY_TORQUE,
        {
            "SteerVelocity": steer_velocity,
            "WheelVelocity": wheel_velocity,
            "SteerTorque": steer_torque,
            "WheelTorque": wheel_torque,
            "Counter": counter,
        },
    )


def make_fault_report(
    node: int, axis: Axis, new_errors: int, active_errors: int, state: AxisState
) -> Frame:
    return _encode(
        node,
        Command.FAULT_REPORT,
        {
            "Axis": int(axis),
            "NewErrors": int(new_errors),
            "ActiveErrors": int(active_errors),
            "AxisState": int(state),
        },
    )


def make_homing_status(
    node: int, axis: Axis, status: HomingState, sensor_position: float = 0.0
) -> Frame:
    return _encode(
        node,
        Command.HOMING_STATUS,
        {"Axis": int(axis), "Status": int(status), "SensorPosition": sensor_position},
    )
