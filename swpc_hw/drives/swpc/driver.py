"""The ``swpc`` drive kind: swpc's own firmware, one dual-axis controller per module
(python-can and the DBC of ``firmware_protocol/``, docs/can-protocol.md).

:class:`SwpcDriver` is :class:`swpc_hw.drives.base.DriverBase` with the controllers'
frames: what a frame tells is the pure core :mod:`swpc_hw.drives.swpc.tracking`; the
dead-man is the controllers' command watchdog, fed with each node's last SetControl
frames (the kernel's broadcast manager on SocketCAN, else re-sent by the I/O step
whenever a node got none for ``refresh_period_s``); every fault frees then disables every
axis of every node.  Every command needs the drives ACTIVE (:class:`LifecycleError` names
the fault that stopped them otherwise), except :meth:`stop_all`, which sends whenever the
bus is open.
"""

from __future__ import annotations

from collections.abc import Callable

import can

from firmware_protocol import codec
from firmware_protocol.codec import Axis, ControlMode, HomingState
from swpc_hw.clock import SYSTEM_CLOCK, Clock
from swpc_hw.drives.base import DriverBase
from swpc_hw.drives.bus import CanConfig
from swpc_hw.drives.errors import CanCommandError
from swpc_hw.drives.swpc.tracking import apply_frame, refresh_frames
from swpc_hw.drives.tracking import Applied, FeedbackRing, NodeTrack, Supervision
from swpc_hw.drives.types import AxisStatus, DriverEvent, ModuleState, where


class SwpcDriver(DriverBase):
    """swpc's module controllers on one bus (module docstring)."""

    thread_name = "swpc-can-io"

    def __init__(
        self,
        config: CanConfig | None = None,
        *,
        clock: Clock = SYSTEM_CLOCK,
        on_event: Callable[[DriverEvent], None] | None = None,
    ) -> None:
        super().__init__(config or CanConfig(), clock=clock, on_event=on_event)
        self._nodes: dict[int, NodeTrack] = {}
        for module, node in self.config.modules.items():
            nd = NodeTrack(module, node, FeedbackRing(self.config.history_len))
            self._nodes[module] = nd
            self._by_node[node] = nd
        self._sync_counter = 0

    # ================================================================ the kind's cores
    def _receive_filters(self) -> list[dict[str, int | bool]] | None:
        """The kernel's receive filters on SocketCAN: the controllers' frames only."""
        return codec.host_receive_filters()

    def _node_of(self, arbitration_id: int) -> int | None:
        return arbitration_id >> codec.NODE_SHIFT

    def _apply_frame(self, msg: can.Message, t: float) -> Applied:
        return apply_frame(self._by_node, msg, t, self._stats)

    def _check(self, now: float, active: bool) -> Supervision:
        return self._check_nodes(
            self._nodes.values(), now, active, lambda nd: bool(nd.commanded), refresh_frames
        )

    def _bring_up(self) -> None:
        """Every node's heartbeat within ``activate_timeout_s``."""
        self._wait_all(
            "heartbeat",
            self._nodes.values,
            lambda nd: nd.alive,
            lambda nd: where(nd.module, nd.node),
            self.config.activate_timeout_s,
        )

    def _after_activate(self) -> None:
        """The watchdog, the feedback rate and the limits to every node."""
        cfg = self.config
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

    # ================================================================ observation
    def modules(self) -> list[int]:
        return list(self._nodes)

    def module_state(self, module: int) -> ModuleState:
        nd = self._node(module)
        with self._lock:
            return nd.snapshot()

    def axis_status(self, module: int, axis: Axis) -> AxisStatus:
        """One axis as its controller's heartbeat tells it: both axes of a module are on
        its controller's node, and share its liveness and heartbeat."""
        return self._module_axis_status(module, axis)

    def _ring(self, module: int) -> FeedbackRing:
        return self._node(module).history

    def _error_names(self, bits: int) -> str:
        return codec.error_names(bits)

    # ================================================================ commands
    def _node(self, module: int) -> NodeTrack:
        return self._configured(self._nodes, module)

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
            self._require_active(what, where(nd.module, nd.node, axis))
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

    def send_sync(self) -> int:
        """Broadcast a SYNC frame; returns its counter (the next samples carry it)."""
        self._require_active("send SYNC")
        with self._lock:
            counter = self._sync_counter
            self._sync_counter = (counter + 1) & 0xFF
        self._send_frames([codec.make_sync(counter)])
        return counter

    def _stopping(self) -> None:
        for nd in self._nodes.values():
            nd.commanded.clear()

    def _stop_frames(self) -> list[codec.Frame]:
        """FREE then DISABLED to every axis of every node."""
        nodes = list(self._nodes.values())
        frames = [
            codec.make_set_control(nd.node, a, ControlMode.FREE) for nd in nodes for a in Axis
        ]
        frames += [codec.make_set_axis_state(nd.node, a, False) for nd in nodes for a in Axis]
        return frames
