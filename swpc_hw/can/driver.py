"""python-can driver of the four caster-module controllers.

Lifecycle (as ros2_control's hardware components)::

    UNCONFIGURED --configure()--> INACTIVE --activate()--> ACTIVE
         ^                          ^  |                     |
         |                          |  +----deactivate()-----+  (also on any fault)
         +------- shutdown() (from any state, idempotent) -> FINALIZED

* INACTIVE: the bus is open; heartbeats and feedback are read; no frame is sent.
* ACTIVE: commands flow; the driver re-sends each enabled axis's last control frame
  whenever a node got no command for ``refresh_period_s`` (it feeds the controllers'
  watchdog itself).

Every fault path (bus-off, lost heartbeat of ``heartbeat_loss_periods`` periods, a
controller's fault report, an exception in a listener) calls :meth:`CanDriver.stop_all`
— FREE then DISABLED to every axis of every node — and drops back to INACTIVE.

Reception runs on python-can's :class:`can.Notifier`.  Error frames, bus-off, unknown
ids, bad DLC, undecodable frames and listener exceptions are counted in
:meth:`CanDriver.stats` and reported as :class:`DriverEvent` (callback and queue).

Positions at this boundary are SI: ``theta_hat`` (steering, rad, 0 at the homing
sensor) and ``psi`` (cumulative wheel angle, rad); the frames carry both wrapped (steering
+-4 turns, wheel +-2**18 turns) and the driver unwraps both on the host.
"""

from __future__ import annotations

import contextlib
import enum
import logging
import math
import queue
import socket
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace

import can
import numpy as np
from numpy.typing import NDArray

from firmware_protocol import codec
from firmware_protocol.codec import Axis, AxisState, ControlMode, HomingState
from swpc_hw.can.config import CanConfig
from swpc_hw.can.errors import (
    CanBusError,
    CanCommandError,
    CanError,
    LifecycleError,
    NodeError,
    NodeTimeoutError,
)
from swpc_hw.can.history import COLUMNS as HISTORY_COLUMNS
from swpc_hw.can.history import FeedbackRing

log = logging.getLogger(__name__)

CAN_ERR_BUSOFF = 0x00000040
"""Linux SocketCAN error class bit (in the error frame's id) for bus-off."""
_AXIS_NAMES = {Axis.STEER: "steer", Axis.WHEEL: "wheel"}


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


class Severity(enum.Enum):
    INFO = "info"
    WARNING = "warning"
    FAULT = "fault"


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

    ``t``: host ``time.monotonic()`` when the position frame was received; ``t_bus``: the
    frame's bus timestamp (python-can, epoch s); ``counter``: the frame's own counter
    (mod 256); ``seq``: the counter unwrapped on the host (monotonic sample index).
    Velocities and torques are NaN if their frame was lost.
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


@dataclass
class DriverStats:
    rx_frames: int = 0
    tx_frames: int = 0
    error_frames: int = 0
    bus_off: int = 0
    unknown_ids: int = 0
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
    rx_buffer_bytes: int | None = None
    """The kernel receive buffer in effect on a socket bus (SocketCAN), bytes; None on
    others."""


@dataclass
class _Node:
    module: int
    node: int
    history: FeedbackRing
    alive: bool = False
    lost_reported: bool = False
    states: tuple[AxisState, AxisState] = (AxisState.DISABLED, AxisState.DISABLED)
    modes: tuple[ControlMode, ControlMode] = (ControlMode.FREE, ControlMode.FREE)
    errors: tuple[int, int] = (0, 0)
    homed: bool = False
    homing: HomingState = HomingState.NOT_HOMED
    homing_seen: bool = False  # a heartbeat showed the steering HOMING since start_homing()
    t_heartbeat: float | None = None
    heartbeats: int = 0
    feedback_frames: int = 0
    last: FeedbackSample | None = None
    seq: int = -1
    last_tx: float = 0.0
    commanded: dict[Axis, tuple[ControlMode, float]] = field(default_factory=dict)


def _where(module: int | None, node: int | None, axis: Axis | None = None) -> str:
    parts = []
    if module is not None:
        parts.append(f"module {module}")
    if node is not None:
        parts.append(f"(node {node})" if module is not None else f"node {node}")
    if axis is not None:
        parts.append(f"axis {int(axis)} ({_AXIS_NAMES[axis]})")
    return " ".join(parts)


class _Receiver(can.Listener):
    def __init__(self, driver: CanDriver) -> None:
        self._driver = driver

    def on_message_received(self, msg: can.Message) -> None:
        self._driver._on_frame(msg)

    def on_error(self, exc: Exception) -> None:
        self._driver._on_listener_error(exc)


