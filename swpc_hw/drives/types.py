"""The drives' data types (every kind's): lifecycle, events, feedback samples, snapshots,
counters."""

from __future__ import annotations

import dataclasses
import enum
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass

from firmware_protocol.codec import Axis, AxisState, ControlMode, HomingState

AXIS_NAMES = {Axis.STEER: "steer", Axis.WHEEL: "wheel"}


class Lifecycle(enum.Enum):
    UNCONFIGURED = "unconfigured"
    INACTIVE = "inactive"
    ACTIVE = "active"
    FINALIZED = "finalized"


class EventKind(enum.Enum):
    HEARTBEAT_LOST = "heartbeat_lost"
    HEARTBEAT_RESTORED = "heartbeat_restored"
    NODE_FAULT = "node_fault"
    BUS_OFF = "bus_off"
    ERROR_FRAME = "error_frame"
    UNKNOWN_ID = "unknown_id"
    BAD_DLC = "bad_dlc"
    DECODE_ERROR = "decode_error"
    LISTENER_ERROR = "listener_error"
    SEND_ERROR = "send_error"
    FEEDBACK_GAP = "feedback_gap"
    HOMING = "homing"
    STOPPED = "stopped"
    SET_UP = "set_up"
    """What a drive's set-up did without (an object it lacks), said once."""


class Severity(enum.Enum):
    INFO = "info"
    WARNING = "warning"
    FAULT = "fault"


def where(module: int | None, node: int | None, axis: Axis | None = None) -> str:
    """``module 2 (node 2) axis 1 (wheel)``: how messages name what they concern."""
    parts = []
    if module is not None:
        parts.append(f"module {module}")
    if node is not None:
        parts.append(f"(node {node})" if module is not None else f"node {node}")
    if axis is not None:
        parts.append(f"axis {int(axis)} ({AXIS_NAMES[axis]})")
    return " ".join(parts)


@dataclass(frozen=True)
class Observation:
    """Something a pure core observed, before the driver stamps and queues it as a
    :class:`DriverEvent`."""

    kind: EventKind
    severity: Severity
    message: str
    module: int | None = None
    node: int | None = None
    axis: Axis | None = None


@dataclass(frozen=True)
class DriverEvent:
    """Something the driver observed; FAULT events have already triggered ``stop_all()``."""

    t: float
    kind: EventKind
    severity: Severity
    message: str
    module: int | None = None
    node: int | None = None
    axis: Axis | None = None


@dataclass(frozen=True)
class FeedbackSample:
    """One feedback sample of a module (both frames with the same counter).

    ``t``: the driver clock's time when the position frame was handled; ``t_bus``: the
    frame's bus time stamp (python-can, epoch s; the driver clock's ``from_wall`` maps
    it); ``counter``: the frame's own counter (mod 256); ``seq``: the counter unwrapped on
    the host (monotonic sample index).  Velocities and torques are NaN if their frame was
    lost.
    """

    t: float
    t_bus: float
    counter: int
    seq: int
    theta_hat: float
    psi: float
    steer_velocity: float = math.nan
    wheel_velocity: float = math.nan
    steer_torque: float = math.nan
    wheel_torque: float = math.nan


AxisSigns = Mapping[int, tuple[int, int]]
"""A robot's polarity: module id -> (steer, wheel), -1 for an axis that turns the other way
round from what its drive reports (docs/commissioning.md).  A module left out is (1, 1).

What the robot's software commands to an axis and reads from it is in the model's sense
(docs/model-and-frames.md); its drive's is ``sign x`` that::

    command_drive = sign * command_model        reading_model = sign * reading_drive
"""


def module_signs(polarity: AxisSigns, module: int) -> tuple[int, int]:
    """``polarity``'s (steer, wheel) signs of ``module`` ((1, 1) when it says nothing of it)."""
    steer, wheel = polarity.get(module, (1, 1))
    return steer, wheel


def axis_sign(polarity: AxisSigns, module: int, axis: Axis) -> int:
    """``polarity``'s sign of ``module``'s ``axis`` (1 when it says nothing of it)."""
    return module_signs(polarity, module)[int(axis)]


def turned_sample(polarity: AxisSigns, module: int, s: FeedbackSample) -> FeedbackSample:
    """``module``'s drive feedback ``s`` in the model's sense: each axis' position,
    velocity and torque times its sign (the sample itself when both are 1)."""
    st, wh = module_signs(polarity, module)
    if st == 1 and wh == 1:
        return s
    return dataclasses.replace(
        s,
        theta_hat=st * s.theta_hat,
        psi=wh * s.psi,
        steer_velocity=st * s.steer_velocity,
        wheel_velocity=wh * s.wheel_velocity,
        steer_torque=st * s.steer_torque,
        wheel_torque=wh * s.wheel_torque,
    )


