"""The virtual CiA 402 drive: one module = two single-axis drives on two CANopen nodes.

Each axis is a :class:`canopen.LocalNode` (canopen's own slave: its object dictionary from
the EDS in ``firmware_protocol/cia402/``, its SDO server, NMT slave with heartbeat
producer, PDO maps and EMCY producer) inside the virtual robot, with what a drive adds
around it here:

* the 402 power state machine (:func:`firmware_protocol.cia402.drive_transition`) on the
  controlword, the modes of operation it supports (0x6502: homing, cyclic synchronous
  position, velocity, torque) and the modes display, which stays where it is when a mode
  is refused (a real drive's behaviour: the host reads it back);
* TPDOs on SYNC (transmission types 1..240), RPDOs applied on reception;
* the heartbeat consumer (0x1016): once the watched node's heartbeat has been seen, a
  silence longer than its time raises EMCY 0x8130 and the fault reaction (the power stage
  off: every axis of the drive free) -- the drive's own dead-man;
* homing (mode 6, methods 17..30: the steering's homing sensor) at the virtual robot's
  homing speed, or an absolute encoder (``homing: absolute``), homed from power-up;
* faults (:meth:`VirtualCia402Module.inject_fault`) as EMCY with their error code.

As it comes from the factory, and no kinder than CiA 301/402 promise: silent until the host
sets its heartbeat producer (0x1017 = 0), PRE-OPERATIONAL after a communication error such
as its heartbeat consumer's timeout (0x1029 sub 1: 0 pre-operational, 1 no change, 2
stopped), profile position with the set-point handshake (bit 4's rising edge takes the
target, statusword bit 12 acknowledges it while bit 4 stays high), optionally in FAULT
from power-up (:attr:`VirtualAxis.power_up_fault`, cleared by
a fault reset unless :attr:`VirtualAxis.fault_clears` is false), and in cyclic synchronous
position the target is taken at each SYNC: the one received since the previous SYNC, else
the last set-point extrapolated for one cycle (an interpolating drive's behaviour), then
held; a target written before the mode is in force is not taken (the drive starts from
where it is).

Time is the virtual robot's: the library's periodic sends (the heartbeat producer) run on
:class:`~simulators.drives.cia402_node.SimNetwork`'s simulated time, never on a thread.
Units: the axis's gear ratio and encoder counts (the same config as the host's), the
drive's rated torque (0x6076).

The physics is the same as the swpc kind's: an axis becomes an
:class:`~simulators.drives.base.AxisModel` (state, mode, setpoint, limits) for
:func:`simulators.drives.base.axis_drive`.  An enabled axis in a torque mode with target
torque 0 is free (the amplifier applies no torque), as the swpc firmware's FREE mode.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import can
from canopen.objectdictionary import ODVariable
from canopen.sdo.exceptions import SdoAbortedError

from firmware_protocol import cia402
from firmware_protocol.cia402 import Mode, PowerState
from firmware_protocol.codec import Axis, AxisState, ControlMode, ErrorFlag
from simulators.drives.base import AxisModel, axis_drive
from simulators.drives.cia402_node import SimNode
from swpc_hw.drives.cia402.config import ABSOLUTE, Cia402Axis, Cia402Drives, Cia402Steer

SUPPORTED_MODES = (
    Mode.HOMING,
    Mode.CYCLIC_SYNC_POSITION,
    Mode.CYCLIC_SYNC_VELOCITY,
    Mode.CYCLIC_SYNC_TORQUE,
)
SENSOR_HOMING_METHODS = range(17, 31)
"""Homing methods on a home switch (17..30): the steering's homing sensor."""
QUICK_STOP_TIME = 0.1
"""s in QUICK STOP ACTIVE before an option code 0..4 switches the power stage off."""
ABORT_VALUE_RANGE = 0x06090030
"""SDO abort: value range of parameter exceeded."""

ERROR_CODES: dict[ErrorFlag, int] = {
    ErrorFlag.OVER_TEMPERATURE: 0x4310,
    ErrorFlag.OVER_TORQUE: 0x2310,
    ErrorFlag.ENCODER: 0x7305,
    ErrorFlag.UNDER_VOLTAGE: 0x3220,
    ErrorFlag.OVER_SPEED: 0x8400,
    ErrorFlag.MOTOR: 0x7121,
}
"""The EMCY code a virtual drive reports for a fault injected as an swpc error flag."""


