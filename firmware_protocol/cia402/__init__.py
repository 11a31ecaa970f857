"""CiA 402 over CANopen: the protocol data both sides use (pure, no I/O).

What a CiA 402 drive is to swpc: one CANopen node per axis, its object dictionary from an
EDS/DCF (``swpc_axis.eds`` here is the virtual drive's, and the list of objects a real
drive must have: ``docs/drives.md``), the 402 power state machine (statusword ->
state, controlword commands, the drive's transitions), the modes of operation, the PDO
mapping swpc configures, and the names of EMCY error codes.

The host (``swpc_hw/drives/cia402/``) and the virtual drive (``simulators/drives/cia402.py``)
both take these from here; SDO, PDO, NMT and EMCY themselves are the ``canopen``
library's.  Objects by CiA 301 / CiA 402 (IEC 61800-7-201) index.
"""

from __future__ import annotations

import enum
from pathlib import Path

EDS_PATH = Path(__file__).with_name("swpc_axis.eds")
"""The object dictionary of one virtual axis (and the default ``drives.object_dictionary``)."""

# ----------------------------------------------------------------------- objects (index)
DEVICE_TYPE = 0x1000
ERROR_REGISTER = 0x1001
GUARD_TIME = 0x100C
"""Node guarding (CiA 301): the master's guard period, ms (0: no life guarding)."""
LIFE_TIME_FACTOR = 0x100D
"""Life guarding: the node stops ``0x100C x 0x100D`` ms after the master's last guard
request (a remote request on the node's ``0x700 + node``, answered with its NMT state and
a toggle bit 7)."""
CONSUMER_HEARTBEAT = 0x1016
PRODUCER_HEARTBEAT = 0x1017
ERROR_CODE = 0x603F
CONTROLWORD = 0x6040
STATUSWORD = 0x6041
QUICK_STOP_OPTION = 0x605A
MODES_OF_OPERATION = 0x6060
MODES_DISPLAY = 0x6061
POSITION_ACTUAL = 0x6064
VELOCITY_ACTUAL = 0x606C
TARGET_TORQUE = 0x6071
MAX_TORQUE = 0x6072
RATED_TORQUE = 0x6076
"""Motor rated torque, mN.m: the unit of every torque object is a thousandth of it."""
TORQUE_ACTUAL = 0x6077
TARGET_POSITION = 0x607A
MAX_PROFILE_VELOCITY = 0x607F
ENCODER_RESOLUTION = 0x608F
"""Factor group: sub 1 encoder increments per sub 2 motor revolutions."""
GEAR_RATIO = 0x6091
"""Factor group: sub 1 motor revolutions per sub 2 shaft revolutions."""
HOMING_METHOD = 0x6098
TARGET_VELOCITY = 0x60FF
SUPPORTED_MODES = 0x6502

# ----------------------------------------------------------------------- COB-IDs
NMT_ID = 0x000
SYNC_ID = 0x080
EMCY_BASE = 0x080
TPDO_BASE = (0x180, 0x280, 0x380, 0x480)
RPDO_BASE = (0x200, 0x300, 0x400, 0x500)
"""PDOs 1-4's COB-IDs (+ node): CiA 301's predefined connection set."""
SDO_TX_BASE = 0x580
SDO_RX_BASE = 0x600
HEARTBEAT_BASE = 0x700
MAX_NODE = 127

NMT_BOOT_UP = 0
NMT_STOPPED = 4
NMT_OPERATIONAL = 5
NMT_PRE_OPERATIONAL = 127
SDO_ABSENT = frozenset({0x06020000, 0x06090011})
"""SDO aborts that say the drive has no such object (0x06020000) or subindex (0x06090011)."""

NMT_NAMES = {
    NMT_BOOT_UP: "boot-up",
    NMT_STOPPED: "STOPPED",
    NMT_OPERATIONAL: "OPERATIONAL",
    NMT_PRE_OPERATIONAL: "PRE-OPERATIONAL",
}
"""The NMT states a heartbeat reports (its byte's low 7 bits)."""


def nmt_name(state: int) -> str:
    """``OPERATIONAL``, or the byte in hex for a state CiA 301 does not name."""
    return NMT_NAMES.get(state & 0x7F, f"0x{state & 0x7F:02X}")


NMT_START = 0x01
NMT_ENTER_PRE_OPERATIONAL = 0x80
NMT_RESET_NODE = 0x81
NMT_RESET_COMMUNICATION = 0x82

