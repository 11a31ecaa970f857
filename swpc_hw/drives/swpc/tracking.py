"""The swpc kind's node tracking: what one received frame tells about its controllers,
and the frames that refresh them (pure cores).

:func:`apply_frame` is a function of the tracked state, one received frame and its time:
it updates the :class:`NodeTrack` the frame concerns and the counters, and returns what
was observed (:class:`Applied`).  No clock, no lock, no I/O: the driver's receive path
calls it under its lock, and the tests call it directly.

Times: ``t`` is when the frame arrived on the bus, on the driver clock's axis (its bus
time stamp mapped by :meth:`swpc_hw.clock.Clock.from_wall`, or the time it was handled
when the stamp is unusable).  A heartbeat's ``t`` is what supervision judges loss by
(:func:`swpc_hw.drives.tracking.check`), so a frame that waited in a receive queue still counts
from when it arrived.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import replace

import can

from firmware_protocol import codec
from firmware_protocol.codec import Axis, AxisState, ControlMode, HomingState
from swpc_hw.drives import tracking
from swpc_hw.drives.tracking import Applied, CheckResult, NodeTrack, error_frame
from swpc_hw.drives.types import (
    DriverStats,
    EventKind,
    FeedbackSample,
    Observation,
    Severity,
    where,
)


def refresh_frames(
    nd: NodeTrack, commanded: Mapping[Axis, tuple[ControlMode, float]] | None = None
) -> list[codec.Frame]:
    """The node's last SetControl per commanded axis (what feeds its watchdog); of
    ``commanded`` instead of the node's own, if given."""
    cmds = nd.commanded if commanded is None else commanded
    return [codec.make_set_control(nd.node, axis, mode, sp) for axis, (mode, sp) in cmds.items()]


def check(
    nodes: Iterable[NodeTrack],
    now: float,
    *,
    t_configured: float,
    loss_after: float,
    refresh_period: float,
    refresh: bool,
) -> CheckResult:
    """:func:`swpc_hw.drives.tracking.check` on the controllers: a node is refreshed while
    it has a commanded axis, with its last SetControl per commanded axis."""
    return tracking.check(
        nodes,
        now,
        t_configured=t_configured,
        loss_after=loss_after,
        refresh_period=refresh_period,
        refresh=refresh,
        refreshed=lambda nd: bool(nd.commanded),
        frames=refresh_frames,
    )


def apply_frame(
    by_node: dict[int, NodeTrack], msg: can.Message, t: float, stats: DriverStats
) -> Applied:
    """Update the tracked state with one received frame (see the module docstring)."""
    out = Applied()
    stats.rx_frames += 1
    if msg.is_error_frame:
        seen = error_frame(msg, stats)
        out.observations.append(seen)
        out.fault = seen.severity is Severity.FAULT
        return out
    node, cmd = codec.split_id(msg.arbitration_id)
    if not msg.is_extended_id and (cmd in codec.HOST_COMMANDS or msg.arbitration_id == 0):
        stats.host_frames += 1  # a host's command (or SYNC) seen on the bus: not ours to apply
        return out
    nd = by_node.get(node)
    if (
        msg.is_extended_id
        or msg.is_remote_frame
        or nd is None
        or cmd not in codec.CONTROLLER_FRAMES
    ):
        stats.unknown_ids += 1
        out.observations.append(
            Observation(
                EventKind.UNKNOWN_ID,
                Severity.WARNING,
                f"unknown frame id 0x{msg.arbitration_id:03x} (node {node}, command {cmd}, "
                f"DLC {msg.dlc})",
            )
        )
        return out
    try:
        dec = codec.parse(msg.arbitration_id, bytes(msg.data))
    except codec.ProtocolError as exc:
        if isinstance(exc, codec.FrameLengthError):
            stats.bad_dlc += 1
            kind = EventKind.BAD_DLC
        else:
            stats.decode_errors += 1
            kind = EventKind.DECODE_ERROR
        out.observations.append(
            Observation(
                kind, Severity.WARNING, f"{where(nd.module, nd.node)}: {exc}", nd.module, nd.node
            )
        )
        return out
    apply_decoded(nd, dec, t, float(msg.timestamp), stats, out)
    return out


def apply_decoded(
    nd: NodeTrack,
    dec: codec.Decoded,
    t: float,
    t_bus: float,
    stats: DriverStats,
    out: Applied,
) -> None:
    """Update one node with one decoded controller frame (see :func:`apply_frame`)."""
    if isinstance(dec, codec.FeedbackPosition):
        _feedback_position(nd, dec, t, t_bus, stats, out)
    elif isinstance(dec, codec.FeedbackVelocityTorque):
        _feedback_velocity_torque(nd, dec, stats)
    elif isinstance(dec, codec.Heartbeat):
        _heartbeat(nd, dec, t, out)
    elif isinstance(dec, codec.FaultReport):
        stats.node_faults += 1
        errs = list(nd.errors)
        errs[dec.axis] = dec.active_errors
        nd.errors = (errs[0], errs[1])
        states = list(nd.states)
        states[dec.axis] = dec.state
        nd.states = (states[0], states[1])
        out.observations.append(
            _obs(
                nd,
                EventKind.NODE_FAULT,
                Severity.FAULT,
                f"{where(nd.module, nd.node, dec.axis)}: fault {codec.error_names(dec.new_errors)} "
                f"(active {codec.error_names(dec.active_errors)})",
                dec.axis,
            )
        )
        out.fault = True
    elif isinstance(dec, codec.HomingStatus):
        nd.homing = dec.status
        if dec.status == HomingState.DONE:
            nd.homed = True
        sensor = (
            f", sensor at {dec.sensor_position:.4f} rad" if dec.status == HomingState.DONE else ""
        )
        out.observations.append(
            _obs(
                nd,
                EventKind.HOMING,
                Severity.WARNING if dec.status == HomingState.FAILED else Severity.INFO,
                f"{where(nd.module, nd.node, dec.axis)}: homing {dec.status.name}{sensor}",
                dec.axis,
            )
        )


