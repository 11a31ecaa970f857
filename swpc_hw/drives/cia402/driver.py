"""The ``cia402`` drive kind: CiA 402 drives over CANopen, on the ``canopen`` library.

One single-axis drive per axis (a module's steering and wheel on two nodes).  canopen does
SDO, PDO, NMT and EMCY (:class:`canopen.Network` with one
:class:`~swpc_hw.drives.cia402.sdo.ClockedRemoteNode` per axis); this module is
:class:`swpc_hw.drives.base.DriverBase` (the lifecycle, the I/O step, the fault path)
with the kind's receive path (it feeds :meth:`canopen.Network.notify` itself: no notifier
thread, so that in lockstep every frame is handled on the clock), the set-up
(:mod:`swpc_hw.drives.cia402.setup`) and the pure cores of
:mod:`swpc_hw.drives.cia402.tracking`, :mod:`~swpc_hw.drives.cia402.pdo` (the process
data), :mod:`~swpc_hw.drives.cia402.commands` and :mod:`~swpc_hw.drives.cia402.status`;
canopen's side outside the set-up is :mod:`swpc_hw.drives.cia402.network`.

Lifecycle
---------
* ``configure()``: open the bus, start the I/O step (the driver's thread on a real clock,
  a :class:`~swpc_hw.clock.SimClock` hook in lockstep) and the host's heartbeat (node
  ``drives.host_node``, every ``refresh_period_s``; on SocketCAN from the kernel with the
  dead-man of :class:`swpc_hw.drives.periodic.KernelRefresh`, renewed by the I/O step).
* ``activate()``: every drive's heartbeat seen; once per boot of a drive, its set-up over
  SDO (PRE-OPERATIONAL): heartbeat producer 0x1017 = ``heartbeat_period_s``, heartbeat
  consumer 0x1016 on the host's heartbeat with the command watchdog
  (``watchdog_timeout_ms``) as its time (or node guarding on a drive without 0x1016: the
  host asks its state every ``refresh_period_s``), quick-stop option 0x605A, homing method 0x6098,
  the motor's rated torque 0x6076 read, the factor group (0x608F, 0x6091) and the modes
  (0x6502) checked against the config, the PDO mapping of
  :data:`firmware_protocol.cia402.RPDO_MAP` / :data:`~firmware_protocol.cia402.TPDO_MAP`
  written (before anything uses it); then NMT start and OPERATIONAL seen on every
  heartbeat; the SYNC (``feedback_rate_hz``) runs from then on.
* commands: RPDO 2 (targets) then RPDO 1 (controlword, mode, torque); the power state
  machine moves one transition per statusword (:func:`~swpc_hw.drives.cia402.tracking.
  supervise`); steering and held wheels in cyclic synchronous position, wheel torque in
  cyclic synchronous torque, "free" a torque of 0 (a drive without a torque mode: its
  power stage off), homing in mode 6.
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
import functools
import math
from collections.abc import Callable, Iterator

import can
from canopen.emcy import EmcyError
from canopen.pdo.base import PdoMap

from firmware_protocol import cia402
from firmware_protocol.cia402 import PowerState
from firmware_protocol.codec import Axis, Frame, HomingState
from swpc_hw.clock import SYSTEM_CLOCK, Clock, SimClock
from swpc_hw.drives.base import DriverBase
from swpc_hw.drives.bus import CanConfig
from swpc_hw.drives.cia402 import commands, status
from swpc_hw.drives.cia402.commands import MODE_TIMEOUT_S, POWER_TIMEOUT_S
from swpc_hw.drives.cia402.config import ABSOLUTE, Cia402Drives
from swpc_hw.drives.cia402.network import (
    HostNetwork,
    answers,
    fault_at_start,
    guard_frame,
    heartbeat_frame,
    read_eds,
    remote_node,
    unreachable,
    write_limits,
    write_mode,
)
from swpc_hw.drives.cia402.pdo import (
    command_frames,
    on_tpdo,
    streams_targets,
    target_frames,
    with_velocity_torque,
)
from swpc_hw.drives.cia402.sdo import ClockedRemoteNode
from swpc_hw.drives.cia402.setup import set_up
from swpc_hw.drives.cia402.tracking import AxisTrack, ModuleTrack, on_emcy, on_heartbeat, supervise
from swpc_hw.drives.errors import (
    CanBusError,
    CanError,
    NodeError,
    NodeTimeoutError,
)
from swpc_hw.drives.tracking import FeedbackRing, Supervision, error_frame
from swpc_hw.drives.types import (
    AxisStatus,
    EventKind,
    FeedbackSample,
    Lifecycle,
    ModuleState,
    Observation,
    Severity,
)


class Cia402Driver(DriverBase):
    """The robot's CiA 402 drives on one bus (module docstring)."""

    thread_name = "swpc-cia402-io"
    kernel_always = True  # the kernel carries the host's heartbeat from configure() on
    silent_until_set_up = True  # 0x1017 = 0 from the factory
    stopped_message = "fault: every axis disabled; drives inactive"

    def __init__(
        self, drives: Cia402Drives, config: CanConfig, *, clock: Clock = SYSTEM_CLOCK
    ) -> None:
        super().__init__(config, clock=clock)
        self.drives = drives
        self._modules = status.module_tracks(drives)
        self._axes = {a.node: a for mt in self._modules.values() for a in mt.axes}
        self._history = {m: FeedbackRing(config.history_len) for m in self._modules}
        self._last: dict[int, FeedbackSample] = {}
        self._network: HostNetwork | None = None
        self._nodes: dict[int, ClockedRemoteNode] = {}
        self._next_heartbeat = 0.0
        self._sync_on = False
        self._sync_seq = 0
        self._next_sync = math.inf
        self._pending: list[Observation] = []  # observed by canopen callbacks in a step
        self._samples: list[tuple[int, FeedbackSample]] = []
        self._resend: list[AxisTrack] = []  # RPDO 1 due again (supervise)
        self._limits: dict[tuple[int, int], tuple[int, int]] = {}
        self._arrival = 0.0  # the arrival of the frame being handled (canopen's callbacks)
        self._said: set[str] = set()

    # ================================================================ lifecycle
    def _before_open(self) -> None:
        read_eds(self.drives)

    def _opened(self, bus: can.BusABC) -> None:
        """canopen's network on the bus, a remote node per axis; the host's heartbeat
        from the kernel on SocketCAN."""
        cfg = self.config
        net = self._network = HostNetwork(bus, self._send)
        for m, mt in self._modules.items():
            for a in mt.axes:
                node = remote_node(self.drives, a, self.clock, cfg.loss_after_s)
                net.add_node(node)
                self._nodes[a.node] = node
                net.subscribe(cia402.HEARTBEAT_BASE + a.node, self._on_heartbeat)
                node.emcy.add_callback(functools.partial(self._on_emcy, a))
                for i in node.tpdo.map or {}:  # the ones swpc maps (a.tpdos): at set-up
                    node.tpdo[i].add_callback(lambda p, a=a, m=m, i=i: self._on_tpdo(m, a, i, p))
        if self._kernel is not None:
            host = self.drives.host_node
            self._kernel.set_node(host, [heartbeat_frame(host)])
        self._next_heartbeat = self._next_renewal = self._configured_at

    def _bring_up(self) -> None:
        """Each drive not set up since its boot reached (:meth:`_reach`), set up
        (:mod:`swpc_hw.drives.cia402.setup`) and watched from its first heartbeat after;
        every drive not OPERATIONAL (just set up, or left PRE-OPERATIONAL by a
        communication error, 0x1029's default) started; OPERATIONAL on every heartbeat.
        :class:`NodeTimeoutError` names the silent drives, :class:`NodeError` a drive whose
        set-up failed (the object and why)."""
        cfg = self.config
        for a in self._tracks():
            if not a.configured:
                self._reach(a)
                for note in set_up(self._nodes[a.node], a, self.drives, cfg):
                    self._say_once(a, note)
                with self._lock:
                    a.configured = True
                    a.controlword = cia402.CW_DISABLE_VOLTAGE
                if a.guarded and self._kernel is not None:
                    with self._tx_lock:  # its guard requests from the kernel, as the heartbeat
                        self._kernel.set_node(a.node, [guard_frame(a)])
        for a in self._tracks():
            if a.nmt != cia402.NMT_OPERATIONAL:
                with self._lock:
                    a.sync_base, a.answered = self._sync_seq, 0  # it answers the SYNCs after
                    a.statusword_seen = False
                self._nodes[a.node].nmt.send_command(cia402.NMT_START)
        self._wait_axes(
            "a heartbeat after its set-up (0x1017)", lambda a: a.watched, cfg.activate_timeout_s
        )
        self._wait_axes(
            "NMT OPERATIONAL", lambda a: a.nmt == cia402.NMT_OPERATIONAL, cfg.activate_timeout_s
        )

    def _say_once(self, a: AxisTrack, note: str) -> None:
        """What a drive lacks and swpc does without: an event, once per service."""
        if note in self._said:
            return
        self._said.add(note)
        obs = Observation(EventKind.SET_UP, Severity.INFO, note, a.module, a.node, a.axis)
        self._observed([obs])

    def _reach(self, a: AxisTrack) -> None:
        """The drive answers an SDO request (0x1000): a drive from the factory sends no
        heartbeat, and one powered before the service missed its boot-up.  If it does not
        (NMT STOPPED, or busy booting), NMT reset communication to it and its boot-up
        awaited, then asked again; :class:`NodeTimeoutError` if still nothing."""
        node = self._nodes[a.node]
        if answers(node):
            return
        t0 = self.clock.now()
        node.nmt.send_command(cia402.NMT_RESET_COMMUNICATION)
        timeout = self.config.activate_timeout_s
        with contextlib.suppress(NodeTimeoutError):
            self._wait_all(
                "a boot-up", lambda: [a], lambda x: (x.t_boot or -math.inf) >= t0,
                lambda x: x.where(), timeout,
            )  # fmt: skip
        if not answers(node):
            raise unreachable(a, timeout, self.config.channel)

    def _activated(self) -> None:
        """The SYNC (``feedback_rate_hz``) runs from now on; an axis known to be in FAULT
        (from an earlier run, or its EMCY) is reset (:meth:`_after_activate` waits)."""
        if not self._sync_on:
            self._sync_on = True
            self._next_sync = self.clock.now()
        for a in self._tracks():
            a.refused_reported = False
            commands.clear_fault(a)

    def _after_activate(self) -> None:
        """A statusword from every drive; a fault present at start reset (the first
        statusword asks for it, :func:`~swpc_hw.drives.cia402.tracking.on_statusword`),
        and :class:`NodeError` with the drive's error code (0x603F) if it does not clear."""
        self._wait_axes(
            "a statusword", lambda a: a.statusword_seen, self.config.activate_timeout_s
        )
        faulted = (PowerState.FAULT, PowerState.FAULT_REACTION_ACTIVE)
        try:
            self._wait_axes("a fault reset", lambda a: a.state not in faulted, POWER_TIMEOUT_S)
        except NodeTimeoutError:
            for a in self._tracks():
                if a.state in faulted:
                    raise fault_at_start(self._nodes[a.node], a, POWER_TIMEOUT_S) from None
            raise

    def _tracks(self) -> Iterator[AxisTrack]:
        for mt in self._modules.values():
            yield from mt.axes

    def _wait_axes(self, what: str, ok: Callable[[AxisTrack], bool], timeout: float) -> None:
        self._wait_all(what, self._tracks, ok, lambda a: a.where(), timeout)

    # ================================================================ transmit
    def _send(self, can_id: int, data: bytes, best_effort: bool = False) -> None:
        """One frame (canopen's, the host's heartbeat, SYNC); a failed send is counted and
        reported, and raised unless ``best_effort``."""
        try:
            self._send_frames([Frame(can_id, bytes(data))], best_effort)
        except CanBusError:
            if not best_effort:
                raise

    def _send_rpdo(self, a: AxisTrack, targets: bool, best_effort: bool = False) -> None:
        """The targets' RPDOs (if ``targets``) then the command's of ``a``: canopen packs
        them (:mod:`swpc_hw.drives.cia402.pdo`)."""
        if targets:
            self._send_targets(a, best_effort)
        for f in command_frames(self._nodes[a.node], a):
            self._send(f.arbitration_id, f.data, best_effort)

    def _send_targets(self, a: AxisTrack, best_effort: bool = False) -> None:
        """The targets' RPDOs of ``a`` (RPDO 2 on most drives): position and velocity."""
        for f in target_frames(self._nodes[a.node], a):
            self._send(f.arbitration_id, f.data, best_effort)

    def _stream_targets(self) -> None:
        """Before each SYNC, the targets to every axis whose cyclic synchronous mode is in
        force (:func:`~swpc_hw.drives.cia402.pdo.streams_targets`)."""
        with self._tx_lock:
            if self._state != Lifecycle.ACTIVE:
                return
            for a in self._tracks():
                if streams_targets(a):
                    with contextlib.suppress(CanError):
                        self._send_targets(a, best_effort=True)

    # ================================================================ commands
    def _module(self, module: int) -> ModuleTrack:
        return self._configured(self._modules, module)

    def _command(self, what: str, module: int, axis: Axis, change: Callable[[AxisTrack], None],
                 targets: bool = True) -> None:  # fmt: skip
        """``change`` (a core of :mod:`swpc_hw.drives.cia402.commands`) to the axis under
        the lock, then its RPDOs."""
        mt = self._module(module)
        a = mt.axes[Axis(axis)]
        with self._tx_lock:
            self._require_active(what, a.where())
            with self._lock:
                before = a.mode
                change(a)
                changed = commands.mode_changed(a, before, self._sync_seq)
            if not (changed and a.mode_by_sdo):
                self._send_rpdo(a, targets)
                return
        # the mode over SDO first, outside the transmit lock (its answer comes through the
        # I/O step, which takes that lock), then the targets and the controlword
        write_mode(self._nodes[a.node], a)
        with self._tx_lock:
            self._send_rpdo(a, targets)

    def enable(self, module: int, axis: Axis) -> None:
        """Closed loop at torque 0; a drive without a torque mode is free with its power
        stage off instead, powered by the next position, velocity or homing command."""

        def change(a: AxisTrack) -> None:
            commands.enable(a, self._sync_seq, self.clock.now)

        self._command("enable", module, axis, change)

    def clear_errors(self, module: int, axes: tuple[Axis, ...] = (Axis.STEER, Axis.WHEEL)) -> None:
        mt = self._module(module)
        self._require_active("clear errors")
        with self._lock:
            for ax in axes:
                commands.clear_fault(mt.axes[Axis(ax)])

    def set_limits(self, module: int, axis: Axis, max_torque: float, max_velocity: float) -> None:
        """Over SDO (a set-up step: 0x6072 max torque, 0x607F max profile velocity, each
        where the drive has it), and applied by the host to every torque and velocity it
        commands (a drive without them has only the host's)."""
        mt = self._module(module)
        a = mt.axes[Axis(axis)]
        self._require_active("set limits", a.where())
        a.max_torque, a.max_velocity = abs(max_torque), abs(max_velocity)
        torque = min(a.torque_units(max_torque), 0xFFFF) if a.torque_mode is not None else 0
        velocity = min(a.to_units(max_velocity), 0xFFFFFFFF)
        if self._limits.get((module, int(axis))) == (torque, velocity):
            return
        say = functools.partial(self._say_once, a)
        write_limits(self._nodes[a.node], a, torque, velocity, say)
        self._limits[(module, int(axis))] = (torque, velocity)

    def set_position(self, module: int, axis: Axis, position: float) -> None:
        def change(a: AxisTrack) -> None:
            commands.position(a, position, self._sync_seq)

        self._command(f"set position {position:g}", module, axis, change)

    def set_velocity(self, module: int, axis: Axis, velocity: float) -> None:
        def change(a: AxisTrack) -> None:
            commands.velocity(a, velocity, self._sync_seq)

        self._command(f"set velocity {velocity:g}", module, axis, change)

    def set_torque(self, module: int, axis: Axis, torque: float) -> None:
        def change(a: AxisTrack) -> None:
            commands.torque(a, torque)

        self._command(f"set torque {torque:g}", module, axis, change, targets=False)

    def hold(self, module: int, axis: Axis) -> None:
        """Cyclic synchronous position at the axis's latest position."""
        a = self._module(module).axes[Axis(axis)]
        if not math.isfinite(a.position):
            raise NodeError(f"{a.where()}: no position feedback, cannot hold it", node=a.node)
        self.set_position(module, axis, a.position)

    def free(self, module: int, axis: Axis) -> None:
        """Its torque mode, target 0; without one, its power stage off (disable voltage:
        no torque, the axis turns freely and its encoder still reports)."""
        a = self._module(module).axes[Axis(axis)]
        if a.torque_mode is not None:
            self.set_torque(module, axis, 0.0)
            return
        self._command("free", module, axis, commands.unpower, targets=False)

    def start_homing(self, module: int) -> None:
        """Mode 6 and the start edge of controlword bit 4 (sent by the power state machine
        once the modes display shows homing); ``homed`` once the drive reports homing
        attained *and* target reached.  An absolute steering is homed already."""
        mt = self._module(module)
        a = mt.steer
        self._require_active("start homing", a.where())
        if self.drives.axes()[module].steer.homing == ABSOLUTE:
            mt.homed, mt.homing = True, HomingState.DONE
            return

        def change(a: AxisTrack) -> None:
            commands.homing(mt, a, self._sync_seq)

        self._command("start homing", module, Axis.STEER, change, targets=False)

    def _stopping(self) -> None:
        for a in self._tracks():
            commands.stop(a, self.clock.now())

    def _stop_frames(self) -> list[Frame]:
        """Disable voltage and torque 0 (RPDO 1) to every axis set up (an axis never set
        up was never enabled); the host's heartbeat goes on."""
        return [f for a in self._tracks() if a.configured
                for f in command_frames(self._nodes[a.node], a)]  # fmt: skip

    # ================================================================ receive + supervise
    def _receive(self, msg: can.Message, t: float) -> None:
        """One frame to canopen (its callbacks below collect what it tells; handled once
        the step's frames are in, :meth:`_drained`), error frames here."""
        clock = self.clock
        stamp = float(msg.timestamp or 0.0)
        with self._lock:
            self._stats.rx_frames += 1
            if stamp:
                self._latency.append(clock.wall() - stamp)
        if msg.is_error_frame:
            with self._lock:
                self._pending.append(error_frame(msg, self._stats))
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

    def _on_emcy(self, a: AxisTrack, e: EmcyError) -> None:
        with self._changed:
            self._stats.node_faults += 1 if e.code & 0xFF00 else 0
            active = self._state == Lifecycle.ACTIVE
            self._pending += on_emcy(a, e.code, e.register, active)
            self._changed.notify_all()

    def _on_tpdo(self, module: int, a: AxisTrack, i: int, p: PdoMap) -> None:
        """TPDO ``i`` of ``a`` (:func:`~swpc_hw.drives.cia402.pdo.on_tpdo`): the module's
        sample once both axes answered a SYNC, its velocities and torques once in."""
        mt = self._modules[module]
        with self._changed:
            got = on_tpdo(mt, a, i, p, self._arrival)
            self._pending += got.observations
            if got.sample is not None:
                self._sample(mt, got.sample)
            ring = self._history[module]
            if got.velocity_torque and len(ring):
                s = with_velocity_torque(mt, a, self._last.get(module))
                if s is not None:
                    vt = (s.steer_velocity, s.wheel_velocity, s.steer_torque, s.wheel_torque)
                    ring.set_last_velocity_torque(vt)
                    self._last[module] = s
            self._changed.notify_all()

    def _sample(self, mt: ModuleTrack, seq: int) -> None:
        t = max(mt.steer.t_feedback, mt.wheel.t_feedback)
        t_bus = self.clock.to_wall(t) if isinstance(self.clock, SimClock) else self.clock.wall()
        s = FeedbackSample(t, t_bus, seq & 0xFF, seq, mt.steer.position, mt.wheel.position)
        self._history[mt.module].append((t, t_bus, seq & 0xFF, seq, s.theta_hat, s.psi))
        self._last[mt.module] = s
        self._samples.append((mt.module, s))

    def _drained(self) -> None:
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

    def _check(self, now: float, active: bool) -> Supervision:
        cfg = self.config
        rate = max(cfg.feedback_rate_hz, 1)
        d = supervise(
            list(self._tracks()),
            now,
            loss_after=cfg.loss_after_s,
            retry=max(3.0 / rate, 0.02),
            power_syncs=math.ceil(POWER_TIMEOUT_S * rate),
            mode_syncs=math.ceil(MODE_TIMEOUT_S * rate),
            sync_period=1.0 / rate,
            active=active,
            sync_seq=self._sync_seq,
        )
        self._resend = d.send
        return Supervision(d.observations, len(d.lost), d.fault, [], d.next_deadline)

    def _keep_alive(self, now: float, active: bool) -> float:
        """The controlwords due again, the host's heartbeat (unless from the kernel), the
        SYNC."""
        cfg = self.config
        resend, self._resend = self._resend, []
        for a in resend:
            with self._tx_lock, contextlib.suppress(CanError):
                if self._state == Lifecycle.ACTIVE:
                    self._send_rpdo(a, targets=False, best_effort=True)
        deadline = math.inf
        if self._kernel is None:
            if now >= self._next_heartbeat:
                frames = [heartbeat_frame(self.drives.host_node)] + [
                    guard_frame(a) for a in self._tracks() if a.guarded and a.configured
                ]
                with contextlib.suppress(CanError):
                    self._send_frames(frames, best_effort=True)
                self._next_heartbeat = max(self._next_heartbeat + cfg.refresh_period_s, now)
            deadline = self._next_heartbeat
        if self._sync_on:
            if now >= self._next_sync:
                self._stream_targets()
                with self._lock:
                    self._sync_seq += 1
                with contextlib.suppress(CanError):
                    self._send(cia402.SYNC_ID, b"", best_effort=True)
                period = 1.0 / max(cfg.feedback_rate_hz, 1)
                self._next_sync = max(self._next_sync + period, now - period)
            deadline = min(deadline, self._next_sync)
        return deadline

    # ================================================================ observation
    def modules(self) -> list[int]:
        return list(self._modules)

    def module_state(self, module: int) -> ModuleState:
        mt = self._module(module)
        with self._lock:
            return status.module_state(mt, self._last.get(module))

    def _ring(self, module: int) -> FeedbackRing:
        self._module(module)
        return self._history[module]

    def _not_reached(self, module: int, what: str, timeout: float) -> NodeTimeoutError:
        mt = self._module(module)
        with self._lock:
            return status.not_reached(mt, what, timeout)

    def axis_status(self, module: int, axis: Axis) -> AxisStatus:
        """What the host knows now of one axis' drive (the console's drives view): its
        power state, NMT state, modes display and error code, in CiA 402's words."""
        mt = self._module(module)
        with self._lock:
            return status.axis_status(mt, mt.axes[Axis(axis)])

    def axis_track(self, module: int, axis: Axis) -> AxisTrack:
        """A copy of what the host knows of one axis (tests, diagnostics)."""
        with self._lock:
            return dataclasses.replace(self._module(module).axes[Axis(axis)])

    def sync_count(self) -> int:
        return self._sync_seq
