"""The driver's command API: every command frame the host sends, as typed methods.

A mixin of :class:`swpc_hw.can.driver.CanDriver`, which owns the bus, the locks and the
lifecycle; here only how each command is built and which setpoint it leaves refreshed.
Every command needs the driver ACTIVE (:class:`LifecycleError` names the fault that
stopped it otherwise), except :meth:`DriverCommands.stop_all`, which sends whenever the
bus is open.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

import can

from firmware_protocol import codec
from firmware_protocol.codec import Axis, ControlMode, HomingState
from swpc_hw.can.errors import CanCommandError, LifecycleError
from swpc_hw.can.node_tracking import NodeTrack
from swpc_hw.can.periodic import KernelRefresh
from swpc_hw.can.recording import Recorder
from swpc_hw.can.supervision import refresh_frames
from swpc_hw.can.types import DriverStats, Lifecycle, where


class DriverCommands:
    """Commands of the module controllers (mixin; state lives in the driver)."""

    _lock: threading.RLock
    _tx_lock: threading.RLock
    _nodes: dict[int, NodeTrack]
    _stats: DriverStats
    _state: Lifecycle
    _fault_cause: str | None
    _bus: can.BusABC | None
    _kernel: KernelRefresh | None
    _recorder: Recorder | None
    _logger: Recorder | None
    _sync_counter: int

    def _send_frames(self, frames: list[codec.Frame], best_effort: bool = False) -> None:
        raise NotImplementedError  # the driver's transmit path

    def _node(self, module: int) -> NodeTrack:
        try:
            return self._nodes[module]
        except KeyError:
            raise CanCommandError(
                f"module {module} is not configured (modules: {sorted(self._nodes)})"
            ) from None

    def _require_active(
        self, what: str, nd: NodeTrack | None = None, axis: Axis | None = None
    ) -> None:
        if self._state != Lifecycle.ACTIVE:
            at = where(nd.module, nd.node, axis) + ": " if nd else ""
            cause = self._fault_cause
            why = f" (stopped by a fault: {cause})" if cause is not None else ""
            raise LifecycleError(f"{at}cannot {what} in state {self._state.value}{why}")

    def _command(
        self,
        what: str,
        module: int,
        axis: Axis | None,
        build: Callable[[int], codec.Frame],
        commanded: tuple[ControlMode, float] | bool | None = False,
    ) -> NodeTrack:
        """Send one command frame; ``commanded`` (if not False) becomes the axis's
        refreshed setpoint (None: no longer refreshed).  Serialised with stop_all() by
        the transmit lock: a command either goes before the stop frames, or after them to
        a disabled axis (which ignores it).

        With the refresh in the kernel, the kernel refreshes the new setpoint *before* the
        frame goes out (and again the old one if it cannot be sent): an axis the command
        enables is fed from its first instant, however long this thread is then held off
        the CPU.  The other way round, a pause between the two (0.2-0.35 s in a VM on a
        loaded host, as a GIL or GC pause would be) tripped the controller's watchdog."""
        nd = self._node(module)
        with self._tx_lock:
            self._require_active(what, nd, axis)
            try:
                frame = build(nd.node)
            except codec.ProtocolError as exc:
                raise CanCommandError(f"{where(nd.module, nd.node, axis)}: {what}: {exc}") from exc
            if commanded is False or axis is None:
                self._send_frames([frame])
                return nd
            assert not isinstance(commanded, bool)
            with self._lock:
                new = dict(nd.commanded)
                if commanded is None:
                    new.pop(axis, None)
                else:
                    new[axis] = commanded
            kernel = self._kernel
            if kernel is None:
                self._send_frames([frame])
            else:
                kernel.set_node(nd.node, refresh_frames(nd, new))
                try:
                    self._send_frames([frame])
                except Exception:
                    kernel.set_node(nd.node, refresh_frames(nd))
                    raise
            with self._lock:
                nd.commanded.clear()
                nd.commanded.update(new)
        return nd

    def enable(self, module: int, axis: Axis) -> None:
        """Enable (closed loop, mode FREE) one axis."""
        axis = Axis(axis)
        self._command(
            "enable",
            module,
            axis,
            lambda n: codec.make_set_axis_state(n, axis, True),
            (ControlMode.FREE, 0.0),
        )

    def disable(self, module: int, axis: Axis) -> None:
        axis = Axis(axis)
        self._command(
            "disable", module, axis, lambda n: codec.make_set_axis_state(n, axis, False), None
        )

    def set_control(
        self, module: int, axis: Axis, mode: ControlMode, setpoint: float = 0.0
    ) -> None:
        """Control mode and setpoint (rad, rad/s or N.m by mode) of one axis."""
        axis, mode = Axis(axis), ControlMode(mode)
        self._command(
            f"set {mode.name} {setpoint:g}",
            module,
            axis,
            lambda n: codec.make_set_control(n, axis, mode, setpoint),
            (mode, setpoint),
        )

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
                None,
            )
        except BaseException:
            with self._lock:
                nd.homing, nd.homing_seen = before
            raise

    def start_recording(self, path: str) -> None:
        """Record every frame in and out to ``path`` until :meth:`stop_recording`.

        python-can's Logger picks the format from the suffix (``.log``: candump, which
        ``cantools decode`` reads with our DBC).  Independent of ``CanConfig.log_path``.
        Frames the kernel sends for the watchdog refresh are not in it (candump sees them).
        """
        with self._lock:
            if self._bus is None or self._state == Lifecycle.FINALIZED:
                raise LifecycleError("start_recording() needs an open bus (configure() first)")
        self.stop_recording()
        rec = Recorder(path)
        with self._lock:
            self._recorder = rec

    def stop_recording(self) -> str | None:
        """Stop the recording started by :meth:`start_recording` (idempotent); returns why
        it stopped early (a failed write), if it did."""
        with self._lock:
            rec, self._recorder = self._recorder, None
        if rec is None:
            return None
        rec.stop()
        return rec.error

    def log_error(self) -> str | None:
        """Why the log of ``CanConfig.log_path`` stopped (a failed write), if it did."""
        return None if self._logger is None else self._logger.error

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
        every fault path calls.  The kernel's periodic refresh is deleted first, so no
        refresh follows the stop frames.  Send failures are counted and re-raised at the
        end.
        """
        with self._tx_lock:
            with self._lock:
                self._stats.stop_all_calls += 1
                nodes = list(self._nodes.values())
                for nd in nodes:
                    nd.commanded.clear()
                bus_open = self._bus is not None and self._state in (
                    Lifecycle.INACTIVE,
                    Lifecycle.ACTIVE,
                )
            if self._kernel is not None:
                self._kernel.stop_all()
            if not bus_open:
                return
            frames = [
                codec.make_set_control(nd.node, a, ControlMode.FREE) for nd in nodes for a in Axis
            ]
            frames += [codec.make_set_axis_state(nd.node, a, False) for nd in nodes for a in Axis]
            self._send_frames(frames, best_effort=True)
