"""What one received CAN Simple frame tells about the ODrive axes (a pure core).

:func:`apply_frame` is a function of the tracked axes and modules, one frame, its time and
whether the drives are ACTIVE: it updates the tracks and returns what was observed
(:class:`swpc_hw.drives.tracking.Applied`), as the swpc kind's core does.  No clock, no
lock, no I/O.

* Liveness and faults come from each axis' heartbeat: a new axis error bit on an axis the
  host drives (ACTIVE) is a fault; an armed axis that drops out of closed loop by itself
  is a fault.  A watchdog expiry of an axis the host leaves alone (INACTIVE: a 0.5.x
  axis counts its watchdog down in IDLE too) is only noted, and so is the expiry the host
  provokes when it proves the watchdog at activation (``AxisTrack.proving``).
* Feedback comes from the axes' cyclic ``Get_Encoder_Estimates`` (never from polls): the
  wheel axis' frame completes a module sample with the steering's latest estimate (both
  converted to the output in rad with the axes' gear ratios).  CAN Simple frames carry no
  counter: a sample's ``seq`` counts the wheel's frames, and lost frames go unseen.
* Homing (index search) ends when the steering's heartbeat, having shown the search,
  shows IDLE again: without an axis error (0.5.x) and with ``Procedure_Result`` SUCCESS
  (0.6.x) it is DONE and the host re-arms the axis (``AxisTrack.rearm``), else FAILED.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import can

from firmware_protocol.codec import Axis, AxisState, ControlMode, Frame, HomingState, ProtocolError
from firmware_protocol.odrive import can_simple as cs
from swpc_hw.drives.odrive.config import ODriveAxis
from swpc_hw.drives.tracking import Applied, FeedbackRing, NodeTrack, error_frame
from swpc_hw.drives.types import (
    DriverStats,
    EventKind,
    FeedbackSample,
    Observation,
    Severity,
    where,
)

TWO_PI = 2.0 * math.pi


def to_output(turns: float, ratio: float) -> float:
    """Axis turns -> rad at the module's output."""
    return turns * TWO_PI / ratio


def to_axis(rad: float, ratio: float) -> float:
    """rad at the module's output -> axis turns."""
    return rad * ratio / TWO_PI


@dataclass
class AxisTrack(NodeTrack):
    """One ODrive axis (its own node).  ``node`` is the axis' node; ``module`` its module."""

    axis: Axis = Axis.STEER
    spec: ODriveAxis = field(default_factory=lambda: ODriveAxis(node=0))
    state: int = cs.AxisState.UNDEFINED
    axis_error: int = 0
    procedure_result: int | None = None
    component_errors: int = 0
    pos: float = math.nan
    """Latest Pos_Estimate (axis turns) and Vel_Estimate (turns/s)."""
    vel: float = math.nan
    estimates: int = 0
    armed: bool = False
    """The host asked for closed loop (and has not disarmed it since)."""
    closed_loop_seen: bool = False
    mode: ControlMode = ControlMode.FREE
    """What the host commanded (FREE: torque 0), as the swpc kind's modes."""
    sent_control: int | None = None
    """The Control_Mode last sent (a mode frame only on a change)."""
    refresh: tuple[Frame, ...] = ()
    """What the refresh repeats (its last setpoint frame; empty: not refreshed)."""
    homing_axis: bool = False
    proving: bool = False
    proven_at: float | None = None
    rearm: bool = False


def new_axis(module: int, axis: Axis, spec: ODriveAxis) -> AxisTrack:
    return AxisTrack(module, spec.node, FeedbackRing(1), axis=axis, spec=spec)


def module_axis_state(ax: AxisTrack) -> AxisState:
    """An ODrive axis as the swpc kind's states: FAULT with an axis error, ENABLED in
    closed loop, HOMING in an index search or homing, else DISABLED."""
    if ax.axis_error:
        return AxisState.FAULT
    if ax.state == cs.AxisState.CLOSED_LOOP_CONTROL:
        return AxisState.ENABLED
    if ax.state in (cs.AxisState.ENCODER_INDEX_SEARCH, cs.AxisState.HOMING):
        return AxisState.HOMING
    return AxisState.DISABLED


