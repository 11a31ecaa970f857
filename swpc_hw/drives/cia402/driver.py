"""The ``cia402`` drive kind: CiA 402 drives over CANopen, on the ``canopen`` library.

One single-axis drive per axis (a module's steering and wheel on two nodes).  canopen does
SDO, PDO, NMT and EMCY (:class:`canopen.Network` with one
:class:`~swpc_hw.drives.cia402.sdo.ClockedRemoteNode` per axis); this module owns the bus,
the lifecycle of :class:`swpc_hw.drives.interface.Drives`, the receive path (it feeds
:meth:`canopen.Network.notify` itself: no notifier thread, so that in lockstep every frame
is handled on the clock) and the pure cores of :mod:`swpc_hw.drives.cia402.tracking`.

Lifecycle
---------
* ``configure()``: open the bus, start the I/O step (the driver's thread on a real clock,
  a :class:`~swpc_hw.clock.SimClock` hook in lockstep) and the host's heartbeat (node
  ``drives.host_node``, every ``refresh_period_s``; on SocketCAN from the kernel with the
  dead-man of :class:`swpc_hw.can.periodic.KernelRefresh`, renewed by the I/O step).
* ``activate()``: every drive's heartbeat seen; once per boot of a drive, its set-up over
  SDO (PRE-OPERATIONAL): heartbeat producer 0x1017 = ``heartbeat_period_s``, heartbeat
  consumer 0x1016 on the host's heartbeat with the command watchdog
  (``watchdog_timeout_ms``) as its time, quick-stop option 0x605A, homing method 0x6098,
  the motor's rated torque 0x6076 read, the factor group (0x608F, 0x6091) and the modes
  (0x6502) checked against the config, the PDO mapping of
  :data:`firmware_protocol.cia402.RPDO_MAP` / :data:`~firmware_protocol.cia402.TPDO_MAP`
  written (before anything uses it); then NMT start and OPERATIONAL seen on every
  heartbeat; the SYNC (``feedback_rate_hz``) runs from then on.
* commands: RPDO 2 (targets) then RPDO 1 (controlword, mode, torque); the power state
  machine moves one transition per statusword (:func:`~swpc_hw.drives.cia402.tracking.
  supervise`); steering and held wheels in cyclic synchronous position, wheel torque in
  cyclic synchronous torque, "free" a torque of 0, homing in mode 6.
* ``stop_all()``: controlword *disable voltage* and target torque 0 to every axis (the
  power stage off: every axis free).  The host's heartbeat goes on while the bus is open:
  it says the host is alive, and a drive whose consumer saw it end would fault.

The drives' own dead-man: a host that stops (``kill -STOP``, a hang) stops its heartbeat
at most ``deadman_s`` after the I/O step's last renewal (on SocketCAN; at once elsewhere),
and every drive's consumer faults its axis ``watchdog_timeout_ms`` later: the same bound
``D + W`` as the swpc kind's (:mod:`services.config.timing`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import queue
import socket
import threading
from collections import deque
from collections.abc import Callable, Iterator

import can
import canopen
import numpy as np
from canopen.emcy import EmcyError
from canopen.pdo.base import PdoMap
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError
from numpy.typing import NDArray

from firmware_protocol import cia402
from firmware_protocol.cia402 import Mode, PowerState
from firmware_protocol.codec import Axis, Frame, HomingState
from swpc_hw.can.config import CanConfig
from swpc_hw.can.errors import (
    CanBusError,
    CanCommandError,
    CanError,
    LifecycleError,
    NodeError,
    NodeTimeoutError,
)
from swpc_hw.can.history import FeedbackRing
from swpc_hw.can.node_tracking import CAN_ERR_BUSOFF, frame_time
from swpc_hw.can.periodic import KernelRefresh
from swpc_hw.can.recording import Recorder, grow_receive_buffer
from swpc_hw.can.types import (
    AXIS_NAMES,
    DriverEvent,
    DriverStats,
    EventKind,
    FeedbackSample,
    Lifecycle,
    ModuleState,
    Observation,
    Severity,
)
from swpc_hw.clock import SYSTEM_CLOCK, Clock, SimClock, wait_until
from swpc_hw.drives.cia402.sdo import ClockedRemoteNode
from swpc_hw.drives.cia402.tracking import (
    AxisTrack,
    ModuleTrack,
    on_emcy,
    on_heartbeat,
    on_statusword,
    pair,
    supervise,
)
from swpc_hw.drives.config import ABSOLUTE, Cia402Drives

log = logging.getLogger(__name__)

IO_WAIT_MAX = 0.05
"""Longest wall wait of the I/O thread for a frame (s): how soon it notices shutdown."""
POWER_TIMEOUT_S = 1.0
"""An axis asked to enable that is not OPERATION ENABLED in a statusword answering a SYNC
sent this long after has refused (robot time, in SYNC periods)."""
MODE_TIMEOUT_S = 0.5
"""A mode whose display has not followed in a statusword answering a SYNC sent this long
after it was commanded was refused (robot time, in SYNC periods)."""


class _HostNetwork(canopen.Network):
    """canopen's network on the driver's bus: every frame it sends is stamped with the
    driver clock's wall time, counted and logged (no notifier: the driver feeds it)."""

    def __init__(self, driver: Cia402Driver, bus: can.BusABC) -> None:
        super().__init__(bus)
        self.driver = driver

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        self.driver._send(can_id, bytes(data))


