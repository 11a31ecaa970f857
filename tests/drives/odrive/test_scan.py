"""``swpc drives scan`` on ODrives: ``Get_Version`` against ODrive's documented layout and
odrive-can's decoder, an axis described from its heartbeat, and the scan on python-can's
``virtual`` bus against the virtual robot's ODrives (both firmware lines) and odrive-can's
mock ODrive (a peer we did not write), in real time.  The scanner sends nothing but remote
``Get_Version`` frames (0.6.x), and nothing at all on 0.5.x.
"""

from __future__ import annotations

import asyncio
import struct
import threading
import uuid
from collections.abc import Iterator

import can
import pytest

from firmware_protocol.codec import Axis, ErrorFlag, ProtocolError
from firmware_protocol.odrive import can_simple as cs
from simulators.options import SimOptions
from simulators.virtual_robot import VirtualRobot
from swpc_hw.drives.odrive import scan as od
from swpc_hw.drives.odrive.config import ODriveDrives
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED


def test_get_version_is_odrives_layout_and_only_060_has_it() -> None:
    """Get_Version (0.6.x): protocol, hardware major / minor / variant, firmware major /
    minor / revision / unreleased, a byte each, as ODrive's CAN protocol table lists them;
    odrive-can's own decoder reads ours.  0.5.x has no version message."""
    from odrive_can.utils import get_dbc

    c = cs.can_simple("0.6")
    assert c.has_version and not cs.can_simple("0.5").has_version
    f = c.version(9, (0, 6, 10), (4, 4, 58), protocol=2, unreleased=True)
    assert f.arbitration_id == 9 << 5 | 0x00
    assert f.data == struct.pack("<8B", 2, 4, 4, 58, 0, 6, 10, 1)
    v = c.decode(f.arbitration_id, f.data)
    assert isinstance(v, cs.Version) and v.node == 9
    assert (v.firmware, v.hardware, v.protocol) == ("0.6.10-dev", "4.4.58", 2)
    f5 = c.version(5, (0, 6, 10), (4, 4, 58))  # odrive-can's DBC has nodes 0..7
    theirs = get_dbc(cs.FIRMWARE_LINES["0.6"]).get_message_by_frame_id(f5.arbitration_id)
    dec = theirs.decode(f5.data)
    assert theirs.name == "Axis5_Get_Version"
    assert [dec[f"Fw_Version_{k}"] for k in ("Major", "Minor", "Revision")] == [0, 6, 10]
    assert [dec[f"Hw_Version_{k}"] for k in ("Major", "Minor", "Variant")] == [4, 4, 58]
    assert c.version_request(9).arbitration_id == 0x120
    with pytest.raises(ProtocolError, match=r"0\.5: no Get_Version"):
        cs.can_simple("0.5").version_request(9)
    assert c.procedure_name(14) == "NOT_CALIBRATED" and c.procedure_name(99) == "99"
    assert cs.can_simple("0.5").procedure_name(None) == "-"


@pytest.mark.parametrize("line", ["0.5", "0.6"])
def test_an_axis_is_described_from_its_heartbeat(line: str) -> None:
    c = cs.can_simple(line)
    over = c.error_bit("OVER_TEMP" if line == "0.5" else "MOTOR_OVER_TEMP")
    hb = cs.Heartbeat(3, over | c.watchdog_bit, cs.AxisState.IDLE,
                      None if line == "0.5" else 0, True, 0b010)  # fmt: skip
    heard = od.AxisHeard(hb, heartbeats=11, first=0.0, last=1.0, estimates=200)
    if c.has_version:
        heard.versions.append(cs.Version(3, 2, 4, 4, 58, 0, 6, 10, 0))
    f = od.describe(c, 3, heard, listened_s=1.0, asked=True)
    assert f.state == "IDLE" and f.fields["heartbeat"] == "10.0 Hz"
    assert f.fault == ("OVER_TEMP" if line == "0.5" else "MOTOR_OVER_TEMP")  # not the watchdog
    assert f.fields["estimates"] == "200 /s"
    if line == "0.5":
        assert f.fields["axis error"] == "WATCHDOG_TIMER_EXPIRED|OVER_TEMP"
        assert f.fields["error flags"] == "encoder"
        assert f.fields["firmware"] == "not reported by this firmware"
        assert f.notes == ["WATCHDOG_TIMER_EXPIRED: a 0.5.x axis left alone reports it "
                           "between runs"]  # fmt: skip
    else:
        assert f.fields["procedure result"] == "SUCCESS"
        assert f.fields["firmware"] == "0.6.10 (hardware 4.4.58)"
        heard.versions.append(heard.versions[0])
        again = od.describe(c, 3, heard, listened_s=1.0, asked=True)
        assert again.duplicate == "2 answers to one Get_Version request"


