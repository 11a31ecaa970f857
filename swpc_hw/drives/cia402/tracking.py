"""What the host knows of each CiA 402 axis, and what it decides from it (pure cores).

No clock, no lock, no I/O: the driver (:mod:`swpc_hw.drives.cia402.driver`) calls these
under its lock with times on its clock, and the tests call them directly.

* :func:`on_statusword` / :func:`on_feedback` -- a TPDO's content into the axis's track;
  a module's feedback sample once both axes answered the same SYNC (:func:`pair`).
* :func:`supervise` -- at ``now``: heartbeat loss (as the swpc kind's
  :func:`swpc_hw.drives.tracking.check`: ``now >= t_heartbeat + loss_after``) of each axis
  watched (from its first heartbeat after its set-up: a drive from the factory sends none
  until the host sets 0x1017, CiA 301's default), the next
  controlword of the 402 power state machine towards what the host asked
  (:func:`firmware_protocol.cia402.host_controlword`, one transition per statusword, sent
  again after ``retry`` when the drive did not follow), and the two refusals a drive can
  make silently: not reaching OPERATION ENABLED, and a mode whose display (0x6061) does
  not follow (the operator sees the mode named in the fault).

Refusals are judged on evidence, not on the host's clock alone: by a statusword that
answers a SYNC sent ``power_syncs`` / ``mode_syncs`` SYNC periods after the command (a
drive that lags, e.g. a simulator on a slow machine, is not taken for one that refuses).
Which SYNC a TPDO answers: its drive answers every SYNC once it is OPERATIONAL, in order,
so the k-th TPDO 1 since then answers the k-th SYNC (a lost TPDO makes the count lag:
the host waits longer, never less).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from firmware_protocol import cia402
from firmware_protocol.cia402 import Mode, PowerState
from firmware_protocol.codec import Axis, AxisState, ControlMode, HomingState
from swpc_hw.drives.types import AXIS_NAMES, EventKind, Observation, Severity


@dataclass
class AxisTrack:
    """One axis: its drive's node, units, last report and what the host asked of it."""

    module: int
    axis: Axis
    node: int
    counts_per_rad: float
    gear_ratio: float
    rated_torque: float = math.nan
    """N.m at the motor (0x6076, read at set-up): torque objects are thousandths of it."""
    # the drive's side
    alive: bool = False
    lost_reported: bool = False
    t_heartbeat: float | None = None
    nmt: int | None = None
    heartbeats: int = 0
    statusword: int | None = None
    statusword_seen: bool = False
    """A statusword seen since the drive was (re)started (NMT start)."""
    state: PowerState = PowerState.NOT_READY_TO_SWITCH_ON
    mode_display: int = 0
    error_code: int = 0
    position: float = math.nan
    velocity: float = math.nan
    torque: float = math.nan
    seq: int = -1
    """The SYNC the last TPDO 1 answered (the host's count: ``sync_base + answered``)."""
    sync_base: int = 0
    """The host's SYNC count when the drive was started (NMT): it answers the next ones."""
    answered: int = 0
    """TPDO 1s received since then."""
    t_feedback: float = math.nan
    configured: bool = False
    position_mode: Mode = Mode.CYCLIC_SYNC_POSITION
    torque_mode: Mode | None = Mode.CYCLIC_SYNC_TORQUE
    velocity_mode: Mode | None = Mode.CYCLIC_SYNC_VELOCITY
    """The modes chosen at set-up from 0x6502 (:func:`swpc_hw.drives.cia402.setup.choose_modes`);
    a drive without a torque mode (None) is free with its power stage off (:attr:`unpowered`)."""
    has_limits: tuple[bool, bool] = (True, True)
    has_profile_velocity: bool = False
    """Whether the drive has 0x6081 (profile position's speed: the run's velocity limit)."""
    """Whether the drive has 0x6072 (max torque) and 0x607F (max profile velocity)."""
    max_torque: float = math.inf
    max_velocity: float = math.inf
    """The run's limits (N.m, rad/s at the output), applied by the host too."""
    rpdos: tuple[tuple[int, ...], ...] = ((1,), (2,))
    """The RPDOs that carry the command group (controlword, mode, torque) and the targets
    group (:func:`swpc_hw.drives.cia402.setup.place`)."""
    tpdos: tuple[tuple[int, ...], ...] = ((1,), (2,))
    """The TPDOs that carry the sample group (statusword, position, modes display) and the
    velocity and torque group; a group's last one completes it."""
    tpdo_values: dict[int, int] = field(default_factory=dict)
    """The latest value of each object the TPDOs carry (index -> raw)."""
    mode_by_sdo: bool = False
    """0x6060 is not PDO-mappable on this drive: each mode is written over SDO when it
    changes (not in RPDO 1)."""
    guarded: bool = False
    """Watched by node guarding (a drive without a heartbeat consumer 0x1016): the host
    asks its state every heartbeat period and takes the answers as its heartbeats."""
    watched: bool = False
    """Its heartbeat judged: from its first heartbeat after its set-up."""
    t_boot: float | None = None
    """When its last boot-up was seen."""
    # the host's side
    enable: bool = False
    unpowered: bool = False
    """Free without a torque mode: its power stage off (``enable`` false) until a position,
    velocity or homing command powers it again; false after a stop, which only ``enable``
    undoes."""
    reset: bool = False
    mode: Mode = Mode.NONE
    target_position: int = 0
    target_velocity: int = 0
    target_torque: int = 0
    enable_sync: int = -1
    """The SYNC count when the last step toward OPERATION ENABLED was commanded (-1: not
    asked)."""
    enable_start: int = -1
    """The SYNC count when OPERATION ENABLED was asked (-1: not asked): every step within
    :data:`POWER_STEPS` windows of it."""
    mode_sync: int = -1
    """The SYNC count when the last mode was commanded (-1: none)."""
    homing_start: bool = False
    homing_sync: int = -1
    """The last SYNC before the homing start was sent: only later statuswords tell."""
    controlword: int = 0
    t_controlword: float = -math.inf
    refused_reported: bool = False
    pp_edge_target: int | None = None
    """Profile position: the target handed over by the last rising edge of bit 4."""
    pp_acked: int | None = None
    """Profile position: the target the drive last acknowledged (None: none yet in this
    mode, so the first is handed over)."""

    def where(self) -> str:
        return f"module {self.module} {AXIS_NAMES[self.axis]} (node {self.node})"

    def to_units(self, rad: float) -> int:
        return round(rad * self.counts_per_rad)

    def torque_units(self, torque: float) -> int:
        """N.m at the output -> thousandths of the motor's rated torque."""
        return round(torque / (self.rated_torque * self.gear_ratio) * 1000.0)

    def torque_si(self, units: int) -> float:
        return units / 1000.0 * self.rated_torque * self.gear_ratio

    def axis_state(self) -> AxisState:
        if self.state in (PowerState.FAULT, PowerState.FAULT_REACTION_ACTIVE):
            return AxisState.FAULT
        if self.state is not PowerState.OPERATION_ENABLED:
            return AxisState.DISABLED
        if self.mode_display == Mode.HOMING and self.homing_start:
            return AxisState.HOMING
        return AxisState.ENABLED

    def control_mode(self) -> ControlMode:
        m = self.mode
        if m in (Mode.CYCLIC_SYNC_POSITION, Mode.PROFILE_POSITION):
            return ControlMode.POSITION
        if m in (Mode.CYCLIC_SYNC_VELOCITY, Mode.PROFILE_VELOCITY):
            return ControlMode.VELOCITY
        if m in (Mode.CYCLIC_SYNC_TORQUE, Mode.PROFILE_TORQUE) and self.target_torque:
            return ControlMode.TORQUE
        if m is Mode.HOMING:
            return ControlMode.HOLD
        return ControlMode.FREE


