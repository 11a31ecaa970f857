"""Python codec of the SWPC controller protocol: pure ``make_*`` builders and ``parse``.

Every frame is defined by ``swpc.dbc`` (the single source of truth) and cantools reads it;
this module adds typed values, SI units at the boundary and error messages that name the
node, the message and the signal.  Hot paths (the simulator sends, and the driver decodes,
thousands of frames per second) use a layout compiled from the same DBC at import
(:func:`frame_layout`: every signal's start bit, length, sign and scaling): a valid frame
packs to, and unpacks from, exactly cantools' bytes and values (checked over random frames
by ``tests/firmware/test_protocol_bytes.py``); anything else goes through cantools, whose
errors name the offending signal.

Frame ids: ``id = node << 5 | command`` (11-bit, ODrive "CAN Simple" layout).  Node 0 is the
broadcast address (``Sync``); controllers are nodes 1..``MAX_NODE``.

Positions are fixed point in the frames, all at ``2*pi/2**17`` rad per count: feedback
steer int20 (range +-4 turns) and wheel int36 (+-2**18 turns), PositionSetpoint and
HomingStatus SensorPosition int32 (+-2**14 turns).  The quantisation step is the same after
hours of rotation as at power-up, which a float32 would not give (its step at 5e5 rad is
0.03 rad).  The feedback counters wrap; :func:`unwrap` restores a continuous angle on the
host.  The module constants (:data:`STEER_LSB`, :data:`STEER_COUNTS_PER_TURN`,
:data:`STEER_SPAN` and the wheel's) are read from the DBC, not repeated here.

The code lives in the package's modules, and this one re-exports their names (import them
from ``firmware_protocol.codec``, as before the split):

- :mod:`~firmware_protocol.codec.ids`: the id layout, :class:`Command`, :class:`Frame`,
  :func:`frame_id` / :func:`split_id`, the host's receive filters;
- :mod:`~firmware_protocol.codec.enums`: the signals' enumerations and :class:`ErrorFlag`;
- :mod:`~firmware_protocol.codec.exceptions`: :class:`ProtocolError` and its subclasses;
- :mod:`~firmware_protocol.codec.dbc`: the DBC, its look-ups and the constants read from it;
- :mod:`~firmware_protocol.codec.layout`: the compiled layout (the hot path);
- :mod:`~firmware_protocol.codec.builders`: the ``make_*`` builders;
- :mod:`~firmware_protocol.codec.decoders`: the decoded records and :func:`parse`.

The public names are in ``__all__``; the private helpers (``_encode`` and the like) are
re-exported too, so whatever the single-file ``codec.py`` offered stays importable here.
"""

from __future__ import annotations

from firmware_protocol.codec.builders import _encode as _encode
from firmware_protocol.codec.builders import _signal_in as _signal_in
from firmware_protocol.codec.builders import (
    make_clear_errors,
    make_fault_report,
    make_feedback_position,
    make_feedback_velocity_torque,
    make_heartbeat,
    make_homing_status,
    make_set_axis_state,
    make_set_control,
    make_set_feedback,
    make_set_limits,
    make_set_watchdog,
    make_start_homing,
    make_sync,
)
from firmware_protocol.codec.dbc import (
    DBC_PATH,
    HEARTBEAT_PERIOD_S,
    POWER_UP_FEEDBACK_RATE_HZ,
    POWER_UP_WATCHDOG_MS,
    STEER_COUNTS_PER_TURN,
    STEER_LSB,
    STEER_SPAN,
    WHEEL_COUNTS_PER_TURN,
    WHEEL_LSB,
    WHEEL_SPAN,
    database,
    message_for,
    signal_scale,
    signal_span,
    unwrap,
    wrap,
)
from firmware_protocol.codec.dbc import _cycle_time_s as _cycle_time_s
from firmware_protocol.codec.dbc import _messages_by_id as _messages_by_id
from firmware_protocol.codec.dbc import _signal_format as _signal_format
from firmware_protocol.codec.decoders import (
    ClearErrors,
    Decoded,
    FaultReport,
    FeedbackPosition,
    FeedbackVelocityTorque,
    Heartbeat,
    HomingStatus,
    SetAxisState,
    SetControl,
    SetFeedback,
    SetLimits,
    SetWatchdog,
    StartHoming,
    Sync,
    parse,
)
from firmware_protocol.codec.decoders import _build as _build
from firmware_protocol.codec.decoders import _decode_values as _decode_values
from firmware_protocol.codec.enums import (
    Axis,
    AxisState,
    ControlMode,
    ErrorFlag,
    HomingState,
    error_names,
)
from firmware_protocol.codec.exceptions import (
    FrameLengthError,
    ProtocolError,
    SignalRangeError,
    UnknownFrameError,
)
from firmware_protocol.codec.ids import (
    BROADCAST_NODE,
    COMMAND_MASK,
    COMMAND_NAMES,
    CONTROLLER_FRAMES,
    HOST_COMMANDS,
    MAX_NODE,
    NODE_SHIFT,
    SYNC_ID,
    Command,
    Frame,
    frame_id,
    host_receive_filters,
    split_id,
)
from firmware_protocol.codec.layout import (
    SignalLayout,
    frame_layout,
    pack_frame,
    unpack_frame,
)

__all__ = [
    "BROADCAST_NODE",
    "COMMAND_MASK",
    "COMMAND_NAMES",
    "CONTROLLER_FRAMES",
    "DBC_PATH",
    "HEARTBEAT_PERIOD_S",
    "HOST_COMMANDS",
    "MAX_NODE",
    "NODE_SHIFT",
    "POWER_UP_FEEDBACK_RATE_HZ",
    "POWER_UP_WATCHDOG_MS",
    "STEER_COUNTS_PER_TURN",
    "STEER_LSB",
    "STEER_SPAN",
    "SYNC_ID",
    "WHEEL_COUNTS_PER_TURN",
    "WHEEL_LSB",
    "WHEEL_SPAN",
    "Axis",
    "AxisState",
    "ClearErrors",
    "Command",
    "ControlMode",
    "Decoded",
    "ErrorFlag",
    "FaultReport",
    "FeedbackPosition",
    "FeedbackVelocityTorque",
    "Frame",
    "FrameLengthError",
    "Heartbeat",
    "HomingState",
    "HomingStatus",
    "ProtocolError",
    "SetAxisState",
    "SetControl",
    "SetFeedback",
    "SetLimits",
    "SetWatchdog",
    "SignalLayout",
    "SignalRangeError",
    "StartHoming",
    "Sync",
    "UnknownFrameError",
    "database",
    "error_names",
    "frame_id",
    "frame_layout",
    "host_receive_filters",
    "make_clear_errors",
    "make_fault_report",
    "make_feedback_position",
    "make_feedback_velocity_torque",
    "make_heartbeat",
    "make_homing_status",
    "make_set_axis_state",
    "make_set_control",
    "make_set_feedback",
    "make_set_limits",
    "make_set_watchdog",
    "make_start_homing",
    "make_sync",
    "message_for",
    "pack_frame",
    "parse",
    "signal_scale",
    "signal_span",
    "split_id",
    "unpack_frame",
    "unwrap",
    "wrap",
]
