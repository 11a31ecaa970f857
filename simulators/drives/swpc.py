"""Virtual SWPC motor controller: the firmware's state machine, reusable by every simulator.

:class:`VirtualController` is transport-free: feed it host frames with :meth:`handle` and
advance time with :meth:`step`; both return the frames the controller would send.
:class:`ControllerEmulator` runs several of them on a python-can bus in one thread (the
back-to-back tests and ``make bench`` use it; a full simulator can drive ``VirtualController``
itself and overwrite ``axes[i].position``/``velocity`` from its physics).

Per-axis state machine (see firmware_protocol/README.md)::

    DISABLED --SetAxisState(ENABLED), no errors--> ENABLED (mode FREE)
    ENABLED  --SetControl--> ENABLED (mode FREE|HOLD|POSITION|VELOCITY|TORQUE)
    ENABLED  --StartHoming (steer)--> HOMING --found--> ENABLED (HOLD at 0) | FAULT
    ENABLED|HOMING --SetAxisState(DISABLED)--> DISABLED
    ENABLED|HOMING --error (watchdog, over-speed, not homed, ...)--> FAULT (free) + FaultReport
    FAULT    --ClearErrors--> DISABLED

Axis dynamics are deliberately simple (rigid inertia ``J`` with viscous friction ``c``):
``J * dv/dt = tau - c * v``; VELOCITY and POSITION modes are ideal first-order loops.
"""

from __future__ import annotations

import math
import threading
from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import can

from firmware_protocol import codec
from firmware_protocol.codec import (
    Axis,
    AxisState,
    ControlMode,
    ErrorFlag,
    Frame,
    HomingState,
)
from simulators.drives.base import AxisModel, VirtualDrive, axis_drive, message
from swpc_hw.clock import SYSTEM_CLOCK, Clock, SimClock, next_instant
from swpc_hw.drives.registry import DrivesConfig
from swpc_hw.drives.swpc.config import SwpcDrives

DEFAULT_RATE_HZ = codec.POWER_UP_FEEDBACK_RATE_HZ
HEARTBEAT_PERIOD_S = codec.HEARTBEAT_PERIOD_S
OVER_SPEED_FACTOR = 1.2


