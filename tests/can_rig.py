"""Back-to-back rig for the CAN driver tests: emulated controllers + an observer on one bus.

The bus is selected by environment variables, so the same tests run on python-can's
``virtual`` interface (default, a unique channel per test) and on SocketCAN::

    SWPC_TEST_CAN_INTERFACE=socketcan SWPC_TEST_CAN_CHANNEL=vcan1,vcan2,vcan3 \
    SWPC_TEST_TIME_FACTOR=4 pytest tests/drives/swpc/test_driver_{lifecycle,commands,faults}.py

``SWPC_TEST_CAN_CHANNEL`` is one interface or a comma-separated pool: each rig takes the
next one (round robin), so with at least as many interfaces as tests every test has a bus
of its own and no frame of one test (e.g. an emulator left running by a failed test)
reaches the next.

Clock: on the ``virtual`` bus the rig runs on a :class:`swpc_hw.clock.SimClock` in lockstep
(the emulator is its master; the test thread is a participant), so a busy host slows a test
down but cannot change its outcome; ``SWPC_TEST_LOCKSTEP=0`` runs it on the real clock.  On
SocketCAN the rig runs in real time (the kernel's bus is real).

``SWPC_TEST_TIME_FACTOR`` (F, default 1) slows the whole rig down by F, for slow machines
(QEMU software emulation runs Python ~12x slower than this host): every protocol period
(feedback, driver refresh, heartbeat, watchdog) is F times longer, every rate F times
lower, and every timeout, sleep and time window of the tests is F times longer
(:func:`T`, :func:`wait_until`, :class:`ScaledDriver`).  Counts of frames per window stay
the same, so the assertions hold unchanged at any F.
"""

from __future__ import annotations

import contextlib
import itertools
import os
import threading
import uuid
from collections.abc import Callable, Iterator
from typing import Any

import can

from simulators.drives.swpc import ControllerEmulator, VirtualController
from swpc_hw.clock import SYSTEM_CLOCK, Clock, SimClock
from swpc_hw.drives.bus import CanConfig
from swpc_hw.drives.swpc.driver import SwpcDriver
from swpc_hw.drives.types import ModuleState

INTERFACE = os.environ.get("SWPC_TEST_CAN_INTERFACE", "virtual")
CHANNELS = [c for c in os.environ.get("SWPC_TEST_CAN_CHANNEL", "").split(",") if c.strip()]
TIME_FACTOR = float(os.environ.get("SWPC_TEST_TIME_FACTOR", "1"))
if not TIME_FACTOR >= 1.0:
    raise ValueError(f"SWPC_TEST_TIME_FACTOR must be >= 1, got {TIME_FACTOR}")
_channel_pool = itertools.cycle([c.strip() for c in CHANNELS])
LOCKSTEP = INTERFACE == "virtual" and os.environ.get("SWPC_TEST_LOCKSTEP", "1") != "0"

_clock: Clock = SYSTEM_CLOCK


def clock() -> Clock:
    """The clock of the rig in use (the real one outside a rig)."""
    return _clock


@contextlib.contextmanager
def rig_clock(lockstep: bool = LOCKSTEP) -> Iterator[Clock]:
    """A fresh clock for one rig; the calling (test) thread is its participant."""
    global _clock
    prev = _clock
    if not lockstep:
        _clock = SYSTEM_CLOCK
        try:
            yield _clock
        finally:
            _clock = prev
        return
    sim = SimClock()
    _clock = sim
    try:
        with sim.participant():
            yield sim
    finally:
        sim.close()
        _clock = prev


def emulator(nodes: Any, channel: str) -> ControllerEmulator:
    """The rig's emulated controllers (nodes: node ids or controllers) on its clock."""
    ctrls = [n if isinstance(n, VirtualController) else controller(n) for n in nodes]
    return ControllerEmulator(ctrls, interface=INTERFACE, channel=channel, clock=_clock)