@dataclass
class ModuleTrack:
    module: int
    steer: AxisTrack
    wheel: AxisTrack
    homed: bool = False
    homing: HomingState = HomingState.NOT_HOMED
    seq_emitted: int = -1
    feedback_frames: int = 0

    @property
    def axes(self) -> tuple[AxisTrack, AxisTrack]:
        return (self.steer, self.wheel)


def _obs(a: AxisTrack, kind: EventKind, severity: Severity, text: str) -> Observation:
    return Observation(kind, severity, f"{a.where()}: {text}", a.module, a.node, a.axis)


def on_heartbeat(a: AxisTrack, nmt: int, t: float) -> list[Observation]:
    """A heartbeat (or boot-up, ``nmt`` 0) at bus time ``t``."""
    out = []
    if nmt == cia402.NMT_BOOT_UP:
        if a.configured:
            out.append(_obs(a, EventKind.NODE_FAULT, Severity.FAULT,
                            "boot-up: the drive restarted (its set-up is lost)"))  # fmt: skip
        a.configured = a.watched = False  # silent again until set up (0x1017's default)
        a.statusword, a.statusword_seen = None, False
        a.t_boot = t
    elif a.configured:
        a.watched = True
    a.nmt = nmt
    a.heartbeats += 1
    a.t_heartbeat = t if a.t_heartbeat is None else max(a.t_heartbeat, t)
    if not a.alive:
        a.alive = True
        if a.lost_reported:
            a.lost_reported = False
            out.append(_obs(a, EventKind.HEARTBEAT_RESTORED, Severity.INFO, "heartbeat restored"))
    return out


