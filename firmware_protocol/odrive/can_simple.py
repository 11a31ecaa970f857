"""ODrive CAN Simple frames through cantools, one codec per firmware line (pure).

ODrive numbers its frames ``id = node << 5 | cmd`` (11-bit ids, node 0..63, one node per
axis: an ODrive v3.6 has two, an S1 or a Pro one).  The DBCs list the messages of nodes
0..7 (``Axis0_*`` .. ``Axis7_*``); the layout of a command is the same for every node, so
:class:`CanSimple` encodes and decodes every node with the ``Axis0_*`` message of the
command and puts the node into the id itself.  Which messages an axis sends and which the
host sends is the DBC's (its senders); the enums' values are checked against its value
tables (``tests/drives/odrive/test_odrive_kind.py``).

Firmware lines (``FIRMWARE_LINES``): ``0.5`` (ODrive v3.6, 0.5.x; heartbeat with the
motor / encoder / controller error flags, axis errors of ``AxisError``) and ``0.6`` (S1,
Pro, 0.6.x; heartbeat with the procedure result, errors of ``ODriveError``).  Only what swpc
uses is decoded into types; the rest of the DBC still decodes with ``cantools decode``.

A frame is taken for an ODrive frame only with its exact DLC and, for a host command, the
exact remote (RTR) use the firmware answers: a frame of swpc's own protocol, whose ids have
the same ``node << 5 | cmd`` layout, never decodes as one
(``tests/drives/odrive/test_odrive_kind.py`` sends
it every swpc frame).
"""

from __future__ import annotations

import enum
import functools
import importlib.util
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cantools
from cantools.database.can import Database, Message

from firmware_protocol.codec import Frame, ProtocolError

NODE_SHIFT = 5
CMD_MASK = (1 << NODE_SHIFT) - 1
MAX_NODE = 0x3F
"""Node ids 0..63 (11-bit ids; ODrive's extended-id mode is not used)."""

FIRMWARE_LINES: dict[str, str] = {"0.5": "odrive-cansimple-0.5.6", "0.6": "odrive-cansimple-0.6.10"}
"""Firmware line -> the DBC of ``odrive-can`` that describes it."""


class Cmd(enum.IntEnum):
    """The command ids swpc uses (``Axis0_<name>`` in the DBC, :data:`MESSAGE_NAMES`;
    ``GET_VERSION`` only where the line's DBC has it: :attr:`CanSimple.has_version`)."""

    GET_VERSION = 0x00
    HEARTBEAT = 0x01
    SET_AXIS_STATE = 0x07
    GET_ENCODER_ESTIMATES = 0x09
    SET_CONTROLLER_MODE = 0x0B
    SET_INPUT_POS = 0x0C
    SET_INPUT_VEL = 0x0D
    SET_INPUT_TORQUE = 0x0E
    SET_LIMITS = 0x0F
    CLEAR_ERRORS = 0x18


MESSAGE_NAMES: dict[Cmd, str] = {
    Cmd.HEARTBEAT: "Heartbeat",
    Cmd.SET_AXIS_STATE: "Set_Axis_State",
    Cmd.GET_ENCODER_ESTIMATES: "Get_Encoder_Estimates",
    Cmd.SET_CONTROLLER_MODE: "Set_Controller_Mode",
    Cmd.SET_INPUT_POS: "Set_Input_Pos",
    Cmd.SET_INPUT_VEL: "Set_Input_Vel",
    Cmd.SET_INPUT_TORQUE: "Set_Input_Torque",
    Cmd.SET_LIMITS: "Set_Limits",
    Cmd.CLEAR_ERRORS: "Clear_Errors",
}


class AxisState(enum.IntEnum):
    """``Axis_State`` / ``Axis_Requested_State`` (the states swpc uses or reports)."""

    UNDEFINED = 0
    IDLE = 1
    STARTUP_SEQUENCE = 2
    FULL_CALIBRATION_SEQUENCE = 3
    MOTOR_CALIBRATION = 4
    ENCODER_INDEX_SEARCH = 6
    ENCODER_OFFSET_CALIBRATION = 7
    CLOSED_LOOP_CONTROL = 8
    HOMING = 11