class _LockedLog(can.Listener):
    """python-can's Logger shared by the receive thread and the senders."""

    def __init__(self, path: str, lock: threading.Lock) -> None:
        self.logger = can.Logger(path)
        self.lock = lock
        self.closed = False

    def on_message_received(self, msg: can.Message) -> None:
        with self.lock:
            if not self.closed:  # a frame racing with stop() is dropped, not an error
                self.logger.on_message_received(msg)

    def stop(self) -> None:
        with self.lock:
            if not self.closed:
                self.closed = True
                self.logger.stop()


SO_RCVBUFFORCE = getattr(socket, "SO_RCVBUFFORCE", 33)  # Linux; not in Python's socket


def grow_receive_buffer(sock: socket.socket, size: int) -> int:
    """Ask the kernel for a ``size``-byte receive buffer on ``sock``; returns the one in effect.

    SO_RCVBUFFORCE (CAP_NET_ADMIN) may exceed net.core.rmem_max; without the capability
    SO_RCVBUF is capped at rmem_max.  Linux doubles the value asked (bookkeeping overhead),
    and a CAN frame's buffer costs several hundred bytes of it.
    """
    try:
        sock.setsockopt(socket.SOL_SOCKET, SO_RCVBUFFORCE, size)
    except OSError:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, size)
    got = int(sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF))
    if got < size:
        log.warning(
            "CAN receive buffer %d bytes, asked %d: raise net.core.rmem_max "
            "(deploy/sysctl/60-swpc-can.conf) or grant CAP_NET_ADMIN",
            got,
            size,
        )
    return got


