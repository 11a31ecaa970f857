"""Real drives without a heartbeat consumer or a torque mode (issue 42, the real drives'
table): Technosoft's iPOS (no 0x1016, modes PP PV HM IP) and Faulhaber's MCDC300 CO (modes
PP PV HM), each given by its published EDS, against the virtual drive serving only what
that EDS declares.

* Node guarding, CiA 301's other error control, is the drive-side dead-man of a drive
  without a heartbeat consumer: the host asks every guarded drive's state each heartbeat
  period, the drive answers with its NMT state and a toggle bit, and stops (EMCY 0x8130,
  power stage off) the life time after the host's last request.
* An axis without a torque mode is free with its power stage off: ``free`` and ``enable``
  switch it off, a position or velocity command powers it again, and once stopped it stays
  off whatever is commanded, until ``enable``.

A whole calibration on each: ``tests/services/whole_runs/test_calibration_on_real_drives.py``.
"""

from __future__ import annotations

import itertools
import threading
import uuid
from collections.abc import Iterator

import can
import pytest

from firmware_protocol import cia402
from firmware_protocol.cia402 import PowerState
from firmware_protocol.codec import Axis, AxisState
from simulators.drives.cia402 import VirtualAxis, VirtualCia402Module
from simulators.options import SimOptions
from simulators.virtual_robot import VirtualRobot
from swpc_hw.clock import SimClock
from swpc_hw.drives.bus import CanConfig
from swpc_hw.drives.cia402.config import Cia402Drives
from swpc_hw.drives.cia402.driver import Cia402Driver
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED
from tests.drives.cia402.test_real_drive_personalities import EDS, personality

RATE = 50
"""Hz: SYNC, as the personalities' set-up test."""


class Recorder(can.Listener):
    """Every frame on the channel with its time on the clock (a second bus)."""

    def __init__(self, clock: SimClock) -> None:
        self.clock = clock
        self.lock = threading.Lock()
        self.frames: list[tuple[float, int, bool, bytes]] = []

    def on_message_received(self, msg: can.Message) -> None:
        with self.lock:
            self.frames.append((self.clock.from_wall(msg.timestamp), msg.arbitration_id,
                                msg.is_remote_frame, bytes(msg.data)))  # fmt: skip


class Rig:
    def __init__(self, name: str) -> None:
        self.cfg = Cia402Drives.model_validate(personality(EDS / f"{name}.eds"))
        self.clock = SimClock()
        ch = f"cia402-guard-{uuid.uuid4().hex[:8]}"
        self.bus = CanConfig(channel=ch, feedback_rate_hz=RATE)
        self.host = Cia402Driver(self.cfg, self.bus, clock=self.clock)
        self.host.configure()
        opts = SimOptions(drives=self.cfg, physics_dt=0.01)
        self.sim = VirtualRobot.open(PAPER_CALIBRATED, channel=ch, clock=self.clock, options=opts)
        self.rec = Recorder(self.clock)
        self.obs = can.Bus(interface="virtual", channel=ch, preserve_timestamps=True)
        self.notifier = can.Notifier(self.obs, [self.rec], timeout=0.05)
        self.sim.start()

    def axis(self, module: int, axis: Axis) -> VirtualAxis:
        d = self.sim.drives[PAPER_CALIBRATED.ids.index(module)]
        assert isinstance(d, VirtualCia402Module)
        return d.axes[int(axis)]

    def close(self) -> None:
        self.notifier.stop()
        self.obs.shutdown()
        self.sim.stop()
        self.host.shutdown()
        self.clock.close()


@pytest.fixture
def technosoft() -> Iterator[Rig]:
    rig = Rig("technosoft_ipos")
    yield rig
    rig.close()


@pytest.fixture
def faulhaber() -> Iterator[Rig]:
    rig = Rig("faulhaber_mcdc300_co")
    yield rig
    rig.close()


