"""``swpc drives scan`` on CiA 402 drives: its pure parts, then the scan on python-can's
``virtual`` bus against peers we did not write (canopen's own slave, ``LocalNode``, with
the virtual drive's EDS or a device of another profile) and against the project's virtual
drives (``simulators/drives/cia402.py`` in the virtual robot), in real time.

Every frame the scanner sends is recorded by an observer on the bus: SDO uploads only, no
download, no PDO, no SYNC, and an NMT command only with ``wake``.
"""

from __future__ import annotations

import threading
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import can
import canopen
import pytest
from canopen import objectdictionary as odm

from firmware_protocol import cia402
from firmware_protocol.codec import Axis, ErrorFlag
from simulators.options import SimOptions
from simulators.virtual_robot import VirtualRobot
from swpc_hw.drives.cia402 import scan as cs
from swpc_hw.drives.cia402.config import Cia402Drives
from swpc_hw.drives.scan import (
    DUPLICATE,
    FOUND,
    MISSING,
    UNEXPECTED,
    Expected,
    FoundNode,
    ScanReport,
    compare,
    parse_nodes,
)
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED

HOST = 127


# ---------------------------------------------------------------------- pure parts


def test_supported_modes_are_named_by_their_bits() -> None:
    assert cs.mode_names(0x000003A0) == ["HM", "CSP", "CSV", "CST"]  # the virtual drive's
    assert cs.mode_names(0x0000036D) == ["PP", "PV", "PT", "HM", "IP", "CSV", "CST"]
    assert cs.mode_names(1 << 4 | 1 << 10 | 1 << 11 | 1 << 16) == [
        "reserved bit 4", "CSTCA", "reserved bit 11", "maker bit 16"
    ]
    assert cs.mode_names(0) == []
    # what swpc's set-up would refuse (its own choice of modes): CSP; CST, else PT; HM
    assert cs.lacking(0x000003A0, 19) == []
    assert cs.lacking(0x000000AD, 19) == []  # PP PV PT HM CSP: profile torque will do
    assert cs.lacking(0x00000025, 19) == []  # PP PV HM: a wheel spins the robot by velocity
    assert cs.lacking(0x00000021, 19) == [  # PP HM
        "for a wheel, a torque or velocity mode (CST or PT or CSV or PV)"
    ]
    lacks = ["a position mode (CSP or PP)",
             "for a wheel, a torque or velocity mode (CST or PT or CSV or PV)"]  # fmt: skip
    assert cs.lacking(0x00000060, 19) == lacks  # HM IP
    assert cs.lacking(0x00000280, 19) == ["homing (HM)"]  # CSP CST
    assert cs.lacking(0x00000280, "absolute") == []  # an absolute steering, or a wheel
    assert cs.device_type_text(0x00020192) == "0x00020192 (CiA 402 servo drive)"
    assert cs.device_type_text(0x00000191) == "0x00000191 (CiA 401: not a 402 drive)"
    assert cs.consumers_text([cia402.consumer_entry(127, 200), 0]) == "node 127: 200 ms"
    assert cs.consumers_text([0]) == "none"


