"""The ``cia402`` drive kind: CiA 402 drives over CANopen on the ``canopen`` library
(:mod:`.driver`; its pure cores :mod:`.commands`, :mod:`.pdo`, :mod:`.status`,
:mod:`.tracking`; canopen's side :mod:`.network`, :mod:`.setup`, :mod:`.sdo`; the drive
scan :mod:`.scan`; :mod:`.config`)."""

from __future__ import annotations

from typing import Any

from swpc_hw.clock import Clock
from swpc_hw.drives.bus import CanConfig
from swpc_hw.drives.cia402.config import Cia402Drives
from swpc_hw.drives.interface import Drives
from swpc_hw.drives.registry import Kind


def _open(config: Any, bus: CanConfig, clock: Clock) -> Drives:
    from swpc_hw.drives.cia402.driver import Cia402Driver  # canopen only when opened

    assert isinstance(config, Cia402Drives)
    return Cia402Driver(config, bus, clock=clock)


KIND = Kind("cia402", Cia402Drives, _open)