@dataclass
class VirtualController:
    """One dual-axis controller (axis 0 steering, axis 1 wheel) at CAN node ``node``."""

    node: int
    rate_hz: int = DEFAULT_RATE_HZ
    watchdog_ms: int = codec.POWER_UP_WATCHDOG_MS  # the firmware's, until the host sets W
    heartbeat_period: float = HEARTBEAT_PERIOD_S
    homing_duration: float = 0.2
    sensor_position: float = 0.3
    """Steering position (power-up coordinate) at which the homing sensor triggers, rad."""
    sync_mode: bool = False
    axes: tuple[AxisModel, AxisModel] = field(default_factory=lambda: (AxisModel(), AxisModel()))
    homed: bool = False
    muted: bool = False
    """A muted controller sends nothing (an unplugged or dead node)."""
    lose: frozenset[int] = frozenset()
    """Commands (:class:`~firmware_protocol.codec.Command`) whose frames never reach the
    host, as from a receive queue that overflowed: a one-shot frame like HomingStatus is
    then gone for good."""
    invalid_frames: int = 0
    commands: int = 0
    _t: float | None = None
    _last_command: float = 0.0
    _next_feedback: float = 0.0
    _next_heartbeat: float = 0.0
    _homing_end: float = 0.0
    _sample_counter: int = 0
    _hb_counter: int = 0

    # ------------------------------------------------------------------ host frames
    def handle(self, frame: Frame, now: float, arrived: float | None = None) -> list[Frame]:
        """Process one frame seen on the bus; return the frames sent in reply.

        ``arrived``: when the frame reached the controller, if earlier than ``now`` (an
        emulator thread that was not scheduled): the watchdog judges a command by its
        arrival, as firmware handling frames in an interrupt would.
        """
        node, cmd = codec.split_id(frame.arbitration_id)
        if frame.arbitration_id == codec.SYNC_ID:
            try:
                msg = codec.parse(frame.arbitration_id, frame.data)
            except codec.ProtocolError:
                self.invalid_frames += 1
                return []
            assert isinstance(msg, codec.Sync)
            if self.sync_mode:
                # what the time up to now brought first (homing done, a fault), then the sample
                return self._advance(now, on_frame=True) + self._feedback(msg.counter)
            return []
        if node != self.node or cmd not in codec.HOST_COMMANDS:
            return []
        try:
            msg2 = codec.parse(frame.arbitration_id, frame.data)
        except codec.ProtocolError:
            self.invalid_frames += 1
            return []
        # the frames the time up to now brought (homing done, a watchdog or over-speed
        # fault) go out before the command's own answer: they were dropped once, and a
        # HomingStatus DONE due as a command arrived never reached the host
        out = self._advance(now, on_frame=True, watchdog_at=arrived)
        self._last_command = now
        self.commands += 1
        return out + self._apply(msg2, now)

    def _apply(self, msg: codec.Decoded, now: float) -> list[Frame]:
        out: list[Frame] = []
        if isinstance(msg, codec.SetAxisState):
            ax = self.axes[msg.axis]
            if msg.enabled and ax.state == AxisState.DISABLED and ax.errors == 0:
                ax.state, ax.mode, ax.setpoint = AxisState.ENABLED, ControlMode.FREE, 0.0
            elif not msg.enabled and ax.state in (AxisState.ENABLED, AxisState.HOMING):
                ax.state, ax.mode, ax.setpoint = AxisState.DISABLED, ControlMode.FREE, 0.0
        elif isinstance(msg, codec.SetControl):
            ax = self.axes[msg.axis]
            if ax.state != AxisState.ENABLED:
                return out
            if msg.mode == ControlMode.POSITION and msg.axis == Axis.STEER and not self.homed:
                return self._fault(msg.axis, ErrorFlag.NOT_HOMED)
            prev_mode, ax.mode = ax.mode, msg.mode
            if msg.mode == ControlMode.VELOCITY:
                ax.setpoint = _clamp(msg.setpoint, ax.max_velocity)
            elif msg.mode == ControlMode.TORQUE:
                ax.setpoint = _clamp(msg.setpoint, ax.max_torque)
            elif msg.mode == ControlMode.POSITION and msg.axis == Axis.STEER:
                # modulo the feedback's wrap (8 turns), nearest the position: the host knows
                # the steering only modulo that span (it unwraps from its first sample)
                ax.setpoint = ax.position + math.remainder(
                    msg.setpoint - ax.position, codec.STEER_SPAN
                )
            elif msg.mode == ControlMode.POSITION:
                ax.setpoint = msg.setpoint
            elif msg.mode == ControlMode.HOLD:
                if prev_mode != ControlMode.HOLD:
                    ax.hold_target = ax.position
                ax.setpoint = 0.0
            else:
                ax.setpoint = 0.0
        elif isinstance(msg, codec.ClearErrors):
            for axis in Axis:
                if msg.axis_mask & (1 << axis):
                    ax = self.axes[axis]
                    ax.errors = 0
                    if ax.state == AxisState.FAULT:
                        ax.state = AxisState.DISABLED
        elif isinstance(msg, codec.SetLimits):
            ax = self.axes[msg.axis]
            ax.max_torque, ax.max_velocity = msg.max_torque, msg.max_velocity
        elif isinstance(msg, codec.SetWatchdog):
            self.watchdog_ms = msg.timeout_ms
        elif isinstance(msg, codec.SetFeedback):
            self.rate_hz, self.sync_mode = msg.rate_hz, msg.sync_mode
            self._next_feedback = now
        elif isinstance(msg, codec.StartHoming):
            ax = self.axes[msg.axis]
            if msg.axis != Axis.STEER or ax.state != AxisState.ENABLED:
                out.append(codec.make_homing_status(self.node, msg.axis, HomingState.FAILED))
            else:
                ax.state, ax.mode = AxisState.HOMING, ControlMode.FREE
                self._homing_end = now + self.homing_duration
                out.append(codec.make_homing_status(self.node, msg.axis, HomingState.IN_PROGRESS))
        return self._send(out)

    # ------------------------------------------------------------------ time
    def step(self, now: float, watchdog_at: float | None = None) -> list[Frame]:
        """Advance to ``now``: dynamics, watchdog, homing, heartbeat and feedback due.

        ``watchdog_at``: judge the watchdog at this earlier time instead, the latest time up
        to which every command that arrived has been handled (a host that only knows its
        receive queue was empty some time before ``now``).
        """
        out = self._advance(now, watchdog_at=watchdog_at)
        if now >= self._next_heartbeat:
            self._next_heartbeat = max(self._next_heartbeat + self.heartbeat_period, now)
            out += self.heartbeat()
        if self.rate_hz > 0 and not self.sync_mode and now >= self._next_feedback:
            period = 1.0 / self.rate_hz
            # catch up without bursting if the caller was late by more than 2 periods
            self._next_feedback = max(self._next_feedback + period, now - 2 * period)
            out += self._feedback(self._sample_counter)
            self._sample_counter = (self._sample_counter + 1) & 0xFF
        return out

    def next_due(self) -> float:
        """Host time of the next frame this controller will send by itself."""
        due = self._next_heartbeat
        if self.rate_hz > 0 and not self.sync_mode:
            due = min(due, self._next_feedback)
        if any(ax.state == AxisState.HOMING for ax in self.axes):
            due = min(due, self._homing_end)
        if self.watchdog_ms > 0 and any(
            ax.state in (AxisState.ENABLED, AxisState.HOMING) for ax in self.axes
        ):
            due = min(due, self._last_command + self.watchdog_ms / 1000.0)
        return due

    def _advance(
        self, now: float, on_frame: bool = False, watchdog_at: float | None = None
    ) -> list[Frame]:
        """Integrate the axes to ``now``, then the watchdog, over-speed and homing checks.

        Over-speed is judged on the velocity an axis reached under the mode in force.  A
        frame handled at the instant of the last update (``dt = 0``, ``on_frame``: always
        so under a simulator's physics, which owns the axes and sets ``_t``) has moved
        nothing: the velocity is the one of the mode before a command that may just have
        changed it (a free caster swinging at 7 rad/s, just put in POSITION mode), so the
        check waits for the next :meth:`step`, after the axes moved under the new mode.
        """
        if self._t is None:
            self._t = now
            self._last_command = now
            self._next_feedback = now
            self._next_heartbeat = now
        dt = max(0.0, now - self._t)
        self._t = now
        out: list[Frame] = []
        for axis, ax in zip(Axis, self.axes, strict=True):
            _integrate(ax, dt)
            if (
                (dt > 0.0 or not on_frame)
                and ax.state == AxisState.ENABLED
                and ax.mode != ControlMode.FREE  # a free axis is moved by the world, not us
                and abs(ax.velocity) > OVER_SPEED_FACTOR * ax.max_velocity
            ):
                out += self._fault(axis, ErrorFlag.OVER_SPEED)
        steer = self.axes[Axis.STEER]
        if steer.state == AxisState.HOMING and now >= self._homing_end:
            steer.position -= self.sensor_position
            self.homed = True
            steer.state, steer.mode = AxisState.ENABLED, ControlMode.HOLD
            steer.hold_target, steer.setpoint = steer.position, 0.0
            out += self._send(
                [
                    codec.make_homing_status(
                        self.node, Axis.STEER, HomingState.DONE, self.sensor_position
                    )
                ]
            )
        at = now if watchdog_at is None else min(now, watchdog_at)
        if self.watchdog_ms > 0 and at - self._last_command > self.watchdog_ms / 1000.0:
            for axis, ax in zip(Axis, self.axes, strict=True):
                if ax.state in (AxisState.ENABLED, AxisState.HOMING):
                    out += self._fault(axis, ErrorFlag.WATCHDOG_TIMEOUT)
        return out

    # ------------------------------------------------------------------ outputs
    def heartbeat(self) -> list[Frame]:
        s, w = self.axes
        frame = codec.make_heartbeat(
            self.node,
            (s.state, w.state),
            (s.mode, w.mode),
            (s.errors, w.errors),
            self.homed,
            self.sync_mode,
            self._hb_counter,
        )
        self._hb_counter = (self._hb_counter + 1) & 0xFF
        return self._send([frame])

    def _feedback(self, counter: int) -> list[Frame]:
        s, w = self.axes
        return self._send(
            [
                codec.make_feedback_position(self.node, s.position, w.position, counter),
                codec.make_feedback_velocity_torque(
                    self.node,
                    _clamp(s.velocity, 32.767),
                    _clamp(w.velocity, 65.534),
                    _clamp(s.torque, 20.47),
                    _clamp(w.torque, 20.47),
                    counter,
                ),
            ]
        )

    def inject_error(self, axis: Axis, error: ErrorFlag) -> list[Frame]:
        """Raise a hardware error (e.g. OVER_TEMPERATURE) on ``axis``."""
        return self._fault(axis, error)

    def _fault(self, axis: Axis, error: ErrorFlag) -> list[Frame]:
        ax = self.axes[axis]
        new = int(error) & ~ax.errors
        ax.errors |= int(error)
        ax.state, ax.mode, ax.setpoint, ax.torque = AxisState.FAULT, ControlMode.FREE, 0.0, 0.0
        return self._send(
            [codec.make_fault_report(self.node, axis, new, ax.errors, AxisState.FAULT)]
        )

    def _send(self, frames: list[Frame]) -> list[Frame]:
        if self.muted:
            return []
        if self.lose:
            return [f for f in frames if codec.split_id(f.arbitration_id)[1] not in self.lose]
        return frames