def test_found_and_expected_are_compared_node_by_node() -> None:
    exp = [Expected(1, "steer", 1), Expected(1, "wheel", 2), Expected(2, "steer", 3),
           Expected(2, "wheel", 4)]  # fmt: skip
    found = [FoundNode(1, "PRE-OPERATIONAL"), FoundNode(2, "x", fault="0x4310 excess"),
             FoundNode(4, "x", duplicate="2 answers to one SDO request"),
             FoundNode(9, "PRE-OPERATIONAL")]  # fmt: skip
    rows = compare(exp, found, configured=True)
    assert [(r.node, r.status) for r in rows] == [
        (1, FOUND), (2, FOUND), (3, MISSING), (4, DUPLICATE), (9, UNEXPECTED)
    ]
    report = ScanReport("cia402", "virtual:x", rows, True, 127, 1.2)
    assert report.problems() == [
        "module 1 wheel (node 2) in FAULT: 0x4310 excess",
        "module 2 steer (node 3) missing",
        "module 2 wheel (node 4): duplicate node id (2 answers to one SDO request)",
    ]
    # without a config nothing is expected, so nothing is unexpected
    assert {r.status for r in compare([], found[:1], configured=False)} == {FOUND}
    # the config naming a node twice
    twice = compare([Expected(1, "steer", 5), Expected(2, "steer", 5)], [FoundNode(5, "x")],
                    configured=True)  # fmt: skip
    assert twice[0].status == DUPLICATE and twice[0].label() == "module 1 steer, module 2 steer"
    assert parse_nodes("1,3-5, 9", 1, 127) == [1, 3, 4, 5, 9]
    with pytest.raises(ValueError, match=r"node ids are 1\.\.127"):
        parse_nodes("0-3", 1, 127)
    with pytest.raises(ValueError, match="'x' is not a node id"):
        parse_nodes("x", 1, 127)


def test_a_node_is_described_from_what_it_answered() -> None:
    reads: dict[tuple[int, int], cs.Value] = {
        (0x1000, 0): 0x00020192, (0x1001, 0): 0x01, (0x1018, 1): 0xFB, (0x1018, 2): 0x60500000,
        (0x1018, 3): cs.Unread(cs.ABSENT), (0x1018, 4): cs.Unread("no answer"),
        (0x6502, 0): 0x3A0, (0x1017, 0): 0, (0x1016, 0): 1, (0x1016, 1): 0x007F00C8,
        (0x6041, 0): 0x0218, (0x603F, 0): 0x8130,
    }  # fmt: skip
    f = cs.describe(5, reads, None, listened_s=1.0, homing=19)
    assert f.fault == "0x8130 life guard or heartbeat error (the host's heartbeat was lost)"
    assert f.fields["NMT"] == "unknown (no heartbeat: 0x1017 = 0)"
    assert f.fields["402 state"] == "fault" and f.fields["consumers"] == "node 127: 200 ms"
    assert f.fields["revision"] == "absent" and f.fields["serial"] == "no answer"
    assert f.fields["name"] == "-"  # not read at all
    assert f.data["absent"] == ["0x1018 sub 3"] and f.data["vendor_id"] == 0xFB
    assert f.duplicate is None and f.notes == []
    # heartbeats at twice the period 0x1017 says: two devices on one node id
    reads[(0x1017, 0)] = 100
    heard = cs.Heard(cia402.NMT_PRE_OPERATIONAL, count=21, first=0.0, last=1.0)
    f = cs.describe(5, reads, heard, listened_s=1.0)
    assert f.duplicate == "21 heartbeats in 1.00 s, 0x1017 = 100 ms allows 11"
    heard.count = 11
    assert cs.describe(5, reads, heard, listened_s=1.0).duplicate is None


# ---------------------------------------------------------------------- on the bus


def network(channel: str) -> canopen.Network:
    net = canopen.Network()
    net.NOTIFIER_CYCLE = 0.05  # disconnect() joins its wait
    return net.connect(interface="virtual", channel=channel)


class Sent(can.Listener):  # type: ignore[misc]
    """Every frame the scanner sends, seen from another node of the bus."""

    def __init__(self) -> None:
        self.frames: list[can.Message] = []
        self.lock = threading.Lock()

    def on_message_received(self, msg: can.Message) -> None:
        with self.lock:
            self.frames.append(msg)

    def from_host(self) -> list[can.Message]:
        """Frames only a master sends: NMT, SYNC, PDOs to the drives, SDO requests."""
        with self.lock:
            return [m for m in self.frames if m.arbitration_id == 0
                    or m.arbitration_id == cia402.SYNC_ID
                    or (0x200 <= m.arbitration_id < 0x580 and m.arbitration_id & 0x80 == 0)
                    or 0x600 <= m.arbitration_id < 0x680]  # fmt: skip