class Frames(can.Listener):  # type: ignore[misc]
    def __init__(self) -> None:
        self.frames: list[can.Message] = []
        self.lock = threading.Lock()

    def on_message_received(self, msg: can.Message) -> None:
        with self.lock:
            self.frames.append(msg)

    def hosts(self, line: str) -> list[can.Message]:
        """Frames only a host sends: its commands and remote frames."""
        c = cs.can_simple(line)
        with self.lock:
            return [m for m in self.frames
                    if m.is_remote_frame or m.arbitration_id & cs.CMD_MASK in c.host_cmds]


@pytest.fixture(params=["0.5", "0.6"])
def odrive_robot(request: pytest.FixtureRequest) -> Iterator[tuple[VirtualRobot, str, str]]:
    line = request.param
    ch = f"scan-odrive-{uuid.uuid4().hex[:8]}"
    opts = SimOptions(drives=ODriveDrives(firmware=line, homing="absolute"), physics_dt=0.005,
                      watchdog_ms=200, feedback_rate_hz=50)  # fmt: skip
    sim = VirtualRobot.open(PAPER_CALIBRATED, channel=ch, options=opts)
    sim.start()
    try:
        yield sim, ch, line
    finally:
        sim.stop()


def test_scan_of_the_virtual_robots_odrives(odrive_robot: tuple[VirtualRobot, str, str]) -> None:
    sim, ch, line = odrive_robot
    sim.inject_fault(2, Axis.STEER, ErrorFlag.OVER_TEMPERATURE)  # node 2
    seen = Frames()
    observer = can.Bus(interface="virtual", channel=ch)
    notifier = can.Notifier(observer, [seen], timeout=0.05)
    bus = can.Bus(interface="virtual", channel=ch)
    try:
        result = od.scan(bus, line, listen_s=1.0)
    finally:
        bus.shutdown()
        notifier.stop()
        observer.shutdown()
    found = {f.node: f for f in result.found}
    print(f"\nodrive {line} scan: {len(found)} axes in {result.elapsed_s:.2f} s")
    assert sorted(found) == list(range(8))
    assert found[2].fault == ("OVER_TEMP" if line == "0.5" else "MOTOR_OVER_TEMP")
    assert all(found[n].fault is None for n in found if n != 2)
    assert all(f.state == "IDLE" and f.fields["estimates"] != "none" for f in found.values())
    sent = seen.hosts(line)
    if line == "0.5":
        assert {f.fields["firmware"] for f in found.values()} == {"not reported by this firmware"}
        assert sent == []  # a 0.5.x axis' watchdog takes any frame: none is sent
        # an idle 0.5.x axis counts its watchdog down: reported, not a fault
        assert "WATCHDOG_TIMER_EXPIRED" in found[0].fields["axis error"] and found[0].notes
    else:
        assert {f.fields["firmware"] for f in found.values()} == {"0.6.10 (hardware 0.0.0)"}
        assert all(f.duplicate is None for f in found.values())
        assert sorted(m.arbitration_id for m in sent) == [n << 5 for n in range(8)]
        assert all(m.is_remote_frame for m in sent)


def test_scan_against_odrive_cans_mock_finds_two_axes_on_one_node() -> None:
    """odrive-can's ODriveCANMock answers any remote frame with the message's zeros: two
    mocks on node 3 answer one Get_Version twice."""
    from odrive_can.mock import ODriveCANMock

    channel = f"odrive-scan-peer-{uuid.uuid4().hex[:8]}"
    ids = (0, 3, 3)
    buses = [can.Bus(interface="virtual", channel=channel) for _ in ids]
    mocks = [ODriveCANMock(axis_id=n, can_bus=b) for n, b in zip(ids, buses, strict=True)]
    for m in mocks:
        m.notifier.timeout = 0.05  # stop() joins its wait (python-can's default: 1 s)
    loop = asyncio.new_event_loop()
    tasks: list[asyncio.Task[None]] = []

    def serve() -> None:
        asyncio.set_event_loop(loop)
        for m in mocks:
            tasks.append(loop.create_task(m.main()))
        loop.run_forever()

    th = threading.Thread(target=serve, daemon=True)
    th.start()
    bus = can.Bus(interface="virtual", channel=channel)
    try:
        result = od.scan(bus, "0.6", listen_s=1.0, version_timeout_s=0.3)
    finally:
        bus.shutdown()

        async def cancel() -> None:
            for t in tasks:
                t.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)

        asyncio.run_coroutine_threadsafe(cancel(), loop).result(timeout=5)
        loop.call_soon_threadsafe(loop.stop)
        th.join(timeout=5)
        for m in mocks:
            m.notifier.stop()
        for b in buses:
            b.shutdown()
    found = {f.node: f for f in result.found}
    assert sorted(found) == [0, 3]
    assert found[0].state == "IDLE" and found[0].duplicate is None
    assert found[0].fields["firmware"] == "0.0.0 (hardware 0.0.0)"  # the mock's zeros
    assert found[3].duplicate == "2 answers to one Get_Version request"
