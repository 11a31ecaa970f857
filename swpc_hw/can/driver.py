"""python-can driver of the caster-module controllers: lifecycle, locks, I/O.

Lifecycle (as ros2_control's hardware components)::

    UNCONFIGURED --configure()--> INACTIVE --activate()--> ACTIVE
         ^                          ^  |                     |
         |                          |  +----deactivate()-----+  (also on any fault)
         +------- shutdown() (from any state, idempotent) -> FINALIZED

* INACTIVE: the bus is open; heartbeats and feedback are read; no frame is sent.
* ACTIVE: commands flow and the controllers' watchdog is fed: on SocketCAN by the
  kernel's broadcast manager with a dead-man (:mod:`swpc_hw.can.periodic`), elsewhere by
  re-sending a node's last control frames whenever it got none for ``refresh_period_s``.

Every fault path (bus-off, lost heartbeat, a controller's fault report, an exception in a
callback) calls :meth:`CanDriver.stop_all` -- FREE then DISABLED to every axis of every
node -- and drops back to INACTIVE.

The logic lives in pure cores: :mod:`swpc_hw.can.node_tracking` (what a frame tells) and
:mod:`swpc_hw.can.supervision` (which nodes are lost, what to refresh).  This module owns
the bus, the locks, the lifecycle and the receive path: one I/O step drains the receive
queue, applies every frame, then supervises at a time taken before the queue was found
empty.  The step runs on the driver's own thread against a real clock, and as a hook of
the master against a :class:`swpc_hw.clock.SimClock` (lockstep with a simulator).

Positions at this boundary are SI: ``theta_hat`` (steering, rad, 0 at the homing sensor)
and ``psi`` (cumulative wheel angle, rad), unwrapped on the host.
"""

from __future__ import annotations

import contextlib
import logging
import math
import queue
import socket
import threading
from collections import deque
from collections.abc import Callable

import can

from firmware_protocol import codec
from firmware_protocol.codec import Axis
from swpc_hw.can.commands import DriverCommands
from swpc_hw.can.config import CanConfig
from swpc_hw.can.errors import (
    CanBusError,
    CanError,
    LifecycleError,
    NodeTimeoutError,
)
from swpc_hw.can.history import FeedbackRing
from swpc_hw.can.node_tracking import Applied, NodeTrack, apply_frame, frame_time
from swpc_hw.can.observation import DriverObservation
from swpc_hw.can.periodic import KernelRefresh
from swpc_hw.can.recording import Recorder, grow_receive_buffer
from swpc_hw.can.supervision import CheckResult, check
from swpc_hw.can.types import (
    DriverEvent,
    DriverStats,
    EventKind,
    FeedbackSample,
    Lifecycle,
    Observation,
    Severity,
    where,
)
from swpc_hw.clock import SYSTEM_CLOCK, Clock, SimClock, wait_until

log = logging.getLogger(__name__)

IO_WAIT_MAX = 0.05
"""Longest wall wait of the I/O thread for a frame (s): how soon it notices shutdown."""