def assert_only_reads(sent: Sent, *, nmt: bool = False) -> None:
    """SDO uploads (initiate 0x40, segments 0x60/0x70) and aborts (0x80) only; NMT reset
    communication to all only when asked."""
    frames = sent.from_host()
    assert frames, "the scanner sent nothing"
    for m in frames:
        if m.arbitration_id == 0:
            assert nmt and bytes(m.data) == bytes([cia402.NMT_RESET_COMMUNICATION, 0]), m
            continue
        assert 0x600 <= m.arbitration_id < 0x680, f"not an SDO request: {m}"
        assert m.data[0] & 0xE0 in (0x40, 0x60, 0x80), f"not an upload: {m}"


def other_profile_od() -> odm.ObjectDictionary:
    """A CANopen device that is not a drive (a CiA 401 I/O module): device type, error
    register, heartbeat producer, an identity without its serial number."""
    od = odm.ObjectDictionary()

    def var(name: str, index: int, sub: int, dtype: int, default: int) -> odm.ODVariable:
        v = odm.ODVariable(name, index, sub)
        v.data_type, v.access_type, v.default = dtype, "ro", default
        return v

    od.add_object(var("Device type", 0x1000, 0, odm.UNSIGNED32, 0x00000191))
    od.add_object(var("Error register", 0x1001, 0, odm.UNSIGNED8, 0))
    hb = var("Producer heartbeat time", 0x1017, 0, odm.UNSIGNED16, 100)
    hb.access_type = "rw"
    od.add_object(hb)
    ident = odm.ODRecord("Identity object", 0x1018)
    for sub, name, value in ((0, "Number of entries", 3), (1, "Vendor-ID", 0x0000AB12),
                             (2, "Product code", 0x00000401), (3, "Revision", 2)):  # fmt: skip
        ident.add_member(var(name, 0x1018, sub, odm.UNSIGNED8 if sub == 0 else odm.UNSIGNED32,
                             value))  # fmt: skip
    od.add_object(ident)
    return od


@pytest.fixture()
def local_bus() -> Iterator[tuple[str, dict[int, canopen.LocalNode], Sent]]:
    """On one virtual bus, canopen's LocalNode as drives: node 1 (identity of a real make,
    the host's heartbeat consumed), node 2 with its heartbeat off (0x1017 = 0), node 3 in
    FAULT, node 4 twice (two devices, one node id), node 10 a CiA 401 I/O module; each
    but node 2 with a heartbeat every 100 ms."""
    ch = f"scan-local-{uuid.uuid4().hex[:8]}"
    nets = [network(ch), network(ch)]
    nodes: dict[int, canopen.LocalNode] = {}
    twins = []
    for n in (1, 2, 3, 4, 10):
        node = canopen.LocalNode(n, other_profile_od() if n == 10 else str(cia402.EDS_PATH))
        nets[0].add_node(node)
        nodes[n] = node
    twin = canopen.LocalNode(4, str(cia402.EDS_PATH))
    nets[1].add_node(twin)
    twins.append(twin)
    one = nodes[1].sdo
    one[0x1018][1].raw, one[0x1018][2].raw = 0x000000FB, 0x60500000  # vendor, product
    one[0x1018][3].raw, one[0x1018][4].raw = 0x01700000, 0x12345678  # revision, serial
    one[cia402.CONSUMER_HEARTBEAT][1].raw = cia402.consumer_entry(HOST, 200)
    one[cia402.STATUSWORD].raw = 0x0250  # switch on disabled, remote
    for node in (nodes[1], nodes[3], nodes[4], twin):
        node.sdo[cia402.PRODUCER_HEARTBEAT].raw = 100  # the EDS' default is CiA 301's: 0
    nodes[2].sdo[cia402.PRODUCER_HEARTBEAT].raw = 0
    three = nodes[3].sdo
    three[cia402.STATUSWORD].raw = 0x0218  # fault
    three[cia402.ERROR_CODE].raw, three[cia402.ERROR_REGISTER].raw = 0x7305, 0x01
    for node in [*nodes.values(), *twins]:
        node.nmt.send_command(cia402.NMT_RESET_NODE)  # boot-up
        node.nmt.send_command(cia402.NMT_ENTER_PRE_OPERATIONAL)  # heartbeat (0x1017)
    observer = can.Bus(interface="virtual", channel=ch)
    sent = Sent()
    notifier = can.Notifier(observer, [sent], timeout=0.05)
    try:
        yield ch, nodes, sent
    finally:
        notifier.stop()
        observer.shutdown()
        for node in [*nodes.values(), *twins]:
            node.nmt.stop_heartbeat()
        for net in nets:
            net.disconnect()


