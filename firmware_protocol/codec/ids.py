"""Frame ids and commands, without the DBC: ``id = node << 5 | command``.

The id layout's constants, the :class:`Command` codes with their DBC message names and
which side sends each, the host's acceptance filters (:func:`host_receive_filters`), the
raw :class:`Frame` and :func:`frame_id` / :func:`split_id`.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

from firmware_protocol.codec.exceptions import ProtocolError

NODE_SHIFT = 5
COMMAND_MASK = (1 << NODE_SHIFT) - 1
BROADCAST_NODE = 0
MAX_NODE = 8
SYNC_ID = 0x000


class Command(enum.IntEnum):
    """Low 5 bits of the frame id.  ``SYNC`` is only used with node 0."""

    SYNC = 0x00
    SET_AXIS_STATE = 0x01
    SET_CONTROL = 0x02
    FAULT_REPORT = 0x03
    FEEDBACK_POSITION = 0x04
    FEEDBACK_VELOCITY_TORQUE = 0x05
    HEARTBEAT = 0x06
    CLEAR_ERRORS = 0x07
    SET_LIMITS = 0x08
    SET_WATCHDOG = 0x09
    SET_FEEDBACK = 0x0A
    START_HOMING = 0x0B
    HOMING_STATUS = 0x0C


#: DBC message name (without the ``N<k>_`` prefix) of each command.
COMMAND_NAMES: dict[Command, str] = {
    Command.SYNC: "Sync",
    Command.SET_AXIS_STATE: "SetAxisState",
    Command.SET_CONTROL: "SetControl",
    Command.FAULT_REPORT: "FaultReport",
    Command.FEEDBACK_POSITION: "FeedbackPosition",
    Command.FEEDBACK_VELOCITY_TORQUE: "FeedbackVelocityTorque",
    Command.HEARTBEAT: "Heartbeat",
    Command.CLEAR_ERRORS: "ClearErrors",
    Command.SET_LIMITS: "SetLimits",
    Command.SET_WATCHDOG: "SetWatchdog",
    Command.SET_FEEDBACK: "SetFeedback",
    Command.START_HOMING: "StartHoming",
    Command.HOMING_STATUS: "HomingStatus",
}

#: Commands the host sends to a controller (each refreshes the controller's watchdog).
HOST_COMMANDS = frozenset(
    {
        Command.SET_AXIS_STATE,
        Command.SET_CONTROL,
        Command.CLEAR_ERRORS,
        Command.SET_LIMITS,
        Command.SET_WATCHDOG,
        Command.SET_FEEDBACK,
        Command.START_HOMING,
    }
)
#: Frames a controller sends to the host.
CONTROLLER_FRAMES = frozenset(
    {
        Command.FAULT_REPORT,
        Command.FEEDBACK_POSITION,
        Command.FEEDBACK_VELOCITY_TORQUE,
        Command.HEARTBEAT,
        Command.HOMING_STATUS,
    }
)


def host_receive_filters() -> list[dict[str, int | bool]]:
    """Acceptance filters (python-can ``can_filters``) for a host: every standard frame
    whose command is not one a host sends, and every extended frame.

    On SocketCAN the kernel applies them: the host's own commands (the kernel's periodic
    watchdog refresh among them, looped back to every socket) never reach its receive
    path, while the controllers' frames and anything unexpected (unknown commands and
    nodes, extended ids) still do.
    """
    out: list[dict[str, int | bool]] = [
        {"can_id": c, "can_mask": COMMAND_MASK, "extended": False}
        for c in range(1 << NODE_SHIFT)
        if c != Command.SYNC and c not in HOST_COMMANDS
    ]
    out.append({"can_id": 0, "can_mask": 0, "extended": True})
    return out


@dataclass(frozen=True)
class Frame:
    """One classic CAN frame (11-bit id): a data frame, or with ``remote`` a remote
    request (RTR) of ``len(data)`` bytes (its data is not sent; CANopen's node guarding
    asks a node's 1-byte state so)."""

    arbitration_id: int
    data: bytes
    remote: bool = False


def frame_id(node: int, command: Command) -> int:
    """``node << 5 | command``; node 0 only for ``Sync``."""
    if command == Command.SYNC:
        if node != BROADCAST_NODE:
            raise ProtocolError(f"Sync is a broadcast (node 0) frame, not node {node}")
    elif not 1 <= node <= MAX_NODE:
        raise ProtocolError(f"node id {node} outside 1..{MAX_NODE}")
    return (node << NODE_SHIFT) | int(command)


def split_id(arbitration_id: int) -> tuple[int, int]:
    """``(node, command)`` of an 11-bit id."""
    return arbitration_id >> NODE_SHIFT, arbitration_id & COMMAND_MASK
