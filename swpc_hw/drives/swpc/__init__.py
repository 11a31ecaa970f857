"""The ``swpc`` drive kind: swpc's own firmware, one dual-axis controller a module
(:mod:`.driver`, :mod:`.tracking`, :mod:`.config`; docs/can-protocol.md)."""

from __future__ import annotations

import dataclasses
from typing import Any

from swpc_hw.clock import Clock
from swpc_hw.drives.bus import CanConfig
from swpc_hw.drives.interface import Drives
from swpc_hw.drives.registry import Kind
from swpc_hw.drives.swpc.config import SwpcDrives


def _open(config: Any, bus: CanConfig, clock: Clock) -> Drives:
    from swpc_hw.drives.swpc.driver import SwpcDriver  # the driver only when opened

    assert isinstance(config, SwpcDrives)
    return SwpcDriver(dataclasses.replace(bus, modules=config.node_map()), clock=clock)


KIND = Kind("swpc", SwpcDrives, _open)