def test_scan_finds_canopens_local_nodes_and_reads_what_each_is(
    local_bus: tuple[str, dict[int, canopen.LocalNode], Sent],
) -> None:
    ch, _nodes, sent = local_bus
    net = network(ch)
    try:
        t0 = time.monotonic()
        result = cs.scan(net, range(1, 128), listen_s=1.0)
        wall = time.monotonic() - t0
    finally:
        net.disconnect()
    print(f"\ncia402 scan of 127 nodes against LocalNodes: {wall:.2f} s (listen 1.0 s, probe "
          f"{result.probe_s:.3f} s), {len(result.found)} found")  # fmt: skip
    found = {f.node: f for f in result.found}
    assert sorted(found) == [1, 2, 3, 4, 10] and result.candidates == 127
    assert result.probe_s < 1.0  # two rounds of 50 ms, not 127 timeouts
    one = found[1].fields
    assert one["NMT"] == "PRE-OPERATIONAL" and one["402 state"] == "switch on disabled"
    assert (one["vendor"], one["product"], one["revision"], one["serial"]) == (
        "0x000000FB", "0x60500000", "0x01700000", "0x12345678"
    )
    assert one["device type"] == "0x00020192 (CiA 402 servo drive)"
    assert one["modes"] == "HM CSP CSV CST" and found[1].data["modes"] == ["HM", "CSP", "CSV",
                                                                           "CST"]
    assert one["heartbeat"] == "100 ms" and one["consumers"] == "node 127: 200 ms"
    assert one["name"] == "swpc virtual CiA 402 axis" and one["software"] == "absent"
    assert found[1].fault is None and found[1].duplicate is None
    # no heartbeat: found by the SDO probe all the same
    assert found[2].fields["NMT"] == "unknown (no heartbeat: 0x1017 = 0)"
    assert found[2].fields["heartbeat"] == "0 ms" and found[2].data["nmt_state"] is None
    # in FAULT: 0x603F named
    assert found[3].fault == "0x7305 incremental sensor 1 fault"
    assert found[3].fields["402 state"] == "fault" and found[3].fields["error register"] == "0x01"
    # two devices on node 4: two answers to the probe (on a host too busy for both within
    # the first 50 ms, their heartbeats at twice the period of 0x1017 tell it)
    dup = found[4].duplicate or ""
    assert dup == "2 answers to one SDO request" or " heartbeats in " in dup, dup
    # another profile: the 402 objects and the serial absent, never an exception
    ten = found[10]
    assert ten.fields["device type"] == "0x00000191 (CiA 401: not a 402 drive)"
    for k in ("modes", "402 state", "serial", "name", "consumers"):
        assert ten.fields[k] == "absent", k
    assert ten.fields["vendor"] == "0x0000AB12" and ten.fault is None
    assert "not a CiA 402 drive (0x1000)" in ten.notes
    assert set(ten.data["absent"]) >= {"0x6502", "0x6041", "0x1018 sub 4", "0x1016"}
    assert_only_reads(sent)


def test_a_drive_lacking_a_mode_swpc_needs_is_noted(
    local_bus: tuple[str, dict[int, canopen.LocalNode], Sent],
) -> None:
    ch, nodes, _sent = local_bus
    nodes[1].sdo[cia402.SUPPORTED_MODES].raw = 0x00000023  # PP VL HM: no mode to spin by
    net = network(ch)
    try:
        result = cs.scan(net, [1], listen_s=0.2, homing={1: 19})
    finally:
        net.disconnect()
    (one,) = [f for f in result.found if f.node == 1]
    assert one.fields["modes"] == "PP VL HM"
    assert one.notes == [
        "lacks what swpc needs: for a wheel, a torque or velocity mode (CST or PT or CSV or PV)"
    ]


