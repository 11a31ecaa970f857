"""The one base of every drive kind: lifecycle, the I/O step, supervision, the fault path,
events; a kind adds only its protocol (as python-can's ``BusABC`` leaves a bus its two
methods).

Lifecycle (as ros2_control's hardware components)::

    UNCONFIGURED --configure()--> INACTIVE --activate()--> ACTIVE
         ^                          ^  |                     |
         |                          |  +----deactivate()-----+  (also on any fault)
         +------- shutdown() (from any state, idempotent) -> FINALIZED

* INACTIVE: the bus is open; heartbeats and feedback are read; no command is sent.
* ACTIVE: commands flow and every enabled axis is kept alive by the kind's dead-man: on
  SocketCAN by the kernel's broadcast manager with a dead-man
  (:mod:`swpc_hw.drives.periodic`), elsewhere from the I/O step.

Every fault path (bus-off, a lost heartbeat, a drive's fault report, an exception in a
callback) drops to INACTIVE (:meth:`DriverBase._begin_fault`), calls :meth:`stop_all`
first, *then* the event callbacks.

One I/O step drains the receive queue, applies every frame, then supervises at a time
taken before the queue was found empty.  The step runs on the driver's own thread against
a real clock, and as a hook of the master against a :class:`swpc_hw.clock.SimClock`
(lockstep with a simulator).

What a kind implements (:class:`swpc_hw.drives.interface.DriveKind`, its abstract methods
and hooks): the receive core (``_apply_frame``: what one frame tells, under the lock; or
``_receive`` for a kind whose library dispatches frames itself), supervision (``_check``:
which drives are lost, what to re-send; ``_keep_alive``: its own periodic frames),
activation (``_bring_up``, ``_after_activate``), the stop (``_stopping``, ``_stop_frames``),
the commands and observations of :class:`swpc_hw.drives.interface.Drives` (``enable`` ...
``start_homing``, ``modules``, ``module_state``) and each module's ring (``_ring``).

Positions at this boundary are SI: ``theta_hat`` (steering, rad, 0 at the homing
reference) and ``psi`` (cumulative wheel angle, rad), unwrapped on the host.
"""

from __future__ import annotations

import contextlib
import logging
import math
import queue
import socket
import threading
from collections import deque
from collections.abc import Callable, Iterable, Mapping
from typing import TypeVar

import can

from firmware_protocol.codec import Frame
from swpc_hw.clock import SYSTEM_CLOCK, Clock, SimClock
from swpc_hw.drives.bus import CanConfig
from swpc_hw.drives.errors import (
    CanBusError,
    CanCommandError,
    CanError,
    LifecycleError,
)
from swpc_hw.drives.interface import DriveKind
from swpc_hw.drives.observation import DriverObservation
from swpc_hw.drives.periodic import KernelRefresh, frame_message
from swpc_hw.drives.recording import Recorder, grow_receive_buffer
from swpc_hw.drives.tracking import NodeTrack, Supervision, check_nodes, frame_time
from swpc_hw.drives.types import (
    DriverEvent,
    DriverStats,
    EventKind,
    FeedbackSample,
    Lifecycle,
    Observation,
    Severity,
)

log = logging.getLogger(__name__)

IO_WAIT_MAX = 0.05
"""Longest wall wait of the I/O thread for a frame (s): how soon it notices shutdown."""
LOG_RETRY_S = 10.0
"""The rolling CAN log, paused by a failed write (a full disk), tries again this often (s)."""

T = TypeVar("T", bound=NodeTrack)


M = TypeVar("M")