class CanDriver(DriverCommands, DriverObservation):
    """Driver of the module controllers on one CAN bus (see the module docstring); its
    command API is :class:`DriverCommands`, its observation API :class:`DriverObservation`."""

    def __init__(
        self,
        config: CanConfig | None = None,
        *,
        clock: Clock = SYSTEM_CLOCK,
        on_event: Callable[[DriverEvent], None] | None = None,
    ) -> None:
        self.config = config or CanConfig()
        self.clock = clock
        self._lockstep = isinstance(clock, SimClock)
        self._state = Lifecycle.UNCONFIGURED
        self._lock = threading.RLock()
        self._changed = threading.Condition(self._lock)
        self._tx_lock = threading.RLock()
        self._nodes: dict[int, NodeTrack] = {}
        self._by_node: dict[int, NodeTrack] = {}
        for module, node in self.config.modules.items():
            nd = NodeTrack(module, node, FeedbackRing(self.config.history_len))
            self._nodes[module] = nd
            self._by_node[node] = nd
        self._stats = DriverStats()
        self._last_arrival = -math.inf  # the latest frame arrival on the clock (_handle)
        self._events: queue.Queue[DriverEvent] = queue.Queue(maxsize=10_000)
        self._event_callbacks: list[Callable[[DriverEvent], None]] = []
        if on_event is not None:
            self._event_callbacks.append(on_event)
        self._feedback_callbacks: list[Callable[[int, FeedbackSample], None]] = []
        self._latency: deque[float] = deque(maxlen=100_000)
        self._bus: can.BusABC | None = None
        self._logger: Recorder | None = None
        self._recorder: Recorder | None = None
        self._kernel: KernelRefresh | None = None
        self._next_renewal = 0.0
        self._io_thread: threading.Thread | None = None
        self._stop_io = threading.Event()
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

    @property
    def refresh_in_kernel(self) -> bool:
        """The watchdog refresh runs in the kernel (SocketCAN broadcast manager)."""
        return self._kernel is not None

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
            kwargs = dict(cfg.bus_kwargs)
            if self._lockstep:
                if cfg.interface != "virtual":
                    raise CanBusError(
                        "a simulated clock needs the in-process bus (interface 'virtual'), "
                        f"not {cfg.interface!r}"
                    )
                kwargs.setdefault("preserve_timestamps", True)  # stamps on the sim clock
            if cfg.interface == "socketcan":
                # in the kernel: our own commands (the periodic refresh, looped back) never
                # reach the receive path
                kwargs.setdefault("can_filters", self._receive_filters())
            try:
                self._bus = can.Bus(
                    interface=cfg.interface, channel=cfg.channel, bitrate=cfg.bitrate, **kwargs
                )
            except (can.CanError, OSError, ValueError, ImportError) as exc:
                raise CanBusError(
                    f"cannot open CAN bus interface={cfg.interface!r} "
                    f"channel={cfg.channel!r}: {exc}"
                ) from exc
            sock = getattr(self._bus, "socket", None)
            if cfg.rx_buffer_bytes and isinstance(sock, socket.socket):
                self._stats.rx_buffer_bytes = grow_receive_buffer(sock, cfg.rx_buffer_bytes)
            kernel = cfg.refresh_in_kernel
            if kernel is None:
                kernel = cfg.interface == "socketcan" and not self._lockstep
            if kernel:
                # the kernel's timers run on the host's time; the budget is robot time
                # (SystemClock(rate=k) against a time-scaled simulator: k robot s a host s)
                rate = self.clock.rate
                self._kernel = KernelRefresh(
                    self._bus, cfg.refresh_period_s / rate, cfg.deadman_s / rate
                )
            if cfg.log_path:
                self._logger = Recorder(
                    cfg.log_path,
                    total_bytes=cfg.log_total_bytes,
                    sample_period_s=cfg.log_idle_period_s,
                )
            self._configured_at = self.clock.now()
            self._state = Lifecycle.INACTIVE
            self._stop_io.clear()
            if isinstance(self.clock, SimClock):
                self.clock.add_hook(self._io_hook)
            else:
                self._io_thread = threading.Thread(
                    target=self._io_loop, name=f"swpc-can-io-{cfg.channel}", daemon=True
                )
                self._io_thread.start()

    def activate(self) -> None:
        """INACTIVE -> ACTIVE: wait for every node's heartbeat, send watchdog/feedback/limits.

        Raises :class:`NodeTimeoutError` naming the silent nodes if a heartbeat is missing
        after ``activate_timeout_s``.
        """
        cfg = self.config
        deadline = self.clock.now() + cfg.activate_timeout_s
        with self._changed:
            if self._state != Lifecycle.INACTIVE:
                raise LifecycleError(f"activate() needs state inactive, not {self._state.value}")

            def all_alive() -> bool:
                return all(nd.alive for nd in self._nodes.values())

            if not wait_until(self.clock, self._changed, all_alive, deadline):
                silent = [nd for nd in self._nodes.values() if not nd.alive]
                names = ", ".join(where(nd.module, nd.node) for nd in silent)
                raise NodeTimeoutError(
                    f"activate(): no heartbeat from {names} within {cfg.activate_timeout_s} s",
                    node=silent[0].node,
                )
            if self._state != Lifecycle.INACTIVE:
                raise LifecycleError(f"activate(): the driver became {self._state.value}")
            self._state = Lifecycle.ACTIVE
            self._fault_cause = None
            self._next_renewal = self.clock.now()
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
        self._stop_io.set()
        if isinstance(self.clock, SimClock):
            self.clock.remove_hook(self._io_hook)
        if self._io_thread is not None and self._io_thread is not threading.current_thread():
            self._io_thread.join(timeout=2.0)
        with self._tx_lock:
            if self._kernel is not None:
                self._kernel.close()
        self.stop_recording()
        if self._logger is not None:
            self._logger.stop()
        if self._bus is not None:
            self._bus.shutdown()
        with self._lock:
            self._state = Lifecycle.FINALIZED
            self._changed.notify_all()

    def _receive_filters(self) -> list[dict[str, int | bool]]:
        """The kernel's receive filters on SocketCAN: the controllers' frames only (a drive
        kind with other frames has its own)."""
        return codec.host_receive_filters()

    # ================================================================ transmit
    def _send_frames(self, frames: list[codec.Frame], best_effort: bool = False) -> None:
        bus = self._bus
        if bus is None:
            raise LifecycleError("the bus is not open (call configure())")
        failure: Exception | None = None
        with self._tx_lock:
            now = self.clock.now()
            stamp = self.clock.wall()
            for f in frames:
                msg = can.Message(
                    arbitration_id=f.arbitration_id,
                    data=f.data,
                    is_extended_id=False,
                    is_rx=False,
                    channel=self.config.channel,
                    timestamp=stamp,
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
                self._log(msg)
                with self._lock:
                    self._stats.tx_frames += 1
                    nd = self._by_node.get(f.arbitration_id >> codec.NODE_SHIFT)
                    if nd is not None:
                        nd.last_tx = now
        if failure is not None:
            self._emit(EventKind.SEND_ERROR, Severity.WARNING, str(failure))
            raise failure

    def _log(self, msg: can.Message) -> None:
        """A frame in or out to the recording, if one is on, and to the rolling log: every
        frame while recording, else as ``CanConfig.log_idle_period_s`` samples them."""
        recorder = self._recorder
        if recorder is not None:
            recorder.write(msg)
        if self._logger is not None:
            self._logger.write(msg, sample=recorder is None)

    # ================================================================ receive + supervise
    def _io_loop(self) -> None:
        """The driver's thread (real clocks): wait for a frame or the next deadline."""
        bus = self._bus
        assert bus is not None
        rate = self.clock.rate
        while not self._stop_io.is_set():
            try:
                deadline = self._io_step(bus)
                wait = min(max((deadline - self.clock.now()) / rate, 0.0), IO_WAIT_MAX)
                msg = bus.recv(wait)
                if msg is not None:
                    self._handle(msg)
            except (can.CanError, OSError, ValueError) as exc:
                if self._stop_io.is_set():
                    return
                self._on_listener_error(exc)
                self._stop_io.wait(IO_WAIT_MAX)
            except Exception as exc:  # a bug: reported as a fault, the loop goes on
                self._on_listener_error(exc)

    def _io_hook(self, now: float) -> None:
        """The I/O step as a :class:`SimClock` hook (lockstep: on the master's thread)."""
        bus = self._bus
        if bus is None or self._stop_io.is_set():
            return
        try:
            self._io_step(bus)
        except Exception as exc:
            self._on_listener_error(exc)

    def _io_step(self, bus: can.BusABC) -> float:
        """Drain the receive queue, then supervise; returns the next deadline.

        ``t_check`` is taken before each ``recv(0)``: when that finds the queue empty,
        every frame that arrived by ``t_check`` has been applied.  A step also ends once
        it has applied a frame that arrived after the step began: the backlog of the
        step's start is then applied, so supervision (and the dead-man's renewal) runs at
        that start time even while frames never stop coming.
        """
        clock = self.clock
        t0 = t_check = clock.now()
        msg = bus.recv(0)
        while msg is not None:
            self._handle(msg)
            if msg.timestamp and clock.from_wall(msg.timestamp) > t0:
                t_check = t0
                break
            t_check = clock.now()
            msg = bus.recv(0)
        return self._supervise(t_check)

    def _handle(self, msg: can.Message) -> None:
        clock = self.clock
        handled = clock.now()
        stamp = float(msg.timestamp or 0.0)
        t = frame_time(stamp, handled, clock.from_wall(stamp)) if stamp else handled
        # frames leave one queue in order: their arrivals never go back in time
        t = self._last_arrival = max(t, self._last_arrival)
        self._log(msg)
        try:
            with self._changed:
                applied = self._apply_frame(msg, t)
                if stamp:
                    self._latency.append(clock.wall() - stamp)
                # events queued before the state drops: whoever sees INACTIVE finds why
                recorded = [self._record(o) for o in applied.observations]
                was_active = applied.fault and self._begin_fault(
                    next((e.message for e in recorded if e.severity is Severity.FAULT), "fault")
                )
                self._changed.notify_all()
                callbacks = self._feedback_callbacks
            if applied.fault:
                self._fault_stop(was_active, recorded)
            else:
                for ev in recorded:
                    self._notify(ev)
            if applied.sample is not None:
                for fn in callbacks:
                    fn(*applied.sample)
        except Exception as exc:
            self._on_listener_error(exc)

    def _apply_frame(self, msg: can.Message, t: float) -> Applied:
        """What one received frame tells (the pure core; under the driver's lock)."""
        return apply_frame(self._by_node, msg, t, self._stats)

    def _on_listener_error(self, exc: Exception) -> None:
        with self._lock:
            self._stats.listener_errors += 1
            self.last_exception = exc
            ev = self._record(
                Observation(
                    EventKind.LISTENER_ERROR,
                    Severity.FAULT,
                    f"exception in the receive path: {type(exc).__name__}: {exc}",
                )
            )
            was_active = self._begin_fault(ev.message)
        self._fault_stop(was_active, [ev])

    def _supervise(self, now: float) -> float:
        cfg = self.config
        loss_after = cfg.heartbeat_loss_periods * cfg.heartbeat_period_s
        with self._lock:
            active = self._state == Lifecycle.ACTIVE
            res = self._check(now, loss_after, active)
            recorded = [
                self._record(
                    Observation(
                        EventKind.HEARTBEAT_LOST,
                        Severity.FAULT,
                        f"{where(nd.module, nd.node)}: no heartbeat for {loss_after:.3f} s",
                        nd.module,
                        nd.node,
                    )
                )
                for nd in res.lost
            ]
            self._stats.heartbeat_losses += len(res.lost)
            was_active = bool(res.lost) and self._begin_fault(recorded[0].message)
        deadline = res.next_deadline
        if res.lost:
            self._fault_stop(was_active, recorded)
            return min(deadline, now + cfg.heartbeat_period_s)
        if res.refresh and active:
            with contextlib.suppress(CanError):
                self._send_frames(res.refresh, best_effort=True)
        if self._kernel is not None and active:
            if now >= self._next_renewal:
                with self._tx_lock:
                    if self._state == Lifecycle.ACTIVE:
                        self._kernel.renew()
                self._next_renewal = now + self._kernel.renew_every * self.clock.rate
            deadline = min(deadline, self._next_renewal)
        return deadline

    def _check(self, now: float, loss_after: float, active: bool) -> CheckResult:
        """Heartbeat loss and the host's refresh at ``now`` (the pure core; lock held)."""
        return check(
            self._nodes.values(),
            now,
            t_configured=self._configured_at,
            loss_after=loss_after,
            refresh_period=self.config.refresh_period_s,
            refresh=active and self._kernel is None,
        )

    # ================================================================ faults and events
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
        stop first: a slow event callback must not hold the stop frames back."""
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

    def _emit(self, kind: EventKind, severity: Severity, message: str) -> None:
        self._notify(self._record(Observation(kind, severity, message)))

    def _record(self, obs: Observation) -> DriverEvent:
        """Stamp, log and queue an observation as an event (cheap; under the lock is fine)."""
        ev = DriverEvent(
            self.clock.now(), obs.kind, obs.severity, obs.message, obs.module, obs.node, obs.axis
        )
        if obs.severity != Severity.INFO:
            self._log_counts[obs.kind] = n = self._log_counts.get(obs.kind, 0) + 1
            if n <= 5 or obs.severity == Severity.FAULT:
                log.warning("%s%s", obs.message, " (further ones counted only)" if n == 5 else "")
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