def modes_of(od: Any) -> tuple[Mode, ...]:
    """The modes a drive whose object dictionary is ``od`` has: its 0x6502 default (a real
    drive's EDS), else :data:`SUPPORTED_MODES`."""
    if cia402.SUPPORTED_MODES in od and od[cia402.SUPPORTED_MODES].default is not None:
        bits = int(od[cia402.SUPPORTED_MODES].default)
        return tuple(m for m in Mode if m and bits & cia402.supported_modes_bit(m))
    return SUPPORTED_MODES


class VirtualAxis(SimNode):
    """One single-axis CiA 402 drive (module docstring)."""

    def __init__(
        self,
        config: Cia402Axis,
        object_dictionary: Path,
        *,
        steer: bool,
        homing_duration: float = 0.2,
        sensor_position: float = 0.0,
    ) -> None:
        super().__init__(config.node, object_dictionary)
        self.config = config
        self.steer = steer
        self.node.add_write_callback(self._on_write)
        self.node.add_read_callback(self._on_read)
        self.model = AxisModel()
        self.counts_per_rad = config.counts_per_rad()
        od_has = self.node.object_dictionary.__contains__
        rated = self._od_default(cia402.RATED_TORQUE) if od_has(cia402.RATED_TORQUE) else 0
        # N.m at the motor: 0x6076, else what the config says the data sheet says
        self.rated_torque = rated / 1000.0 if rated > 0 else (config.rated_torque or 0.1)
        self.modes = modes_of(self.node.object_dictionary)
        """The modes this drive has: its EDS's 0x6502 (a personality), else the four
        swpc's own EDS declares."""
        self.state = PowerState.NOT_READY_TO_SWITCH_ON
        self.controlword = 0
        self.mode = Mode.NONE
        self.target_position = 0
        self.target_velocity = 0
        self.target_torque = 0
        self.error_code = 0
        absolute = isinstance(config, Cia402Steer) and config.homing == ABSOLUTE
        self.homed = absolute or not steer
        self.sensor_position = 0.0 if absolute or not steer else float(sensor_position)
        self.homing_duration = float(homing_duration)
        self.homing_end = math.inf
        self.homing_attained = False
        self.homing_error = False
        self.quick_stop_end = math.inf
        self.consumer_node = 0
        self.consumer_time = 0.0
        self.host_seen: float | None = None
        self.booted = False
        self.position = 0.0
        self.velocity = 0.0
        self.torque = 0.0
        self.sync_count = 0
        self.power_up_fault = 0
        """An error code the drive is in FAULT with from power-up (0: none)."""
        self.fault_clears = True
        """Whether a fault reset clears a fault (false: its cause persists)."""
        # cyclic synchronous position: the set-point in force (counts), the target
        # received since the last SYNC, the last cycle's change and the cycles missed
        self.csp_setpoint = 0
        # profile position: the set-point taken at bit 4's last rising edge, and its
        # acknowledgement (statusword bit 12 while bit 4 stays high)
        self.pp_setpoint = 0
        self.pp_ack = False
        self.csp_fresh: int | None = None
        self.csp_delta = 0
        self.csp_missed = 0

    # ------------------------------------------------------------------ object dictionary
    def _on_write(self, index: int, subindex: int, od: ODVariable, data: bytes) -> None:
        """Every write (SDO or RPDO) before it is stored: the drive acts on it, or refuses it
        (an SDO abort names why)."""
        value = od.decode_raw(data)
        assert isinstance(value, int)
        if index == cia402.CONTROLWORD:
            self._on_controlword(value)
        elif index == cia402.MODES_OF_OPERATION:
            if value in [int(m) for m in self.modes]:
                if value != self.mode:
                    self.homing_attained = self.homing_error = False
                    if value == Mode.CYCLIC_SYNC_POSITION:
                        self._csp_start()
                    if value == Mode.PROFILE_POSITION:
                        self._pp_start()
                self.mode = Mode(value)
            elif value != 0:
                raise SdoAbortedError(ABORT_VALUE_RANGE)  # an RPDO's is dropped: display stays
        elif index == cia402.TARGET_POSITION:
            self.target_position = value
            if self.mode is Mode.CYCLIC_SYNC_POSITION and self._csp_in_force():
                self.csp_fresh = value
        elif index == cia402.TARGET_VELOCITY:
            self.target_velocity = value
        elif index == cia402.TARGET_TORQUE:
            self.target_torque = value
        elif index == cia402.HOMING_METHOD and value not in SENSOR_HOMING_METHODS and value != 0:
            raise SdoAbortedError(ABORT_VALUE_RANGE)
        elif index == cia402.MAX_PROFILE_VELOCITY:
            self.model.max_velocity = value / self.counts_per_rad
        elif index == cia402.MAX_TORQUE:
            self.model.max_torque = self._torque_si(value)
        elif index == cia402.CONSUMER_HEARTBEAT and subindex == 1:
            self.consumer_node, ms = cia402.parse_consumer_entry(value)
            self.consumer_time = ms / 1000.0
            self.host_seen = None  # the consumer starts at the next heartbeat it sees

    def _on_read(self, index: int, subindex: int, od: ODVariable) -> int | None:
        """An SDO read of what the drive knows now (a TPDO carries what it knew at the
        SYNC): statusword and modes display, in any NMT state."""
        if index == cia402.STATUSWORD:
            return self.statusword()
        if index == cia402.MODES_DISPLAY:
            return int(self.mode)
        if index == cia402.SUPPORTED_MODES and od.default is None:  # the drive knows
            return sum(cia402.supported_modes_bit(m) for m in self.modes)
        if index == cia402.ENCODER_RESOLUTION and subindex in (1, 2):  # its encoder's
            return self.config.counts_per_turn if subindex == 1 else 1
        unset = subindex not in self.node.data_store.get(index, {})
        if unset and od.default is None and od.value is None:
            return 0  # an EDS without a default for it (a real drive has some value)
        return None

    def _torque_si(self, per_mille: int) -> float:
        """A torque object's value (thousandths of the rated torque) at the output, N.m."""
        return per_mille / 1000.0 * self.rated_torque * self.config.gear_ratio

    def _torque_units(self, torque: float) -> int:
        return round(torque / (self.rated_torque * self.config.gear_ratio) * 1000.0)

    # ------------------------------------------------------------------ 402 state machine
    def _csp_in_force(self) -> bool:
        return self.state is PowerState.OPERATION_ENABLED

    def _csp_start(self) -> None:
        """Cyclic synchronous position comes into force: from where the axis is, any
        target received before ignored."""
        self.csp_setpoint = round(self.position * self.counts_per_rad)
        self.csp_fresh, self.csp_delta, self.csp_missed = None, 0, 0

    def _pp_start(self) -> None:
        """Profile position comes into force: it holds where the axis is."""
        self.pp_setpoint = round(self.position * self.counts_per_rad)
        self.pp_ack = False

    def _csp_sync(self) -> None:
        """At a SYNC: the target received since the last one, else one cycle
        extrapolated, then held (module docstring)."""
        if self.csp_fresh is not None:
            self.csp_delta = self.csp_fresh - self.csp_setpoint if self.csp_missed == 0 else 0
            self.csp_setpoint, self.csp_fresh, self.csp_missed = self.csp_fresh, None, 0
        elif self.csp_missed == 0:
            self.csp_setpoint += self.csp_delta
            self.csp_missed = 1
        else:
            self.csp_delta = 0

    def _on_controlword(self, cw: int) -> None:
        prev, self.controlword = self.controlword, cw
        before = self.state
        self.state = cia402.drive_transition(self.state, cw, prev)
        if before is PowerState.FAULT and self.state is not before and not self.fault_clears:
            self.state = PowerState.FAULT  # the cause persists: reset again, still FAULT
        enabled = self.state is PowerState.OPERATION_ENABLED
        if enabled and before is not self.state and self.mode is Mode.CYCLIC_SYNC_POSITION:
            self._csp_start()
        if enabled and before is not self.state and self.mode is Mode.PROFILE_POSITION:
            self._pp_start()
        if enabled and self.mode is Mode.PROFILE_POSITION:
            edge = cw & cia402.CW_NEW_SETPOINT and not prev & cia402.CW_NEW_SETPOINT
            if edge:  # the set-point handshake: take the target, acknowledge it
                self.pp_setpoint, self.pp_ack = self.target_position, True
            elif not cw & cia402.CW_NEW_SETPOINT:
                self.pp_ack = False
        if before is PowerState.FAULT and self.state is not PowerState.FAULT:
            self.error_code = 0
            self._store(cia402.ERROR_CODE, 0)
            self._store(cia402.ERROR_REGISTER, 0)
            self.node.emcy.reset()
        if self.state is PowerState.QUICK_STOP_ACTIVE and before is not self.state:
            self.quick_stop_end = self.net.now + QUICK_STOP_TIME
        start = cw & cia402.CW_HOMING_START and not prev & cia402.CW_HOMING_START
        if start and self.state is PowerState.OPERATION_ENABLED and self.mode is Mode.HOMING:
            self._start_homing()
        if not cw & cia402.CW_HOMING_START and self.homing_end < math.inf:
            self.homing_end = math.inf  # bit 4 low: homing interrupted
            self.homing_error = True

    def _start_homing(self) -> None:
        self.homing_attained = self.homing_error = False
        if not self.steer or (self.homed and self.sensor_position == 0.0):
            self.homing_attained = True  # absolute encoder (or a wheel): home is here
            return
        if self._read(cia402.HOMING_METHOD) not in SENSOR_HOMING_METHODS:
            self.homing_error = True  # no method assigned (0)
            return
        self.homing_end = self.net.now + self.homing_duration

    def fault(self, code: int) -> None:
        """The fault reaction: power stage off (free), EMCY with ``code``; a
        communication error (0x81xx) also changes the NMT state as 0x1029 sub 1 says."""
        if self.state is PowerState.FAULT:
            return
        self.state = PowerState.FAULT  # the reaction of a virtual drive takes no time
        self.error_code = code
        self.homing_end = math.inf
        register = 0x01 | (0x10 if code & 0xFF00 == 0x8100 else 0)
        self._store(cia402.ERROR_CODE, code)
        self._store(cia402.ERROR_REGISTER, register)
        self.node.emcy.send(code, register)
        if code & 0xFF00 == 0x8100:
            self._error_behaviour()

    def statusword(self) -> int:
        extra = cia402.SW_REMOTE
        if self.mode is Mode.PROFILE_POSITION and self.state is PowerState.OPERATION_ENABLED:
            if self.pp_ack:
                extra |= cia402.SW_SETPOINT_ACK
            if (
                abs(self.position * self.counts_per_rad - self.pp_setpoint)
                < 0.001 * self.counts_per_rad
            ):
                extra |= cia402.SW_TARGET_REACHED
        if self.mode is Mode.HOMING:
            if self.homing_attained:
                extra |= cia402.SW_HOMING_ATTAINED | cia402.SW_TARGET_REACHED
            if self.homing_error:
                extra |= cia402.SW_HOMING_ERROR
        return cia402.statusword(self.state, extra)

    # ------------------------------------------------------------------ time
    def boot(self, now: float) -> None:
        """Power-up: boot-up message, PRE-OPERATIONAL, the heartbeat producer (0x1017)."""
        self.net.now = now
        self.node.data_store.clear()
        self.state = PowerState.SWITCH_ON_DISABLED  # transitions 0, 1: automatic
        self.controlword = 0
        self.consumer_time = 0.0
        self.host_seen = None
        self.guard_toggle, self.guarded_at = 0, None
        self.node.nmt.send_command(cia402.NMT_RESET_NODE)  # state 0: sends the boot-up
        self.node.nmt.send_command(cia402.NMT_ENTER_PRE_OPERATIONAL)  # heartbeat if 0x1017
        self.booted = True
        if self.power_up_fault:
            self.fault(self.power_up_fault)

    def receive(self, msg: can.Message, now: float) -> None:
        self.net.now = now
        cob = msg.arbitration_id
        if msg.is_remote_frame:
            if cob == cia402.HEARTBEAT_BASE + self.config.node:
                self._guard(now)
            return
        if self.consumer_node and cob == cia402.HEARTBEAT_BASE + self.consumer_node:
            self.host_seen = now
            return
        if cob == cia402.SYNC_ID and len(msg.data) <= 1:
            self._on_sync()
            return
        was = self.node.nmt.state
        self.net.notify(cob, bytearray(msg.data), now)
        if cob == cia402.NMT_ID:
            self._on_nmt(was, now)

    def _on_nmt(self, was: str, now: float) -> None:
        state = self.node.nmt.state
        if state == "INITIALISING":  # reset node / communication: boot again
            self.boot(now)
        elif state == "OPERATIONAL" and was != state:
            self.node.rpdo.read()  # the mapping the host wrote over SDO
            self.node.tpdo.read()
        elif was == "OPERATIONAL" != state and self.state is PowerState.OPERATION_ENABLED:
            self.state = PowerState.SWITCH_ON_DISABLED  # no PDOs any more: power off

    def _on_sync(self) -> None:
        if self.node.nmt.state != "OPERATIONAL":
            return
        self.sync_count += 1
        if self.mode is Mode.CYCLIC_SYNC_POSITION and self._csp_in_force():
            self._csp_sync()
        self._store(cia402.STATUSWORD, self.statusword())
        self._store(cia402.MODES_DISPLAY, int(self.mode))
        self._store(cia402.POSITION_ACTUAL, round(self.position * self.counts_per_rad))
        self._store(cia402.VELOCITY_ACTUAL, round(self.velocity * self.counts_per_rad))
        self._store(cia402.TORQUE_ACTUAL, self._torque_units(self.torque))
        self._transmit_tpdos(self.sync_count)

    def step(self, now: float) -> None:
        self.net.now = now
        if not self.booted:
            self.boot(now)
        if (
            self.consumer_time > 0
            and self.host_seen is not None
            and now - self.host_seen > self.consumer_time
        ):
            self.host_seen = None
            self.fault(0x8130)
        if self.guarded_at is not None and now - self.guarded_at > self.life_time:
            self.guarded_at = None  # a life guarding event: "life guard error"
            self.fault(0x8130)
        if now >= self.homing_end:
            self.homing_end = math.inf
            self.homed = True
            self.homing_attained = True
        if now >= self.quick_stop_end:
            self.quick_stop_end = math.inf
            has = cia402.QUICK_STOP_OPTION in self.node.object_dictionary
            option = self._read(cia402.QUICK_STOP_OPTION) if has else 2  # 402's default
            qsa = self.state is PowerState.QUICK_STOP_ACTIVE
            if qsa and option in cia402.QUICK_STOP_TO_DISABLED:
                self.state = PowerState.SWITCH_ON_DISABLED
        self.net.run_periodic(now)

    def next_due(self) -> float:
        due = min(self.net.next_due(), self.homing_end, self.quick_stop_end)
        if self.consumer_time > 0 and self.host_seen is not None:
            due = min(due, self.host_seen + self.consumer_time + 1e-6)
        if self.guarded_at is not None:
            due = min(due, self.guarded_at + self.life_time + 1e-6)
        return due

    # ------------------------------------------------------------------ physics
    def axis_model(self) -> AxisModel:
        """The drive's state as the physics' axis (module docstring)."""
        ax = self.model
        ax.state, ax.mode, ax.setpoint = AxisState.DISABLED, ControlMode.FREE, 0.0
        if self.state is PowerState.QUICK_STOP_ACTIVE:
            ax.state, ax.mode = AxisState.ENABLED, ControlMode.HOLD
        elif self.state is PowerState.OPERATION_ENABLED:
            ax.state = AxisState.ENABLED
            m = self.mode
            if m is Mode.HOMING:
                if self.homing_end < math.inf:
                    ax.state = AxisState.HOMING
                else:
                    ax.mode = ControlMode.HOLD
            elif m is Mode.CYCLIC_SYNC_POSITION:
                ax.mode = ControlMode.POSITION
                ax.setpoint = self.csp_setpoint / self.counts_per_rad
            elif m is Mode.PROFILE_POSITION:
                ax.mode = ControlMode.POSITION
                ax.setpoint = self.pp_setpoint / self.counts_per_rad
            elif m in (Mode.CYCLIC_SYNC_VELOCITY, Mode.PROFILE_VELOCITY):
                ax.mode = ControlMode.VELOCITY
                ax.setpoint = self.target_velocity / self.counts_per_rad
            elif m in (Mode.CYCLIC_SYNC_TORQUE, Mode.PROFILE_TORQUE) and self.target_torque != 0:
                ax.mode, ax.setpoint = ControlMode.TORQUE, self._torque_si(self.target_torque)
        return ax

    def sense(self, position: float, velocity: float, torque: float | None) -> None:
        self.position = position
        self.velocity = self.model.velocity = velocity
        self.torque = self.model.friction * velocity if torque is None else torque
        self.model.position, self.model.torque = position, self.torque