@dataclass(frozen=True)
class ModuleState:
    """Latest known state of one module's controller (a snapshot)."""

    module: int
    node: int
    alive: bool
    states: tuple[AxisState, AxisState]
    modes: tuple[ControlMode, ControlMode]
    errors: tuple[int, int]
    homed: bool
    homing: HomingState
    feedback: FeedbackSample | None
    t_heartbeat: float | None
    heartbeats: int
    feedback_frames: int

    @property
    def theta_hat(self) -> float:
        return self.feedback.theta_hat if self.feedback else math.nan

    @property
    def psi(self) -> float:
        return self.feedback.psi if self.feedback else math.nan


@dataclass(frozen=True)
class AxisStatus:
    """What the host knows now of one axis' drive (a snapshot; the console's drives view).

    In the kind's own words where the kinds differ: ``state`` is swpc's axis state
    (``ENABLED``), the CiA 402 power state (``operation enabled``) or the ODrive's axis
    state (``CLOSED_LOOP_CONTROL``); ``nmt`` the CANopen NMT state its heartbeat reports
    (``OPERATIONAL``; None for a kind without NMT); ``mode`` the mode in force (swpc and
    ODrive: the host's control mode, ``POSITION``; CiA 402: the modes display 0x6061,
    ``CYCLIC_SYNC_POSITION``); ``error`` the kind's error word or code (0: none) and
    ``error_name`` it named (``OVER_TEMPERATURE``, ``0x4310 excess temperature drive``,
    ``MOTOR_OVER_TEMP``; ``none`` for 0).  ``fault``: the drive is in fault by its kind's
    rule (an ODrive's watchdog expiry alone is not one: a 0.5.x axis left alone reports it,
    as ``swpc drives scan`` says).  ``homed``: the steering's homing (None for a wheel,
    which does not home); ``torque_mode`` below."""

    module: int
    axis: Axis
    node: int
    alive: bool
    t_heartbeat: float | None
    """The driver clock's time of the drive's last heartbeat (None: none yet)."""
    heartbeats: int
    state: str
    nmt: str | None
    mode: str
    error: int
    error_name: str
    fault: bool
    homed: bool | None
    torque_mode: bool = True
    """Whether the axis has a torque mode (a CiA 402 drive may not: it is then free with
    its power stage off, and a wheel spins the robot by velocity)."""


def axis_status_of_module(
    st: ModuleState, axis: Axis, error_name: Callable[[int], str], fault_on_error: bool = False
) -> AxisStatus:
    """One axis as its module's snapshot tells it: node, liveness, heartbeat and homing the
    module's (right for a dual-axis controller on one node), its error word named by
    ``error_name``; in fault when its state says so, or with ``fault_on_error`` when it
    reports an error (a CiA 402 drive's EMCY comes before the statusword showing FAULT)."""
    axis = Axis(axis)
    error = int(st.errors[axis])
    return AxisStatus(
        module=st.module,
        axis=axis,
        node=st.node,
        alive=st.alive,
        t_heartbeat=st.t_heartbeat,
        heartbeats=st.heartbeats,
        state=st.states[axis].name,
        nmt=None,
        mode=st.modes[axis].name,
        error=error,
        error_name=error_name(error) if error else "none",
        fault=st.states[axis] == AxisState.FAULT or (fault_on_error and error != 0),
        homed=st.homed if axis == Axis.STEER else None,
    )


@dataclass
class DriverStats:
    rx_frames: int = 0
    tx_frames: int = 0
    error_frames: int = 0
    bus_off: int = 0
    unknown_ids: int = 0
    host_frames: int = 0
    """Host commands seen on the bus (another host tool's; on SocketCAN the kernel filters
    them out before the driver)."""
    bad_dlc: int = 0
    decode_errors: int = 0
    listener_errors: int = 0
    send_errors: int = 0
    feedback_gaps: int = 0
    """Feedback samples missing according to the frames' counters."""
    unpaired_feedback: int = 0
    heartbeat_losses: int = 0
    node_faults: int = 0
    stop_all_calls: int = 0
    periodic_renewals: int = 0
    """Dead-man renewals of the kernel's periodic refresh (SocketCAN broadcast manager)."""
    rx_buffer_bytes: int | None = None
    """The kernel receive buffer in effect on a socket bus (SocketCAN), bytes; None on
    others."""
