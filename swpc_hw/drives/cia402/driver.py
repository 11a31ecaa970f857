"""The ``cia402`` drive kind: CiA 402 drives over CANopen, on the ``canopen`` library.

One single-axis drive per axis (a module's steering and wheel on two nodes).  canopen does
SDO, PDO, NMT and EMCY (:class:`canopen.Network` with one
:class:`~swpc_hw.drives.cia402.sdo.ClockedRemoteNode` per axis); this module is
:class:`swpc_hw.drives.base.DriverBase` (the lifecycle, the I/O step, the fault path)
with the kind's receive path (it feeds :meth:`canopen.Network.notify` itself: no notifier
thread, so that in lockstep every frame is handled on the clock), the set-up
(:mod:`swpc_hw.drives.cia402.setup`) and the pure cores of
:mod:`swpc_hw.drives.cia402.tracking`.

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
import math
from collections.abc import Callable, Iterator

import can
import canopen
from canopen.emcy import EmcyError
from canopen.pdo.base import PdoMap
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from firmware_protocol import cia402
from firmware_protocol.cia402 import Mode, PowerState
from firmware_protocol.codec import Axis, Frame, HomingState
from swpc_hw.clock import SYSTEM_CLOCK, Clock, SimClock
from swpc_hw.drives.base import DriverBase
from swpc_hw.drives.bus import CanConfig
from swpc_hw.drives.cia402.config import ABSOLUTE, Cia402Drives
from swpc_hw.drives.cia402.sdo import ClockedRemoteNode
from swpc_hw.drives.cia402.setup import OPTIONAL, PROFILE_VELOCITY, set_up
from swpc_hw.drives.cia402.tracking import (
    AxisTrack,
    ModuleTrack,
    on_emcy,
    on_heartbeat,
    on_statusword,
    pair,
    supervise,
)
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

POWER_TIMEOUT_S = 1.0
"""An axis asked to enable that has not followed a step's controlword toward OPERATION
ENABLED in a statusword answering a SYNC sent this long after it has refused (robot time,
in SYNC periods; :func:`~swpc_hw.drives.cia402.tracking.supervise`)."""
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
        self._network: _HostNetwork | None = None
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
        for eds in self.drives.eds_files():
            try:
                canopen.import_od(str(eds))
            except Exception as exc:
                raise CanBusError(
                    f"drives.object_dictionary {eds}: cannot read it as an EDS/DCF: {exc}"
                ) from exc

    def _opened(self, bus: can.BusABC) -> None:
        """canopen's network on the bus, a remote node per axis; the host's heartbeat
        from the kernel on SocketCAN."""
        cfg = self.config
        net = self._network = _HostNetwork(self, bus)
        for m, mt in self._modules.items():
            for a in mt.axes:
                mc = self.drives.axes()[m]
                node = ClockedRemoteNode(
                    a.node,
                    str(self.drives.eds(mc.steer if a.axis == Axis.STEER else mc.wheel)),
                    self.clock,
                    timeout=cfg.loss_after_s,
                )
                net.add_node(node)
                self._nodes[a.node] = node
                net.subscribe(cia402.HEARTBEAT_BASE + a.node, self._on_heartbeat)
                node.emcy.add_callback(self._emcy_callback(a))
                for i in node.tpdo.map or {}:  # the ones swpc maps (a.tpdos): at set-up
                    node.tpdo[i].add_callback(lambda p, a=a, m=m, i=i: self._on_tpdo(m, a, i, p))
        if self._kernel is not None:
            self._kernel.set_node(self.drives.host_node, [self._heartbeat_frame()])
        self._next_heartbeat = self._next_renewal = self._configured_at

    @staticmethod
    def _guard_frame(a: AxisTrack) -> Frame:
        """Node guarding's request of ``a``'s state (a remote frame, 1 byte)."""
        return Frame(cia402.HEARTBEAT_BASE + a.node, b"\x00", remote=True)

    def _heartbeat_frame(self) -> Frame:
        host = self.drives.host_node
        return Frame(cia402.HEARTBEAT_BASE + host, bytes([cia402.NMT_OPERATIONAL]))

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
                        self._kernel.set_node(a.node, [self._guard_frame(a)])
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
        if self._answers(node):
            return
        t0 = self.clock.now()
        node.nmt.send_command(cia402.NMT_RESET_COMMUNICATION)
        timeout = self.config.activate_timeout_s
        with contextlib.suppress(NodeTimeoutError):
            self._wait_all(
                "a boot-up", lambda: [a], lambda x: (x.t_boot or -math.inf) >= t0,
                lambda x: x.where(), timeout,
            )  # fmt: skip
        if not self._answers(node):
            raise NodeTimeoutError(
                f"{a.where()}: no answer to an SDO request (0x1000) and no boot-up after NMT "
                f"reset communication within {timeout:g} s: check its power, its wiring "
                f"to this bus ({self.config.channel}) and its node id",
                node=a.node,
            )

    @staticmethod
    def _answers(node: ClockedRemoteNode) -> bool:
        try:
            node.sdo.upload(cia402.DEVICE_TYPE, 0)
        except SdoCommunicationError:
            return False
        except SdoAbortedError:
            pass  # an abort is an answer
        return True

    def _activated(self) -> None:
        """The SYNC (``feedback_rate_hz``) runs from now on; an axis known to be in FAULT
        (from an earlier run, or its EMCY) is reset (:meth:`_after_activate` waits)."""
        if not self._sync_on:
            self._sync_on = True
            self._next_sync = self.clock.now()
        faulted = (PowerState.FAULT, PowerState.FAULT_REACTION_ACTIVE)
        for a in self._tracks():
            a.refused_reported = False
            if a.state in faulted or a.error_code:
                a.reset = True

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
                    raise NodeError(
                        f"{a.where()}: in FAULT since before the run, and a fault reset did "
                        f"not clear it within {POWER_TIMEOUT_S:g} s: {self._error_code(a)}; "
                        "its cause is still there (the drive's manual says what each code "
                        "needs)",
                        node=a.node,
                        axis=int(a.axis),
                    ) from None
            raise

    def _error_code(self, a: AxisTrack) -> str:
        """The drive's error code 0x603F, named (or the one its EMCY gave)."""
        code = a.error_code
        if cia402.ERROR_CODE in self._nodes[a.node].object_dictionary:
            with contextlib.suppress(SdoAbortedError, SdoCommunicationError):
                code = int(self._nodes[a.node].sdo[cia402.ERROR_CODE].raw)
        return f"error code 0x603F = 0x{code:04X} ({cia402.emcy_name(code)})"

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
        them."""
        if targets:
            self._send_targets(a, best_effort)
        for f in self._command_frames(a):
            self._send(f.arbitration_id, f.data, best_effort)

    def _pdo_frames(self, a: AxisTrack, group: int, values: dict[int, int]) -> list[Frame]:
        """The RPDOs of one group of ``a`` (:attr:`AxisTrack.rpdos`), each object it maps
        set from ``values`` (an object the drive lacks is in no map)."""
        out = []
        for i in a.rpdos[group]:
            p = self._nodes[a.node].rpdo[i]
            for v in p.map:
                if v.index in values:
                    p[f"0x{v.index:04X}"].raw = values[v.index]
            out.append(Frame(p.cob_id or cia402.RPDO_BASE[i - 1] + a.node, bytes(p.data)))
        return out

    def _send_targets(self, a: AxisTrack, best_effort: bool = False) -> None:
        """The targets' RPDOs of ``a`` (RPDO 2 on most drives): position and velocity."""
        values = {cia402.TARGET_POSITION: a.target_position,
                  cia402.TARGET_VELOCITY: a.target_velocity}  # fmt: skip
        for f in self._pdo_frames(a, 1, values):
            self._send(f.arbitration_id, f.data, best_effort)

    def _stream_targets(self) -> None:
        """Before each SYNC, RPDO 2 to every axis whose cyclic synchronous mode is in force:
        such a drive takes the target received in each SYNC cycle, and extrapolates or
        holds when none came (CiA 402), so the target is sent every cycle, not only when
        it changes; before the mode is in force a target is not taken."""
        cyclic = (Mode.CYCLIC_SYNC_POSITION, Mode.CYCLIC_SYNC_VELOCITY)
        with self._tx_lock:
            if self._state != Lifecycle.ACTIVE:
                return
            for a in self._tracks():
                enabled = a.state is PowerState.OPERATION_ENABLED
                if a.enable and enabled and a.mode in cyclic and a.mode_display == a.mode:
                    with contextlib.suppress(CanError):
                        self._send_targets(a, best_effort=True)

    def _command_frames(self, a: AxisTrack) -> list[Frame]:
        """The command's RPDOs of ``a`` (RPDO 1 on most drives): controlword, mode (unless
        over SDO), target torque (where it has a torque mode)."""
        values = {cia402.CONTROLWORD: a.controlword, cia402.MODES_OF_OPERATION: int(a.mode),
                  cia402.TARGET_TORQUE: a.target_torque}  # fmt: skip
        return self._pdo_frames(a, 0, values)

    # ================================================================ commands
    def _module(self, module: int) -> ModuleTrack:
        return self._configured(self._modules, module)

    def _command(self, what: str, module: int, axis: Axis, change: Callable[[AxisTrack], None],
                 targets: bool = True) -> None:  # fmt: skip
        mt = self._module(module)
        a = mt.axes[Axis(axis)]
        with self._tx_lock:
            self._require_active(what, a.where())
            with self._lock:
                before = a.mode
                change(a)
                changed = a.mode is not before
                if changed:
                    a.mode_sync = self._sync_seq
                    a.refused_reported = False
                    a.pp_acked = None  # profile position: the first target handed over
            if not (changed and a.mode_by_sdo):
                self._send_rpdo(a, targets)
                return
        # the mode over SDO first, outside the transmit lock (its answer comes through the
        # I/O step, which takes that lock), then the targets and the controlword
        self._write_mode(a)
        with self._tx_lock:
            self._send_rpdo(a, targets)

    def _write_mode(self, a: AxisTrack) -> None:
        """0x6060 over SDO (a drive on which it is not PDO-mappable)."""
        try:
            self._nodes[a.node].sdo[cia402.MODES_OF_OPERATION].raw = int(a.mode)
        except (SdoAbortedError, SdoCommunicationError) as exc:
            raise NodeError(
                f"{a.where()}: mode {cia402.mode_name(a.mode)} (0x6060 over SDO): {exc}",
                node=a.node, axis=int(a.axis),
            ) from exc  # fmt: skip

    def _power(self, a: AxisTrack) -> None:
        """OPERATION ENABLED asked (the power state machine moves one step per
        statusword)."""
        if not a.enable:
            a.enable, a.refused_reported = True, False
            a.enable_sync = a.enable_start = self._sync_seq
        a.unpowered = False

    def _powered(self, a: AxisTrack) -> None:
        """A command to an axis freed without a torque mode powers it again; one stopped
        stays off until :meth:`enable`."""
        if a.unpowered:
            self._power(a)

    def enable(self, module: int, axis: Axis) -> None:
        """Closed loop at torque 0; a drive without a torque mode is free with its power
        stage off instead, powered by the next position, velocity or homing command."""

        def change(a: AxisTrack) -> None:
            if a.torque_mode is None:
                a.enable, a.unpowered, a.enable_sync, a.enable_start = False, True, -1, -1
                return
            self._power(a)
            a.mode, a.target_torque = a.torque_mode, 0
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
        node = self._nodes[a.node]
        has = list(a.has_limits)
        for k, (index, value) in enumerate(
            ((cia402.MAX_TORQUE, torque), (cia402.MAX_PROFILE_VELOCITY, velocity))
        ):
            if not has[k]:
                continue
            try:
                node.sdo[index].raw = value
            except SdoAbortedError as exc:
                if exc.code not in cia402.SDO_ABSENT:
                    raise NodeError(
                        f"{a.where()}: set limits 0x{index:04X}: {exc}", node=a.node, axis=int(axis)
                    ) from exc
                has[k] = False  # its EDS has it, the drive does not: the host's limit only
                self._say_once(a, f"{a.where()}: no 0x{index:04X} on the drive: {OPTIONAL[index]}")
            except SdoCommunicationError as exc:
                raise NodeError(
                    f"{a.where()}: set limits 0x{index:04X}: {exc}", node=a.node, axis=int(axis)
                ) from exc
        a.has_limits = (has[0], has[1])
        if a.position_mode is Mode.PROFILE_POSITION and a.has_profile_velocity:
            try:  # profile position travels at 0x6081: the run's velocity limit
                node.sdo[PROFILE_VELOCITY].raw = velocity
            except (SdoAbortedError, SdoCommunicationError) as exc:
                raise NodeError(
                    f"{a.where()}: set limits 0x6081: {exc}", node=a.node, axis=int(axis)
                ) from exc
        self._limits[(module, int(axis))] = (torque, velocity)

    def set_position(self, module: int, axis: Axis, position: float) -> None:
        def change(a: AxisTrack) -> None:
            self._powered(a)
            a.mode, a.target_position, a.target_torque = (
                a.position_mode, a.to_units(position), 0
            )  # fmt: skip

        self._command(f"set position {position:g}", module, axis, change)

    def set_velocity(self, module: int, axis: Axis, velocity: float) -> None:
        def change(a: AxisTrack) -> None:
            if a.velocity_mode is None:
                raise NodeError(
                    f"{a.where()}: the drive has no velocity mode (0x6502) or no target "
                    "velocity 0x60FF", node=a.node, axis=int(a.axis),
                )  # fmt: skip
            v = max(-a.max_velocity, min(a.max_velocity, velocity))
            self._powered(a)
            a.mode, a.target_velocity, a.target_torque = a.velocity_mode, a.to_units(v), 0

        self._command(f"set velocity {velocity:g}", module, axis, change)

    def set_torque(self, module: int, axis: Axis, torque: float) -> None:
        def change(a: AxisTrack) -> None:
            if a.torque_mode is None:
                raise NodeError(
                    f"{a.where()}: the drive has no torque mode (0x6502): drive it by "
                    "velocity", node=a.node, axis=int(a.axis),
                )  # fmt: skip
            t = max(-a.max_torque, min(a.max_torque, torque))
            a.mode, a.target_torque = a.torque_mode, a.torque_units(t)

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

        def change(a: AxisTrack) -> None:
            a.enable, a.unpowered, a.enable_sync, a.enable_start = False, True, -1, -1

        self._command("free", module, axis, change, targets=False)

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
            self._powered(a)
            a.mode = Mode.HOMING
            a.homing_start = True
            a.homing_sync = self._sync_seq
            mt.homing = HomingState.IN_PROGRESS

        self._command("start homing", module, Axis.STEER, change, targets=False)

    def _stopping(self) -> None:
        for a in self._tracks():
            a.enable = a.unpowered = False
            a.homing_start = False
            a.reset = False
            a.target_torque = 0
            a.controlword = cia402.CW_DISABLE_VOLTAGE
            a.t_controlword = self.clock.now()
            a.enable_sync = a.enable_start = -1

    def _stop_frames(self) -> list[Frame]:
        """Disable voltage and torque 0 (RPDO 1) to every axis set up (an axis never set
        up was never enabled); the host's heartbeat goes on."""
        return [f for a in self._tracks() if a.configured for f in self._command_frames(a)]

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

    def _emcy_callback(self, a: AxisTrack) -> Callable[[EmcyError], None]:
        return lambda e: self._on_emcy(a, e)

    def _on_emcy(self, a: AxisTrack, e: EmcyError) -> None:
        with self._changed:
            self._stats.node_faults += 1 if e.code & 0xFF00 else 0
            active = self._state == Lifecycle.ACTIVE
            self._pending += on_emcy(a, e.code, e.register, active)
            self._changed.notify_all()

    def _on_tpdo(self, module: int, a: AxisTrack, i: int, p: PdoMap) -> None:
        """TPDO ``i`` of ``a``: its objects kept; the last TPDO of the sample group
        completes a statusword and position (:attr:`AxisTrack.tpdos`), the last of the
        velocity and torque group those."""
        mt = self._modules[module]
        with self._changed:
            mt.feedback_frames += 1
            got = a.tpdo_values
            for v in p.map:
                got[v.index] = int(v.raw)
            if i == a.tpdos[0][-1]:
                sw = got.get(cia402.STATUSWORD, 0)
                pos = got.get(cia402.POSITION_ACTUAL, 0)
                disp = got.get(cia402.MODES_DISPLAY, 0)
                a.answered += 1
                seq = a.sync_base + a.answered
                self._pending += on_statusword(mt, a, sw, disp, pos, seq, self._arrival)
                s = pair(mt)
                if s is not None:
                    self._sample(mt, s)
            elif len(a.tpdos) > 1 and i == a.tpdos[1][-1]:
                if cia402.VELOCITY_ACTUAL in got:  # 0x606C and 0x6077 are optional
                    a.velocity = got[cia402.VELOCITY_ACTUAL] / a.counts_per_rad
                if cia402.TORQUE_ACTUAL in got:
                    a.torque = a.torque_si(got[cia402.TORQUE_ACTUAL])
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
                frames = [self._heartbeat_frame()] + [
                    self._guard_frame(a) for a in self._tracks() if a.guarded and a.configured
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

    def _ring(self, module: int) -> FeedbackRing:
        self._module(module)
        return self._history[module]

    def _not_reached(self, module: int, what: str, timeout: float) -> NodeTimeoutError:
        mt = self._module(module)
        with self._lock:
            states = ", ".join(f"{a.where()} {a.state.value}" for a in mt.axes)
        return NodeTimeoutError(
            f"module {module}: {what} not reached within {timeout} s ({states}, homed "
            f"{mt.homed})",
            node=mt.steer.node,
        )

    def axis_status(self, module: int, axis: Axis) -> AxisStatus:
        """What the host knows now of one axis' drive (the console's drives view): its
        power state, NMT state, modes display and error code, in CiA 402's words."""
        mt = self._module(module)
        a = mt.axes[Axis(axis)]
        with self._lock:
            faulted = a.state in (PowerState.FAULT, PowerState.FAULT_REACTION_ACTIVE)
            return AxisStatus(
                module=module,
                axis=a.axis,
                node=a.node,
                alive=a.alive,
                t_heartbeat=a.t_heartbeat,
                heartbeats=a.heartbeats,
                state=a.state.value,
                nmt=None if a.nmt is None else cia402.nmt_name(a.nmt),
                mode=cia402.mode_name(a.mode_display),
                error=a.error_code,
                error_name=cia402.emcy_name(a.error_code) if a.error_code else "none",
                fault=faulted or a.error_code != 0,  # the EMCY comes before the statusword
                homed=mt.homed if a.axis is Axis.STEER else None,
                torque_mode=a.torque_mode is not None,
            )

    def axis_track(self, module: int, axis: Axis) -> AxisTrack:
        """A copy of what the host knows of one axis (tests, diagnostics)."""
        with self._lock:
            return dataclasses.replace(self._module(module).axes[Axis(axis)])

    def sync_count(self) -> int:
        return self._sync_seq
