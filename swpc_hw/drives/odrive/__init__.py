"""The ``odrive`` drive kind: ODrive axes over CAN Simple (:mod:`.driver`, :mod:`.tracking`,
:mod:`.config`)."""

from __future__ import annotations

import dataclasses
from typing import Any

from swpc_hw.clock import Clock
from swpc_hw.drives.bus import CanConfig
from swpc_hw.drives.interface import Drives
from swpc_hw.drives.odrive.config import ODriveDrives
from swpc_hw.drives.registry import Kind


def _open(config: Any, bus: CanConfig, clock: Clock) -> Drives:
    """ODrive axes: the encoder estimates come at the config's ``encoder_rate_hz`` (set on
    the ODrive), else at the service's feedback rate, which the ODrive must then be set to."""
    from swpc_hw.drives.odrive.driver import ODriveDriver  # the driver only when opened

    assert isinstance(config, ODriveDrives)
    rate = config.encoder_rate_hz or bus.feedback_rate_hz
    return ODriveDriver(config, dataclasses.replace(bus, feedback_rate_hz=rate), clock=clock)


KIND = Kind("odrive", ODriveDrives, _open)
