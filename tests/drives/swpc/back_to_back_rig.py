"""The back-to-back rig of the driver tests (``test_driver_lifecycle.py``,
``test_driver_commands.py``, ``test_driver_faults.py``; their fixtures ``rig`` and
``active`` in ``conftest.py`` beside them): the CAN driver against emulated controllers on
a real python-can bus.

Default bus: python-can ``virtual`` with a unique channel per test.  The same modules run
on SocketCAN with ``SWPC_TEST_CAN_INTERFACE=socketcan SWPC_TEST_CAN_CHANNEL=vcan1,vcan2,...``
and, on a slow machine, ``SWPC_TEST_TIME_FACTOR`` (see :mod:`tests.can_rig`).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import pytest

from firmware_protocol import codec
from firmware_protocol.codec import Axis, ControlMode
from simulators.drives.swpc import ControllerEmulator, VirtualController
from swpc_hw.drives.swpc.driver import SwpcDriver
from tests.can_rig import (
    INTERFACE,
    Observer,
    ScaledDriver,
    can_config,
    emulator,
    new_channel,
    rig_clock,
)

NODES = (1, 2, 3, 4)
virtual_only = pytest.mark.skipif(
    INTERFACE != "virtual", reason="error frames can only be injected on the virtual bus"
)


@dataclass
class Rig:
    channel: str
    emu: ControllerEmulator
    drv: SwpcDriver
    obs: Observer

    def ctrl(self, node: int) -> VirtualController:
        return self.emu.controllers[node]

    def host_frames(self, since: float = 0.0) -> list[codec.Decoded]:
        """Host -> controller frames seen on the bus after ``since`` (monotonic)."""
        out = []
        for t, m in self.obs.snapshot():
            _node, cmd = codec.split_id(m.arbitration_id)
            if t >= since and (cmd in codec.HOST_COMMANDS or m.arbitration_id == 0):
                out.append(codec.parse(m.arbitration_id, bytes(m.data)))
        return out


def make_rig(nodes: tuple[int, ...] = NODES, **cfg: object) -> Iterator[Rig]:
    with rig_clock():
        channel = new_channel()
        obs = Observer(channel)
        emu = emulator(nodes, channel)
        emu.start()
        drv = ScaledDriver(can_config(channel, **cfg))
        try:
            yield Rig(channel, emu, drv, obs)
        finally:
            drv.shutdown()
            emu.stop()
            obs.close()
            assert emu.error is None


def stop_frames(frames: list[codec.Decoded]) -> tuple[set[tuple[int, Axis]], set[tuple[int, Axis]]]:
    free = {
        (f.node, f.axis)
        for f in frames
        if isinstance(f, codec.SetControl) and f.mode == ControlMode.FREE
    }
    disabled = {
        (f.node, f.axis) for f in frames if isinstance(f, codec.SetAxisState) and not f.enabled
    }
    return free, disabled


ALL_AXES = {(n, a) for n in NODES for a in Axis}