class ControlMode(enum.IntEnum):
    """``Control_Mode`` of ``Set_Controller_Mode``."""

    VOLTAGE_CONTROL = 0
    TORQUE_CONTROL = 1
    VELOCITY_CONTROL = 2
    POSITION_CONTROL = 3


class InputMode(enum.IntEnum):
    """``Input_Mode`` of ``Set_Controller_Mode`` (swpc sends PASSTHROUGH)."""

    INACTIVE = 0
    PASSTHROUGH = 1
    VEL_RAMP = 2
    POS_FILTER = 3
    TRAP_TRAJ = 5
    TORQUE_RAMP = 6


class ProcedureResult(enum.IntEnum):
    """``Procedure_Result`` of a 0.6.x heartbeat (how the last state request ended; the
    ones swpc uses or reports: the DBC names every value, :meth:`CanSimple.procedure_name`)."""

    SUCCESS = 0
    BUSY = 1
    CANCELLED = 2
    DISARMED = 3
    INVALID_STATE = 13
    """The requested state is not allowed from where the axis is."""
    NOT_CALIBRATED = 14
    """The requested state needs a calibration the axis has not had (closed loop before the
    motor and encoder calibration)."""


# ------------------------------------------------------------------ decoded frames


@dataclass(frozen=True)
class Heartbeat:
    """An axis' heartbeat.  ``procedure_result``: 0.6.x only (None on 0.5.x);
    ``component_errors``: 0.5.x only, bit 0 motor, bit 1 encoder, bit 2 controller."""

    node: int
    axis_error: int
    state: int
    procedure_result: int | None
    trajectory_done: bool
    component_errors: int = 0


@dataclass(frozen=True)
class Version:
    """``Get_Version`` (0.6.x; an axis answers a remote frame of it): the firmware and
    hardware versions and the CAN protocol's."""

    node: int
    protocol: int
    hw_major: int
    hw_minor: int
    hw_variant: int
    fw_major: int
    fw_minor: int
    fw_revision: int
    fw_unreleased: int

    @property
    def firmware(self) -> str:
        """``0.6.10`` (``-dev`` for an unreleased build)."""
        dev = "-dev" if self.fw_unreleased else ""
        return f"{self.fw_major}.{self.fw_minor}.{self.fw_revision}{dev}"

    @property
    def hardware(self) -> str:
        return f"{self.hw_major}.{self.hw_minor}.{self.hw_variant}"


@dataclass(frozen=True)
class EncoderEstimates:
    """``Get_Encoder_Estimates``: position (turns) and velocity (turns/s) of the axis."""

    node: int
    pos: float
    vel: float


@dataclass(frozen=True)
class SetAxisState:
    node: int
    state: int


@dataclass(frozen=True)
class SetControllerMode:
    node: int
    control_mode: int
    input_mode: int


@dataclass(frozen=True)
class SetInputPos:
    node: int
    pos: float
    vel_ff: float
    torque_ff: float


@dataclass(frozen=True)
class SetInputVel:
    node: int
    vel: float
    torque_ff: float


@dataclass(frozen=True)
class SetInputTorque:
    node: int
    torque: float


@dataclass(frozen=True)
class SetLimits:
    node: int
    velocity_limit: float
    current_limit: float


@dataclass(frozen=True)
class ClearErrors:
    node: int


@dataclass(frozen=True)
class Poll:
    """A remote (RTR) request for an axis message (``cmd``): it feeds a 0.5.x watchdog."""

    node: int
    cmd: int


Decoded = (
    Heartbeat
    | Version
    | EncoderEstimates
    | SetAxisState
    | SetControllerMode
    | SetInputPos
    | SetInputVel
    | SetInputTorque
    | SetLimits
    | ClearErrors
    | Poll
)
SETPOINTS = (SetInputPos, SetInputVel, SetInputTorque)
"""The setpoint frames (what feeds a 0.6.x axis watchdog)."""


def split_id(arbitration_id: int) -> tuple[int, int]:
    """``(node, cmd)`` of an 11-bit CAN Simple id."""
    return arbitration_id >> NODE_SHIFT, arbitration_id & CMD_MASK