def _clamp(x: float, limit: float) -> float:
    return max(-limit, min(limit, x))


def _integrate(ax: AxisModel, dt: float) -> None:
    """Advance one axis by ``dt``: ``J dv/dt = tau - c v`` or an ideal loop per mode."""
    if dt <= 0.0:
        return
    powered = ax.state in (AxisState.ENABLED, AxisState.HOMING)
    mode = ax.mode if ax.state == AxisState.ENABLED else ControlMode.FREE
    if ax.state == AxisState.HOMING:
        v = 0.5  # homing search speed, rad/s
        ax.torque = ax.friction * v
    elif not powered or mode == ControlMode.FREE:
        v = ax.velocity * math.exp(-dt * ax.friction / ax.inertia)
        ax.torque = 0.0
    elif mode == ControlMode.HOLD:
        v = 0.0
        ax.position = ax.hold_target
        ax.torque = 0.0
    elif mode == ControlMode.VELOCITY:
        v = ax.setpoint
        ax.torque = _clamp(ax.friction * v, ax.max_torque)
    elif mode == ControlMode.POSITION:
        v = _clamp((ax.setpoint - ax.position) / max(dt, 0.02), ax.max_velocity)
        ax.torque = _clamp(ax.friction * v, ax.max_torque)
    else:  # TORQUE
        tau = _clamp(ax.setpoint, ax.max_torque)
        decay = math.exp(-dt * ax.friction / ax.inertia)
        v_inf = tau / ax.friction
        v = v_inf + (ax.velocity - v_inf) * decay
        ax.torque = tau
    if mode == ControlMode.POSITION:
        # the position loop moves by its own velocity alone: averaged with the velocity of
        # the step before (the trapezoid), it overshot its set-point whenever a step was
        # longer than the one before, and under uneven steps (a loaded host) never settled
        ax.position += v * dt
    else:
        ax.position += 0.5 * (ax.velocity + v) * dt
    ax.velocity = v