# ----------------------------------------------------------------------- the PDOs swpc maps
PdoEntry = tuple[int, int, int]
"""(index, sub-index, bits) of one mapped object."""

RPDO_MAP: dict[int, tuple[PdoEntry, ...]] = {
    1: ((CONTROLWORD, 0, 16), (MODES_OF_OPERATION, 0, 8), (TARGET_TORQUE, 0, 16)),
    2: ((TARGET_POSITION, 0, 32), (TARGET_VELOCITY, 0, 32)),
}
"""Host -> drive, applied on reception (transmission type :data:`RPDO_ASYNC`): RPDO 2 (the
targets) is sent before RPDO 1 (controlword, mode), so a mode starts on its own target.
Each group in its PDO where the drive's mapping has room; spread over PDOs 3 and 4 where it
has not (:func:`swpc_hw.drives.cia402.setup.place`)."""
TPDO_MAP: dict[int, tuple[PdoEntry, ...]] = {
    1: ((STATUSWORD, 0, 16), (POSITION_ACTUAL, 0, 32), (MODES_DISPLAY, 0, 8)),
    2: ((VELOCITY_ACTUAL, 0, 32), (TORQUE_ACTUAL, 0, 16)),
}
"""Drive -> host, on every SYNC (transmission type :data:`TPDO_ON_SYNC`): one feedback
sample of both axes of a module is the pair of TPDOs after one SYNC."""
TPDO_ON_SYNC = 1
RPDO_ASYNC = 255


def consumer_entry(node: int, time_ms: int) -> int:
    """A 0x1016 entry: watch ``node``'s heartbeat, ``time_ms`` without one is a loss."""
    if not 1 <= node <= MAX_NODE or not 0 <= time_ms <= 0xFFFF:
        raise ValueError(f"heartbeat consumer: node {node} (1..127), time {time_ms} ms (0..65535)")
    return (node << 16) | time_ms


def parse_consumer_entry(value: int) -> tuple[int, int]:
    """(node, time ms) of a 0x1016 entry (time 0: not watched)."""
    return (value >> 16) & 0x7F, value & 0xFFFF


# ----------------------------------------------------------------------- modes of operation
class Mode(enum.IntEnum):
    """0x6060 / 0x6061 (the ones swpc uses or may meet)."""

    NONE = 0
    PROFILE_POSITION = 1
    PROFILE_VELOCITY = 3
    PROFILE_TORQUE = 4
    HOMING = 6
    CYCLIC_SYNC_POSITION = 8
    CYCLIC_SYNC_VELOCITY = 9
    CYCLIC_SYNC_TORQUE = 10


def mode_name(value: int) -> str:
    try:
        return Mode(value).name
    except ValueError:
        return f"mode {value}"


def supported_modes_bit(mode: Mode) -> int:
    """The bit of ``mode`` in 0x6502 (bit ``mode - 1`` for the profile's modes 1..10)."""
    return 1 << (int(mode) - 1)


# ----------------------------------------------------------------------- power state machine
class PowerState(enum.Enum):
    NOT_READY_TO_SWITCH_ON = "not ready to switch on"
    SWITCH_ON_DISABLED = "switch on disabled"
    READY_TO_SWITCH_ON = "ready to switch on"
    SWITCHED_ON = "switched on"
    OPERATION_ENABLED = "operation enabled"
    QUICK_STOP_ACTIVE = "quick stop active"
    FAULT_REACTION_ACTIVE = "fault reaction active"
    FAULT = "fault"


_STATE_BITS: tuple[tuple[int, int, PowerState], ...] = (
    (0x4F, 0x00, PowerState.NOT_READY_TO_SWITCH_ON),
    (0x4F, 0x40, PowerState.SWITCH_ON_DISABLED),
    (0x6F, 0x21, PowerState.READY_TO_SWITCH_ON),
    (0x6F, 0x23, PowerState.SWITCHED_ON),
    (0x6F, 0x27, PowerState.OPERATION_ENABLED),
    (0x6F, 0x07, PowerState.QUICK_STOP_ACTIVE),
    (0x4F, 0x0F, PowerState.FAULT_REACTION_ACTIVE),
    (0x4F, 0x08, PowerState.FAULT),
)
"""(mask, value, state) of the statusword's bits 0-3, 5, 6 (CiA 402 table 30)."""