HEARTBEAT_ERROR = 0x8130
"""The EMCY of a drive whose heartbeat consumer timed out (the host's heartbeat lapsed)."""


def on_emcy(a: AxisTrack, code: int, register: int, active: bool = True) -> list[Observation]:
    """An EMCY: a fault naming its error code (code 0: the drive's error reset).

    A heartbeat error while the drives are not ``active`` (every axis disabled by the host:
    between runs, or while a run solves) stops nothing: the drives' dead-man tripped on a
    host that stalled, and the next activation resets it.  It is a warning then, not a
    fault that would end a run whose motion is over."""
    if code & 0xFF00 == 0:
        a.error_code = 0
        return []
    a.error_code = code
    text = f"EMCY {cia402.emcy_name(code)} (error register 0x{register:02X})"
    if code == HEARTBEAT_ERROR and not active:
        return [_obs(a, EventKind.NODE_FAULT, Severity.WARNING,
                     f"{text} while every axis was disabled: the drive's dead-man tripped on "
                     "a stalled host; the next activation resets it")]  # fmt: skip
    return [_obs(a, EventKind.NODE_FAULT, Severity.FAULT, text)]


def on_statusword(m: ModuleTrack, a: AxisTrack, statusword: int, mode_display: int,
                  position: int, seq: int, t: float) -> list[Observation]:  # fmt: skip
    """TPDO 1 of an axis (answering SYNC ``seq``)."""
    out: list[Observation] = []
    before = a.state
    a.statusword = statusword
    a.state = cia402.power_state(statusword)
    a.mode_display = mode_display
    a.position = position / a.counts_per_rad
    first = a.statusword_seen is False
    a.statusword_seen = True
    a.seq = seq
    a.t_feedback = t
    if a.state is PowerState.FAULT and first:
        a.reset = True  # present at start: the activation resets it (or refuses)
        text = f"in FAULT at start (statusword 0x{statusword:04X}): fault reset"
        out.append(_obs(a, EventKind.NODE_FAULT, Severity.WARNING, text))
    elif a.state is PowerState.FAULT and before is not PowerState.FAULT and not a.error_code:
        out.append(_obs(a, EventKind.NODE_FAULT, Severity.FAULT,
                        f"statusword 0x{statusword:04X}: FAULT"))  # fmt: skip
    if a.state is not PowerState.FAULT:
        a.reset = False
        if before is PowerState.FAULT:
            a.error_code = 0  # reset (its EMCY 0x0000 may come later, or never)
    if a is m.steer and a.homing_start and seq > a.homing_sync and mode_display == Mode.HOMING:
        if statusword & cia402.SW_HOMING_ERROR:
            a.homing_start = False
            m.homing = HomingState.FAILED
            out.append(_obs(a, EventKind.HOMING, Severity.WARNING,
                            f"homing FAILED (statusword 0x{statusword:04X})"))  # fmt: skip
        elif statusword & cia402.SW_HOMING_ATTAINED and statusword & cia402.SW_TARGET_REACHED:
            # attained *and* target reached: the move has ended (canopen's homing() takes
            # attained alone); bit 4 goes low again (the next homing needs its edge)
            a.homing_start = False
            m.homed = True
            m.homing = HomingState.DONE
            out.append(_obs(a, EventKind.HOMING, Severity.INFO, "homing DONE"))
    return out


def pair(m: ModuleTrack) -> int | None:
    """The SYNC both axes of ``m`` have answered and no sample was made of yet."""
    s, w = m.steer.seq, m.wheel.seq
    if s == w and s > m.seq_emitted:
        m.seq_emitted = s
        return s
    return None


def _new_setpoint(a: AxisTrack) -> bool:
    """Profile position's handshake (:data:`firmware_protocol.cia402.CW_NEW_SETPOINT`):
    bit 4 stays high until the drive acknowledges, then goes low; it rises again for a
    target not yet acknowledged once the drive has taken its acknowledgement back."""
    ack = bool((a.statusword or 0) & cia402.SW_SETPOINT_ACK)
    if a.controlword & cia402.CW_NEW_SETPOINT:
        if ack:
            a.pp_acked = a.pp_edge_target
            return False
        return True
    return not ack and a.target_position != a.pp_acked