def sync_module(md: NodeTrack, steer: AxisTrack, wheel: AxisTrack) -> None:
    """The module track (what :meth:`NodeTrack.snapshot` reports) from its two axes."""
    md.alive = steer.alive and wheel.alive
    md.states = (module_axis_state(steer), module_axis_state(wheel))
    md.modes = (
        steer.mode if steer.armed else ControlMode.FREE,
        wheel.mode if wheel.armed else ControlMode.FREE,
    )
    md.errors = (steer.axis_error, wheel.axis_error)
    md.heartbeats = steer.heartbeats + wheel.heartbeats
    times = [t for t in (steer.t_heartbeat, wheel.t_heartbeat) if t is not None]
    md.t_heartbeat = min(times) if len(times) == 2 else None


def _obs(
    ax: AxisTrack, kind: EventKind, severity: Severity, message: str
) -> Observation:
    return Observation(
        kind, severity, f"{where(ax.module, ax.node, ax.axis)}: {message}", ax.module, ax.node,
        ax.axis,
    )  # fmt: skip


def apply_frame(
    codec: cs.CanSimple,
    axes: dict[int, AxisTrack],
    modules: dict[int, NodeTrack],
    msg: can.Message,
    t: float,
    stats: DriverStats,
    active: bool,
) -> Applied:
    """Update the tracks with one received frame (module docstring)."""
    out = Applied()
    stats.rx_frames += 1
    if msg.is_error_frame:
        seen = error_frame(msg, stats)
        out.observations.append(seen)
        out.fault = seen.severity is Severity.FAULT
        return out
    node, cmd = cs.split_id(msg.arbitration_id)
    ax = axes.get(node)
    try:
        if msg.is_extended_id:
            raise ProtocolError("extended id: CAN Simple uses 11-bit ids")
        dec = codec.decode(msg.arbitration_id, bytes(msg.data), bool(msg.is_remote_frame))
    except ProtocolError as exc:
        if ax is not None and not msg.is_extended_id and "DLC" in str(exc):
            stats.bad_dlc += 1
            out.observations.append(_obs(ax, EventKind.BAD_DLC, Severity.WARNING, str(exc)))
        else:
            stats.unknown_ids += 1
            out.observations.append(
                Observation(
                    EventKind.UNKNOWN_ID,
                    Severity.WARNING,
                    f"unknown frame id 0x{msg.arbitration_id:x} (not ODrive CAN Simple "
                    f"{codec.line}: {exc})",
                )
            )
        return out
    if isinstance(dec, cs.Poll) or cmd in codec.host_cmds:
        stats.host_frames += 1  # a host's command or poll seen on the bus: not ours to apply
        return out
    if ax is None:
        stats.unknown_ids += 1
        out.observations.append(
            Observation(
                EventKind.UNKNOWN_ID,
                Severity.WARNING,
                f"frame id 0x{msg.arbitration_id:03x} from ODrive node {node}, which is not "
                "one of the robot's axes",
            )
        )
        return out
    md = modules[ax.module]
    if isinstance(dec, cs.Heartbeat):
        _heartbeat(codec, ax, md, dec, t, active, out)
    elif isinstance(dec, cs.EncoderEstimates):
        _estimates(axes, md, ax, dec, t, float(msg.timestamp), out)
    return out