class DriverBase(DriverObservation, DriveKind):
    """The robot's drives of one kind on one bus (module docstring).

    ``kernel_always``: the kernel's refresh (SocketCAN) runs from ``configure()`` (a kind
    whose host heartbeat it carries) rather than only while ACTIVE.
    ``silent_until_set_up``: the kind's devices say nothing until the host has set them up
    (CiA 402 drives from the factory: heartbeat producer 0x1017 = 0), so a service brings
    them up once (``activate()`` then ``deactivate()``: nothing moves) to watch them
    between runs.
    """

    thread_name = "swpc-drives-io"
    kernel_always = False
    silent_until_set_up = False
    stopped_message = "fault: all axes freed and disabled; driver inactive"

    def __init__(
        self,
        config: CanConfig,
        *,
        clock: Clock = SYSTEM_CLOCK,
        on_event: Callable[[DriverEvent], None] | None = None,
    ) -> None:
        self.config = config
        self.clock = clock
        self.last_exception: BaseException | None = None
        self._lockstep = isinstance(clock, SimClock)
        self._state = Lifecycle.UNCONFIGURED
        self._fault_cause: str | None = None
        self._lock = threading.RLock()
        self._changed = threading.Condition(self._lock)
        self._tx_lock = threading.RLock()
        self._by_node: dict[int, NodeTrack] = {}
        """Tracks by CAN node: a sent frame stamps its node's ``last_tx``."""
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
        self._log_counts: dict[EventKind, int] = {}

    # ================================================================ lifecycle
    @property
    def state(self) -> Lifecycle:
        return self._state

    @property
    def fault_cause(self) -> str | None:
        """Why the drives last dropped from ACTIVE on a fault (None after activate() or an
        orderly deactivate())."""
        return self._fault_cause

    @property
    def refresh_in_kernel(self) -> bool:
        """The dead-man's refresh runs in the kernel (SocketCAN broadcast manager)."""
        return self._kernel is not None

    def __enter__(self) -> DriverBase:
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
            filters = self._receive_filters()
            if cfg.interface == "socketcan" and filters is not None:
                # in the kernel: our own commands (the periodic refresh, looped back) never
                # reach the receive path
                kwargs.setdefault("can_filters", filters)
            self._before_open()
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
                    retry_s=LOG_RETRY_S,
                    now=self.clock.now,
                )
            self._configured_at = self.clock.now()
            self._opened(self._bus)
            self._state = Lifecycle.INACTIVE
            self._stop_io.clear()
            if isinstance(self.clock, SimClock):
                self.clock.add_hook(self._io_hook)
            else:
                self._io_thread = threading.Thread(
                    target=self._io_loop, name=f"{self.thread_name}-{cfg.channel}", daemon=True
                )
                self._io_thread.start()

    def activate(self) -> None:
        """INACTIVE -> ACTIVE: the kind's bring-up (every drive alive, its dead-man armed),
        then commands flow; :class:`NodeTimeoutError` names the silent drives."""
        with self._changed:
            if self._state != Lifecycle.INACTIVE:
                raise LifecycleError(f"activate() needs state inactive, not {self._state.value}")
        self._bring_up()
        with self._changed:
            if self._state != Lifecycle.INACTIVE:
                raise LifecycleError(f"activate(): the drives became {self._state.value}")
            self._state = Lifecycle.ACTIVE
            self._fault_cause = None
            if not self.kernel_always:
                self._next_renewal = self.clock.now()
            self._activated()
        self._after_activate()

    def deactivate(self) -> None:
        """ACTIVE -> INACTIVE: every axis free and disabled, nothing sent any more."""
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

    def stop_all(self) -> None:
        """Every axis stopped (the kind's :meth:`_stop_frames`), the refreshed setpoints
        forgotten and the kernel's refresh of them deleted first, so none follows the stop
        frames.  Sends regardless of the lifecycle state as long as the bus is open: what
        every fault path calls.  Send failures are counted and re-raised at the end."""
        with self._tx_lock:
            with self._lock:
                self._stats.stop_all_calls += 1
                self._stopping()
                bus_open = self._bus is not None and self._state in (
                    Lifecycle.INACTIVE,
                    Lifecycle.ACTIVE,
                )
            if self._kernel is not None and not self.kernel_always:
                self._kernel.stop_all()
            if not bus_open:
                return
            self._send_frames(self._stop_frames(), best_effort=True)

    def _require_active(self, what: str, at: str = "") -> None:
        """:class:`LifecycleError` unless ACTIVE, naming the fault that stopped the drives
        (``at``: what the command concerns, ``module 2 (node 2) axis 1 (wheel)``)."""
        if self._state != Lifecycle.ACTIVE:
            cause = self._fault_cause
            why = f" (stopped by a fault: {cause})" if cause is not None else ""
            prefix = f"{at}: " if at else ""
            raise LifecycleError(f"{prefix}cannot {what} in state {self._state.value}{why}")

    # ================================================================ transmit
    def _send_frames(self, frames: list[Frame], best_effort: bool = False) -> None:
        bus = self._bus
        if bus is None:
            raise LifecycleError("the bus is not open (call configure())")
        failure: Exception | None = None
        with self._tx_lock:
            now = self.clock.now()
            stamp = self.clock.wall()
            for f in frames:
                msg = frame_message(f, self.config.channel, stamp)
                node = self._node_of(f.arbitration_id)
                try:
                    bus.send(msg)
                except (can.CanError, OSError) as exc:
                    with self._lock:
                        self._stats.send_errors += 1
                    at = "" if node is None else f"node {node}: "
                    failure = failure or CanBusError(
                        f"{at}send 0x{f.arbitration_id:03x} failed: {exc}"
                    )
                    if not best_effort:
                        break
                    continue
                self._log(msg)
                with self._lock:
                    self._stats.tx_frames += 1
                    nd = None if node is None else self._by_node.get(node)
                    if nd is not None:
                        nd.last_tx = now
        if failure is not None:
            self._emit(EventKind.SEND_ERROR, Severity.WARNING, str(failure))
            raise failure

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
                    self._drained()
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
        self._drained()
        return self._supervise(t_check)

    def _handle(self, msg: can.Message) -> None:
        """One received frame: its arrival on the clock, the log, the kind's receive."""
        clock = self.clock
        handled = clock.now()
        stamp = float(msg.timestamp or 0.0)
        t = frame_time(stamp, handled, clock.from_wall(stamp)) if stamp else handled
        # frames leave one queue in order: their arrivals never go back in time
        t = self._last_arrival = max(t, self._last_arrival)
        self._log(msg)
        try:
            self._receive(msg, t)
        except Exception as exc:
            self._on_listener_error(exc)

    def _receive(self, msg: can.Message, t: float) -> None:
        """Apply one frame (:meth:`_apply_frame`, under the lock), then its fault path or
        its events, then the feedback callbacks."""
        clock = self.clock
        stamp = float(msg.timestamp or 0.0)
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

    def _supervise(self, now: float) -> float:
        """The kind's supervision at ``now`` (:meth:`_check`): a lost drive is a fault;
        then the refresh, the kind's own periodic frames and the dead-man's renewal."""
        with self._lock:
            active = self._state == Lifecycle.ACTIVE
            sup = self._check(now, active)
            self._stats.heartbeat_losses += sup.lost
        if sup.observations:
            self._observed(sup.observations)
        if sup.fault:
            return min(sup.next_deadline, now + self.config.heartbeat_period_s)
        if sup.refresh and active:
            with contextlib.suppress(CanError):
                self._send_frames(sup.refresh, best_effort=True)
        deadline = min(sup.next_deadline, self._keep_alive(now, active))
        return min(deadline, self._renew(now, active))

    def _renew(self, now: float, active: bool) -> float:
        """The dead-man's renewal of the kernel's refresh (every half of it); returns when
        the next one is due."""
        kernel = self._kernel
        if kernel is None or not (active or self.kernel_always):
            return math.inf
        if now >= self._next_renewal:
            with self._tx_lock:
                if self.kernel_always or self._state == Lifecycle.ACTIVE:
                    kernel.renew()
            # the kernel counts host seconds: renew_every of them on this clock
            self._next_renewal = now + kernel.renew_every * self.clock.rate
        return self._next_renewal

    @staticmethod
    def _configured(tracks: Mapping[int, M], module: int) -> M:
        """``tracks[module]``, or the error that names the modules configured."""
        if module not in tracks:
            raise CanCommandError(f"module {module} is not configured (modules: {sorted(tracks)})")
        return tracks[module]

    def _check_nodes(
        self,
        nodes: Iterable[T],
        now: float,
        active: bool,
        refreshed: Callable[[T], bool],
        frames: Callable[[T], list[Frame]],
    ) -> Supervision:
        """:func:`swpc_hw.drives.tracking.check_nodes` on node tracks, a lost node a FAULT."""
        return check_nodes(
            nodes,
            now,
            t_configured=self._configured_at,
            loss_after=self.config.loss_after_s,
            refresh_period=self.config.refresh_period_s,
            refresh=active and self._kernel is None,
            refreshed=refreshed,
            frames=frames,
        )

    # ================================================================ faults and events
    def _observed(self, obs: list[Observation]) -> None:
        """Observations outside the receive path: a FAULT among them stops every axis
        first, then every event goes to the callbacks."""
        with self._lock:
            recorded = [self._record(o) for o in obs]
            fault = next((e for e in recorded if e.severity is Severity.FAULT), None)
            was_active = fault is not None and self._begin_fault(fault.message)
        if fault is not None:
            self._fault_stop(was_active, recorded)
        else:
            for ev in recorded:
                self._notify(ev)

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

    def _begin_fault(self, cause: str) -> bool:
        """Drop from ACTIVE to INACTIVE (no more commands); True if the drives were active.

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
        """Every fault path, after :meth:`_begin_fault`: stop_all() if the drives were
        active, *then* the event callbacks with the fault's ``events``, then STOPPED.  The
        motors stop first: a slow event callback must not hold the stop frames back."""
        if was_active:
            try:
                self.stop_all()
            except CanError as exc:
                log.error("stop_all() after a fault failed: %s", exc)
        for ev in events:
            self._notify(ev)
        if was_active:
            self._emit(EventKind.STOPPED, Severity.INFO, self.stopped_message)
        with self._changed:
            self._changed.notify_all()
