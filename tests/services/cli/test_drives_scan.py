"""``swpc drives scan`` as a technician runs it: the real command (``services.cli.main``)
against the virtual robot's drives on python-can's ``virtual`` bus, with a robot config
that names a node the bus does not have and misses one it has; its tables, its JSON, its
exit status and its one line on stderr."""

from __future__ import annotations

import json
import uuid
from collections.abc import Iterator
from pathlib import Path

import can
import pytest
import yaml

from firmware_protocol.codec import Axis, ErrorFlag
from services.cli import main
from simulators.options import SimOptions
from simulators.virtual_robot import VirtualRobot
from swpc_hw.drives.cia402.config import Cia402Drives
from swpc_hw.drives.odrive.config import ODriveDrives
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED


def robot(drives: object) -> Iterator[tuple[VirtualRobot, str]]:
    ch = f"cli-scan-{uuid.uuid4().hex[:8]}"
    opts = SimOptions(drives=drives, physics_dt=0.005, watchdog_ms=200,  # type: ignore[arg-type]
                      feedback_rate_hz=50)  # fmt: skip
    sim = VirtualRobot.open(PAPER_CALIBRATED, channel=ch, options=opts)
    sim.start()
    try:
        yield sim, ch
    finally:
        sim.stop()


@pytest.fixture(scope="module")
def cia402_robot() -> Iterator[tuple[VirtualRobot, str]]:
    yield from robot(Cia402Drives())


def config(tmp_path: Path, drives: object) -> str:
    path = tmp_path / "robot.yaml"
    path.write_text(yaml.safe_dump({"drives": drives}), encoding="utf-8")
    return str(path)


def test_a_configured_node_missing_fails_naming_its_module_axis_and_node(
    cia402_robot: tuple[VirtualRobot, str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _sim, ch = cia402_robot
    modules = {m: {"steer": {"node": 2 * m - 1}, "wheel": {"node": 2 * m}} for m in (1, 2, 3)}
    modules[4] = {"steer": {"node": 7}, "wheel": {"node": 20}}  # the bus has node 8 instead
    path = config(tmp_path, {"kind": "cia402", "modules": modules})
    argv = ["drives", "scan", "--channel", ch, "--config", path, "--listen", "0.5"]
    assert main(argv) == 1
    out, err = capsys.readouterr()
    assert err.strip().splitlines() == [
        "swpc drives scan: error: module 4 wheel (node 20) missing"
    ]
    lines = out.splitlines()
    header = lines[0].split()
    assert header[:5] == ["node", "expected", "status", "NMT", "402"]
    first = lines[: lines.index("")]  # the state table; the identity table follows
    row = {ln.split()[0]: ln for ln in first if ln[:1].isdigit()}
    assert "module 4 wheel  MISSING" in row["20"]
    assert row["8"].split()[1:3] == ["-", "unexpected"]
    assert row["1"].split()[1:6] == ["module", "1", "steer", "found", "unknown"]
    assert "unknown (no heartbeat: 0x1017 = 0)  switch on disabled" in row["1"]
    assert any("HM CSP CSV CST" in ln for ln in lines)
    summary = lines[-1]
    assert summary.startswith(f"cia402 on virtual:{ch}: 8 node(s) found of 127 probed in ")
    assert summary.endswith("config: 1 missing, 1 unexpected, 0 duplicate")
    # the same for machines
    assert main([*argv, "--json"]) == 1
    out, err = capsys.readouterr()
    doc = json.loads(out)
    assert doc["ok"] is False and doc["problems"] == ["module 4 wheel (node 20) missing"]
    nodes = {n["node"]: n for n in doc["nodes"]}
    assert nodes[20]["status"] == "MISSING" and nodes[20]["expected"] == [
        {"module": 4, "axis": "wheel"}
    ]
    assert nodes[8]["status"] == "unexpected" and nodes[8]["data"]["product_code"] == 0x402
    assert nodes[3]["data"]["modes"] == ["HM", "CSP", "CSV", "CST"]
    assert nodes[3]["data"]["producer_heartbeat_ms"] == 0  # CiA 301's default
    assert nodes[3]["data"]["power_state"] == "SWITCH_ON_DISABLED"
    assert "software_version" in nodes[3]["data"] and "0x100A" in nodes[3]["data"]["absent"]
    assert err.startswith("swpc drives scan: error: module 4 wheel (node 20) missing")
    # --nodes narrows the probe to the config's nodes and these: silent node 8 goes unseen
    assert main([*argv, "--json", "--nodes", "30"]) == 1
    doc = json.loads(capsys.readouterr().out)
    assert doc["candidates"] == 9 and 8 not in {n["node"] for n in doc["nodes"]}


def test_the_config_matching_the_bus_passes(
    cia402_robot: tuple[VirtualRobot, str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _sim, ch = cia402_robot
    path = config(tmp_path, "cia402")  # the default numbering: nodes 1..8
    host = can.Bus(interface="virtual", channel=ch)  # a host's heartbeat, as swpc serve's
    beat = host.send_periodic(can.Message(arbitration_id=0x77F, data=[5], is_extended_id=False),
                              0.1)  # fmt: skip
    try:
        assert main(["drives", "scan", "--channel", ch, "--config", path, "--listen", "0.5"]) == 0
    finally:
        beat.stop()
        host.shutdown()
    out, err = capsys.readouterr()
    assert err == "" and out.splitlines()[-1].endswith("0 missing, 0 unexpected, 0 duplicate")
    assert "node 127 (drives.host_node) sends heartbeats: a host (swpc serve?) is running" in out


@pytest.fixture(scope="module")
def odrive_robot() -> Iterator[tuple[VirtualRobot, str]]:
    yield from robot(ODriveDrives(firmware="0.6", homing="absolute"))


def test_an_odrive_axis_in_fault_fails_the_scan(
    odrive_robot: tuple[VirtualRobot, str], capsys: pytest.CaptureFixture[str]
) -> None:
    sim, ch = odrive_robot
    assert main(["drives", "scan", "--kind", "odrive", "--channel", ch, "--listen", "0.5"]) == 0
    out, _ = capsys.readouterr()
    assert "0.6.10 (hardware 0.0.0)" in out and "IDLE" in out
    sim.inject_fault(2, Axis.WHEEL, ErrorFlag.OVER_TEMPERATURE)  # node 3
    assert main(["drives", "scan", "--kind", "odrive", "--channel", ch, "--listen", "0.5"]) == 1
    out, err = capsys.readouterr()
    assert err.strip() == "swpc drives scan: error: node 3 in FAULT: MOTOR_OVER_TEMP"


def test_what_the_command_refuses(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    cases = [
        (["drives", "scan"], "give --config (a robot config) or --kind"),
        (["drives", "scan", "--kind", "odrive", "--wake"], "--wake is for cia402 drives"),
        (["drives", "scan", "--kind", "cia402", "--nodes", "0-3"], "--nodes: '0-3'"),
        (["drives", "scan", "--kind", "swpc", "--config", config(tmp_path, "cia402")],
         "--kind swpc but"),
        (["drives", "scan", "--kind", "swpc", "--interface", "nosuch"],
         "cannot open CAN bus interface='nosuch'"),
    ]  # fmt: skip
    for argv, what in cases:
        assert main(argv) == 2, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and what in err[0], err
    with pytest.raises(SystemExit):
        main(["drives", "scan", "--help"])
    text = capsys.readouterr().out
    assert "This RESETS THE DRIVES' COMMUNICATION" in " ".join(text.split())