class CanDriver:
    """Driver of the module controllers on one CAN bus (see the module docstring)."""

    def __init__(
        self,
        config: CanConfig | None = None,
        *,
        on_event: Callable[[DriverEvent], None] | None = None,
    ) -> None:
        self.config = config or CanConfig()
        self._state = Lifecycle.UNCONFIGURED
        self._lock = threading.RLock()
        self._changed = threading.Condition(self._lock)
        self._tx_lock = threading.Lock()
        self._log_lock = threading.Lock()
        self._nodes: dict[int, _Node] = {}
        self._by_node: dict[int, _Node] = {}
        for module, node in self.config.modules.items():
            nd = _Node(module, node, FeedbackRing(self.config.history_len))
            self._nodes[module] = nd
            self._by_node[node] = nd
        self._stats = DriverStats()
        self._events: queue.Queue[DriverEvent] = queue.Queue(maxsize=10_000)
        self._event_callbacks: list[Callable[[DriverEvent], None]] = []
        if on_event is not None:
            self._event_callbacks.append(on_event)
        self._feedback_callbacks: list[Callable[[int, FeedbackSample], None]] = []
        self._latency: deque[float] = deque(maxlen=100_000)
        self._bus: can.BusABC | None = None
        self._notifier: can.Notifier | None = None
        self._logger: _LockedLog | None = None
        self._recorder: _LockedLog | None = None
        self._supervisor: threading.Thread | None = None
        self._stop_supervisor = threading.Event()
        self._wake = threading.Event()
        self._configured_at = 0.0
        self._fault_cause: str | None = None
        self._sync_counter = 0
        self.last_exception: BaseException | None = None
        self._log_counts: dict[EventKind, int] = {}

    # ================================================================ lifecycle
    @property
    def state(self) -> Lifecycle:
        return self._state

    @property
    def fault_cause(self) -> str | None:
        """Why the driver last dropped from ACTIVE on a fault (None after activate() or an
        orderly deactivate())."""
        return self._fault_cause

    def __enter__(self) -> CanDriver:
        if self._state == Lifecycle.UNCONFIGURED:
            self.configure()
        return self

    def __exit__(self, *exc: object) -> None:
        self.shutdown()

    def configure(self) -> None:
        """UNCONFIGURED -> INACTIVE: open the bus, start reception and supervision."""
        with self._lock:
            if self._state != Lifecycle.UNCONFIGURED:
                raise LifecycleError(
                    f"configure() needs state unconfigured, not {self._state.value}"
                )
            cfg = self.config
            try:
                self._bus = can.Bus(
                    interface=cfg.interface,
                    channel=cfg.channel,
                    bitrate=cfg.bitrate,
                    **dict(cfg.bus_kwargs),
                )
            except (can.CanError, OSError, ValueError, ImportError) as exc:
                raise CanBusError(
                    f"cannot open CAN bus interface={cfg.interface!r} "
                    f"channel={cfg.channel!r}: {exc}"
                ) from exc
            sock = getattr(self._bus, "socket", None)
            if cfg.rx_buffer_bytes and isinstance(sock, socket.socket):
                self._stats.rx_buffer_bytes = grow_receive_buffer(sock, cfg.rx_buffer_bytes)
            listeners: list[can.Listener] = [_Receiver(self)]
            if cfg.log_path:
                self._logger = _LockedLog(cfg.log_path, self._log_lock)
                listeners.append(self._logger)
            self._configured_at = time.monotonic()
            self._notifier = can.Notifier(self._bus, listeners, timeout=0.1)
            self._stop_supervisor.clear()
            self._supervisor = threading.Thread(
                target=self._supervise, name="swpc-can-supervisor", daemon=True
            )
            self._state = Lifecycle.INACTIVE
            self._supervisor.start()

    def activate(self) -> None:
        """INACTIVE -> ACTIVE: wait for every node's heartbeat, send watchdog/feedback/limits.

        Raises :class:`NodeTimeoutError` naming the silent nodes if a heartbeat is missing
        after ``activate_timeout_s``.
        """
        cfg = self.config
        deadline = time.monotonic() + cfg.activate_timeout_s
        with self._changed:
            if self._state != Lifecycle.INACTIVE:
                raise LifecycleError(f"activate() needs state inactive, not {self._state.value}")
            while True:
                silent = [nd for nd in self._nodes.values() if not nd.alive]
                if not silent:
                    break
                left = deadline - time.monotonic()
                if left <= 0:
                    names = ", ".join(_where(nd.module, nd.node) for nd in silent)
                    raise NodeTimeoutError(
                        f"activate(): no heartbeat from {names} within {cfg.activate_timeout_s} s",
                        node=silent[0].node,
                    )
                self._changed.wait(left)
            self._state = Lifecycle.ACTIVE
            self._fault_cause = None
        frames: list[codec.Frame] = []
        for nd in self._nodes.values():
            frames.append(codec.make_set_watchdog(nd.node, cfg.watchdog_timeout_ms))
            frames.append(codec.make_set_feedback(nd.node, cfg.feedback_rate_hz, cfg.sync_mode))
            if cfg.max_torque is not None or cfg.max_velocity is not None:
                for axis in Axis:
                    frames.append(
                        codec.make_set_limits(
                            nd.node,
                            axis,
                            (cfg.max_torque or (65.535, 65.535))[axis],
                            (cfg.max_velocity or (655.35, 655.35))[axis],
                        )
                    )
        self._send_frames(frames)

    def deactivate(self) -> None:
        """ACTIVE -> INACTIVE: free and disable every axis, stop sending."""
        with self._lock:
            if self._state != Lifecycle.ACTIVE:
                raise LifecycleError(f"deactivate() needs state active, not {self._state.value}")
        self.stop_all()
        with self._lock:
            if self._state == Lifecycle.ACTIVE:
                self._state = Lifecycle.INACTIVE
                self._fault_cause = None

    def shutdown(self) -> None:
        """Any state -> FINALIZED (idempotent): stop_all if active, close everything."""
        with self._lock:
            if self._state == Lifecycle.FINALIZED:
                return
            was_active = self._state == Lifecycle.ACTIVE
        if was_active:
            with contextlib.suppress(CanError):
                self.stop_all()
        self._stop_supervisor.set()
        self._wake.set()
        if self._supervisor is not None and self._supervisor is not threading.current_thread():
            self._supervisor.join(timeout=2.0)
        if self._notifier is not None:
            self._notifier.stop(timeout=1.0)
        self.stop_recording()
        if self._logger is not None:
            self._logger.stop()
        if self._bus is not None:
            self._bus.shutdown()
        with self._lock:
            self._state = Lifecycle.FINALIZED
            self._changed.notify_all()

    # ================================================================ commands
    def _node(self, module: int) -> _Node:
        try:
            return self._nodes[module]
        except KeyError:
            raise CanCommandError(
                f"module {module} is not configured (modules: {sorted(self._nodes)})"
            ) from None

    def _require_active(self, what: str, nd: _Node | None = None, axis: Axis | None = None) -> None:
        if self._state != Lifecycle.ACTIVE:
            where = _where(nd.module, nd.node, axis) + ": " if nd else ""
            cause = self._fault_cause
            why = f" (stopped by a fault: {cause})" if cause is not None else ""
            raise LifecycleError(f"{where}cannot {what} in state {self._state.value}{why}")

    def _command(
        self, what: str, module: int, axis: Axis | None, build: Callable[[int], codec.Frame]
    ) -> _Node:
        nd = self._node(module)
        self._require_active(what, nd, axis)
        try:
            frame = build(nd.node)
        except codec.ProtocolError as exc:
            raise CanCommandError(f"{_where(nd.module, nd.node, axis)}: {what}: {exc}") from exc
        self._send_frames([frame])
        return nd

    def enable(self, module: int, axis: Axis) -> None:
        """Enable (closed loop, mode FREE) one axis."""
        axis = Axis(axis)
        nd = self._command(
            "enable", module, axis, lambda n: codec.make_set_axis_state(n, axis, True)
        )
        with self._lock:
            nd.commanded[axis] = (ControlMode.FREE, 0.0)

    def disable(self, module: int, axis: Axis) -> None:
        axis = Axis(axis)
        nd = self._command(
            "disable", module, axis, lambda n: codec.make_set_axis_state(n, axis, False)
        )
        with self._lock:
            nd.commanded.pop(axis, None)

    def set_control(
        self, module: int, axis: Axis, mode: ControlMode, setpoint: float = 0.0
    ) -> None:
        """Control mode and setpoint (rad, rad/s or N.m by mode) of one axis."""
        axis, mode = Axis(axis), ControlMode(mode)
        nd = self._command(
            f"set {mode.name} {setpoint:g}",
            module,
            axis,
            lambda n: codec.make_set_control(n, axis, mode, setpoint),
        )
        with self._lock:
            nd.commanded[axis] = (mode, setpoint)

    def set_position(self, module: int, axis: Axis, position: float) -> None:
        self.set_control(module, axis, ControlMode.POSITION, position)

    def set_velocity(self, module: int, axis: Axis, velocity: float) -> None:
        self.set_control(module, axis, ControlMode.VELOCITY, velocity)

    def set_torque(self, module: int, axis: Axis, torque: float) -> None:
        self.set_control(module, axis, ControlMode.TORQUE, torque)

    def hold(self, module: int, axis: Axis) -> None:
        """Hold the current position (steering lock / wheel brake)."""
        self.set_control(module, axis, ControlMode.HOLD)

    def free(self, module: int, axis: Axis) -> None:
        """Zero torque (the axis turns freely)."""
        self.set_control(module, axis, ControlMode.FREE)

    def clear_errors(self, module: int, axes: tuple[Axis, ...] = (Axis.STEER, Axis.WHEEL)) -> None:
        mask = sum(1 << int(a) for a in axes)
        self._command("clear errors", module, None, lambda n: codec.make_clear_errors(n, mask))

    def set_limits(self, module: int, axis: Axis, max_torque: float, max_velocity: float) -> None:
        axis = Axis(axis)
        self._command(
            "set limits",
            module,
            axis,
            lambda n: codec.make_set_limits(n, axis, max_torque, max_velocity),
        )

    def start_homing(self, module: int) -> None:
        """Start the steering axis's homing run (the axis must be enabled)."""
        nd = self._node(module)
        with self._lock:  # before the frame: the controller's answers may come back at once
            before = nd.homing, nd.homing_seen
            nd.homing, nd.homing_seen = HomingState.IN_PROGRESS, False
        try:
            self._command(
                "start homing",
                module,
                Axis.STEER,
                lambda n: codec.make_start_homing(n, Axis.STEER),
            )
        except BaseException:
            with self._lock:
                nd.homing, nd.homing_seen = before
            raise
        with self._lock:
            nd.commanded.pop(Axis.STEER, None)

    def start_recording(self, path: str) -> None:
        """Record every frame in and out to ``path`` until :meth:`stop_recording`.

        python-can's Logger picks the format from the suffix (``.log``: candump, which
        ``cantools decode`` reads with our DBC).  Independent of ``CanConfig.log_path``.
        """
        with self._lock:
            if self._notifier is None:
                raise LifecycleError("start_recording() needs an open bus (configure() first)")
            self.stop_recording()
            rec = _LockedLog(path, threading.Lock())
            self._recorder = rec
            self._notifier.add_listener(rec)

    def stop_recording(self) -> None:
        """Stop the recording started by :meth:`start_recording` (idempotent)."""
        with self._lock:
            rec, self._recorder = self._recorder, None
            if rec is None:
                return
            if self._notifier is not None:
                with contextlib.suppress(ValueError):
                    self._notifier.remove_listener(rec)
        rec.stop()

    def send_sync(self) -> int:
        """Broadcast a SYNC frame; returns its counter (the next samples carry it)."""
        self._require_active("send SYNC")
        with self._lock:
            counter = self._sync_counter
            self._sync_counter = (counter + 1) & 0xFF
        self._send_frames([codec.make_sync(counter)])
        return counter

    def stop_all(self) -> None:
        """FREE then DISABLED to every axis of every node; clears the refreshed setpoints.

        Sends regardless of the lifecycle state as long as the bus is open; this is what
        every fault path calls.  Send failures are counted and re-raised at the end.
        """
        with self._lock:
            self._stats.stop_all_calls += 1
            nodes = list(self._nodes.values())
            for nd in nodes:
                nd.commanded.clear()
            bus_open = self._bus is not None and self._state in (
                Lifecycle.INACTIVE,
                Lifecycle.ACTIVE,
            )
        if not bus_open:
            return
        frames = [
            codec.make_set_control(nd.node, a, ControlMode.FREE) for nd in nodes for a in Axis
        ]
        frames += [codec.make_set_axis_state(nd.node, a, False) for nd in nodes for a in Axis]
        self._send_frames(frames, best_effort=True)

    # ================================================================ observation
    def module_state(self, module: int) -> ModuleState:
        nd = self._node(module)
        with self._lock:
            return ModuleState(
                module=nd.module,
                node=nd.node,
                alive=nd.alive,
                states=nd.states,
                modes=nd.modes,
                errors=nd.errors,
                homed=nd.homed,
                homing=nd.homing,
                feedback=nd.last,
                t_heartbeat=nd.t_heartbeat,
                heartbeats=nd.heartbeats,
                feedback_frames=nd.feedback_frames,
            )

    def modules(self) -> list[int]:
        return list(self._nodes)

    def history(self, module: int) -> list[FeedbackSample]:
        """The kept feedback samples of a module, oldest first (objects made on demand;
        :meth:`history_arrays` for computation)."""
        nd = self._node(module)
        with self._lock:
            a = nd.history.array()
        samples = []
        for r in a.tolist():
            f = dict(zip(HISTORY_COLUMNS, r, strict=True))
            f["counter"], f["seq"] = int(f["counter"]), int(f["seq"])
            samples.append(FeedbackSample(**f))
        return samples

    def history_arrays(self, module: int) -> dict[str, NDArray[np.float64]]:
        """Feedback history as columns (the fields of :class:`FeedbackSample`)."""
        nd = self._node(module)
        with self._lock:
            return nd.history.columns()

    def clear_history(self) -> None:
        with self._lock:
            for nd in self._nodes.values():
                nd.history.clear()

    def stats(self) -> DriverStats:
        with self._lock:
            return replace(self._stats)

    def latencies(self) -> NDArray[np.float64]:
        """Receive latencies (host wall time at processing minus the frame timestamp), s."""
        with self._lock:
            return np.array(self._latency, dtype=float)

    def clear_latencies(self) -> None:
        with self._lock:
            self._latency.clear()

    def events(self) -> list[DriverEvent]:
        """Drain the event queue."""
        out: list[DriverEvent] = []
        while True:
            try:
                out.append(self._events.get_nowait())
            except queue.Empty:
                return out

    def add_event_callback(self, fn: Callable[[DriverEvent], None]) -> None:
        """``fn(event)`` on every event, on the thread that raised it, in the order added."""
        with self._lock:
            self._event_callbacks = [*self._event_callbacks, fn]

    def remove_event_callback(self, fn: Callable[[DriverEvent], None]) -> None:
        """Undo :meth:`add_event_callback` (no-op for a callback not registered)."""
        with self._lock:
            self._event_callbacks = [f for f in self._event_callbacks if f != fn]

    def add_feedback_callback(self, fn: Callable[[int, FeedbackSample], None]) -> None:
        """``fn(module, sample)`` on every position frame, on the receive thread.

        An exception in ``fn`` is a listener error: counted, reported, and a fault.
        """
        self._feedback_callbacks.append(fn)

    def threads(self) -> list[threading.Thread]:
        """The driver's threads (receive and supervisor), e.g. to measure their CPU time."""
        out = [
            t
            for t in threading.enumerate()
            if self._bus is not None
            and t.name.startswith("Notifier for bus")
            and str(self._bus.channel_info) in t.name
        ]
        if self._supervisor is not None:
            out.append(self._supervisor)
        return out

    def wait_for(
        self,
        module: int,
        predicate: Callable[[ModuleState], bool],
        timeout: float,
        what: str = "condition",
    ) -> ModuleState:
        """Block until ``predicate(module_state)`` holds; :class:`NodeTimeoutError` otherwise."""
        nd = self._node(module)
        deadline = time.monotonic() + timeout
        with self._changed:
            while True:
                st = self.module_state(module)
                if predicate(st):
                    return st
                left = deadline - time.monotonic()
                if left <= 0:
                    raise NodeTimeoutError(
                        f"{_where(nd.module, nd.node)}: {what} not reached within {timeout} s "
                        f"(states {[s.name for s in st.states]}, errors "
                        f"{[codec.error_names(e) for e in st.errors]}, homed {st.homed}, "
                        f"homing {st.homing.name})",
                        node=nd.node,
                    )
                self._changed.wait(left)

    def wait_axis_state(
        self, module: int, axis: Axis, state: AxisState, timeout: float = 1.0
    ) -> None:
        axis = Axis(axis)
        self.wait_for(
            module,
            lambda s: s.states[axis] == state,
            timeout,
            f"axis {int(axis)} ({_AXIS_NAMES[axis]}) state {state.name}",
        )

    # ================================================================ transmit
    def _send_frames(self, frames: list[codec.Frame], best_effort: bool = False) -> None:
        bus = self._bus
        if bus is None:
            raise LifecycleError("the bus is not open (call configure())")
        failure: Exception | None = None
        now = time.monotonic()
        with self._tx_lock:
            for f in frames:
                msg = can.Message(
                    arbitration_id=f.arbitration_id,
                    data=f.data,
                    is_extended_id=False,
                    is_rx=False,
                    channel=self.config.channel,
                    timestamp=time.time(),
                )
                try:
                    bus.send(msg)
                except (can.CanError, OSError) as exc:
                    node, _ = codec.split_id(f.arbitration_id)
                    with self._lock:
                        self._stats.send_errors += 1
                    failure = failure or CanBusError(
                        f"node {node}: send 0x{f.arbitration_id:03x} failed: {exc}"
                    )
                    if not best_effort:
                        break
                    continue
                if self._logger is not None:
                    self._logger.on_message_received(msg)
                rec = self._recorder
                if rec is not None:
                    rec.on_message_received(msg)
                with self._lock:
                    self._stats.tx_frames += 1
                    nd = self._by_node.get(f.arbitration_id >> codec.NODE_SHIFT)
                    if nd is not None:
                        nd.last_tx = now
        if failure is not None:
            self._emit(EventKind.SEND_ERROR, Severity.WARNING, str(failure))
            raise failure

    # ================================================================ receive
    def _on_frame(self, msg: can.Message) -> None:
        t = time.monotonic()
        callbacks: list[tuple[int, FeedbackSample]] = []
        events: list[tuple[EventKind, Severity, str, _Node | None, Axis | None]] = []
        fault = False
        with self._changed:
            st = self._stats
            st.rx_frames += 1
            if msg.timestamp:
                self._latency.append(time.time() - msg.timestamp)
            if msg.is_error_frame:
                st.error_frames += 1
                if msg.arbitration_id & CAN_ERR_BUSOFF:
                    st.bus_off += 1
                    events.append((EventKind.BUS_OFF, Severity.FAULT, "CAN bus-off", None, None))
                    fault = True
                else:
                    events.append(
                        (
                            EventKind.ERROR_FRAME,
                            Severity.WARNING,
                            f"error frame class 0x{msg.arbitration_id:08x} "
                            f"data {bytes(msg.data).hex()}",
                            None,
                            None,
                        )
                    )
            else:
                fault = self._on_data_frame(msg, t, callbacks, events)
            # events queued before the state drops: whoever sees INACTIVE finds its cause
            recorded = [self._record(*e) for e in events]
            was_active = fault and self._begin_fault(
                next((ev.message for ev in recorded if ev.severity is Severity.FAULT), "fault")
            )
            self._changed.notify_all()
        if fault:
            self._fault_stop(was_active, recorded)
        else:
            for ev in recorded:
                self._notify(ev)
        for module, sample in callbacks:
            for fn in self._feedback_callbacks:
                fn(module, sample)  # exceptions go to Notifier -> on_error

    def _on_data_frame(
        self,
        msg: can.Message,
        t: float,
        callbacks: list[tuple[int, FeedbackSample]],
        events: list[tuple[EventKind, Severity, str, _Node | None, Axis | None]],
    ) -> bool:
        st = self._stats
        node, cmd = codec.split_id(msg.arbitration_id)
        nd = self._by_node.get(node)
        if (
            msg.is_extended_id
            or msg.is_remote_frame
            or nd is None
            or cmd not in codec.CONTROLLER_FRAMES
        ):
            st.unknown_ids += 1
            events.append(
                (
                    EventKind.UNKNOWN_ID,
                    Severity.WARNING,
                    f"unknown frame id 0x{msg.arbitration_id:03x} (node {node}, command {cmd}, "
                    f"DLC {msg.dlc})",
                    None,
                    None,
                )
            )
            return False
        try:
            dec = codec.parse(msg.arbitration_id, bytes(msg.data))
        except codec.ProtocolError as exc:
            if isinstance(exc, codec.FrameLengthError):
                st.bad_dlc += 1
                kind = EventKind.BAD_DLC
            else:
                st.decode_errors += 1
                kind = EventKind.DECODE_ERROR
            where = _where(nd.module, nd.node)
            events.append((kind, Severity.WARNING, f"{where}: {exc}", nd, None))
            return False
        if isinstance(dec, codec.FeedbackPosition):
            nd.feedback_frames += 1
            if nd.last is None:
                seq, theta, psi = dec.counter, dec.steer, dec.wheel
            else:
                gap = (dec.counter - nd.last.counter - 1) & 0xFF
                if gap:
                    st.feedback_gaps += gap
                    events.append(
                        (
                            EventKind.FEEDBACK_GAP,
                            Severity.WARNING,
                            f"{_where(nd.module, nd.node)}: {gap} feedback sample(s) missing "
                            "before "
                            f"counter {dec.counter}",
                            nd,
                            None,
                        )
                    )
                seq = nd.seq + gap + 1
                theta = codec.unwrap(nd.last.theta_hat, dec.steer, codec.STEER_SPAN)
                psi = codec.unwrap(nd.last.psi, dec.wheel, codec.WHEEL_SPAN)
            if nd.last is not None and math.isnan(nd.last.steer_velocity):
                st.unpaired_feedback += 1
            sample = FeedbackSample(t, float(msg.timestamp), dec.counter, seq, theta, psi)
            nd.seq = seq
            nd.last = sample
            nd.history.append((t, sample.t_bus, dec.counter, seq, theta, psi))
            callbacks.append((nd.module, sample))
        elif isinstance(dec, codec.FeedbackVelocityTorque):
            nd.feedback_frames += 1
            last = nd.last
            if last is not None and last.counter == dec.counter and math.isnan(last.steer_velocity):
                full = replace(
                    last,
                    steer_velocity=dec.steer_velocity,
                    wheel_velocity=dec.wheel_velocity,
                    steer_torque=dec.steer_torque,
                    wheel_torque=dec.wheel_torque,
                )
                nd.last = full
                if len(nd.history):  # the newest row is ``last`` unless cleared since
                    nd.history.set_last_velocity_torque(
                        (dec.steer_velocity, dec.wheel_velocity, dec.steer_torque,
                         dec.wheel_torque)
                    )
            else:
                st.unpaired_feedback += 1
        elif isinstance(dec, codec.Heartbeat):
            return self._on_heartbeat(nd, dec, t, events)
        elif isinstance(dec, codec.FaultReport):
            st.node_faults += 1
            errs = list(nd.errors)
            errs[dec.axis] = dec.active_errors
            nd.errors = (errs[0], errs[1])
            states = list(nd.states)
            states[dec.axis] = dec.state
            nd.states = (states[0], states[1])
            events.append(
                (
                    EventKind.NODE_FAULT,
                    Severity.FAULT,
                    f"{_where(nd.module, nd.node, dec.axis)}: fault "
                    f"{codec.error_names(dec.new_errors)} "
                    f"(active {codec.error_names(dec.active_errors)})",
                    nd,
                    dec.axis,
                )
            )
            return True
        elif isinstance(dec, codec.HomingStatus):
            nd.homing = dec.status
            if dec.status == HomingState.DONE:
                nd.homed = True
            events.append(
                (
                    EventKind.HOMING,
                    Severity.WARNING if dec.status == HomingState.FAILED else Severity.INFO,
                    f"{_where(nd.module, nd.node, dec.axis)}: homing {dec.status.name}"
                    + (
                        f", sensor at {dec.sensor_position:.4f} rad"
                        if dec.status == HomingState.DONE
                        else ""
                    ),
                    nd,
                    dec.axis,
                )
            )
        return False

    def _on_heartbeat(
        self,
        nd: _Node,
        hb: codec.Heartbeat,
        t: float,
        events: list[tuple[EventKind, Severity, str, _Node | None, Axis | None]],
    ) -> bool:
        fault = False
        for axis in Axis:
            if hb.states[axis] == AxisState.FAULT and nd.states[axis] != AxisState.FAULT:
                events.append(
                    (
                        EventKind.NODE_FAULT,
                        Severity.FAULT,
                        f"{_where(nd.module, nd.node, axis)}: heartbeat reports FAULT "
                        f"({codec.error_names(hb.errors[axis])})",
                        nd,
                        axis,
                    )
                )
                fault = True
        if hb.states[Axis.STEER] == AxisState.HOMING:
            nd.homing_seen = True
        elif nd.homing == HomingState.IN_PROGRESS and nd.homing_seen and hb.homed:
            # homing ran and ended homed, but its HomingStatus frame (sent once) was lost,
            # e.g. by a receive queue that overflowed: the heartbeat repeats the outcome
            nd.homing = HomingState.DONE
            events.append(
                (
                    EventKind.HOMING,
                    Severity.WARNING,
                    f"{_where(nd.module, nd.node, Axis.STEER)}: homing DONE by the heartbeat "
                    "(its HomingStatus frame was not received)",
                    nd,
                    Axis.STEER,
                )
            )
        nd.states, nd.modes, nd.errors, nd.homed = hb.states, hb.modes, hb.errors, hb.homed
        nd.t_heartbeat = t
        nd.heartbeats += 1
        if not nd.alive:
            nd.alive = True
            if nd.lost_reported:
                nd.lost_reported = False
                events.append(
                    (
                        EventKind.HEARTBEAT_RESTORED,
                        Severity.INFO,
                        f"{_where(nd.module, nd.node)}: heartbeat restored",
                        nd,
                        None,
                    )
                )
        return fault

    def _on_listener_error(self, exc: Exception) -> None:
        with self._lock:
            self._stats.listener_errors += 1
            self.last_exception = exc
            ev = self._record(
                EventKind.LISTENER_ERROR,
                Severity.FAULT,
                f"exception in the receive thread: {type(exc).__name__}: {exc}",
            )
            was_active = self._begin_fault(ev.message)
        self._fault_stop(was_active, [ev])

    # ================================================================ supervision
    def _supervise(self) -> None:
        cfg = self.config
        loss_after = cfg.heartbeat_loss_periods * cfg.heartbeat_period_s
        while not self._stop_supervisor.is_set():
            now = time.monotonic()
            lost: list[_Node] = []
            refresh: list[codec.Frame] = []
            deadlines = [now + 0.1]
            was_active = False
            with self._lock:
                for nd in self._nodes.values():
                    ref = nd.t_heartbeat if nd.t_heartbeat is not None else self._configured_at
                    due = ref + loss_after
                    if now >= due:
                        if nd.alive or not nd.lost_reported:
                            nd.alive = False
                            nd.lost_reported = True
                            self._stats.heartbeat_losses += 1
                            lost.append(nd)
                    else:
                        deadlines.append(due)
                    if self._state == Lifecycle.ACTIVE and nd.commanded:
                        if now - nd.last_tx >= cfg.refresh_period_s:
                            refresh += [
                                codec.make_set_control(nd.node, axis, mode, sp)
                                for axis, (mode, sp) in nd.commanded.items()
                            ]
                            deadlines.append(now + cfg.refresh_period_s)
                        else:
                            deadlines.append(nd.last_tx + cfg.refresh_period_s)
                recorded = [
                    self._record(
                        EventKind.HEARTBEAT_LOST,
                        Severity.FAULT,
                        f"{_where(nd.module, nd.node)}: no heartbeat for {loss_after:.3f} s",
                        nd,
                    )
                    for nd in lost
                ]
                if lost:  # after the events are queued: whoever sees INACTIVE finds why
                    was_active = self._begin_fault(recorded[0].message)
                    refresh = []
            if lost:
                self._fault_stop(was_active, recorded)
            else:
                for ev in recorded:
                    self._notify(ev)
            if refresh and self._state == Lifecycle.ACTIVE:
                with contextlib.suppress(CanError):
                    self._send_frames(refresh, best_effort=True)
            wait = min(deadlines) - time.monotonic()
            if wait > 0:
                self._wake.wait(wait)
                self._wake.clear()

    def _begin_fault(self, cause: str) -> bool:
        """Drop from ACTIVE to INACTIVE (no more commands); True if the driver was active.

        ``cause`` (the fault's message) is kept for :attr:`fault_cause`, and commands refused
        afterwards name it: a caller that meets the refusal before the fault's event
        callback has run still learns why.
        """
        with self._lock:
            active = self._state == Lifecycle.ACTIVE
            if active:
                self._state = Lifecycle.INACTIVE
                self._fault_cause = cause
            return active

    def _fault_stop(self, was_active: bool, events: list[DriverEvent]) -> None:
        """Every fault path, after :meth:`_begin_fault`: stop_all() if the driver was active,
        *then* the event callbacks with the fault's ``events``, then STOPPED.  The motors
        stop first: a slow event callback (the callbacks ran first once) held the stop
        frames back for as long as it took, with the wheels still under torque."""
        if was_active:
            try:
                self.stop_all()
            except CanError as exc:
                log.error("stop_all() after a fault failed: %s", exc)
        for ev in events:
            self._notify(ev)
        if was_active:
            self._emit(
                EventKind.STOPPED,
                Severity.INFO,
                "fault: all axes freed and disabled; driver inactive",
            )
        with self._changed:
            self._changed.notify_all()

    def _emit(
        self,
        kind: EventKind,
        severity: Severity,
        message: str,
        nd: _Node | None = None,
        axis: Axis | None = None,
    ) -> None:
        self._notify(self._record(kind, severity, message, nd, axis))

    def _record(
        self,
        kind: EventKind,
        severity: Severity,
        message: str,
        nd: _Node | None = None,
        axis: Axis | None = None,
    ) -> DriverEvent:
        """Create, log and queue an event (cheap; may be called under the lock)."""
        ev = DriverEvent(
            time.monotonic(),
            kind,
            severity,
            message,
            nd.module if nd else None,
            nd.node if nd else None,
            axis,
        )
        if severity != Severity.INFO:
            self._log_counts[kind] = n = self._log_counts.get(kind, 0) + 1
            if n <= 5 or severity == Severity.FAULT:
                log.warning("%s%s", message, " (further ones counted only)" if n == 5 else "")
        with contextlib.suppress(queue.Full):
            self._events.put_nowait(ev)
        return ev

    def _notify(self, ev: DriverEvent) -> None:
        """Call the event callbacks (outside the driver's lock)."""
        for fn in self._event_callbacks:
            try:
                fn(ev)
            except Exception as exc:  # a broken callback must not stop the fault path
                with self._lock:
                    self._stats.listener_errors += 1
                    self.last_exception = exc
                log.error("event callback %r raised %s", fn, exc)

    def iter_modules(self) -> Iterator[ModuleState]:
        for module in self._nodes:
            yield self.module_state(module)


def raise_if_faulted(state: ModuleState) -> None:
    """Raise :class:`NodeError` naming node and axis if ``state`` shows a fault."""
    for axis in Axis:
        if state.states[axis] == AxisState.FAULT or state.errors[axis]:
            raise NodeError(
                f"{_where(state.module, state.node, axis)}: "
                f"{state.states[axis].name} {codec.error_names(state.errors[axis])}",
                node=state.node,
                axis=int(axis),
            )