FEEDBACK_RATE_HZ = round(200 / TIME_FACTOR)
"""Feedback rate of the rig's controllers and driver (200 Hz at F = 1)."""
WATCHDOG_MS = round(100 * TIME_FACTOR)
"""Controller watchdog timeout set by the driver (100 ms at F = 1)."""


def T(seconds: float) -> float:
    """A test time (timeout, sleep, window, bound) in rig seconds: ``seconds * F``."""
    return seconds * TIME_FACTOR


def new_channel() -> str:
    """A fresh channel name (virtual) or the next configured SocketCAN interface."""
    return next(_channel_pool) if CHANNELS else f"swpc-test-{uuid.uuid4().hex[:8]}"


def controller(node: int) -> VirtualController:
    """An emulated controller with the rig's periods (feedback, heartbeat, watchdog)."""
    return VirtualController(
        node, rate_hz=FEEDBACK_RATE_HZ, watchdog_ms=WATCHDOG_MS, heartbeat_period=T(0.1)
    )


def can_config(channel: str, **cfg: Any) -> CanConfig:
    """The driver configuration of the rig: defaults with every period scaled by F."""
    scaled: dict[str, Any] = {
        "feedback_rate_hz": FEEDBACK_RATE_HZ,
        "watchdog_timeout_ms": WATCHDOG_MS,
        "refresh_period_s": T(0.02),
        "heartbeat_period_s": T(0.1),
        "deadman_s": T(0.5),
        "activate_timeout_s": T(cfg.pop("activate_timeout_s", 1.0)),
    }
    return CanConfig(interface=INTERFACE, channel=channel, **{**scaled, **cfg})


class ScaledDriver(SwpcDriver):
    """The real :class:`SwpcDriver` on the rig's clock; only the tests' wait timeouts are
    multiplied by F."""

    def __init__(self, config: CanConfig, **kwargs: Any) -> None:
        kwargs.setdefault("clock", _clock)
        super().__init__(config, **kwargs)

    def wait_for(
        self,
        module: int,
        predicate: Callable[[ModuleState], bool],
        timeout: float,
        what: str = "condition",
    ) -> ModuleState:
        return super().wait_for(module, predicate, T(timeout), what)


class Observer(can.Listener):
    """Records every frame seen on the bus (its own bus instance), with the time of its
    bus stamp on the rig's clock.  In lockstep it reads its bus when asked (every frame
    sent up to now is there); on a real clock a thread reads it."""

    def __init__(self, channel: str) -> None:
        self.clock = _clock
        self.bus = can.Bus(interface=INTERFACE, channel=channel)
        self.frames: list[tuple[float, can.Message]] = []
        self._lock = threading.Lock()
        lockstep = isinstance(self.clock, SimClock)
        self._notifier = None if lockstep else can.Notifier(self.bus, [self], timeout=0.05)

    def on_message_received(self, msg: can.Message) -> None:
        t = self.clock.from_wall(msg.timestamp) if msg.timestamp else self.clock.now()
        with self._lock:
            self.frames.append((t, msg))

    def snapshot(self) -> list[tuple[float, can.Message]]:
        if self._notifier is None:
            msg = self.bus.recv(0)
            while msg is not None:
                self.on_message_received(msg)
                msg = self.bus.recv(0)
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
        if self._notifier is not None:
            self._notifier.stop(timeout=1.0)
        self.bus.shutdown()


def sleep(seconds: float) -> None:
    """Sleep ``seconds`` of rig time (pass ``T(x)`` for a scaled duration)."""
    _clock.sleep(seconds)


def now() -> float:
    return _clock.now()


def wait_until(pred: Callable[[], bool], timeout: float = 2.0, step: float = 0.005) -> bool:
    """Poll ``pred`` every ``step`` s of rig time until true or ``T(timeout)``."""
    end = _clock.now() + T(timeout)
    while _clock.now() < end:
        if pred():
            return True
        _clock.sleep(step)
    return pred()
