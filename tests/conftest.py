"""Test-session set-up shared by every module."""

from __future__ import annotations

import pytest

from swpc_hw.heap_freeze import freeze_startup_heap


def pytest_collection_finish(session: pytest.Session) -> None:
    """Freeze the heap that collecting the test modules left behind, as ``swpc serve`` and
    ``swpc sim`` freeze theirs at start-up.

    With every test module imported, a full garbage collection walks ~110 000 objects
    and holds the GIL for ~90 ms: the rig's driver then misses its 20 ms refreshes for
    longer than the controllers' 100 ms watchdog (WATCHDOG_TIMEOUT in
    ``test_driver_refresh_keeps_the_watchdog_fed`` in 1 of 3 runs of the driver and
    service modules together), and the emulated controllers skip feedback samples.
    """
    freeze_startup_heap()