def dbc_path(line: str) -> Path:
    """The DBC of a firmware line, from the installed ``odrive-can`` package (found without
    importing it: only its data is used)."""
    if line not in FIRMWARE_LINES:
        raise ProtocolError(
            f"ODrive firmware line {line!r} unknown (known: {', '.join(FIRMWARE_LINES)})"
        )
    spec = importlib.util.find_spec("odrive_can")
    if spec is None or not spec.submodule_search_locations:
        raise ProtocolError("the odrive-can package (ODrive's CAN Simple DBCs) is not installed")
    return Path(next(iter(spec.submodule_search_locations))) / "dbc" / f"{FIRMWARE_LINES[line]}.dbc"


class CanSimple:
    """The frames of one firmware line (module docstring).  Immutable; :func:`can_simple`
    keeps one per line."""

    def __init__(self, line: str) -> None:
        self.line = line
        self.path = dbc_path(line)
        db = cantools.database.load_file(str(self.path))
        assert isinstance(db, Database)
        self.database = db
        self._msgs: dict[int, Message] = {}
        self.axis_cmds: frozenset[int] = frozenset()
        axis: set[int] = set()
        host: set[int] = set()
        for m in db.messages:
            node, cmd = split_id(m.frame_id)
            if node != 0:
                continue
            self._msgs[cmd] = m
            (axis if "ODrive_Axis0" in m.senders else host).add(cmd)
        self.axis_cmds = frozenset(axis)
        """Commands an axis sends (heartbeat, estimates, errors, ...)."""
        self.host_cmds = frozenset(host)
        """Commands the host sends."""
        for cmd, name in MESSAGE_NAMES.items():
            if self._msgs.get(cmd) is None or self._msgs[cmd].name != f"Axis0_{name}":
                raise ProtocolError(f"{self.path.name}: no Axis0_{name} at command 0x{cmd:02x}")
        self.watchdog_bit = self.error_bit("WATCHDOG_TIMER_EXPIRED")
        version = self._msgs.get(Cmd.GET_VERSION)
        self.has_version = version is not None and version.name == "Axis0_Get_Version"
        """The line has ``Get_Version`` (0.6.x; 0.5.x reports no version over CAN)."""

    # ------------------------------------------------------------------ ids and names
    def message(self, cmd: int) -> Message:
        return self._msgs[cmd]

    def frame_id(self, node: int, cmd: int) -> int:
        if not 0 <= node <= MAX_NODE:
            raise ProtocolError(f"ODrive node id {node} outside 0..{MAX_NODE}")
        return node << NODE_SHIFT | int(cmd)

    def error_choices(self) -> dict[int, str]:
        """The axis error bits of the heartbeat's ``Axis_Error`` (value -> name)."""
        sig = self._msgs[Cmd.HEARTBEAT].get_signal_by_name("Axis_Error")
        return {int(v): str(n) for v, n in (sig.choices or {}).items()}

    def procedure_name(self, value: int | None) -> str:
        """``"NOT_CALIBRATED"``: a 0.6.x heartbeat's ``Procedure_Result`` by its DBC name
        (the number when the DBC has no name for it; ``"-"`` on 0.5.x, which has none)."""
        if value is None or self.line == "0.5":
            return "-"
        sig = self._msgs[Cmd.HEARTBEAT].get_signal_by_name("Procedure_Result")
        names = {int(v): str(n) for v, n in (sig.choices or {}).items()}
        return names.get(value, str(value))

    def error_bit(self, name: str) -> int:
        for value, n in self.error_choices().items():
            if n == name:
                return value
        raise ProtocolError(f"{self.path.name}: no axis error {name}")

    def error_names(self, bits: int) -> str:
        """``"WATCHDOG_TIMER_EXPIRED|OVER_TEMP"`` (unknown bits in hex; ``"none"``)."""
        if not bits:
            return "none"
        names = [n for v, n in sorted(self.error_choices().items()) if v and bits & v == v]
        rest = bits
        for v in self.error_choices():
            if v and bits & v == v:
                rest &= ~v
        if rest:
            names.append(f"0x{rest:x}")
        return "|".join(names)

    # ------------------------------------------------------------------ encode
    def encode(self, node: int, cmd: Cmd, values: dict[str, Any] | None = None) -> Frame:
        """A data frame of ``cmd`` to or from ``node`` (signals by their DBC names)."""
        msg = self._msgs[cmd]
        vals = values or {}
        for k, v in vals.items():
            if isinstance(v, float) and not math.isfinite(v):
                raise ProtocolError(f"{msg.name[6:]}: {k} = {v} is not finite")
        try:
            data = msg.encode(vals, scaling=True, strict=True) if msg.signals else b""
        except (cantools.database.EncodeError, KeyError, ValueError) as exc:
            raise ProtocolError(f"{msg.name[6:]}: {exc}") from exc
        return Frame(self.frame_id(node, cmd), bytes(data))

    def set_axis_state(self, node: int, state: AxisState) -> Frame:
        return self.encode(node, Cmd.SET_AXIS_STATE, {"Axis_Requested_State": int(state)})

    def set_controller_mode(
        self, node: int, control: ControlMode, input_mode: InputMode = InputMode.PASSTHROUGH
    ) -> Frame:
        return self.encode(
            node,
            Cmd.SET_CONTROLLER_MODE,
            {"Control_Mode": int(control), "Input_Mode": int(input_mode)},
        )

    def set_input_pos(self, node: int, turns: float) -> Frame:
        return self.encode(
            node, Cmd.SET_INPUT_POS, {"Input_Pos": turns, "Vel_FF": 0.0, "Torque_FF": 0.0}
        )

    def set_input_vel(self, node: int, turns_per_s: float) -> Frame:
        return self.encode(
            node, Cmd.SET_INPUT_VEL, {"Input_Vel": turns_per_s, "Input_Torque_FF": 0.0}
        )

    def set_input_torque(self, node: int, torque: float) -> Frame:
        return self.encode(node, Cmd.SET_INPUT_TORQUE, {"Input_Torque": torque})

    def set_limits(self, node: int, velocity_limit: float, current_limit: float) -> Frame:
        return self.encode(
            node,
            Cmd.SET_LIMITS,
            {"Velocity_Limit": velocity_limit, "Current_Limit": current_limit},
        )

    def clear_errors(self, node: int) -> Frame:
        msg = self._msgs[Cmd.CLEAR_ERRORS]
        return self.encode(node, Cmd.CLEAR_ERRORS, {"Identify": 0} if msg.signals else None)

    def heartbeat(
        self,
        node: int,
        axis_error: int,
        state: AxisState,
        *,
        procedure_result: int = 0,
        trajectory_done: bool = True,
        component_errors: int = 0,
    ) -> Frame:
        v: dict[str, Any] = {
            "Axis_Error": axis_error,
            "Axis_State": int(state),
            "Trajectory_Done_Flag": int(trajectory_done),
        }
        if self.line == "0.5":
            v["Motor_Error_Flag"] = component_errors & 1
            v["Encoder_Error_Flag"] = component_errors >> 1 & 1
            v["Controller_Error_Flag"] = component_errors >> 2 & 1
        else:
            v["Procedure_Result"] = procedure_result
        return self.encode(node, Cmd.HEARTBEAT, v)

    def version(self, node: int, firmware: tuple[int, int, int], hardware: tuple[int, int, int],
                protocol: int = 0, unreleased: bool = False) -> Frame:
        """An axis' ``Get_Version`` answer (:class:`ProtocolError` on a line without it)."""
        if not self.has_version:
            raise ProtocolError(f"ODrive firmware {self.line}: no Get_Version message")
        return self.encode(node, Cmd.GET_VERSION, {
            "Protocol_Version": protocol,
            "Hw_Version_Major": hardware[0], "Hw_Version_Minor": hardware[1],
            "Hw_Version_Variant": hardware[2],
            "Fw_Version_Major": firmware[0], "Fw_Version_Minor": firmware[1],
            "Fw_Version_Revision": firmware[2], "Fw_Version_Unreleased": int(unreleased),
        })  # fmt: skip

    def version_request(self, node: int) -> Frame:
        """The remote frame's id that asks ``node`` for its version (no data: send it as a
        remote frame of DLC 8)."""
        if not self.has_version:
            raise ProtocolError(f"ODrive firmware {self.line}: no Get_Version message")
        return Frame(self.frame_id(node, Cmd.GET_VERSION), b"")

    def encoder_estimates(self, node: int, pos: float, vel: float) -> Frame:
        return self.encode(
            node, Cmd.GET_ENCODER_ESTIMATES, {"Pos_Estimate": pos, "Vel_Estimate": vel}
        )

    # ------------------------------------------------------------------ decode
    def decode(self, arbitration_id: int, data: bytes, remote: bool = False) -> Decoded | None:
        """The frame as swpc reads it; None for an ODrive frame swpc does not use.

        :class:`ProtocolError` for a frame that is not an ODrive frame at all (an id above
        the 11-bit range, a command the DBC does not have, a DLC other than the DBC's, a
        remote frame of a host command)."""
        if not 0 <= arbitration_id <= 0x7FF:
            raise ProtocolError(f"id 0x{arbitration_id:x} is not an 11-bit CAN Simple id")
        node, cmd = split_id(arbitration_id)
        msg = self._msgs.get(cmd)
        if msg is None:
            raise ProtocolError(f"id 0x{arbitration_id:03x}: no ODrive command 0x{cmd:02x}")
        if remote:
            if cmd not in self.axis_cmds:
                raise ProtocolError(
                    f"id 0x{arbitration_id:03x}: remote frame of host command {msg.name[6:]}"
                )
            return Poll(node, cmd)
        if len(data) != msg.length:
            raise ProtocolError(
                f"id 0x{arbitration_id:03x} ({msg.name[6:]}): DLC {len(data)}, the DBC says "
                f"{msg.length}"
            )
        if cmd not in _DECODERS:
            return None
        v = msg.decode(data, decode_choices=False, scaling=True) if msg.signals else {}
        decoded: Decoded = _DECODERS[cmd](self, node, v)
        return decoded