SW_VOLTAGE_ENABLED = 1 << 4
SW_WARNING = 1 << 7
SW_REMOTE = 1 << 9
SW_TARGET_REACHED = 1 << 10
SW_HOMING_ATTAINED = 1 << 12
SW_SETPOINT_ACK = 1 << 12
"""Bit 12 in profile position mode: the set-point was taken (the handshake's answer)."""
"""Bit 12 in homing mode; other modes give it other meanings."""
SW_HOMING_ERROR = 1 << 13


def power_state(statusword: int) -> PowerState:
    for mask, value, state in _STATE_BITS:
        if statusword & mask == value:
            return state
    return PowerState.NOT_READY_TO_SWITCH_ON


def statusword(state: PowerState, extra: int = 0) -> int:
    """The statusword a drive reports in ``state`` (plus ``extra`` bits: remote, target
    reached, homing)."""
    for _mask, value, s in _STATE_BITS:
        if s is state:
            voltage = (
                SW_VOLTAGE_ENABLED
                if state in (PowerState.SWITCHED_ON, PowerState.OPERATION_ENABLED,
                             PowerState.QUICK_STOP_ACTIVE)
                else 0
            )  # fmt: skip
            return value | voltage | extra
    raise AssertionError(state)


CW_SHUTDOWN = 0x0006
CW_SWITCH_ON = 0x0007
CW_DISABLE_VOLTAGE = 0x0000
CW_QUICK_STOP = 0x0002
CW_DISABLE_OPERATION = 0x0007
CW_ENABLE_OPERATION = 0x000F
CW_HOMING_START = 0x0010
"""Bit 4 in homing mode: a rising edge starts homing."""
CW_NEW_SETPOINT = 0x0010
"""Bit 4 in profile position mode: a rising edge hands the drive the target (0x607A); the
drive acknowledges it (statusword bit 12, :data:`SW_SETPOINT_ACK`), then the host takes
bit 4 low again and the drive its acknowledgement (the set-point handshake)."""
CW_CHANGE_IMMEDIATELY = 0x0020
"""Bit 5 in profile position mode: a new set-point replaces the one in progress."""
CW_FAULT_RESET = 0x0080
"""Bit 7: a rising edge resets a fault."""


class Command(enum.Enum):
    """What a controlword's bits 0-3 command (CiA 402 table 28; fault reset apart)."""

    SHUTDOWN = "shutdown"
    SWITCH_ON = "switch on"
    DISABLE_VOLTAGE = "disable voltage"
    QUICK_STOP = "quick stop"
    ENABLE_OPERATION = "enable operation"


def command(controlword: int) -> Command:
    if not controlword & 0x2:
        return Command.DISABLE_VOLTAGE
    if not controlword & 0x4:
        return Command.QUICK_STOP
    if not controlword & 0x1:
        return Command.SHUTDOWN
    if not controlword & 0x8:
        return Command.SWITCH_ON  # also "disable operation" from OPERATION ENABLED
    return Command.ENABLE_OPERATION


QUICK_STOP_TO_DISABLED = frozenset({0, 1, 2, 3, 4})
"""0x605A option codes after whose stop the drive goes to SWITCH ON DISABLED (5-8 stay in
QUICK STOP ACTIVE)."""


def drive_transition(
    state: PowerState, controlword: int, previous: int
) -> PowerState:
    """The drive's side: the state after receiving ``controlword`` (``previous``: the one
    before it, for the fault reset's rising edge).  Transitions 2-12 and 15 of CiA 402;
    the automatic ones (0, 1, 13, 14, the end of a quick stop) are the drive's own."""
    cmd = command(controlword)
    S = PowerState
    if state is S.FAULT:
        if controlword & CW_FAULT_RESET and not previous & CW_FAULT_RESET:
            return S.SWITCH_ON_DISABLED
        return state
    if state in (S.FAULT_REACTION_ACTIVE, S.NOT_READY_TO_SWITCH_ON):
        return state
    if cmd in (Command.DISABLE_VOLTAGE,):
        return S.SWITCH_ON_DISABLED
    if cmd is Command.QUICK_STOP:
        return S.QUICK_STOP_ACTIVE if state is S.OPERATION_ENABLED else (
            state if state is S.QUICK_STOP_ACTIVE else S.SWITCH_ON_DISABLED
        )
    if state is S.SWITCH_ON_DISABLED:
        return S.READY_TO_SWITCH_ON if cmd is Command.SHUTDOWN else state
    if state is S.READY_TO_SWITCH_ON:
        return S.SWITCHED_ON if cmd in (Command.SWITCH_ON, Command.ENABLE_OPERATION) else state
    if state is S.SWITCHED_ON:
        if cmd is Command.SHUTDOWN:
            return S.READY_TO_SWITCH_ON
        return S.OPERATION_ENABLED if cmd is Command.ENABLE_OPERATION else state
    if state is S.OPERATION_ENABLED:
        if cmd is Command.SHUTDOWN:
            return S.READY_TO_SWITCH_ON
        return S.SWITCHED_ON if cmd is Command.SWITCH_ON else state
    if state is S.QUICK_STOP_ACTIVE:
        return S.OPERATION_ENABLED if cmd is Command.ENABLE_OPERATION else state
    return state


