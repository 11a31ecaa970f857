"""``swpc drives scan`` on swpc's own controllers: the virtual robot's controllers on
python-can's ``virtual`` bus, in real time; the scan only listens (a frame to a
controller would feed its watchdog), and a latched error is its fault."""

from __future__ import annotations

import uuid

import can

from firmware_protocol import codec
from firmware_protocol.codec import Axis, ErrorFlag
from simulators.options import SimOptions
from simulators.virtual_robot import VirtualRobot
from swpc_hw.drives.scan import MISSING, UNEXPECTED, ScanReport, compare
from swpc_hw.drives.swpc import scan as sw
from swpc_hw.drives.swpc.config import SwpcDrives
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED


def test_scan_of_the_virtual_robots_controllers() -> None:
    ch = f"scan-swpc-{uuid.uuid4().hex[:8]}"
    sim = VirtualRobot.open(PAPER_CALIBRATED, channel=ch, options=SimOptions(physics_dt=0.005))
    sim.start()
    bus = can.Bus(interface="virtual", channel=ch)
    observer = can.Bus(interface="virtual", channel=ch)
    try:
        sim.inject_fault(3, Axis.WHEEL, ErrorFlag.OVER_TEMPERATURE)
        result = sw.scan(bus, listen_s=1.0)
        heard = []
        while (m := observer.recv(0)) is not None:
            heard.append(m)
    finally:
        bus.shutdown()
        observer.shutdown()
        sim.stop()
    found = {f.node: f for f in result.found}
    assert sorted(found) == [1, 2, 3, 4]
    three = found[3]
    assert three.fault == "wheel OVER_TEMPERATURE"
    assert three.fields["errors steer/wheel"] == "- / OVER_TEMPERATURE"
    assert three.fields["wheel"].startswith("FAULT/")
    assert found[1].fault is None and found[1].fields["homed"] == "no"
    assert found[1].fields["heartbeat"] != "-"
    hosts = [m for m in heard if codec.split_id(m.arbitration_id)[1] in codec.HOST_COMMANDS
             or m.arbitration_id == codec.SYNC_ID]  # fmt: skip
    assert hosts == []  # nothing sent: the scan only listens
    # against a config of five modules (the fifth on node 5), node 4 not in it
    cfg = SwpcDrives(modules={1: 1, 2: 2, 3: 3, 5: 5})
    report = ScanReport("swpc", ch, compare(sw.expected(cfg), result.found, configured=True),
                        True, 0, result.elapsed_s)  # fmt: skip
    assert {r.node: r.status for r in report.rows}[4] == UNEXPECTED
    assert {r.node: r.status for r in report.rows}[5] == MISSING
    assert report.problems() == [
        "module 3 (node 3) in FAULT: wheel OVER_TEMPERATURE", "module 5 (node 5) missing"
    ]
