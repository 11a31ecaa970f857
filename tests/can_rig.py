"""Back-to-back rig for the CAN driver tests: emulated controllers + an observer on one bus.

The bus is selected by environment variables, so the same tests run on python-can's
``virtual`` interface (default, a unique channel per test) and on SocketCAN::

    SWPC_TEST_CAN_INTERFACE=socketcan SWPC_TEST_CAN_CHANNEL=vcan0 pytest tests/test_driver.py
"""

from __future__ import annotations

import os
import threading
import time
import uuid
from collections.abc import Callable

import can

INTERFACE = os.environ.get("SWPC_TEST_CAN_INTERFACE", "virtual")
FIXED_CHANNEL = os.environ.get("SWPC_TEST_CAN_CHANNEL")


def new_channel() -> str:
    """A fresh channel name (virtual) or the configured SocketCAN interface."""
    return FIXED_CHANNEL or f"swpc-test-{uuid.uuid4().hex[:8]}"


class Observer(can.Listener):
    """Records every frame seen on the bus (its own bus instance), with host time."""

    def __init__(self, channel: str) -> None:
        self.bus = can.Bus(interface=INTERFACE, channel=channel)
        self.frames: list[tuple[float, can.Message]] = []
        self._lock = threading.Lock()
        self._notifier = can.Notifier(self.bus, [self], timeout=0.05)

    def on_message_received(self, msg: can.Message) -> None:
        with self._lock:
            self.frames.append((time.monotonic(), msg))

    def snapshot(self) -> list[tuple[float, can.Message]]:
        with self._lock:
            return list(self.frames)

    def clear(self) -> None:
        with self._lock:
            self.frames.clear()

    def ids(self, pred: Callable[[int], bool] | None = None) -> list[int]:
        return [
            m.arbitration_id for _, m in self.snapshot() if pred is None or pred(m.arbitration_id)
        ]

    def send(self, msg: can.Message) -> None:
        self.bus.send(msg)

    def close(self) -> None:
        self._notifier.stop(timeout=1.0)
        self.bus.shutdown()


def wait_until(pred: Callable[[], bool], timeout: float = 2.0, step: float = 0.005) -> bool:
    """Poll ``pred`` every ``step`` s until true or ``timeout`` (test helper)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(step)
    return pred()