class VirtualCia402Module:
    """One module's virtual CiA 402 drives (steering and wheel): a
    :class:`simulators.drives.base.VirtualDrive`."""

    def __init__(
        self, config: Cia402Drives, module: int, *, homing_duration: float, sensor_position: float
    ) -> None:
        axes = config.axes()[module]
        self.axes = (
            VirtualAxis(axes.steer, config.eds(axes.steer), steer=True,
                        homing_duration=homing_duration, sensor_position=sensor_position),
            VirtualAxis(axes.wheel, config.eds(axes.wheel), steer=False),
        )  # fmt: skip
        self.muted = False
        self.heartbeats = 0
        self.feedback_frames = 0
        self._ids = {a.config.node for a in self.axes}
        self._hb = {cia402.HEARTBEAT_BASE + n for n in self._ids}
        self._fb = {cia402.TPDO_BASE[0] + n for n in self._ids}

    @property
    def homed(self) -> bool:
        return self.axes[Axis.STEER].homed

    @property
    def sensor_position(self) -> float:
        return self.axes[Axis.STEER].sensor_position

    def _out(self) -> list[can.Message]:
        out = [m for a in self.axes for m in a.net.take()]
        if self.muted:
            return []
        for m in out:
            if m.arbitration_id in self._hb:
                self.heartbeats += 1
            elif m.arbitration_id in self._fb:
                self.feedback_frames += 1
        return out

    def receive(self, msg: can.Message, now: float) -> list[can.Message]:
        if msg.is_error_frame or msg.is_extended_id:
            return []
        cob = msg.arbitration_id
        node = cob & 0x7F
        guard = cob & 0x780 == cia402.HEARTBEAT_BASE and node in self._ids
        if msg.is_remote_frame and not guard:  # node guarding's requests only
            return []
        if (
            node
            and node not in self._ids
            and cob >= cia402.TPDO_BASE[0]
            and (cob & 0x780 != cia402.HEARTBEAT_BASE)
        ):
            return []  # another node's SDO / PDO
        for a in self.axes:
            a.receive(msg, now)
        return self._out()

    def step(self, now: float) -> list[can.Message]:
        for a in self.axes:
            a.step(now)
        return self._out()

    def next_due(self) -> float:
        return min(a.next_due() for a in self.axes)

    def feedback_rate(self) -> float:
        return 0.0  # TPDOs on the host's SYNC

    def drive(
        self, axis: Axis, position: float, dt: float, position_tau: float
    ) -> tuple[str, float]:
        return axis_drive(self.axes[axis].axis_model(), axis, position, dt, position_tau)

    def sense(self, axis: Axis, position: float, velocity: float, torque: float | None) -> None:
        self.axes[axis].sense(position, velocity, torque)

    def inject_fault(self, axis: Axis, error: ErrorFlag) -> list[can.Message]:
        self.axes[axis].fault(ERROR_CODES.get(error, 0x1000))
        return self._out()

    def params(self) -> dict[str, Any]:
        return {
            "kind": "cia402",
            "steer_node": self.axes[Axis.STEER].config.node,
            "wheel_node": self.axes[Axis.WHEEL].config.node,
        }


def build(
    config: Any,
    module: int,
    *,
    feedback_rate_hz: int,
    watchdog_ms: int,
    homing_duration: float,
    sensor_position: float,
) -> VirtualCia402Module:
    """The builder of :data:`simulators.drives.factory.BUILDERS` (the feedback rate and the
    dead-man are the host's to set over CANopen: SYNC and 0x1016)."""
    assert isinstance(config, Cia402Drives)
    return VirtualCia402Module(
        config, module, homing_duration=homing_duration, sensor_position=sensor_position
    )