def _heartbeat(
    codec: cs.CanSimple,
    ax: AxisTrack,
    md: NodeTrack,
    hb: cs.Heartbeat,
    t: float,
    active: bool,
    out: Applied,
) -> None:
    new_bits = hb.axis_error & ~ax.axis_error
    was_state = ax.state
    ax.state, ax.axis_error = hb.state, hb.axis_error
    ax.procedure_result, ax.component_errors = hb.procedure_result, hb.component_errors
    ax.t_heartbeat = t if ax.t_heartbeat is None else max(ax.t_heartbeat, t)
    ax.heartbeats += 1
    if not ax.alive:
        ax.alive = True
        if ax.lost_reported:
            ax.lost_reported = False
            out.observations.append(
                _obs(ax, EventKind.HEARTBEAT_RESTORED, Severity.INFO, "heartbeat restored")
            )
    state_name = _state_name(hb.state)
    if new_bits:
        names = codec.error_names(new_bits)
        if ax.proving and new_bits == codec.watchdog_bit:
            ax.proven_at = t
            out.observations.append(
                _obs(ax, EventKind.NODE_FAULT, Severity.INFO, "watchdog proven: it expired")
            )
        elif active and ax.armed:
            out.observations.append(
                _obs(
                    ax, EventKind.NODE_FAULT, Severity.FAULT,
                    f"axis error {names} (state {state_name})",
                )
            )
            out.fault = True
        elif new_bits == codec.watchdog_bit and not ax.armed:
            out.observations.append(
                _obs(ax, EventKind.NODE_FAULT, Severity.INFO,
                     "watchdog expired while the host leaves the axis alone")
            )
        else:
            out.observations.append(
                _obs(ax, EventKind.NODE_FAULT, Severity.WARNING, f"axis error {names}")
            )
    if hb.state == cs.AxisState.CLOSED_LOOP_CONTROL:
        ax.closed_loop_seen = True
    elif (
        active
        and ax.armed
        and ax.closed_loop_seen
        and not ax.homing_axis
        and not new_bits
        and hb.state == cs.AxisState.IDLE
        and was_state == cs.AxisState.CLOSED_LOOP_CONTROL
    ):
        out.observations.append(
            _obs(ax, EventKind.NODE_FAULT, Severity.FAULT, "left closed loop by itself (IDLE)")
        )
        out.fault = True
    if ax.homing_axis:
        _homing(codec, ax, md, hb, out)


def _homing(
    codec: cs.CanSimple, ax: AxisTrack, md: NodeTrack, hb: cs.Heartbeat, out: Applied
) -> None:
    if hb.state == cs.AxisState.ENCODER_INDEX_SEARCH:
        md.homing_seen = True
        return
    if not md.homing_seen or hb.state == cs.AxisState.UNDEFINED:
        return
    ax.homing_axis = False
    ok = hb.axis_error == 0 and hb.procedure_result in (None, cs.ProcedureResult.SUCCESS)
    md.homing = HomingState.DONE if ok else HomingState.FAILED
    md.homed = md.homed or ok
    ax.rearm = ok
    ax.closed_loop_seen = False
    why = "" if ok else (
        f" (axis error {codec.error_names(hb.axis_error)}, procedure result "
        f"{hb.procedure_result})"
    )
    out.observations.append(
        _obs(
            ax, EventKind.HOMING, Severity.INFO if ok else Severity.WARNING,
            f"index search {'DONE' if ok else 'FAILED'}{why}",
        )
    )


REFUSED_RESULTS = frozenset({cs.ProcedureResult.INVALID_STATE, cs.ProcedureResult.NOT_CALIBRATED})
"""0.6.x ``Procedure_Result`` values of a closed-loop request the axis refused."""

CALIBRATE_ADVICE = (
    "the axis is not calibrated (or closed loop is not a state it may enter now): run the "
    "motor and encoder calibration (requested_state FULL_CALIBRATION_SEQUENCE in odrivetool) "
    "and keep it (save_configuration(); on 0.5.x first <axis>.motor.config.pre_calibrated and "
    "<axis>.encoder.config.pre_calibrated = True), or have the "
    "ODrive calibrate at every power-up (<axis>.config.startup_motor_calibration and "
    "startup_encoder_offset_calibration = True, or startup_encoder_index_search with an "
    "index), docs/drives.md"
)