@dataclass
class Decision:
    lost: list[AxisTrack] = field(default_factory=list)
    send: list[AxisTrack] = field(default_factory=list)
    """Axes whose RPDO 1 (controlword) goes out now (their ``controlword`` set)."""
    observations: list[Observation] = field(default_factory=list)
    fault: bool = False
    next_deadline: float = math.inf


POWER_STEPS = 4
"""Steps of the power state machine a drive is given a window each for, at most (a fault
reset, shutdown, switch on, enable operation): one that keeps falling back is refused."""


def supervise(
    axes: list[AxisTrack],
    now: float,
    *,
    loss_after: float,
    retry: float,
    power_syncs: int,
    mode_syncs: int,
    sync_period: float,
    active: bool,
    sync_seq: int = 0,
) -> Decision:
    """Heartbeat loss, the power state machine and the refusals at ``now`` (module
    docstring).  Controlwords only while ``active``.

    Each step toward OPERATION ENABLED (shutdown, switch on, enable operation: a new
    controlword) gets its own ``power_syncs``, counted from ``sync_seq`` (the SYNCs the
    host has sent) in the SYNCs the drive's statuswords answer: a drive whose answers lag
    the host's SYNCs (a simulator behind in an emulated machine) is judged on its own time
    for each step, not on the host's reaction to it."""
    d = Decision()
    for a in axes:
        due = a.t_heartbeat + loss_after if a.watched and a.t_heartbeat is not None else math.inf
        if now >= due:
            if a.alive or not a.lost_reported:
                a.alive = False
                a.lost_reported = True
                d.lost.append(a)
                d.observations.append(
                    _obs(a, EventKind.HEARTBEAT_LOST, Severity.FAULT,
                         f"no heartbeat for {loss_after:.3f} s")
                )  # fmt: skip
                d.fault = True
        elif due < math.inf:
            d.next_deadline = min(d.next_deadline, due)
        if not active or a.statusword is None:
            continue
        pp = a.mode is Mode.PROFILE_POSITION and a.mode_display == Mode.PROFILE_POSITION
        cw = cia402.host_controlword(
            a.state, a.enable, a.reset, a.controlword,
            a.homing_start and a.mode_display == Mode.HOMING,
            profile_position=pp, new_setpoint=pp and _new_setpoint(a),
        )  # fmt: skip
        if cw is not None and (cw != a.controlword or now - a.t_controlword >= retry):
            target = PowerState.OPERATION_ENABLED if a.enable else PowerState.SWITCH_ON_DISABLED
            if cw != a.controlword or a.state is not target:
                if pp and cw & ~a.controlword & cia402.CW_NEW_SETPOINT:
                    a.pp_edge_target = a.target_position  # the edge hands this one over
                if cw != a.controlword and a.enable and a.enable_sync >= 0 and (
                    a.state is not PowerState.OPERATION_ENABLED
                ):
                    a.enable_sync = max(a.enable_sync, sync_seq)  # the next step's window
                a.controlword = cw
                a.t_controlword = now
                d.send.append(a)
        if a.refused_reported or not a.enable:
            continue
        refused_mode = a.mode is not Mode.NONE and a.mode_display != a.mode
        if a.state is not PowerState.OPERATION_ENABLED:
            late = a.enable_sync >= 0 and a.seq >= a.enable_sync + power_syncs
            steps = POWER_STEPS * power_syncs
            if late or (a.enable_start >= 0 and a.seq >= a.enable_start + steps):
                a.refused_reported = True
                d.fault = True
                d.observations.append(
                    _obs(a, EventKind.NODE_FAULT, Severity.FAULT,
                         f"did not reach OPERATION ENABLED: controlword 0x{a.controlword:04X} "
                         f"not followed within {power_syncs * sync_period:g} s (statusword "
                         f"0x{a.statusword:04X}: {a.state.value})")
                )  # fmt: skip
        elif refused_mode and a.mode_sync >= 0 and a.seq >= a.mode_sync + mode_syncs:
            a.refused_reported = True
            d.fault = True
            d.observations.append(
                _obs(a, EventKind.NODE_FAULT, Severity.FAULT,
                     f"the drive refused mode {cia402.mode_name(a.mode)} (0x6060 = "
                     f"{int(a.mode)}): modes display 0x6061 still "
                     f"{cia402.mode_name(a.mode_display)} {mode_syncs * sync_period:g} s after it")
            )  # fmt: skip
    return d