def _heartbeat(cs: CanSimple, node: int, v: dict[str, Any]) -> Heartbeat:
    if cs.line == "0.5":
        flags = (
            int(v["Motor_Error_Flag"])
            | int(v["Encoder_Error_Flag"]) << 1
            | int(v["Controller_Error_Flag"]) << 2
        )
        return Heartbeat(
            node, int(v["Axis_Error"]), int(v["Axis_State"]), None,
            bool(v["Trajectory_Done_Flag"]), flags,
        )  # fmt: skip
    return Heartbeat(
        node, int(v["Axis_Error"]), int(v["Axis_State"]), int(v["Procedure_Result"]),
        bool(v["Trajectory_Done_Flag"]),
    )  # fmt: skip


_VERSION_SIGNALS = (
    "Protocol_Version", "Hw_Version_Major", "Hw_Version_Minor", "Hw_Version_Variant",
    "Fw_Version_Major", "Fw_Version_Minor", "Fw_Version_Revision", "Fw_Version_Unreleased",
)  # fmt: skip
"""``Get_Version``'s signals in :class:`Version`'s order."""

_DECODERS: dict[int, Any] = {
    Cmd.GET_VERSION: lambda cs, n, v: Version(n, *(int(v[k]) for k in _VERSION_SIGNALS)),
    Cmd.HEARTBEAT: _heartbeat,
    Cmd.GET_ENCODER_ESTIMATES: lambda cs, n, v: EncoderEstimates(
        n, float(v["Pos_Estimate"]), float(v["Vel_Estimate"])
    ),
    Cmd.SET_AXIS_STATE: lambda cs, n, v: SetAxisState(n, int(v["Axis_Requested_State"])),
    Cmd.SET_CONTROLLER_MODE: lambda cs, n, v: SetControllerMode(
        n, int(v["Control_Mode"]), int(v["Input_Mode"])
    ),
    Cmd.SET_INPUT_POS: lambda cs, n, v: SetInputPos(
        n, float(v["Input_Pos"]), float(v["Vel_FF"]), float(v["Torque_FF"])
    ),
    Cmd.SET_INPUT_VEL: lambda cs, n, v: SetInputVel(
        n, float(v["Input_Vel"]), float(v["Input_Torque_FF"])
    ),
    Cmd.SET_INPUT_TORQUE: lambda cs, n, v: SetInputTorque(n, float(v["Input_Torque"])),
    Cmd.SET_LIMITS: lambda cs, n, v: SetLimits(
        n, float(v["Velocity_Limit"]), float(v["Current_Limit"])
    ),
    Cmd.CLEAR_ERRORS: lambda cs, n, v: ClearErrors(n),
}


@functools.cache
def can_simple(line: str) -> CanSimple:
    """The codec of a firmware line (loaded once)."""
    return CanSimple(line)