def host_controlword(
    state: PowerState,
    enable: bool,
    reset: bool,
    last: int,
    homing_start: bool = False,
    profile_position: bool = False,
    new_setpoint: bool = False,
) -> int | None:
    """The host's side: the next controlword towards OPERATION ENABLED (``enable``) or
    SWITCH ON DISABLED, one transition per statusword; None while the drive is in a state
    it leaves by itself (fault reaction) or in FAULT without ``reset`` (a fault is reset
    only when asked: :meth:`Drives.clear_errors`).  ``last``: the controlword sent before
    (the fault reset needs a rising edge of bit 7).  In OPERATION ENABLED the mode's bits:
    homing's start (bit 4), profile position's change-immediately (bit 5) and new
    set-point (bit 4, ``new_setpoint``)."""
    S = PowerState
    if state is S.FAULT_REACTION_ACTIVE:
        return None
    if state is S.FAULT:
        if not reset:
            return None
        return CW_DISABLE_VOLTAGE if last & CW_FAULT_RESET else CW_FAULT_RESET
    if not enable:
        return CW_DISABLE_VOLTAGE
    nxt = {
        S.NOT_READY_TO_SWITCH_ON: CW_DISABLE_VOLTAGE,
        S.SWITCH_ON_DISABLED: CW_SHUTDOWN,
        S.READY_TO_SWITCH_ON: CW_SWITCH_ON,
        S.SWITCHED_ON: CW_ENABLE_OPERATION,
        S.QUICK_STOP_ACTIVE: CW_DISABLE_VOLTAGE,
        S.OPERATION_ENABLED: CW_ENABLE_OPERATION,
    }[state]
    if state is S.OPERATION_ENABLED and homing_start:
        nxt |= CW_HOMING_START
    if state is S.OPERATION_ENABLED and profile_position:
        nxt |= CW_CHANGE_IMMEDIATELY | (CW_NEW_SETPOINT if new_setpoint else 0)
    return nxt


# ----------------------------------------------------------------------- EMCY
EMCY_NAMES: dict[int, str] = {
    0x1000: "generic error",
    0x2310: "continuous over-current",
    0x2320: "short circuit at outputs",
    0x3210: "DC link over-voltage",
    0x3220: "DC link under-voltage",
    0x4210: "excess temperature device",
    0x4310: "excess temperature drive",
    0x5530: "EEPROM / data storage error",
    0x6320: "parameter error",
    0x7121: "motor blocked",
    0x7305: "incremental sensor 1 fault",
    0x8110: "CAN overrun (objects lost)",
    0x8120: "CAN in error passive mode",
    0x8130: "life guard or heartbeat error (the host's heartbeat was lost)",
    0x8140: "recovered from bus-off",
    0x8400: "velocity speed controller (over-speed)",
    0x8611: "following error",
    0xFF00: "device specific",
}
"""CiA 301 / CiA 402 error codes (the drive's manual has its own device-specific ones)."""

_EMCY_CLASSES = (
    (0x0000, 0xFF00, "error reset / no error"),
    (0x1000, 0xFF00, "generic error"),
    (0x2000, 0xF000, "current"),
    (0x3000, 0xF000, "voltage"),
    (0x4000, 0xF000, "temperature"),
    (0x5000, 0xFF00, "device hardware"),
    (0x6000, 0xF000, "device software"),
    (0x7000, 0xFF00, "additional modules"),
    (0x8000, 0xF000, "monitoring"),
    (0x9000, 0xFF00, "external error"),
    (0xF000, 0xFF00, "additional functions"),
    (0xFF00, 0xFF00, "device specific"),
)


def emcy_name(code: int) -> str:
    """``0x4310 excess temperature drive``: the code and what it means (its class when
    the code itself is not a standard one)."""
    name = EMCY_NAMES.get(code)
    if name is None:
        name = next((d for c, m, d in _EMCY_CLASSES if code & m == c), "unknown")
        name += " (class)"
    return f"0x{code:04X} {name}"