def unproven_cause(codec: cs.CanSimple, ax: AxisTrack, window: float) -> tuple[str, bool]:
    """Why the watchdog proof of activation did not see ``ax``'s watchdog expire: the
    cause as its heartbeats tell it, and whether the watchdog itself is to blame (an axis
    that entered closed loop and stayed armed ``window`` s after its last frame).

    An axis that refused closed loop never armed its watchdog: 0.5.x latches the axis
    error INVALID_STATE (closed loop before the motor and encoder are calibrated), 0.6.x
    reports ``Procedure_Result`` INVALID_STATE or NOT_CALIBRATED."""
    other = ax.axis_error & ~codec.watchdog_bit
    invalid = codec.error_bit("INVALID_STATE") if codec.line == "0.5" else 0
    if other & invalid:
        names = codec.error_names(other)
        return f"refused closed loop (axis error {names}): {CALIBRATE_ADVICE}", False
    if not ax.closed_loop_seen and ax.procedure_result in REFUSED_RESULTS:
        return (
            f"refused closed loop (procedure result {codec.procedure_name(ax.procedure_result)}):"
            f" {CALIBRATE_ADVICE}",
            False,
        )
    if other:
        return f"axis error {codec.error_names(other)} (state {_state_name(ax.state)})", False
    if not ax.closed_loop_seen:
        result = (
            "" if ax.procedure_result is None
            else f", procedure result {codec.procedure_name(ax.procedure_result)}"
        )  # fmt: skip
        return f"never entered closed loop (state {_state_name(ax.state)}{result})", False
    return f"still armed {window:.3f} s after its last frame", True


def unproven_message(
    codec: cs.CanSimple, failed: list[AxisTrack], window: float, watchdog_ms: int
) -> str:
    """Activation's refusal of the axes whose watchdog was not proven: each axis with its
    cause (:func:`unproven_cause`); the watchdog's settings only for the axes it concerns."""
    parts: list[str] = []
    armed: list[str] = []
    for a in failed:
        cause, watchdog = unproven_cause(codec, a, window)
        text = f"{where(a.module, a.node, a.axis)}: {cause}"
        (armed if watchdog else parts).append(text)
    if armed:
        parts.append(
            f"the axis watchdog did not stop {'; '.join(armed)}: set "
            f"<axis>.config.enable_watchdog = True and watchdog_timeout = "
            f"{watchdog_ms / 1000.0:g} s on the ODrive (docs/drives.md)"
        )
    return "; ".join(parts)


def _state_name(state: int) -> str:
    try:
        return cs.AxisState(state).name
    except ValueError:
        return str(state)


def _estimates(
    axes: dict[int, AxisTrack],
    md: NodeTrack,
    ax: AxisTrack,
    est: cs.EncoderEstimates,
    t: float,
    t_bus: float,
    out: Applied,
) -> None:
    ax.pos, ax.vel = est.pos, est.vel
    ax.estimates += 1
    md.feedback_frames += 1
    if ax.axis != Axis.WHEEL:
        return
    steer = next(a for a in axes.values() if a.module == ax.module and a.axis == Axis.STEER)
    ratio_s, ratio_w = steer.spec.gear_ratio, ax.spec.gear_ratio
    seq = md.seq + 1
    theta = to_output(steer.pos, ratio_s)
    psi = to_output(ax.pos, ratio_w)
    sample = FeedbackSample(
        t,
        t_bus,
        seq & 0xFF,
        seq,
        theta,
        psi,
        steer_velocity=to_output(steer.vel, ratio_s),
        wheel_velocity=to_output(ax.vel, ratio_w),
    )
    md.seq, md.last = seq, sample
    md.history.append((t, t_bus, seq & 0xFF, seq, theta, psi))
    md.history.set_last_velocity_torque(
        (sample.steer_velocity, sample.wheel_velocity, math.nan, math.nan)
    )
    out.sample = (ax.module, sample)
