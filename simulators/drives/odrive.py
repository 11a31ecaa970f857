"""The virtual ODrive: CAN Simple axes with the same physics as the other virtual drives.

:class:`VirtualODriveAxis` is one axis' firmware logic, transport-free (frames in through
:meth:`~VirtualODriveAxis.handle`, time through :meth:`~VirtualODriveAxis.step`, both
return the frames it sends), as ODrive documents it and, for 0.5.x, as its firmware source
does it (``Firmware/communication/can/can_simple.cpp``, ``MotorControl/axis.cpp``):

* axis states IDLE, CLOSED_LOOP_CONTROL, ENCODER_INDEX_SEARCH (the steering turns at the
  homing speed for ``homing_duration``, then its position is referenced to the index and
  the axis goes IDLE); a state request with an axis error active is refused;
* an axis whose motor and encoder are not calibrated (``calibrated`` False: a new ODrive,
  or one whose calibration was not saved) refuses closed loop and stays IDLE: 0.5.x
  latches the axis error INVALID_STATE (``axis.cpp``: closed loop needs the motor
  calibrated and the encoder ready), 0.6.x reports ``Procedure_Result`` NOT_CALIBRATED;
* control modes position, velocity and torque with passthrough inputs, ``Set_Limits``
  (velocity limit, current limit through the axis' torque constant and gear ratio);
* error bits of the line's DBC; ``Clear_Errors`` clears them;
* the axis watchdog (``watchdog_timeout``) with each line's feeding rule:
  0.5.x feeds it on *every* frame addressed to the axis' node, remote polls included, and
  counts it down in every state (an idle axis the host leaves alone reports
  WATCHDOG_TIMER_EXPIRED); 0.6.x feeds it on the setpoint frames (``Set_Input_Pos``,
  ``Set_Input_Vel``, ``Set_Input_Torque``) and checks it in closed loop only (ODrive's own
  CAN example feeds it with its setpoints; the exact set is not in the DBC).  Entering closed
  loop feeds it on both.  On expiry the axis is disarmed (IDLE) with the error latched;
* cyclic heartbeat (``T_hb``) and ``Get_Encoder_Estimates`` at the encoder rate; a remote
  poll of the estimates is answered (0.5.x does; swpc never polls), and on 0.6.x one of
  ``Get_Version`` (firmware 0.6.10, hardware 0.0.0: ``swpc drives scan`` asks it).

:class:`ODriveVirtualDrive` is one module's two axes as a
:class:`simulators.drives.base.VirtualDrive`: it turns each axis' state into the swpc
controller's axis model and hands it to :func:`simulators.drives.base.axis_drive`, so the
physics is the same as the swpc virtual drive's: torque control at exactly zero is a free
axis, position control of the steering is the first-order position loop, a wheel in
position control is held (braked: the only wheel position command swpc sends is a hold).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import can

from firmware_protocol.codec import (
    HEARTBEAT_PERIOD_S,
    Axis,
    AxisState,
    ControlMode,
    ErrorFlag,
    Frame,
    ProtocolError,
)
from firmware_protocol.odrive import can_simple as cs
from simulators.drives.base import AxisModel, axis_drive
from swpc_hw.drives.odrive.config import ODriveAxis, ODriveDrives

TWO_PI = 2.0 * math.pi
UNLIMITED = 1e9

FAULT_NAMES = {
    "0.5": {ErrorFlag.OVER_TEMPERATURE: "OVER_TEMP", ErrorFlag.ENCODER: "ENCODER_FAILED"},
    "0.6": {
        ErrorFlag.OVER_TEMPERATURE: "MOTOR_OVER_TEMP",
        ErrorFlag.UNDER_VOLTAGE: "DC_BUS_UNDER_VOLTAGE",
    },
}
"""swpc's injected hardware errors as each line's axis error (others: MOTOR_FAILED on
0.5.x, DRV_FAULT on 0.6.x)."""
DEFAULT_FAULT = {"0.5": "MOTOR_FAILED", "0.6": "DRV_FAULT"}
VIRTUAL_FIRMWARE = (0, 6, 10)
"""What a virtual 0.6.x axis answers to ``Get_Version``: the firmware of its DBC
(``odrive-cansimple-0.6.10``), hardware 0.0.0 (no board)."""
VIRTUAL_HARDWARE = (0, 0, 0)


@dataclass
class VirtualODriveAxis:
    """One axis (one node) of a virtual ODrive (module docstring).  Positions are axis
    turns; ``position`` / ``velocity`` are written by the physics (:meth:`sense`)."""

    node: int
    line: str
    spec: ODriveAxis
    encoder_rate_hz: float
    watchdog_timeout: float
    heartbeat_period: float = HEARTBEAT_PERIOD_S
    homing_duration: float = 0.2
    state: cs.AxisState = cs.AxisState.IDLE
    axis_error: int = 0
    procedure_result: int = cs.ProcedureResult.SUCCESS
    control_mode: int = cs.ControlMode.POSITION_CONTROL
    input_pos: float = 0.0
    input_vel: float = 0.0
    input_torque: float = 0.0
    vel_limit: float = UNLIMITED
    current_limit: float = UNLIMITED
    position: float = 0.0
    velocity: float = 0.0
    muted: bool = False
    estimates: int = 0
    feeds: int = 0
    _last_feed: float | None = None
    _index_end: float = math.inf
    _next_heartbeat: float | None = None
    _next_estimate: float | None = None
    index_found: bool = False
    calibrated: bool = True
    """The motor and encoder calibrations are done (saved, or run at start-up)."""
    codec: cs.CanSimple = field(init=False)

    def __post_init__(self) -> None:
        self.codec = cs.can_simple(self.line)

    # ------------------------------------------------------------------ frames in
    def handle(self, msg: can.Message, now: float) -> list[Frame]:
        """A frame seen on the bus at ``now``; the frames this axis answers with."""
        if msg.is_error_frame or msg.is_extended_id:
            return []
        node, _ = cs.split_id(msg.arbitration_id)
        if node != self.node:
            return []
        out = self._start(now)
        if self.line == "0.5":
            self._feed(now)  # can_simple.cpp: do_command() feeds before it looks at the frame
        try:
            dec = self.codec.decode(msg.arbitration_id, bytes(msg.data), msg.is_remote_frame)
        except ProtocolError:
            return out
        if isinstance(dec, cs.Poll):
            if dec.cmd == cs.Cmd.GET_ENCODER_ESTIMATES:
                out += self._estimate()
            elif dec.cmd == cs.Cmd.GET_VERSION and self.codec.has_version:
                out += self._send([self.codec.version(self.node, VIRTUAL_FIRMWARE,
                                                      VIRTUAL_HARDWARE)])  # fmt: skip
            return out
        if self.line == "0.6" and isinstance(dec, cs.SETPOINTS):
            self._feed(now)
        if isinstance(dec, cs.SetAxisState):
            self._request(dec.state, now)
        elif isinstance(dec, cs.SetControllerMode):
            self.control_mode = dec.control_mode
        elif isinstance(dec, cs.SetInputPos):
            self.input_pos = dec.pos
        elif isinstance(dec, cs.SetInputVel):
            self.input_vel = dec.vel
        elif isinstance(dec, cs.SetInputTorque):
            self.input_torque = dec.torque
        elif isinstance(dec, cs.SetLimits):
            self.vel_limit, self.current_limit = dec.velocity_limit, dec.current_limit
        elif isinstance(dec, cs.ClearErrors):
            self.axis_error = 0
        return out

    def _feed(self, now: float) -> None:
        self._last_feed = now
        self.feeds += 1

    def _request(self, state: int, now: float) -> None:
        if state == cs.AxisState.IDLE:
            self.state = cs.AxisState.IDLE
            return
        if self.axis_error:  # refused: the axis stays where it is
            self.procedure_result = cs.ProcedureResult.DISARMED
            return
        if state == cs.AxisState.CLOSED_LOOP_CONTROL and not self.calibrated:
            self.state = cs.AxisState.IDLE  # refused (module docstring)
            if self.line == "0.5":
                self.axis_error |= self.codec.error_bit("INVALID_STATE")
            else:
                self.procedure_result = cs.ProcedureResult.NOT_CALIBRATED
        elif state == cs.AxisState.CLOSED_LOOP_CONTROL:
            self.state = cs.AxisState.CLOSED_LOOP_CONTROL
            self.procedure_result = cs.ProcedureResult.SUCCESS
            self._feed(now)  # axis.cpp: entering closed loop feeds the watchdog
        elif state == cs.AxisState.ENCODER_INDEX_SEARCH:
            self.state = cs.AxisState.ENCODER_INDEX_SEARCH
            self.procedure_result = cs.ProcedureResult.BUSY
            self._index_end = now + self.homing_duration

    # ------------------------------------------------------------------ time
    def _start(self, now: float) -> list[Frame]:
        if self._next_heartbeat is None:
            self._next_heartbeat = self._next_estimate = now
            self._last_feed = now
        return []

    def watchdog_due(self) -> float:
        """When the watchdog expires unless fed (inf: not counting)."""
        if self.watchdog_timeout <= 0 or self._last_feed is None or self.axis_error:
            return math.inf
        counting = self.line == "0.5" or self.state == cs.AxisState.CLOSED_LOOP_CONTROL
        return self._last_feed + self.watchdog_timeout if counting else math.inf

    def step(self, now: float) -> list[Frame]:
        """The axis' own logic at ``now``: index search, watchdog, heartbeat, estimates."""
        out = self._start(now)
        if self.state == cs.AxisState.ENCODER_INDEX_SEARCH and now >= self._index_end:
            self.index_found = True
            self.state = cs.AxisState.IDLE
            self.procedure_result = cs.ProcedureResult.SUCCESS
            self._index_end = math.inf
        if now > self.watchdog_due():
            self.axis_error |= self.codec.watchdog_bit
            self.state = cs.AxisState.IDLE
        assert self._next_heartbeat is not None and self._next_estimate is not None
        if now >= self._next_heartbeat:
            self._next_heartbeat = max(self._next_heartbeat + self.heartbeat_period, now)
            out += self._send(
                [
                    self.codec.heartbeat(
                        self.node,
                        self.axis_error,
                        self.state,
                        procedure_result=self.procedure_result,
                    )
                ]
            )
        if self.encoder_rate_hz > 0 and now >= self._next_estimate:
            period = 1.0 / self.encoder_rate_hz
            self._next_estimate = max(self._next_estimate + period, now - 2 * period)
            out += self._estimate()
        return out

    def next_due(self) -> float:
        if self._next_heartbeat is None or self._next_estimate is None:
            return -math.inf
        due = min(self._next_heartbeat, self._index_end)
        if self.encoder_rate_hz > 0:
            due = min(due, self._next_estimate)
        wd = self.watchdog_due()
        return min(due, math.nextafter(wd, math.inf)) if math.isfinite(wd) else due

    def _estimate(self) -> list[Frame]:
        frames = self._send([self.codec.encoder_estimates(self.node, self.position, self.velocity)])
        self.estimates += len(frames)
        return frames

    def _send(self, frames: list[Frame]) -> list[Frame]:
        return [] if self.muted else frames

    def inject(self, name: str) -> None:
        """Latch the axis error ``name`` (a DBC name): the axis is disarmed."""
        self.axis_error |= self.codec.error_bit(name)
        self.state = cs.AxisState.IDLE

    # ------------------------------------------------------------------ physics view
    def model(self, m: AxisModel, wheel: bool) -> AxisModel:
        """``m`` (the swpc axis model the physics reads, SI at the output) set from this
        axis' state (module docstring)."""
        r = self.spec.gear_ratio
        m.max_velocity = self.vel_limit * TWO_PI / r
        m.max_torque = self.current_limit * self.spec.torque_constant * r
        m.errors = self.axis_error
        if self.axis_error:
            m.state, m.mode = AxisState.FAULT, ControlMode.FREE
        elif self.state == cs.AxisState.ENCODER_INDEX_SEARCH:
            m.state, m.mode = AxisState.HOMING, ControlMode.FREE
        elif self.state == cs.AxisState.CLOSED_LOOP_CONTROL:
            m.state = AxisState.ENABLED
            if self.control_mode == cs.ControlMode.POSITION_CONTROL:
                if wheel:
                    m.mode = ControlMode.HOLD
                else:
                    m.mode, m.setpoint = ControlMode.POSITION, self.input_pos * TWO_PI / r
            elif self.control_mode == cs.ControlMode.VELOCITY_CONTROL:
                m.mode, m.setpoint = ControlMode.VELOCITY, self.input_vel * TWO_PI / r
            elif self.control_mode == cs.ControlMode.TORQUE_CONTROL and self.input_torque != 0:
                m.mode, m.setpoint = ControlMode.TORQUE, self.input_torque * r
            else:
                m.mode = ControlMode.FREE
        else:
            m.state, m.mode = AxisState.DISABLED, ControlMode.FREE
        return m