class ControllerEmulator:
    """Run virtual controllers on a python-can bus in one thread (no busy loop).

    On a real clock the thread sleeps in ``bus.recv(timeout)`` until the next frame is
    due, so a command is answered within the OS wake-up latency.  On a
    :class:`swpc_hw.clock.SimClock` the thread is the clock's master: it handles the
    commands sent up to the current time, steps the controllers to the next instant
    anything is due (at most ``max_step`` later), puts their frames on the bus stamped with
    that instant, and advances the clock (lockstep: the driver's I/O step and every
    waiting test run before time moves on again).
    """

    def __init__(
        self,
        controllers: Sequence[VirtualController],
        *,
        interface: str = "virtual",
        channel: str = "swpc",
        bus: can.BusABC | None = None,
        clock: Clock = SYSTEM_CLOCK,
        max_step: float = 0.005,
        **bus_kwargs: Any,
    ) -> None:
        self.controllers = {c.node: c for c in controllers}
        self.clock = clock
        self.max_step = float(max_step)
        self._own_bus = bus is None
        if isinstance(clock, SimClock):
            bus_kwargs.setdefault("preserve_timestamps", True)
        self.bus = (
            bus if bus is not None else can.Bus(interface=interface, channel=channel, **bus_kwargs)
        )
        self.lock = threading.Lock()
        self.sent: Counter[int] = Counter()
        self.received: list[tuple[float, Frame]] = []
        self.record_received = True
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.error: BaseException | None = None

    # context manager ---------------------------------------------------
    def __enter__(self) -> ControllerEmulator:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def start(self) -> None:
        target = self._run_lockstep if isinstance(self.clock, SimClock) else self._run
        self._thread = threading.Thread(target=target, name="swpc-emulator", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        if self._own_bus:
            self.bus.shutdown()

    @property
    def thread(self) -> threading.Thread | None:
        return self._thread

    def send_raw(self, msg: can.Message) -> None:
        """Put an arbitrary frame on the bus (error frames, unknown ids, bad DLC)."""
        with self.lock:
            msg.timestamp = self.clock.wall()
            self.bus.send(msg)

    def mute(self, node: int, muted: bool = True) -> None:
        with self.lock:
            self.controllers[node].muted = muted

    def _transmit(self, frames: Iterable[Frame], stamp: float) -> None:
        for f in frames:
            self.bus.send(
                can.Message(
                    arbitration_id=f.arbitration_id,
                    data=f.data,
                    is_extended_id=False,
                    timestamp=stamp,
                )
            )
            self.sent[f.arbitration_id] += 1

    def _run(self) -> None:
        clock = self.clock
        try:
            while not self._stop.is_set():
                # frames that arrived while this thread was not running come first: a
                # command that arrived in time fed the watchdog (stepping first faulted
                # the axes of a controller whose commands sat in the queue).  Every frame
                # that arrived before `horizon` has then been handled; one that arrives
                # while this thread waits for the GIL after the queue was found empty sits
                # in the queue, so the watchdog is judged at `horizon`, not at `now`
                horizon = clock.now()
                self._handle_queued(self.bus.recv(0))
                now = clock.now()
                with self.lock:
                    for c in self.controllers.values():
                        self._transmit(c.step(now, watchdog_at=horizon), clock.wall())
                    due = min(c.next_due() for c in self.controllers.values())
                timeout = min(max((due - clock.now()) / clock.rate, 0.0), 0.05)
                self._handle_queued(self.bus.recv(timeout=timeout if timeout > 0 else 0))
        except BaseException as exc:  # surfaced to the test through .error
            self.error = exc
            raise

    def _run_lockstep(self) -> None:
        clock = self.clock
        assert isinstance(clock, SimClock)
        try:
            while not self._stop.is_set():
                if not clock.wait_for_demand(self._stop):
                    continue
                t = clock.now()
                self._handle_queued(self.bus.recv(0))  # what was sent up to t
                with self.lock:
                    due = min(c.next_due() for c in self.controllers.values())
                t_next = next_instant(t, [due, clock.next_wake(), t + self.max_step])
                with self.lock:
                    for c in self.controllers.values():
                        self._transmit(c.step(t_next), clock.to_wall(t_next))
                clock.advance_to(t_next, self._stop)
        except BaseException as exc:  # surfaced to the test through .error
            self.error = exc
            if not self._stop.is_set():
                raise

    def _handle_queued(self, msg: can.Message | None) -> None:
        """Handle ``msg`` and every frame already queued behind it."""
        while msg is not None:
            self._on_frame(msg)
            msg = self.bus.recv(0)

    def _on_frame(self, msg: can.Message) -> None:
        if msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id:
            return
        frame = Frame(msg.arbitration_id, bytes(msg.data))
        clock = self.clock
        now = clock.now()
        # the bus's receive stamp on the clock's axis (when it reached the controller)
        arrived = min(now, clock.from_wall(msg.timestamp)) if msg.timestamp else None
        with self.lock:
            if self.record_received:
                self.received.append((now, frame))
            for c in self.controllers.values():
                self._transmit(c.handle(frame, now, arrived), clock.wall())


class SwpcVirtualDrive:
    """swpc's own firmware (:class:`~simulators.drives.swpc.VirtualController`):
    one dual-axis controller on one node."""

    def __init__(self, controller: VirtualController) -> None:
        self.controller = controller
        self.heartbeats = 0
        self.feedback_frames = 0
        self._hb_id = codec.frame_id(controller.node, codec.Command.HEARTBEAT)
        self._fb_id = codec.frame_id(controller.node, codec.Command.FEEDBACK_POSITION)

    @property
    def homed(self) -> bool:
        return self.controller.homed

    @property
    def muted(self) -> bool:
        return self.controller.muted

    @muted.setter
    def muted(self, value: bool) -> None:
        self.controller.muted = value

    @property
    def sensor_position(self) -> float:
        return self.controller.sensor_position

    def _out(self, frames: list[Frame]) -> list[can.Message]:
        for f in frames:
            if f.arbitration_id == self._fb_id:
                self.feedback_frames += 1
            elif f.arbitration_id == self._hb_id:
                self.heartbeats += 1
        return [message(f) for f in frames]

    def receive(self, msg: can.Message, now: float) -> list[can.Message]:
        if msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id:
            return []
        c = self.controller
        if msg.arbitration_id != codec.SYNC_ID and msg.arbitration_id >> codec.NODE_SHIFT != c.node:
            return []
        c._t = now  # the physics owns the axes: the firmware logic only, no dt
        return self._out(c.handle(Frame(msg.arbitration_id, bytes(msg.data)), now))

    def step(self, now: float) -> list[can.Message]:
        self.controller._t = now  # the physics owns the axes: the firmware logic only
        return self._out(self.controller.step(now))

    def next_due(self) -> float:
        return self.controller.next_due()

    def feedback_rate(self) -> float:
        c = self.controller
        return float(c.rate_hz) if c.rate_hz > 0 and not c.sync_mode else 0.0

    def drive(
        self, axis: Axis, position: float, dt: float, position_tau: float
    ) -> tuple[str, float]:
        return axis_drive(self.controller.axes[axis], axis, position, dt, position_tau)

    def sense(
        self, axis: Axis, position: float, velocity: float, torque: float | None
    ) -> None:
        ax = self.controller.axes[axis]
        ax.position = position
        ax.velocity = velocity
        ax.torque = ax.friction * velocity if torque is None else torque

    def inject_fault(self, axis: Axis, error: ErrorFlag) -> list[can.Message]:
        return self._out(self.controller.inject_error(axis, error))

    def params(self) -> dict[str, Any]:
        return {"kind": "swpc", "node": self.controller.node}


def build(
    config: DrivesConfig,
    module: int,
    *,
    feedback_rate_hz: int,
    watchdog_ms: int,
    homing_duration: float,
    sensor_position: float,
) -> VirtualDrive:
    assert isinstance(config, SwpcDrives)
    return SwpcVirtualDrive(
        VirtualController(
            node=config.node_map()[module],
            rate_hz=feedback_rate_hz,
            watchdog_ms=watchdog_ms,
            homing_duration=homing_duration,
            sensor_position=sensor_position,
        )
    )