@pytest.fixture()
def virtual_robot() -> Iterator[tuple[VirtualRobot, str]]:
    ch = f"scan-sim-{uuid.uuid4().hex[:8]}"
    opts = SimOptions(drives=Cia402Drives(), physics_dt=0.005, seed=3)
    sim = VirtualRobot.open(PAPER_CALIBRATED, channel=ch, options=opts)
    sim.start()
    try:
        yield sim, ch
    finally:
        sim.stop()


def test_scan_of_the_virtual_robots_drives_and_wake(
    virtual_robot: tuple[VirtualRobot, str],
) -> None:
    sim, ch = virtual_robot
    sent = Sent()
    observer = can.Bus(interface="virtual", channel=ch)
    notifier = can.Notifier(observer, [sent], timeout=0.05)
    net = network(ch)
    try:
        sim.inject_fault(2, Axis.WHEEL, ErrorFlag.OVER_TEMPERATURE)  # node 4
        result = cs.scan(net, range(1, 128), listen_s=1.0)
        assert_only_reads(sent)
        found = {f.node: f for f in result.found}
        assert sorted(found) == list(range(1, 9))
        for f in found.values():  # as they come from the box: silent (CiA 301's 0x1017 = 0)
            assert f.fields["NMT"] == "unknown (no heartbeat: 0x1017 = 0)"
            assert f.fields["product"] == "0x00000402" and f.fields["revision"] == "0x00010000"
            assert f.fields["modes"] == "HM CSP CSV CST" and f.fields["heartbeat"] == "0 ms"
            assert f.fields["name"] == "swpc virtual CiA 402 axis"
            assert f.fields["402 state"] == ("fault" if f.node == 4 else "switch on disabled")
        assert found[4].fault == "0x4310 excess temperature drive"
        assert found[4].fields["error register"] == "0x01"
        assert [f.node for f in found.values() if f.fault] == [4]
        print(f"\ncia402 scan of 127 nodes, the virtual robot's 8 drives: "
              f"{result.elapsed_s:.2f} s (probe {result.probe_s:.3f} s)")  # fmt: skip
        # --wake: one NMT reset communication to all, every drive boots again
        with sent.lock:
            sent.frames.clear()
        woken = cs.scan(net, range(1, 9), listen_s=0.5, wake=True)
        assert_only_reads(sent, nmt=True)
        nmt = [m for m in sent.from_host() if m.arbitration_id == 0]
        assert len(nmt) == 1
        assert {f.node for f in woken.found} == set(range(1, 9))
        assert all(f.data["boot_ups"] == 1 for f in woken.found), [
            (f.node, f.data["boot_ups"]) for f in woken.found
        ]
        assert woken.elapsed_s >= 2.0  # a wake listens 2 s for the boot-ups
    finally:
        net.disconnect()
        notifier.stop()
        observer.shutdown()