class Cia402Driver:
    """The robot's CiA 402 drives on one bus (module docstring)."""

    def __init__(
        self, drives: Cia402Drives, config: CanConfig, *, clock: Clock = SYSTEM_CLOCK
    ) -> None:
        self.drives = drives
        self.config = config
        self.clock = clock
        self.last_exception: BaseException | None = None
        self._lockstep = isinstance(clock, SimClock)
        self._state = Lifecycle.UNCONFIGURED
        self._fault_cause: str | None = None
        self._lock = threading.RLock()
        self._changed = threading.Condition(self._lock)
        self._tx_lock = threading.RLock()
        self._modules: dict[int, ModuleTrack] = {}
        self._axes: dict[int, AxisTrack] = {}
        self._history: dict[int, FeedbackRing] = {}
        self._last: dict[int, FeedbackSample] = {}
        for m, mod in drives.axes().items():
            tracks = []
            for axis, a in ((Axis.STEER, mod.steer), (Axis.WHEEL, mod.wheel)):
                tr = AxisTrack(m, axis, a.node, a.counts_per_rad(), a.gear_ratio)
                tracks.append(tr)
                self._axes[a.node] = tr
            mt = ModuleTrack(m, tracks[0], tracks[1])
            if mod.steer.homing == ABSOLUTE:
                mt.homed, mt.homing = True, HomingState.DONE
            self._modules[m] = mt
            self._history[m] = FeedbackRing(config.history_len)
        self._stats = DriverStats()
        self._bus: can.BusABC | None = None
        self._network: _HostNetwork | None = None
        self._nodes: dict[int, ClockedRemoteNode] = {}
        self._kernel: KernelRefresh | None = None
        self._next_renewal = 0.0
        self._next_heartbeat = 0.0
        self._sync_on = False
        self._sync_seq = 0
        self._next_sync = math.inf
        self._configured_at = 0.0
        self._last_arrival = -math.inf
        self._io_thread: threading.Thread | None = None
        self._stop_io = threading.Event()
        self._events: queue.Queue[DriverEvent] = queue.Queue(maxsize=10_000)
        self._event_callbacks: list[Callable[[DriverEvent], None]] = []
        self._feedback_callbacks: list[Callable[[int, FeedbackSample], None]] = []
        self._pending: list[Observation] = []  # observed by canopen callbacks in a step
        self._samples: list[tuple[int, FeedbackSample]] = []
        self._logger: Recorder | None = None
        self._recorder: Recorder | None = None
        self._limits: dict[tuple[int, int], tuple[int, int]] = {}
        self._latency: deque[float] = deque(maxlen=10_000)
        self._arrival = 0.0  # the arrival of the frame being handled (canopen's callbacks)

    # ================================================================ lifecycle
    @property
    def state(self) -> Lifecycle:
        return self._state

    @property
    def fault_cause(self) -> str | None:
        return self._fault_cause

    @property
    def refresh_in_kernel(self) -> bool:
        """The host's heartbeat comes from the kernel (SocketCAN broadcast manager)."""
        return self._kernel is not None

    def configure(self) -> None:
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
                kwargs.setdefault("preserve_timestamps", True)
            try:
                od = canopen.import_od(str(self.drives.object_dictionary))
            except Exception as exc:
                raise CanBusError(
                    f"drives.object_dictionary {self.drives.object_dictionary}: cannot read "
                    f"it as an EDS/DCF: {exc}"
                ) from exc
            del od
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
            net = self._network = _HostNetwork(self, self._bus)
            for m, mt in self._modules.items():
                for a in mt.axes:
                    node = ClockedRemoteNode(
                        a.node,
                        str(self.drives.object_dictionary),
                        self.clock,
                        timeout=cfg.heartbeat_loss_periods * cfg.heartbeat_period_s,
                    )
                    net.add_node(node)
                    self._nodes[a.node] = node
                    net.subscribe(cia402.HEARTBEAT_BASE + a.node, self._on_heartbeat)
                    node.emcy.add_callback(self._emcy_callback(a))
                    for i in cia402.TPDO_MAP:
                        node.tpdo[i].add_callback(lambda p, a=a, m=m: self._on_tpdo(m, a, p))
            kernel = cfg.refresh_in_kernel
            if kernel is None:
                kernel = cfg.interface == "socketcan" and not self._lockstep
            if kernel:
                # the kernel's timers run on host time; the budget is robot time
                rate = self.clock.rate
                self._kernel = KernelRefresh(
                    self._bus, cfg.refresh_period_s / rate, cfg.deadman_s / rate
                )
                self._kernel.set_node(self.drives.host_node, [self._heartbeat_frame()])
            if cfg.log_path:
                self._logger = Recorder(
                    cfg.log_path,
                    total_bytes=cfg.log_total_bytes,
                    sample_period_s=cfg.log_idle_period_s,
                )
            self._configured_at = self._next_heartbeat = self._next_renewal = self.clock.now()
            self._state = Lifecycle.INACTIVE
            self._stop_io.clear()
            if isinstance(self.clock, SimClock):
                self.clock.add_hook(self._io_hook)
            else:
                self._io_thread = threading.Thread(
                    target=self._io_loop, name=f"swpc-cia402-io-{cfg.channel}", daemon=True
                )
                self._io_thread.start()

    def _heartbeat_frame(self) -> Frame:
        host = self.drives.host_node
        return Frame(cia402.HEARTBEAT_BASE + host, bytes([cia402.NMT_OPERATIONAL]))

    def activate(self) -> None:
        """INACTIVE -> ACTIVE (module docstring); :class:`NodeTimeoutError` names the silent
        drives, :class:`NodeError` a drive whose set-up failed (the object and why)."""
        cfg = self.config
        with self._changed:
            if self._state != Lifecycle.INACTIVE:
                raise LifecycleError(f"activate() needs state inactive, not {self._state.value}")
        self._wait_all("heartbeat", lambda a: a.alive, cfg.activate_timeout_s)
        for a in self._tracks():
            if not a.configured:
                self._set_up(a)
        self._wait_all(
            "NMT OPERATIONAL", lambda a: a.nmt == cia402.NMT_OPERATIONAL, cfg.activate_timeout_s
        )
        with self._changed:
            if not self._sync_on:
                self._sync_on = True
                self._next_sync = self.clock.now()
            if self._state != Lifecycle.INACTIVE:
                raise LifecycleError(f"activate(): the drives became {self._state.value}")
            self._state = Lifecycle.ACTIVE
            self._fault_cause = None
            for a in self._tracks():
                a.refused_reported = False
        self._wait_all(
            "a statusword", lambda a: a.statusword is not None, cfg.activate_timeout_s
        )

    def _tracks(self) -> Iterator[AxisTrack]:
        for mt in self._modules.values():
            yield from mt.axes

    def _wait_all(self, what: str, ok: Callable[[AxisTrack], bool], timeout: float) -> None:
        deadline = self.clock.now() + timeout
        with self._changed:
            if not wait_until(
                self.clock, self._changed, lambda: all(ok(a) for a in self._tracks()), deadline
            ):
                bad = [a for a in self._tracks() if not ok(a)]
                raise NodeTimeoutError(
                    f"activate(): no {what} from {', '.join(a.where() for a in bad)} within "
                    f"{timeout:g} s",
                    node=bad[0].node,
                    axis=int(bad[0].axis),
                )

    def _set_up(self, a: AxisTrack) -> None:
        """One drive's set-up over SDO (module docstring), then NMT start."""
        cfg = self.config
        node = self._nodes[a.node]
        node.nmt.send_command(cia402.NMT_ENTER_PRE_OPERATIONAL)
        axes = self.drives.axes()[a.module]
        ax = axes.steer if a.axis is Axis.STEER else axes.wheel
        step = "0x1000"
        try:
            step = "0x1017 producer heartbeat time"
            node.sdo[cia402.PRODUCER_HEARTBEAT].raw = round(1000 * cfg.heartbeat_period_s)
            step = "0x1016 consumer heartbeat time"
            node.sdo[cia402.CONSUMER_HEARTBEAT][1].raw = cia402.consumer_entry(
                self.drives.host_node, cfg.watchdog_timeout_ms
            )
            step = "0x605A quick stop option code"
            node.sdo[cia402.QUICK_STOP_OPTION].raw = self.drives.quick_stop_option
            step = "0x6502 supported drive modes"
            supported = int(node.sdo[cia402.SUPPORTED_MODES].raw)
            needed = [Mode.CYCLIC_SYNC_POSITION, Mode.CYCLIC_SYNC_TORQUE]
            homing = getattr(ax, "homing", ABSOLUTE)
            if homing != ABSOLUTE:
                needed.append(Mode.HOMING)
            missing = [m.name for m in needed if not supported & cia402.supported_modes_bit(m)]
            if missing:
                raise NodeError(
                    f"{a.where()}: the drive does not support mode(s) {', '.join(missing)} "
                    f"(0x6502 = 0x{supported:08X})",
                    node=a.node,
                    axis=int(a.axis),
                )
            if homing != ABSOLUTE:
                step = f"0x6098 homing method {homing}"
                node.sdo[cia402.HOMING_METHOD].raw = int(homing)
            step = "0x6076 motor rated torque"
            a.rated_torque = int(node.sdo[cia402.RATED_TORQUE].raw) / 1000.0
            od = node.object_dictionary
            if cia402.ENCODER_RESOLUTION in od:
                step = "0x608F position encoder resolution"
                inc = int(node.sdo[cia402.ENCODER_RESOLUTION][1].raw)
                rev = int(node.sdo[cia402.ENCODER_RESOLUTION][2].raw)
                self._check_factor(a, "counts_per_turn", ax.counts_per_turn, inc / rev, step)
            if cia402.GEAR_RATIO in od:
                step = "0x6091 gear ratio"
                mot = int(node.sdo[cia402.GEAR_RATIO][1].raw)
                shaft = int(node.sdo[cia402.GEAR_RATIO][2].raw)
                self._check_factor(a, "gear_ratio", ax.gear_ratio, mot / shaft, step)
            for maps, layout, base, ttype in (
                (node.tpdo, cia402.TPDO_MAP, cia402.TPDO_BASE, cia402.TPDO_ON_SYNC),
                (node.rpdo, cia402.RPDO_MAP, cia402.RPDO_BASE, cia402.RPDO_ASYNC),
            ):
                for i, entries in layout.items():
                    step = f"PDO mapping {'TPDO' if maps is node.tpdo else 'RPDO'} {i}"
                    p = maps[i]
                    p.read()
                    p.clear()
                    for index, sub, bits in entries:
                        p.add_variable(index, sub, bits)
                    p.cob_id = base[i - 1] + a.node
                    p.trans_type = ttype
                    p.event_timer = 0 if maps is node.tpdo else None
                    p.enabled = True
                    p.save()
        except (SdoAbortedError, SdoCommunicationError) as exc:
            raise NodeError(
                f"{a.where()}: set-up {step}: {exc}", node=a.node, axis=int(a.axis)
            ) from exc
        with self._lock:
            a.configured = True
            a.controlword = cia402.CW_DISABLE_VOLTAGE
            a.sync_base, a.answered = self._sync_seq, 0  # it answers the SYNCs after this
        node.nmt.send_command(cia402.NMT_START)

    def _check_factor(self, a: AxisTrack, key: str, mine: float, theirs: float, obj: str) -> None:
        if not math.isclose(mine, theirs, rel_tol=1e-9):
            raise NodeError(
                f"{a.where()}: drives.modules.{a.module}.{AXIS_NAMES[a.axis]}.{key} is {mine:g} "
                f"but the drive's {obj} says {theirs:g}: the units would be wrong",
                node=a.node,
                axis=int(a.axis),
            )

    def deactivate(self) -> None:
        with self._lock:
            if self._state != Lifecycle.ACTIVE:
                raise LifecycleError(f"deactivate() needs state active, not {self._state.value}")
        self.stop_all()
        with self._lock:
            if self._state == Lifecycle.ACTIVE:
                self._state = Lifecycle.INACTIVE
                self._fault_cause = None

    def shutdown(self) -> None:
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

    # ================================================================ transmit
    def _send(self, can_id: int, data: bytes, best_effort: bool = False) -> None:
        bus = self._bus
        if bus is None:
            raise LifecycleError("the bus is not open (call configure())")
        msg = can.Message(
            arbitration_id=can_id,
            data=data,
            is_extended_id=False,
            is_rx=False,
            channel=self.config.channel,
            timestamp=self.clock.wall(),
        )
        with self._tx_lock:
            try:
                bus.send(msg)
            except (can.CanError, OSError) as exc:
                with self._lock:
                    self._stats.send_errors += 1
                err = CanBusError(f"send 0x{can_id:03x} failed: {exc}")
                self._emit(EventKind.SEND_ERROR, Severity.WARNING, str(err))
                if not best_effort:
                    raise err from exc
                return
            self._log(msg)
            with self._lock:
                self._stats.tx_frames += 1

    def _log(self, msg: can.Message) -> None:
        recorder = self._recorder
        if recorder is not None:
            recorder.write(msg)
        if self._logger is not None:
            self._logger.write(msg, sample=recorder is None)

    def _send_rpdo(self, a: AxisTrack, targets: bool, best_effort: bool = False) -> None:
        """RPDO 2 (targets, if ``targets``) then RPDO 1 of ``a``: canopen packs them."""
        node = self._nodes[a.node]
        if targets:
            p2 = node.rpdo[2]
            p2[f"0x{cia402.TARGET_POSITION:04X}"].raw = a.target_position
            p2[f"0x{cia402.TARGET_VELOCITY:04X}"].raw = a.target_velocity
            self._send(p2.cob_id or cia402.RPDO_BASE[1] + a.node, bytes(p2.data), best_effort)
        p1 = node.rpdo[1]
        p1[f"0x{cia402.CONTROLWORD:04X}"].raw = a.controlword
        p1[f"0x{cia402.MODES_OF_OPERATION:04X}"].raw = int(a.mode)
        p1[f"0x{cia402.TARGET_TORQUE:04X}"].raw = a.target_torque
        self._send(p1.cob_id or cia402.RPDO_BASE[0] + a.node, bytes(p1.data), best_effort)

    # ================================================================ commands
    def _module(self, module: int) -> ModuleTrack:
        try:
            return self._modules[module]
        except KeyError:
            raise CanCommandError(
                f"module {module} is not configured (modules: {sorted(self._modules)})"
            ) from None

    def _require_active(self, what: str, a: AxisTrack | None = None) -> None:
        if self._state != Lifecycle.ACTIVE:
            at = f"{a.where()}: " if a else ""
            why = f" (stopped by a fault: {self._fault_cause})" if self._fault_cause else ""
            raise LifecycleError(f"{at}cannot {what} in state {self._state.value}{why}")

    def _command(self, what: str, module: int, axis: Axis, change: Callable[[AxisTrack], None],
                 targets: bool = True) -> None:  # fmt: skip
        mt = self._module(module)
        a = mt.axes[Axis(axis)]
        with self._tx_lock:
            self._require_active(what, a)
            with self._lock:
                before = a.mode
                change(a)
                if a.mode is not before:
                    a.mode_sync = self._sync_seq
                    a.refused_reported = False
            self._send_rpdo(a, targets)

    def enable(self, module: int, axis: Axis) -> None:
        def change(a: AxisTrack) -> None:
            if not a.enable:
                a.enable, a.enable_sync, a.refused_reported = True, self._sync_seq, False
            a.mode, a.target_torque = Mode.CYCLIC_SYNC_TORQUE, 0
            nxt = cia402.host_controlword(a.state, True, a.reset, a.controlword)
            if nxt is not None:
                a.controlword, a.t_controlword = nxt, self.clock.now()

        self._command("enable", module, axis, change)

    def clear_errors(self, module: int, axes: tuple[Axis, ...] = (Axis.STEER, Axis.WHEEL)) -> None:
        mt = self._module(module)
        self._require_active("clear errors")
        with self._lock:
            for ax in axes:
                a = mt.axes[Axis(ax)]
                # the code stays until the drive has left FAULT: a FAULT statusword
                # still on its way is then not taken for a new fault
                if a.state in (PowerState.FAULT, PowerState.FAULT_REACTION_ACTIVE) or a.error_code:
                    a.reset = True

    def set_limits(self, module: int, axis: Axis, max_torque: float, max_velocity: float) -> None:
        """Over SDO (a set-up step: 0x6072 max torque, 0x607F max profile velocity)."""
        mt = self._module(module)
        a = mt.axes[Axis(axis)]
        self._require_active("set limits", a)
        torque = min(a.torque_units(max_torque), 0xFFFF)
        velocity = min(a.to_units(max_velocity), 0xFFFFFFFF)
        if self._limits.get((module, int(axis))) == (torque, velocity):
            return
        node = self._nodes[a.node]
        try:
            node.sdo[cia402.MAX_TORQUE].raw = torque
            node.sdo[cia402.MAX_PROFILE_VELOCITY].raw = velocity
        except (SdoAbortedError, SdoCommunicationError) as exc:
            raise NodeError(f"{a.where()}: set limits: {exc}", node=a.node, axis=int(axis)) from exc
        self._limits[(module, int(axis))] = (torque, velocity)

    def set_position(self, module: int, axis: Axis, position: float) -> None:
        def change(a: AxisTrack) -> None:
            a.mode, a.target_position, a.target_torque = (
                Mode.CYCLIC_SYNC_POSITION, a.to_units(position), 0
            )  # fmt: skip

        self._command(f"set position {position:g}", module, axis, change)

    def set_velocity(self, module: int, axis: Axis, velocity: float) -> None:
        def change(a: AxisTrack) -> None:
            a.mode, a.target_velocity, a.target_torque = (
                Mode.CYCLIC_SYNC_VELOCITY, a.to_units(velocity), 0
            )  # fmt: skip

        self._command(f"set velocity {velocity:g}", module, axis, change)

    def set_torque(self, module: int, axis: Axis, torque: float) -> None:
        def change(a: AxisTrack) -> None:
            a.mode, a.target_torque = Mode.CYCLIC_SYNC_TORQUE, a.torque_units(torque)

        self._command(f"set torque {torque:g}", module, axis, change, targets=False)

    def hold(self, module: int, axis: Axis) -> None:
        """Cyclic synchronous position at the axis's latest position."""
        a = self._module(module).axes[Axis(axis)]
        if not math.isfinite(a.position):
            raise NodeError(f"{a.where()}: no position feedback, cannot hold it", node=a.node)
        self.set_position(module, axis, a.position)

    def free(self, module: int, axis: Axis) -> None:
        """Cyclic synchronous torque, target 0."""
        self.set_torque(module, axis, 0.0)

    def start_homing(self, module: int) -> None:
        """Mode 6 and the start edge of controlword bit 4 (sent by the power state machine
        once the modes display shows homing); ``homed`` once the drive reports homing
        attained *and* target reached.  An absolute steering is homed already."""
        mt = self._module(module)
        a = mt.steer
        self._require_active("start homing", a)
        if self.drives.axes()[module].steer.homing == ABSOLUTE:
            mt.homed, mt.homing = True, HomingState.DONE
            return

        def change(a: AxisTrack) -> None:
            a.mode = Mode.HOMING
            a.homing_start = True
            a.homing_sync = self._sync_seq
            mt.homing = HomingState.IN_PROGRESS

        self._command("start homing", module, Axis.STEER, change, targets=False)

    def stop_all(self) -> None:
        """Disable voltage and torque 0 to every axis (sent whenever the bus is open)."""
        with self._tx_lock:
            with self._lock:
                self._stats.stop_all_calls += 1
                for a in self._tracks():
                    a.enable = False
                    a.homing_start = False
                    a.reset = False
                    a.target_torque = 0
                    a.controlword = cia402.CW_DISABLE_VOLTAGE
                    a.t_controlword = self.clock.now()
                    a.enable_sync = -1
                bus_open = self._bus is not None and self._state in (
                    Lifecycle.INACTIVE,
                    Lifecycle.ACTIVE,
                )
            if not bus_open:
                return
            for a in self._tracks():
                if a.configured:  # (an axis never set up was never enabled)
                    self._send_rpdo(a, targets=False, best_effort=True)

    # ================================================================ receive + supervise
    def _io_loop(self) -> None:
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
                    self._flush()
            except (can.CanError, OSError, ValueError) as exc:
                if self._stop_io.is_set():
                    return
                self._on_listener_error(exc)
                self._stop_io.wait(IO_WAIT_MAX)
            except Exception as exc:
                self._on_listener_error(exc)

    def _io_hook(self, now: float) -> None:
        bus = self._bus
        if bus is None or self._stop_io.is_set():
            return
        try:
            self._io_step(bus)
        except Exception as exc:
            self._on_listener_error(exc)

    def _io_step(self, bus: can.BusABC) -> float:
        """Drain the receive queue (as the swpc kind's), then supervise at a time taken
        before the queue was found empty; returns the next deadline."""
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
        self._flush()
        return self._supervise(t_check)

    def _handle(self, msg: can.Message) -> None:
        clock = self.clock
        handled = clock.now()
        stamp = float(msg.timestamp or 0.0)
        t = frame_time(stamp, handled, clock.from_wall(stamp)) if stamp else handled
        t = self._last_arrival = max(t, self._last_arrival)
        self._log(msg)
        with self._lock:
            self._stats.rx_frames += 1
            if stamp:
                self._latency.append(clock.wall() - stamp)
        if msg.is_error_frame:
            with self._lock:
                self._stats.error_frames += 1
                if msg.arbitration_id & CAN_ERR_BUSOFF:
                    self._stats.bus_off += 1
                    self._pending.append(
                        Observation(EventKind.BUS_OFF, Severity.FAULT, "CAN bus-off")
                    )
                else:
                    self._pending.append(
                        Observation(
                            EventKind.ERROR_FRAME,
                            Severity.WARNING,
                            f"error frame class 0x{msg.arbitration_id:08x} "
                            f"data {bytes(msg.data).hex()}",
                        )
                    )
            return
        if msg.is_remote_frame or msg.is_extended_id or self._network is None:
            return
        self._arrival = t
        self._network.notify(msg.arbitration_id, bytearray(msg.data), t)

    # canopen's callbacks (on the I/O step's thread, from notify(); ``_arrival`` is the
    # frame's arrival on the clock)
    def _on_heartbeat(self, can_id: int, data: bytearray, timestamp: float) -> None:
        a = self._axes.get(can_id - cia402.HEARTBEAT_BASE)
        if a is None or not data:
            return
        with self._changed:
            self._pending += on_heartbeat(a, data[0] & 0x7F, self._arrival)
            self._changed.notify_all()

    def _emcy_callback(self, a: AxisTrack) -> Callable[[EmcyError], None]:
        return lambda e: self._on_emcy(a, e)

    def _on_emcy(self, a: AxisTrack, e: EmcyError) -> None:
        with self._changed:
            self._stats.node_faults += 1 if e.code & 0xFF00 else 0
            active = self._state == Lifecycle.ACTIVE
            self._pending += on_emcy(a, e.code, e.register, active)
            self._changed.notify_all()

    def _on_tpdo(self, module: int, a: AxisTrack, p: PdoMap) -> None:
        mt = self._modules[module]
        with self._changed:
            mt.feedback_frames += 1
            if p is self._nodes[a.node].tpdo[1]:
                sw = int(p[f"0x{cia402.STATUSWORD:04X}"].raw)
                pos = int(p[f"0x{cia402.POSITION_ACTUAL:04X}"].raw)
                disp = int(p[f"0x{cia402.MODES_DISPLAY:04X}"].raw)
                a.answered += 1
                seq = a.sync_base + a.answered
                self._pending += on_statusword(mt, a, sw, disp, pos, seq, self._arrival)
                s = pair(mt)
                if s is not None:
                    self._sample(mt, s)
            else:
                a.velocity = int(p[f"0x{cia402.VELOCITY_ACTUAL:04X}"].raw) / a.counts_per_rad
                a.torque = a.torque_si(int(p[f"0x{cia402.TORQUE_ACTUAL:04X}"].raw))
                ring = self._history[module]
                last = self._last.get(module)
                if len(ring) and last is not None and last.seq == a.seq:
                    vt = (mt.steer.velocity, mt.wheel.velocity, mt.steer.torque, mt.wheel.torque)
                    ring.set_last_velocity_torque(vt)
                    self._last[module] = dataclasses.replace(
                        last, steer_velocity=vt[0], wheel_velocity=vt[1], steer_torque=vt[2],
                        wheel_torque=vt[3],
                    )
            self._changed.notify_all()

    def _sample(self, mt: ModuleTrack, seq: int) -> None:
        t = max(mt.steer.t_feedback, mt.wheel.t_feedback)
        t_bus = self.clock.to_wall(t) if isinstance(self.clock, SimClock) else self.clock.wall()
        s = FeedbackSample(t, t_bus, seq & 0xFF, seq, mt.steer.position, mt.wheel.position)
        self._history[mt.module].append((t, t_bus, seq & 0xFF, seq, s.theta_hat, s.psi))
        self._last[mt.module] = s
        self._samples.append((mt.module, s))

    def _flush(self) -> None:
        """The observations and samples the frames of this step made: faults stop every
        axis first, then the callbacks."""
        with self._lock:
            obs, self._pending = self._pending, []
            samples, self._samples = self._samples, []
            callbacks = self._feedback_callbacks
        if obs:
            self._observed(obs)
        for module, s in samples:
            for fn in callbacks:
                try:
                    fn(module, s)
                except Exception as exc:
                    self._on_listener_error(exc)

    def _observed(self, obs: list[Observation]) -> None:
        with self._lock:
            recorded = [self._record(o) for o in obs]
            fault = next((e for e in recorded if e.severity is Severity.FAULT), None)
            was_active = fault is not None and self._begin_fault(fault.message)
        if fault is not None:
            self._fault_stop(was_active, recorded)
        else:
            for ev in recorded:
                self._notify(ev)

    def _supervise(self, now: float) -> float:
        cfg = self.config
        loss_after = cfg.heartbeat_loss_periods * cfg.heartbeat_period_s
        with self._lock:
            active = self._state == Lifecycle.ACTIVE
            d = supervise(
                list(self._tracks()),
                now,
                t_configured=self._configured_at,
                loss_after=loss_after,
                retry=max(3.0 / max(cfg.feedback_rate_hz, 1), 0.02),
                power_syncs=math.ceil(POWER_TIMEOUT_S * max(cfg.feedback_rate_hz, 1)),
                mode_syncs=math.ceil(MODE_TIMEOUT_S * max(cfg.feedback_rate_hz, 1)),
                sync_period=1.0 / max(cfg.feedback_rate_hz, 1),
                active=active,
            )
            self._stats.heartbeat_losses += len(d.lost)
        deadline = d.next_deadline
        if d.observations:
            self._observed(d.observations)
        if d.fault:
            return min(deadline, now + cfg.heartbeat_period_s)
        for a in d.send:
            with self._tx_lock, contextlib.suppress(CanError):
                if self._state == Lifecycle.ACTIVE:
                    self._send_rpdo(a, targets=False, best_effort=True)
        if self._kernel is None:
            if now >= self._next_heartbeat:
                f = self._heartbeat_frame()
                with contextlib.suppress(CanError):
                    self._send(f.arbitration_id, f.data, best_effort=True)
                self._next_heartbeat = max(self._next_heartbeat + cfg.refresh_period_s, now)
            deadline = min(deadline, self._next_heartbeat)
        elif now >= self._next_renewal:
            with self._tx_lock:
                self._kernel.renew()
            # the kernel counts host seconds: renew_every of them on this clock
            self._next_renewal = now + self._kernel.renew_every * self.clock.rate
            deadline = min(deadline, self._next_renewal)
        if self._sync_on:
            if now >= self._next_sync:
                with self._lock:
                    self._sync_seq += 1
                with contextlib.suppress(CanError):
                    self._send(cia402.SYNC_ID, b"", best_effort=True)
                period = 1.0 / max(cfg.feedback_rate_hz, 1)
                self._next_sync = max(self._next_sync + period, now - period)
            deadline = min(deadline, self._next_sync)
        return deadline

    # ================================================================ faults and events
    def _begin_fault(self, cause: str) -> bool:
        with self._lock:
            active = self._state == Lifecycle.ACTIVE
            if active:
                self._state = Lifecycle.INACTIVE
                self._fault_cause = cause
            return active

    def _fault_stop(self, was_active: bool, events: list[DriverEvent]) -> None:
        if was_active:
            try:
                self.stop_all()
            except CanError as exc:
                log.error("stop_all() after a fault failed: %s", exc)
        for ev in events:
            self._notify(ev)
        if was_active:
            self._emit(
                EventKind.STOPPED, Severity.INFO, "fault: every axis disabled; drives inactive"
            )
        with self._changed:
            self._changed.notify_all()

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

    def _emit(self, kind: EventKind, severity: Severity, message: str) -> None:
        self._notify(self._record(Observation(kind, severity, message)))

    def _record(self, obs: Observation) -> DriverEvent:
        ev = DriverEvent(
            self.clock.now(), obs.kind, obs.severity, obs.message, obs.module, obs.node, obs.axis
        )
        if obs.severity != Severity.INFO:
            log.warning("%s", obs.message)
        with contextlib.suppress(queue.Full):
            self._events.put_nowait(ev)
        return ev

    def _notify(self, ev: DriverEvent) -> None:
        for fn in self._event_callbacks:
            try:
                fn(ev)
            except Exception as exc:
                with self._lock:
                    self._stats.listener_errors += 1
                    self.last_exception = exc
                log.error("event callback %r raised %s", fn, exc)

    # ================================================================ observation
    def modules(self) -> list[int]:
        return list(self._modules)

    def module_state(self, module: int) -> ModuleState:
        mt = self._module(module)
        s, w = mt.steer, mt.wheel
        with self._lock:
            feedback = self._last.get(module)
            beats = [a.t_heartbeat for a in mt.axes if a.t_heartbeat is not None]
            return ModuleState(
                module=module,
                node=s.node,
                alive=s.alive and w.alive,
                states=(s.axis_state(), w.axis_state()),
                modes=(s.control_mode(), w.control_mode()),
                errors=(s.error_code, w.error_code),
                homed=mt.homed,
                homing=mt.homing,
                feedback=feedback,
                t_heartbeat=min(beats) if len(beats) == 2 else None,
                heartbeats=s.heartbeats + w.heartbeats,
                feedback_frames=mt.feedback_frames,
            )

    def history_arrays(self, module: int) -> dict[str, NDArray[np.float64]]:
        self._module(module)
        with self._lock:
            return self._history[module].columns()

    def history_since(
        self, module: int, cursor: int, since: float = -np.inf
    ) -> tuple[NDArray[np.float64], int]:
        self._module(module)
        with self._lock:
            rows, cursor = self._history[module].since(cursor)
        rows = rows[rows[:, 0] >= since] if since > -np.inf else rows
        return np.ascontiguousarray(rows[:, [0, 4, 5]]), cursor

    def wait_for(
        self,
        module: int,
        predicate: Callable[[ModuleState], bool],
        timeout: float,
        what: str = "condition",
    ) -> ModuleState:
        mt = self._module(module)
        deadline = self.clock.now() + timeout
        reached: list[ModuleState] = []

        def holds() -> bool:
            st = self.module_state(module)
            if predicate(st):
                reached.append(st)
                return True
            return False

        with self._changed:
            if wait_until(self.clock, self._changed, holds, deadline):
                return reached[-1]
        states = ", ".join(f"{a.where()} {a.state.value}" for a in mt.axes)
        raise NodeTimeoutError(
            f"module {module}: {what} not reached within {timeout} s ({states}, homed "
            f"{mt.homed})",
            node=mt.steer.node,
        )

    def stats(self) -> DriverStats:
        with self._lock:
            st = dataclasses.replace(self._stats)
        if self._kernel is not None:
            st.periodic_renewals = self._kernel.renewals
        return st

    def events(self) -> list[DriverEvent]:
        out: list[DriverEvent] = []
        while True:
            try:
                out.append(self._events.get_nowait())
            except queue.Empty:
                return out

    def add_feedback_callback(self, fn: Callable[[int, FeedbackSample], None]) -> None:
        with self._lock:
            self._feedback_callbacks = [*self._feedback_callbacks, fn]

    def add_event_callback(self, fn: Callable[[DriverEvent], None]) -> None:
        with self._lock:
            self._event_callbacks = [*self._event_callbacks, fn]

    def remove_event_callback(self, fn: Callable[[DriverEvent], None]) -> None:
        with self._lock:
            self._event_callbacks = [f for f in self._event_callbacks if f != fn]

    def threads(self) -> list[threading.Thread]:
        return [self._io_thread] if self._io_thread is not None else []

    def axis_track(self, module: int, axis: Axis) -> AxisTrack:
        """A copy of what the host knows of one axis (tests, diagnostics)."""
        with self._lock:
            return dataclasses.replace(self._module(module).axes[Axis(axis)])

    def sync_count(self) -> int:
        return self._sync_seq

    # ================================================================ recording
    def start_recording(self, path: str) -> None:
        with self._lock:
            if self._bus is None or self._state == Lifecycle.FINALIZED:
                raise LifecycleError("start_recording() needs an open bus (configure() first)")
        self.stop_recording()
        rec = Recorder(path)
        with self._lock:
            self._recorder = rec

    def stop_recording(self) -> str | None:
        with self._lock:
            rec, self._recorder = self._recorder, None
        if rec is None:
            return None
        rec.stop()
        return rec.error

    def log_error(self) -> str | None:
        return None if self._logger is None else self._logger.error