class ODriveVirtualDrive:
    """One module's steering and wheel ODrive axes (module docstring)."""

    def __init__(
        self,
        steer: VirtualODriveAxis,
        wheel: VirtualODriveAxis,
        *,
        homing: str,
        sensor_position: float,
    ) -> None:
        self.axes = (steer, wheel)
        self.models = (AxisModel(), AxisModel())
        self.homing = homing
        self._sensor_position = float(sensor_position)
        self._offset = self._sensor_position if homing == "none" else 0.0
        self.heartbeats = 0
        self.feedback_frames = 0

    @property
    def homed(self) -> bool:
        """Index search done, or referenced at power-up (absolute encoder, or none: the
        power-up position is the reference, kept in :attr:`_offset`)."""
        return self.homing != "index" or self.axes[Axis.STEER].index_found

    @property
    def muted(self) -> bool:
        return self.axes[0].muted

    @muted.setter
    def muted(self, value: bool) -> None:
        for a in self.axes:
            a.muted = value

    @property
    def sensor_position(self) -> float:
        return self._sensor_position

    def _out(self, frames: list[Frame]) -> list[can.Message]:
        for f in frames:
            cmd = f.arbitration_id & cs.CMD_MASK
            if cmd == cs.Cmd.HEARTBEAT:
                self.heartbeats += 1
            elif cmd == cs.Cmd.GET_ENCODER_ESTIMATES:
                self.feedback_frames += 1
        return [
            can.Message(arbitration_id=f.arbitration_id, data=f.data, is_extended_id=False)
            for f in frames
        ]

    def receive(self, msg: can.Message, now: float) -> list[can.Message]:
        out: list[Frame] = []
        for a in self.axes:
            out += a.handle(msg, now)
        return self._out(out)

    def step(self, now: float) -> list[can.Message]:
        out: list[Frame] = []
        for a in self.axes:
            out += a.step(now)
        return self._out(out)

    def next_due(self) -> float:
        return min(a.next_due() for a in self.axes)

    def feedback_rate(self) -> float:
        return max(a.encoder_rate_hz for a in self.axes)

    def drive(
        self, axis: Axis, position: float, dt: float, position_tau: float
    ) -> tuple[str, float]:
        ax = self.axes[axis]
        m = ax.model(self.models[axis], wheel=axis == Axis.WHEEL)
        off = self._offset if axis == Axis.STEER else 0.0
        return axis_drive(m, axis, position + off, dt, position_tau)

    def sense(
        self, axis: Axis, position: float, velocity: float, torque: float | None
    ) -> None:
        m = self.models[axis]
        off = self._offset if axis == Axis.STEER else 0.0
        m.position, m.velocity = position + off, velocity
        m.torque = m.friction * velocity if torque is None else torque
        ax = self.axes[axis]
        r = ax.spec.gear_ratio
        ax.position = (position + off) * r / TWO_PI
        ax.velocity = velocity * r / TWO_PI

    def inject_fault(self, axis: Axis, error: ErrorFlag) -> list[can.Message]:
        ax = self.axes[axis]
        ax.inject(FAULT_NAMES[ax.line].get(error, DEFAULT_FAULT[ax.line]))
        return []  # CAN Simple has no fault frame: the next heartbeat reports it

    def params(self) -> dict[str, Any]:
        return {
            "kind": "odrive",
            "firmware": self.axes[0].line,
            "homing": self.homing,
            "steer_node": self.axes[0].node,
            "wheel_node": self.axes[1].node,
        }


def odrive_virtual_drive(
    config: ODriveDrives,
    module: int,
    *,
    feedback_rate_hz: int,
    watchdog_ms: int,
    homing_duration: float,
    sensor_position: float,
) -> ODriveVirtualDrive:
    """One module's virtual ODrive axes of ``config`` (module map filled in): the encoder
    rate is the config's (else ``feedback_rate_hz``), the watchdog ``watchdog_ms``."""
    md = config.module_map()[module]
    rate = config.encoder_rate_hz or feedback_rate_hz

    def axis(spec: ODriveAxis, homing_s: float) -> VirtualODriveAxis:
        return VirtualODriveAxis(
            node=spec.node,
            line=config.firmware,
            spec=spec,
            encoder_rate_hz=rate,
            watchdog_timeout=watchdog_ms / 1000.0,
            homing_duration=homing_s,
        )

    return ODriveVirtualDrive(
        axis(md.steer, homing_duration),
        axis(md.wheel, homing_duration),
        homing=config.homing,
        sensor_position=sensor_position,
    )
