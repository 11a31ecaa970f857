"""A module's virtual drives: what the virtual robot needs of each drive kind.

The virtual robot (:mod:`simulators.virtual_robot`) moves the physics and hands every CAN
frame to every module's :class:`VirtualDrive`; each kind turns frames into its drives'
state and that state into a drive of the physics (:func:`simulators.axis_drives.axis_drive`'s
``(kind, value)``: passive, a rate, a brake, a wheel torque), and reads the encoders the
physics writes back.  :func:`virtual_drives` is the one place that knows the kinds (as
:func:`swpc_hw.drives.registry.open_drives` on the host side).

Positions handed to :meth:`VirtualDrive.sense` are at the module's output, SI: the
steering as the drive reports it (its homing reference, multi-turn), the wheel's
cumulative angle.  A kind with gears and counts converts them itself.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, Protocol

import can

from firmware_protocol import codec
from firmware_protocol.codec import Axis, ErrorFlag, Frame
from simulators import cia402_drive
from simulators.axis_drives import axis_drive
from simulators.virtual_controller import VirtualController
from swpc_hw.drives.odrive.config import ODriveDrives
from swpc_hw.drives.registry import DrivesConfig
from swpc_hw.drives.swpc.config import SwpcDrives


class VirtualDrive(Protocol):
    """One module's drives (steering and wheel) on the bus."""

    @property
    def homed(self) -> bool:
        """The steering has been homed (its reported angle is ``theta - beta``)."""
        ...

    muted: bool
    """Heartbeat loss: the drives send nothing while muted."""

    @property
    def sensor_position(self) -> float:
        """The steering's power-up coordinate of the homing reference (rad)."""
        ...

    heartbeats: int
    feedback_frames: int
    """Heartbeats and feedback frames sent (counters)."""

    def receive(self, msg: can.Message, now: float) -> list[can.Message]:
        """A frame from the bus (every frame: the drive keeps what is its own) at simulated
        time ``now``; the frames it answers with."""
        ...

    def step(self, now: float) -> list[can.Message]:
        """The drives' own logic at ``now`` (watchdogs, homing, heartbeats, feedback)."""
        ...

    def next_due(self) -> float:
        """The next simulated time :meth:`step` has something to do."""
        ...

    def feedback_rate(self) -> float:
        """The rate of its free-running feedback (Hz; 0: none, or on SYNC): the virtual
        robot's tick is never longer than its period."""
        ...

    def drive(
        self, axis: Axis, position: float, dt: float, position_tau: float
    ) -> tuple[str, float]:
        """What ``axis`` does to the physics over the next ``dt`` (``position``: where it
        is now): :func:`simulators.axis_drives.axis_drive`'s ``(kind, value)``."""
        ...

    def sense(
        self, axis: Axis, position: float, velocity: float, torque: float | None
    ) -> None:
        """The encoder's reading after a tick; ``torque``: the torque applied (0 passive or
        braked), None for an axis in a rate loop (the drive estimates its own)."""
        ...

    def inject_fault(self, axis: Axis, error: ErrorFlag) -> list[can.Message]:
        """Latch a hardware error on ``axis`` (as the drive reports it on its bus)."""
        ...

    def params(self) -> dict[str, Any]:
        """What the truth document says of these drives (kind, nodes)."""
        ...


def message(frame: Frame) -> can.Message:
    """A classic 11-bit data frame."""
    return can.Message(arbitration_id=frame.arbitration_id, data=frame.data, is_extended_id=False)


class SwpcVirtualDrive:
    """swpc's own firmware (:class:`~simulators.virtual_controller.VirtualController`):
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


def _swpc(
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


def _odrive(config: DrivesConfig, module: int, **kwargs: Any) -> VirtualDrive:
    from simulators.virtual_odrive import odrive_virtual_drive

    assert isinstance(config, ODriveDrives)
    return odrive_virtual_drive(config, module, **kwargs)


BUILDERS: dict[str, Callable[..., VirtualDrive]] = {
    "swpc": _swpc,
    "cia402": cia402_drive.build,
    "odrive": _odrive,
}
"""kind -> builder of one module's virtual drives."""


def virtual_drives(
    config: DrivesConfig,
    modules: Sequence[int],
    *,
    feedback_rate_hz: int,
    watchdog_ms: int,
    homing_duration: float,
    sensor_positions: Sequence[float],
) -> list[VirtualDrive]:
    """Every module's virtual drives, in ``modules`` order, of ``config``'s kind."""
    config = config.for_modules(list(modules))
    problems = config.check_modules(list(modules))
    if problems:
        raise ValueError("; ".join(problems))
    build = BUILDERS.get(config.kind)
    if build is None:
        raise ValueError(f"no virtual drives of kind {config.kind!r} (known: {sorted(BUILDERS)})")
    return [
        build(
            config,
            m,
            feedback_rate_hz=feedback_rate_hz,
            watchdog_ms=watchdog_ms,
            homing_duration=homing_duration,
            sensor_position=float(sensors),
        )
        for m, sensors in zip(modules, sensor_positions, strict=True)
    ]