def _obs(
    nd: NodeTrack, kind: EventKind, severity: Severity, message: str, axis: Axis | None = None
) -> Observation:
    return Observation(kind, severity, message, nd.module, nd.node, axis)


def _feedback_position(
    nd: NodeTrack,
    dec: codec.FeedbackPosition,
    t: float,
    t_bus: float,
    stats: DriverStats,
    out: Applied,
) -> None:
    """A position frame starts a sample: counters paired, positions unwrapped (the frames
    carry the steering +-4 turns and the wheel +-2**18 turns, wrapped)."""
    nd.feedback_frames += 1
    if nd.last is None:
        seq, theta, psi = dec.counter, dec.steer, dec.wheel
    else:
        gap = (dec.counter - nd.last.counter - 1) & 0xFF
        if gap:
            stats.feedback_gaps += gap
            out.observations.append(
                _obs(
                    nd,
                    EventKind.FEEDBACK_GAP,
                    Severity.WARNING,
                    f"{where(nd.module, nd.node)}: {gap} feedback sample(s) missing before "
                    f"counter {dec.counter}",
                )
            )
        seq = nd.seq + gap + 1
        theta = codec.unwrap(nd.last.theta_hat, dec.steer, codec.STEER_SPAN)
        psi = codec.unwrap(nd.last.psi, dec.wheel, codec.WHEEL_SPAN)
    if nd.last is not None and math.isnan(nd.last.steer_velocity):
        stats.unpaired_feedback += 1
    sample = FeedbackSample(t, t_bus, dec.counter, seq, theta, psi)
    nd.seq = seq
    nd.last = sample
    nd.history.append((t, t_bus, dec.counter, seq, theta, psi))
    out.sample = (nd.module, sample)


def _feedback_velocity_torque(
    nd: NodeTrack, dec: codec.FeedbackVelocityTorque, stats: DriverStats
) -> None:
    """The second frame of a sample completes the one with the same counter."""
    nd.feedback_frames += 1
    last = nd.last
    if last is None or last.counter != dec.counter or not math.isnan(last.steer_velocity):
        stats.unpaired_feedback += 1
        return
    values = (dec.steer_velocity, dec.wheel_velocity, dec.steer_torque, dec.wheel_torque)
    nd.last = replace(
        last,
        steer_velocity=values[0],
        wheel_velocity=values[1],
        steer_torque=values[2],
        wheel_torque=values[3],
    )
    if len(nd.history):  # the newest row is ``last`` unless cleared since
        nd.history.set_last_velocity_torque(values)


def _heartbeat(nd: NodeTrack, hb: codec.Heartbeat, t: float, out: Applied) -> None:
    """A heartbeat: axis states (a new FAULT is a fault), homing outcome, liveness."""
    for axis in Axis:
        if hb.states[axis] == AxisState.FAULT and nd.states[axis] != AxisState.FAULT:
            out.observations.append(
                _obs(
                    nd,
                    EventKind.NODE_FAULT,
                    Severity.FAULT,
                    f"{where(nd.module, nd.node, axis)}: heartbeat reports FAULT "
                    f"({codec.error_names(hb.errors[axis])})",
                    axis,
                )
            )
            out.fault = True
    if hb.states[Axis.STEER] == AxisState.HOMING:
        nd.homing_seen = True
    elif nd.homing == HomingState.IN_PROGRESS and nd.homing_seen and hb.homed:
        # homing ran and ended homed, but its HomingStatus frame (sent once) was lost,
        # e.g. by a receive queue that overflowed: the heartbeat repeats the outcome
        nd.homing = HomingState.DONE
        out.observations.append(
            _obs(
                nd,
                EventKind.HOMING,
                Severity.WARNING,
                f"{where(nd.module, nd.node, Axis.STEER)}: homing DONE by the heartbeat "
                "(its HomingStatus frame was not received)",
                Axis.STEER,
            )
        )
    nd.states, nd.modes, nd.errors, nd.homed = hb.states, hb.modes, hb.errors, hb.homed
    nd.t_heartbeat = t if nd.t_heartbeat is None else max(nd.t_heartbeat, t)
    nd.heartbeats += 1
    if not nd.alive:
        nd.alive = True
        if nd.lost_reported:
            nd.lost_reported = False
            out.observations.append(
                _obs(
                    nd,
                    EventKind.HEARTBEAT_RESTORED,
                    Severity.INFO,
                    f"{where(nd.module, nd.node)}: heartbeat restored",
                )
            )
