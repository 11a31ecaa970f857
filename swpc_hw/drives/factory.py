"""The one place that knows the drive kinds: a robot config's ``drives:`` -> :class:`Drives`.

Each kind registers an opener in :data:`OPENERS`; nothing else in swpc asks which kind a
robot has.  The opener gets the kind's config (module map filled in), the bus and timing
settings (:class:`~swpc_hw.can.config.CanConfig`: interface, channel, bitrate, feedback
rate, watchdog, refresh, heartbeat loss, limits, dead-man, CAN log) and the clock.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

from swpc_hw.can.config import CanConfig
from swpc_hw.can.driver import CanDriver
from swpc_hw.can.errors import CanConfigError
from swpc_hw.clock import SYSTEM_CLOCK, Clock
from swpc_hw.drives.cia402.driver import Cia402Driver
from swpc_hw.drives.config import Cia402Drives, DrivesConfig, ODriveDrives, SwpcDrives
from swpc_hw.drives.interface import Drives
from swpc_hw.drives.odrive.driver import ODriveDriver


def _open_swpc(config: Any, bus: CanConfig, clock: Clock) -> Drives:
    assert isinstance(config, SwpcDrives)
    return CanDriver(dataclasses.replace(bus, modules=config.node_map()), clock=clock)


def _open_odrive(config: Any, bus: CanConfig, clock: Clock) -> Drives:
    """ODrive axes: the encoder estimates come at the config's ``encoder_rate_hz`` (set on
    the ODrive), else at the service's feedback rate, which the ODrive must then be set to."""
    assert isinstance(config, ODriveDrives)
    rate = config.encoder_rate_hz or bus.feedback_rate_hz
    return ODriveDriver(config, dataclasses.replace(bus, feedback_rate_hz=rate), clock=clock)


def _open_cia402(config: Any, bus: CanConfig, clock: Clock) -> Drives:
    assert isinstance(config, Cia402Drives)
    return Cia402Driver(config, bus, clock=clock)


OPENERS: dict[str, Callable[[Any, CanConfig, Clock], Drives]] = {
    "swpc": _open_swpc,
    "odrive": _open_odrive,
    "cia402": _open_cia402,
}
"""kind -> opener (module docstring)."""


def open_drives(
    config: DrivesConfig, bus: CanConfig, module_ids: list[int], *, clock: Clock = SYSTEM_CLOCK
) -> Drives:
    """The drives of ``config`` for a robot with ``module_ids``, UNCONFIGURED (call
    ``configure()``); :class:`~swpc_hw.can.errors.CanConfigError` for a config that does
    not fit the robot or a kind that is not known."""
    problems = config.check_modules(module_ids)
    if problems:
        raise CanConfigError("; ".join(problems))
    opener = OPENERS.get(config.kind)
    if opener is None:
        raise CanConfigError(
            f"drives.kind: unknown kind {config.kind!r} (known: {', '.join(sorted(OPENERS))})"
        )
    return opener(config.for_modules(module_ids), bus, clock)
