"""The ``odrive`` drive kind: ODrive axes over CAN Simple, behind :class:`Drives`.

One node per axis (a v3.6 has two, an S1 or a Pro one); a module is a steering axis and a
wheel axis (:class:`swpc_hw.drives.odrive.config.ODriveDrives`).  :class:`ODriveDriver` is
:class:`swpc_hw.drives.base.DriverBase` with the ODrive's frames: the base's lifecycle,
receive path, fault path, kernel refresh with its dead-man and recording; the ODrive's
pure core is :mod:`swpc_hw.drives.odrive.tracking` (what a frame tells); supervision is
the base's, per axis node (which axes are lost, what to refresh).

On the bus:

* the axes' heartbeats are the liveness and fault source (axis error, state, procedure
  result); their cyclic ``Get_Encoder_Estimates`` are the feedback: the host never polls
  (a 0.5.x axis takes every frame addressed to it, remote polls included, as a feed of its
  watchdog);
* commands: ``Set_Axis_State`` (closed loop / idle / index search), ``Set_Controller_Mode``
  (position for the steering and a held wheel, torque for a driven or free wheel and a free
  steering, velocity for the validation drive), ``Set_Input_Pos`` / ``Set_Input_Torque`` /
  ``Set_Input_Vel``, ``Set_Limits``, ``Clear_Errors``;
* the drive's own dead-man is the axis watchdog (``watchdog_timeout``, set on the ODrive to
  the robot's ``limits.watchdog_ms``): every armed axis gets its last setpoint frame again
  every ``T_ref`` (a setpoint frame feeds the watchdog on both firmware lines), from the
  kernel's broadcast manager on SocketCAN with the swpc kind's dead-man
  (:class:`~swpc_hw.drives.periodic.KernelRefresh`: a stopped service stops every frame to
  every axis, so each axis' watchdog disarms it within ``D + W``), elsewhere from the
  driver's I/O step (a :class:`~swpc_hw.clock.SimClock` hook in lockstep);
* :meth:`ODriveDriver.activate` proves that dead-man before anything moves: it arms every
  axis at zero torque, sends it nothing, and waits for its heartbeat to report
  ``WATCHDOG_TIMER_EXPIRED`` within ``W + L`` (the expiry, then the heartbeat that reports
  it, which may be as late as a heartbeat may be before its node counts as lost); an axis
  that stays armed is refused with the setting to fix.  The same window checks the encoder
  estimates' rate.

Units: the wire's turns of the axis, turns/s and N.m at the motor, A; SI at the module's
output above, through each axis' gear ratio and torque constant.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable

import can

from firmware_protocol.codec import Axis, ControlMode, Frame, HomingState, ProtocolError
from firmware_protocol.odrive import can_simple as cs
from swpc_hw.clock import SYSTEM_CLOCK, Clock, wait_until
from swpc_hw.drives.base import DriverBase
from swpc_hw.drives.bus import CanConfig
from swpc_hw.drives.errors import CanCommandError, LifecycleError, NodeError
from swpc_hw.drives.odrive.config import ODriveDrives
from swpc_hw.drives.odrive.tracking import (
    AxisTrack,
    apply_frame,
    new_axis,
    sync_module,
    to_axis,
    unproven_message,
)
from swpc_hw.drives.tracking import Applied, FeedbackRing, NodeTrack, Supervision
from swpc_hw.drives.types import AxisStatus, EventKind, Lifecycle, ModuleState, Severity, where

TWO_PI = 2.0 * math.pi
MIN_RATE_FRACTION = 0.5
"""The encoder estimates must come at least at this fraction of the configured rate."""


PROOF_HOST_BOUND = 4.0
"""The watchdog proof waits at most this many windows of the host's time for the drives'
own (their heartbeats)."""


class ODriveDriver(DriverBase):
    """The robot's ODrive axes on one bus (module docstring)."""

    def __init__(self, drives: ODriveDrives, config: CanConfig, *, clock: Clock = SYSTEM_CLOCK):
        super().__init__(config, clock=clock)
        self.drives = drives
        self.codec = cs.can_simple(drives.firmware)
        self._axes: dict[int, AxisTrack] = {}
        self._module_axes: dict[int, tuple[AxisTrack, AxisTrack]] = {}
        self._nodes: dict[int, NodeTrack] = {}
        for module, md in drives.module_map().items():
            steer = new_axis(module, Axis.STEER, md.steer)
            wheel = new_axis(module, Axis.WHEEL, md.wheel)
            self._axes[md.steer.node] = steer
            self._axes[md.wheel.node] = wheel
            self._module_axes[module] = (steer, wheel)
            track = NodeTrack(module, md.steer.node, FeedbackRing(config.history_len))
            if drives.homing != "index":  # referenced from power-up
                track.homed, track.homing = True, HomingState.DONE
            self._nodes[module] = track
        self._by_node = dict(self._axes)

    thread_name = "swpc-can-io"

    # ================================================================ the kind's cores
    def _receive_filters(self) -> list[dict[str, int | bool]] | None:
        """Every standard frame of a command an axis sends (any node: a foreign node is
        reported), and every extended frame; our own commands never come back."""
        out: list[dict[str, int | bool]] = [
            {"can_id": c, "can_mask": cs.CMD_MASK, "extended": False}
            for c in sorted(self.codec.axis_cmds)
        ]
        out.append({"can_id": 0, "can_mask": 0, "extended": True})
        return out

    def _node_of(self, arbitration_id: int) -> int | None:
        return arbitration_id >> cs.NODE_SHIFT

    def _apply_frame(self, msg: can.Message, t: float) -> Applied:
        applied = apply_frame(
            self.codec,
            self._axes,
            self._nodes,
            msg,
            t,
            self._stats,
            self._state == Lifecycle.ACTIVE,
        )
        ax = self._axes.get(msg.arbitration_id >> cs.NODE_SHIFT)
        if ax is not None:
            self._sync(ax.module)
        return applied

    def _sync(self, module: int) -> None:
        steer, wheel = self._module_axes[module]
        sync_module(self._nodes[module], steer, wheel)

    def _check(self, now: float, active: bool) -> Supervision:
        """Heartbeat loss per axis node, the refresh of each armed axis' setpoint."""
        sup = self._check_nodes(
            list(self._axes.values()), now, active, lambda a: bool(a.refresh),
            lambda a: list(a.refresh),
        )  # fmt: skip
        for module in {self._axes[o.node].module for o in sup.observations if o.node is not None}:
            self._sync(module)
        if sup.fault:  # nothing is re-armed after a fault
            for ax in self._axes.values():
                ax.rearm = False
        return sup

    def _keep_alive(self, now: float, active: bool) -> float:
        """An axis whose index search ended is held where it ended."""
        for ax in [a for a in self._axes.values() if a.rearm]:
            ax.rearm = False
            with contextlib.suppress(LifecycleError, CanCommandError):
                self._hold_axis(ax, "hold after the index search")
        return math.inf

    # ================================================================ lifecycle
    def _bring_up(self) -> None:
        """Every axis alive and its watchdog proven (module docstring);
        :class:`NodeTimeoutError` names a silent axis, :class:`NodeError` an axis whose
        watchdog or encoder rate is not what the robot needs."""
        axes = list(self._axes.values())
        self._wait_all(
            "heartbeat",
            lambda: axes,
            lambda a: a.alive,
            lambda a: where(a.module, a.node, a.axis),
            self.config.activate_timeout_s,
        )
        if self.config.watchdog_timeout_ms > 0:
            self._prove_watchdogs(axes)

    def _activated(self) -> None:
        for ax in self._axes.values():
            ax.proving, ax.armed, ax.refresh = False, False, ()
            ax.mode, ax.sent_control, ax.closed_loop_seen = ControlMode.FREE, None, False

    def _after_activate(self) -> None:
        """Every axis' errors cleared, its limits sent."""
        cfg = self.config
        axes = list(self._axes.values())
        frames = [self.codec.clear_errors(ax.node) for ax in axes]
        if cfg.max_torque is not None or cfg.max_velocity is not None:
            for ax in axes:
                frames.append(
                    self._limits_frame(
                        ax,
                        (cfg.max_torque or (math.inf, math.inf))[ax.axis],
                        (cfg.max_velocity or (math.inf, math.inf))[ax.axis],
                    )
                )
        self._send_frames(frames)

    def _prove_watchdogs(self, axes: list[AxisTrack]) -> None:
        """Arm every axis at zero torque, send it nothing, and wait for its heartbeat to
        report the watchdog's expiry; the estimates' rate is measured in the same window.

        The window ``W + L`` (watchdog, heartbeat loss) must be over on the host's clock and
        on each drive's own time, counted in its heartbeats (more than
        ``ceil((W + L) / T_hb)`` since the arming): a drive whose time lags the host's (a
        simulator that cannot keep up, in an emulated machine) is given the window it is
        owed.  The wait ends at :data:`PROOF_HOST_BOUND` windows of the host's time
        whatever the drives say (a drive whose heartbeats stop is lost)."""
        cfg, clock, c = self.config, self.clock, self.codec
        window = cfg.watchdog_timeout_ms / 1000.0 + cfg.loss_after_s
        beats = math.ceil(window / cfg.heartbeat_period_s - 1e-9)
        counts: dict[int, int] = {}
        heard: dict[int, int] = {}
        with self._changed:
            for ax in axes:
                ax.proving, ax.proven_at, ax.closed_loop_seen = True, None, False
                counts[ax.node] = ax.estimates
                heard[ax.node] = ax.heartbeats
        frames: list[Frame] = []
        for ax in axes:
            frames += [
                c.clear_errors(ax.node),
                c.set_controller_mode(ax.node, cs.ControlMode.TORQUE_CONTROL),
                c.set_input_torque(ax.node, 0.0),
                c.set_axis_state(ax.node, cs.AxisState.CLOSED_LOOP_CONTROL),
            ]
        t_arm = clock.now()
        self._send_frames(frames)
        with self._changed:

            def settled(drive_time: bool) -> bool:
                return all(
                    a.proven_at is not None
                    or bool(a.axis_error & ~c.watchdog_bit)
                    or (drive_time and a.heartbeats - heard[a.node] > beats)
                    for a in axes
                )

            # the window on the host's time, then on each drive's (a drive whose
            # heartbeat is faster than T_hb still gets the host's window)
            wait_until(clock, self._changed, lambda: settled(False), t_arm + window)
            wait_until(
                clock, self._changed, lambda: settled(True), t_arm + PROOF_HOST_BOUND * window
            )
            t_end = clock.now()
            failed = [a for a in axes if a.proven_at is None]
            for a in axes:
                a.proving = False
            span = max(t_end - t_arm, 1e-9)
            rates = {a.node: (a.estimates - counts[a.node]) / span for a in axes}
        if failed:
            with contextlib.suppress(Exception):
                self._send_frames(
                    [c.set_axis_state(a.node, cs.AxisState.IDLE) for a in axes], best_effort=True
                )
            raise NodeError(
                f"activate(): {unproven_message(c, failed, window, cfg.watchdog_timeout_ms)}",
                node=failed[0].node,
            )
        want = cfg.feedback_rate_hz
        if want > 0 and window * want >= 4:
            slow = [a for a in axes if rates[a.node] < MIN_RATE_FRACTION * want]
            if slow:
                names = ", ".join(
                    f"{where(a.module, a.node, a.axis)} at {rates[a.node]:.1f} Hz" for a in slow
                )
                raise NodeError(
                    f"activate(): encoder estimates of {names}; the robot needs {want} Hz "
                    f"(encoder_msg_rate_ms = {1000 / want:g} on the ODrive)",
                    node=slow[0].node,
                )

    # ================================================================ commands
    def _axis(self, module: int, axis: Axis) -> AxisTrack:
        try:
            return self._module_axes[module][Axis(axis)]
        except KeyError:
            raise CanCommandError(
                f"module {module} is not configured (modules: {sorted(self._module_axes)})"
            ) from None

    def _axis_command(
        self,
        what: str,
        ax: AxisTrack,
        build: Callable[[], list[Frame]],
        refresh: tuple[Frame, ...] | None = None,
        mode: ControlMode | None = None,
        armed: bool | None = None,
    ) -> None:
        """Send ``build()``'s frames to one axis; ``refresh`` (if given) is what the refresh
        repeats from now on (empty: nothing), handed to the kernel before the frames go
        out (the swpc kind's rule: an armed axis is fed from its first instant)."""
        with self._tx_lock:
            self._require_active(what, where(ax.module, ax.node, ax.axis))
            try:
                frames = build()
            except ProtocolError as exc:
                at = where(ax.module, ax.node, ax.axis)
                raise CanCommandError(f"{at}: {what}: {exc}") from exc
            kernel = self._kernel
            if refresh is not None and kernel is not None:
                kernel.set_node(ax.node, list(refresh))
            try:
                self._send_frames(frames)
            except Exception:
                if refresh is not None and kernel is not None:
                    kernel.set_node(ax.node, list(ax.refresh))
                raise
            with self._lock:
                if refresh is not None:
                    ax.refresh = refresh
                if mode is not None:
                    ax.mode = mode
                if armed is not None:
                    if armed and not ax.armed:
                        ax.closed_loop_seen = False
                    ax.armed = armed
                self._sync(ax.module)
                self._changed.notify_all()

    def _mode_frames(self, ax: AxisTrack, control: cs.ControlMode) -> list[Frame]:
        if ax.sent_control == control:
            return []
        ax.sent_control = control
        return [self.codec.set_controller_mode(ax.node, control)]

    def enable(self, module: int, axis: Axis) -> None:
        """Closed loop at zero torque (FREE)."""
        ax = self._axis(module, axis)
        zero = self.codec.set_input_torque(ax.node, 0.0)

        def build() -> list[Frame]:
            ax.sent_control = None
            return [
                *self._mode_frames(ax, cs.ControlMode.TORQUE_CONTROL),
                zero,
                self.codec.set_axis_state(ax.node, cs.AxisState.CLOSED_LOOP_CONTROL),
            ]

        self._axis_command("enable", ax, build, (zero,), ControlMode.FREE, armed=True)

    def disable(self, module: int, axis: Axis) -> None:
        ax = self._axis(module, axis)
        self._axis_command(
            "disable",
            ax,
            lambda: [self.codec.set_axis_state(ax.node, cs.AxisState.IDLE)],
            (),
            ControlMode.FREE,
            armed=False,
        )

    def set_torque(self, module: int, axis: Axis, torque: float) -> None:
        """Torque control at ``torque`` N.m at the output (``/ gear_ratio`` at the motor)."""
        ax = self._axis(module, axis)
        frame = self.codec.set_input_torque(ax.node, torque / ax.spec.gear_ratio)
        self._axis_command(
            f"set torque {torque:g}",
            ax,
            lambda: [*self._mode_frames(ax, cs.ControlMode.TORQUE_CONTROL), frame],
            (frame,),
            ControlMode.TORQUE,
        )

    def free(self, module: int, axis: Axis) -> None:
        """Zero torque (closed loop): the axis turns freely."""
        ax = self._axis(module, axis)
        frame = self.codec.set_input_torque(ax.node, 0.0)
        self._axis_command(
            "free",
            ax,
            lambda: [*self._mode_frames(ax, cs.ControlMode.TORQUE_CONTROL), frame],
            (frame,),
            ControlMode.FREE,
        )

    def set_position(self, module: int, axis: Axis, position: float) -> None:
        """Position control to ``position`` rad at the output (axis turns on the wire)."""
        ax = self._axis(module, axis)
        self._position(ax, to_axis(position, ax.spec.gear_ratio), ControlMode.POSITION,
                       f"set position {position:g}")  # fmt: skip

    def _position(self, ax: AxisTrack, turns: float, mode: ControlMode, what: str) -> None:
        frame = self.codec.set_input_pos(ax.node, turns)
        self._axis_command(
            what,
            ax,
            lambda: [*self._mode_frames(ax, cs.ControlMode.POSITION_CONTROL), frame],
            (frame,),
            mode,
        )

    def hold(self, module: int, axis: Axis) -> None:
        """Position control at the axis' latest estimate (a held wheel, a locked steering)."""
        self._hold_axis(self._axis(module, axis), "hold")

    def _hold_axis(self, ax: AxisTrack, what: str) -> None:
        if not math.isfinite(ax.pos):
            raise CanCommandError(
                f"{where(ax.module, ax.node, ax.axis)}: {what}: no encoder estimate yet"
            )
        if not ax.armed:  # after an index search the axis is IDLE: arm it holding
            frame = self.codec.set_input_pos(ax.node, ax.pos)

            def build() -> list[Frame]:
                ax.sent_control = None
                return [
                    *self._mode_frames(ax, cs.ControlMode.POSITION_CONTROL),
                    frame,
                    self.codec.set_axis_state(ax.node, cs.AxisState.CLOSED_LOOP_CONTROL),
                ]

            self._axis_command(what, ax, build, (frame,), ControlMode.HOLD, armed=True)
            return
        self._position(ax, ax.pos, ControlMode.HOLD, what)

    def set_velocity(self, module: int, axis: Axis, velocity: float) -> None:
        ax = self._axis(module, axis)
        frame = self.codec.set_input_vel(ax.node, to_axis(velocity, ax.spec.gear_ratio))
        self._axis_command(
            f"set velocity {velocity:g}",
            ax,
            lambda: [*self._mode_frames(ax, cs.ControlMode.VELOCITY_CONTROL), frame],
            (frame,),
            ControlMode.VELOCITY,
        )

    def _limits_frame(self, ax: AxisTrack, max_torque: float, max_velocity: float) -> Frame:
        """``Set_Limits``: the velocity limit in axis turns/s, the current limit in A
        (``max_torque / (gear_ratio x torque_constant)``)."""
        spec = ax.spec
        return self.codec.set_limits(
            ax.node,
            to_axis(max_velocity, spec.gear_ratio) if math.isfinite(max_velocity) else 1e9,
            max_torque / (spec.gear_ratio * spec.torque_constant)
            if math.isfinite(max_torque)
            else 1e9,
        )

    def set_limits(self, module: int, axis: Axis, max_torque: float, max_velocity: float) -> None:
        ax = self._axis(module, axis)
        self._axis_command(
            "set limits", ax, lambda: [self._limits_frame(ax, max_torque, max_velocity)]
        )

    def clear_errors(self, module: int, axes: tuple[Axis, ...] = (Axis.STEER, Axis.WHEEL)) -> None:
        for a in axes:
            ax = self._axis(module, a)
            frames = [self.codec.clear_errors(ax.node)]
            self._axis_command("clear errors", ax, frames.copy)

    def start_homing(self, module: int) -> None:
        """The steering's reference: an index search (the axis turns until its encoder's
        index, then is held there), or nothing to do with an absolute encoder or none."""
        nd = self._nodes.get(module)
        ax = self._axis(module, Axis.STEER)
        assert nd is not None
        if self.drives.homing != "index":
            self._emit(
                EventKind.HOMING,
                Severity.INFO,
                f"{where(module, ax.node, Axis.STEER)}: homing {self.drives.homing}: referenced "
                "at power-up",
            )
            return
        with self._lock:
            before = nd.homing, nd.homing_seen
            nd.homing, nd.homing_seen = HomingState.IN_PROGRESS, False
            ax.homing_axis = True
        try:
            self._axis_command(
                "start homing",
                ax,
                lambda: [self.codec.set_axis_state(ax.node, cs.AxisState.ENCODER_INDEX_SEARCH)],
                armed=False,
            )
        except BaseException:
            with self._lock:
                nd.homing, nd.homing_seen = before
                ax.homing_axis = False
            raise

    def _stopping(self) -> None:
        """The refresh ends (kernel tasks deleted before the stop frames)."""
        for ax in self._axes.values():
            ax.refresh, ax.armed, ax.proving = (), False, False
            ax.mode, ax.sent_control = ControlMode.FREE, None
        for m in self._module_axes:
            self._sync(m)

    def _stop_frames(self) -> list[Frame]:
        """Zero torque then IDLE to every axis."""
        c = self.codec
        axes = list(self._axes.values())
        frames = [c.set_input_torque(ax.node, 0.0) for ax in axes]
        frames += [c.set_axis_state(ax.node, cs.AxisState.IDLE) for ax in axes]
        return frames

    # ================================================================ observation
    def modules(self) -> list[int]:
        return list(self._nodes)

    def module_state(self, module: int) -> ModuleState:
        nd = self._module(module)
        with self._lock:
            return nd.snapshot()

    def axis_status(self, module: int, axis: Axis) -> AxisStatus:
        """One axis as its own heartbeats tell it (each axis is a node of its own): its
        axis state, the host's control mode while it is armed, its axis error named; in
        fault with an axis error other than the watchdog's (a 0.5.x axis left alone
        reports that one, as ``swpc drives scan`` says)."""
        ax = self._axis(module, axis)
        md = self._module(module)
        with self._lock:
            try:
                state = cs.AxisState(ax.state).name
            except ValueError:
                state = f"state {ax.state}"
            error = ax.axis_error
            return AxisStatus(
                module=module,
                axis=ax.axis,
                node=ax.node,
                alive=ax.alive,
                t_heartbeat=ax.t_heartbeat,
                heartbeats=ax.heartbeats,
                state=state,
                nmt=None,
                mode=(ax.mode if ax.armed else ControlMode.FREE).name,
                error=error,
                error_name=self.codec.error_names(error),
                fault=bool(error & ~self.codec.watchdog_bit),
                homed=md.homed if ax.axis == Axis.STEER else None,
            )

    def _ring(self, module: int) -> FeedbackRing:
        return self._module(module).history

    def _module(self, module: int) -> NodeTrack:
        return self._configured(self._nodes, module)

    def _error_names(self, bits: int) -> str:
        return self.codec.error_names(bits)

    def axis_states(self) -> dict[int, dict[str, object]]:
        """Every axis by node: module, axis, state, axis error (named), last estimate."""
        with self._lock:
            return {
                n: {
                    "module": a.module,
                    "axis": a.axis.name.lower(),
                    "alive": a.alive,
                    "state": a.state,
                    "axis_error": self.codec.error_names(a.axis_error),
                    "pos": a.pos,
                    "estimates": a.estimates,
                }
                for n, a in self._axes.items()
            }
