"""A module's virtual drives of the robot config's kind: the one place that knows the kinds
(as :func:`swpc_hw.drives.registry.open_drives` on the host side).

The virtual robot (:mod:`simulators.virtual_robot`) moves the physics and hands every CAN
frame to every module's :class:`~simulators.drives.base.VirtualDrive`; each kind turns
frames into its drives' state and that state into a drive of the physics
(:func:`simulators.drives.base.axis_drive`'s ``(kind, value)``: passive, a rate, a brake, a
wheel torque), and reads the encoders the physics writes back.

Positions handed to ``VirtualDrive.sense`` are at the module's output, SI: the steering as
the drive reports it (its homing reference, multi-turn), the wheel's cumulative angle.  A
kind with gears and counts converts them itself.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from simulators.drives import cia402, swpc
from simulators.drives.base import VirtualDrive
from swpc_hw.drives.odrive.config import ODriveDrives
from swpc_hw.drives.registry import DrivesConfig


def _odrive(config: DrivesConfig, module: int, **kwargs: Any) -> VirtualDrive:
    from simulators.drives.odrive import odrive_virtual_drive

    assert isinstance(config, ODriveDrives)
    return odrive_virtual_drive(config, module, **kwargs)


BUILDERS: dict[str, Callable[..., VirtualDrive]] = {
    "swpc": swpc.build,
    "cia402": cia402.build,
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