def test_scan_reads_real_drives_published_object_dictionaries() -> None:
    """canopen's LocalNode serving each of the seven real drives' EDS files
    (``tests/drives/cia402/eds/``, their survey in its README): every one found by the
    probe though none but Pilz's configured file sends a heartbeat (CiA 301's 0x1017 = 0),
    its identity and modes as its maker wrote them, the modes swpc needs and it lacks
    noted, what it lacks absent, what its file gives no value for named by its abort."""
    eds = sorted((Path(__file__).with_name("eds")).glob("*.eds"))
    names = [p.stem for p in eds]
    ch = f"scan-eds-{uuid.uuid4().hex[:8]}"
    peer = network(ch)
    locals_ = []
    for node, path in enumerate(eds, 1):
        local = canopen.LocalNode(node, canopen.import_od(str(path), node))
        peer.add_node(local)
        local.nmt.send_command(cia402.NMT_RESET_NODE)
        local.nmt.send_command(cia402.NMT_ENTER_PRE_OPERATIONAL)
        locals_.append(local)
    net = network(ch)
    try:
        result = cs.scan(net, range(1, 128), listen_s=0.5,
                         homing={n: 19 for n in range(1, len(eds) + 1)})  # fmt: skip
    finally:
        net.disconnect()
        for local in locals_:
            local.nmt.stop_heartbeat()
        peer.disconnect()
    f = {names[x.node - 1]: x for x in result.found}
    assert sorted(f) == sorted(names)
    assert {n: x.fields["vendor"] for n, x in f.items() if n != "pilz_prbt"} == {
        "elmo_gold": "0x0000009A", "faulhaber_mcdc300_co": "0x00000147",
        "schunk_prl120": "0x00000000", "technosoft_idm_iscm": "0x000001A3",
        "technosoft_ipos": "0x000001A3", "wittenstein_simco": "0x0000010A",
        "yiyou_euservo": "0x00000668",
    }  # fmt: skip
    assert {n: x.fields["modes"] for n, x in f.items() if n != "elmo_gold"} == {
        "faulhaber_mcdc300_co": "PP PV HM", "pilz_prbt": "PP VL IP", "schunk_prl120": "HM IP",
        "technosoft_idm_iscm": "PP PV HM IP",
        "technosoft_ipos": "PP PV HM IP maker bit 16 maker bit 17 maker bit 18 maker bit 19 "
        "maker bit 20",
        "wittenstein_simco": "PP PV PT HM IP CSP CSV CST",
        "yiyou_euservo": "PP PV PT IP CSP CSV CST",
    }  # fmt: skip
    # Elmo's file declares 0x6502 without a value: canopen's slave aborts the read
    assert f["elmo_gold"].fields["modes"] == "abort 0x060A0023: Resource not available"
    # what swpc's set-up says of them too (docs/drives.md's table of real drives)
    assert f["yiyou_euservo"].notes == ["lacks what swpc needs: homing (HM)"]
    assert f["elmo_gold"].notes == []  # no 0x6502 value: the set-up tries the modes
    for name in ("faulhaber_mcdc300_co", "technosoft_idm_iscm", "wittenstein_simco"):
        assert f[name].notes == [], name  # PP PV HM: a wheel spins the robot by velocity
    assert f["schunk_prl120"].notes == [
        "lacks what swpc needs: a position mode (CSP or PP), "
        "for a wheel, a torque or velocity mode (CST or PT or CSV or PV)"
    ]
    assert f["pilz_prbt"].notes == [
        "lacks what swpc needs: for a wheel, a torque or velocity mode (CST or PT or CSV or "
        "PV), homing (HM)"
    ]
    # absent: what the file does not have at all
    idm = f["technosoft_idm_iscm"]
    assert idm.fields["consumers"] == "absent" and idm.fields["product"] == "absent"
    assert idm.data["absent"] == ["0x1008", "0x100A", "0x1016", "0x1018 sub 2", "0x1018 sub 3",
                                  "0x1018 sub 4"]  # fmt: skip
    yiyou = f["yiyou_euservo"]
    assert (yiyou.fields["product"], yiyou.fields["revision"], yiyou.fields["serial"]) == (
        "0x00220811", "0x00000010", "absent"
    )
    assert (yiyou.fields["name"], yiyou.fields["software"]) == ("EuPH11D-101", "V135")
    assert f["faulhaber_mcdc300_co"].fields["software"] == "3150.68B"
    # the silent ones found by the probe; Pilz's DCF configures a heartbeat
    pilz = f["pilz_prbt"]
    assert (pilz.fields["NMT"], pilz.fields["heartbeat"]) == ("PRE-OPERATIONAL", "100 ms")
    assert all(x.fields["NMT"] == "unknown (no heartbeat: 0x1017 = 0)"
               for n, x in f.items() if n != "pilz_prbt")  # fmt: skip
    assert all(x.fault is None and x.duplicate is None for x in f.values())