def test_a_drive_without_a_heartbeat_consumer_is_guarded_and_stops_when_the_host_does(
    technosoft: Rig,
) -> None:
    rig, host, clock = technosoft, technosoft.host, technosoft.clock
    guard_ms, factor = round(1000 * rig.bus.refresh_period_s), 10
    with clock.participant():
        host.activate()
        for m in host.modules():
            host.enable(m, Axis.STEER)
            host.enable(m, Axis.WHEEL)
            host.start_homing(m)
        host.wait_for(1, lambda s: s.homed, 5.0, "homed")
        for node in rig.cfg.nodes():
            ax = rig.axis((node + 1) // 2, Axis.STEER if node % 2 else Axis.WHEEL)
            od = ax.node.object_dictionary
            assert ax._read(cia402.GUARD_TIME) == guard_ms, od[cia402.GUARD_TIME].name
            assert ax._read(cia402.LIFE_TIME_FACTOR) == factor
            assert ax._read(cia402.PRODUCER_HEARTBEAT) == 0  # guarding, not heartbeats
        host.set_velocity(2, Axis.WHEEL, 2.0)
        clock.sleep(0.5)
        assert rig.axis(2, Axis.WHEEL).state is PowerState.OPERATION_ENABLED
        for m in host.modules():
            for axis in (Axis.STEER, Axis.WHEEL):
                st = host.axis_status(m, axis)
                assert st.alive and st.nmt == "OPERATIONAL", st
        # the host stops: no guard request, no SYNC
        clock.remove_hook(host._io_hook)
        clock.sleep(0.6)
    rig.notifier.stop()  # every frame read (its thread ends)
    frames = rig.rec.frames
    for node in rig.cfg.nodes():
        asks = [t for t, i, rtr, _ in frames if rtr and i == cia402.HEARTBEAT_BASE + node]
        answers = [d[0] for t, i, rtr, d in frames  # after the boot-up, to the requests
                   if not rtr and i == cia402.HEARTBEAT_BASE + node and t >= asks[0] - 1e-3]
        gaps = [b - a for a, b in itertools.pairwise(asks)]
        assert len(asks) > 20 and max(gaps) == pytest.approx(guard_ms / 1000, abs=1e-6)
        toggles = [a >> 7 for a in answers]
        assert toggles == [k % 2 for k in range(len(toggles))], node  # 0, 1, 0, ...
        assert answers[-1] & 0x7F == cia402.NMT_OPERATIONAL
        emcy = [t for t, i, _, d in frames
                if i == cia402.EMCY_BASE + node and d[:2] == b"\x30\x81"]  # fmt: skip
        assert emcy, f"node {node}: no EMCY 0x8130 after the guard requests stopped"
        late = emcy[0] - asks[-1]
        assert guard_ms * factor / 1000 <= late <= guard_ms * factor / 1000 + 0.01 + 1e-6
    for d in rig.sim.drives:
        for ax in d.axes:  # type: ignore[attr-defined]
            assert ax.state is PowerState.FAULT and ax.error_code == 0x8130
            assert ax.axis_model().state is AxisState.DISABLED  # free
    print(f"\nnode guarding: {len(rig.cfg.nodes())} drives stopped (EMCY 0x8130) "
          f"{guard_ms * factor} ms after the host's last guard request")  # fmt: skip


def test_an_axis_without_a_torque_mode_is_free_off_powered_by_commands_and_stays_off_after_a_stop(
    faulhaber: Rig,
) -> None:
    rig, host, clock = faulhaber, faulhaber.host, faulhaber.clock
    wheel = rig.axis(2, Axis.WHEEL)
    with clock.participant():
        host.activate()
        host.enable(2, Axis.WHEEL)
        clock.sleep(0.2)
        assert wheel.state is PowerState.SWITCH_ON_DISABLED  # enabled = free: power off
        assert not host.axis_status(2, Axis.WHEEL).torque_mode
        with pytest.raises(Exception, match=r"no torque mode \(0x6502\): drive it by velocity"):
            host.set_torque(2, Axis.WHEEL, 0.5)
        host.set_velocity(2, Axis.WHEEL, 3.0)
        clock.sleep(0.5)
        assert wheel.state is PowerState.OPERATION_ENABLED
        assert wheel.velocity == pytest.approx(3.0, rel=0.05)
        host.free(2, Axis.WHEEL)
        clock.sleep(0.2)
        assert wheel.state is PowerState.SWITCH_ON_DISABLED
        assert wheel.axis_model().state is AxisState.DISABLED  # no torque: it rolls freely
        host.hold(2, Axis.WHEEL)  # a position command powers it again
        clock.sleep(0.3)
        assert wheel.state is PowerState.OPERATION_ENABLED
        host.free(2, Axis.WHEEL)  # free, then a stop: a command after it powers nothing
        host.stop_all()
        host.set_velocity(2, Axis.WHEEL, 3.0)  # e.g. a run's command racing its abort
        clock.sleep(0.5)
        assert wheel.state is PowerState.SWITCH_ON_DISABLED
        assert wheel.axis_model().state is AxisState.DISABLED  # no torque: not driven
