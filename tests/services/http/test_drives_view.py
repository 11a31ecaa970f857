"""``GET /drives`` (the console's Drives view) on the in-process simulator, for each drive
kind: the configured drives before any run (each axis on the node the robot config gives
it, nothing watched while the simulator's time stands still), every drive alive with a
fresh heartbeat once a run has brought them up, and a fault injected on one axis with
:meth:`simulators.virtual_robot.VirtualRobot.inject_fault` shown on that axis by its
named error code, in fault, the others not.  Each kind's heartbeat ages during the spin
are printed.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from firmware_protocol.codec import Axis, ErrorFlag
from tests.service_rig import SHORT, sim_service, start, wait_spinning, wait_state


@dataclass(frozen=True)
class KindCase:
    kind: str
    nodes: dict[int, tuple[int, int]]
    """Module id -> (steering node, wheel node): the kind's default numbering
    (docs/drives.md), what the robot config ``drives: <kind>`` gives."""
    running: str
    """Every axis' state during a spin."""
    held: str
    """The mode of the wheel held still (the locked module's) during a spin."""
    driven: str
    """The mode of a wheel that drives the spin."""
    error: int
    error_name: str
    """Module 2 wheel's error after ``inject_fault(2, WHEEL, OVER_TEMPERATURE)``."""
    axis_detail: bool


CASES = [
    KindCase("swpc", {1: (1, 1), 2: (2, 2), 3: (3, 3), 4: (4, 4)}, "ENABLED", "HOLD", "TORQUE",
             int(ErrorFlag.OVER_TEMPERATURE), "OVER_TEMPERATURE", True),
    KindCase("odrive", {1: (0, 1), 2: (2, 3), 3: (4, 5), 4: (6, 7)}, "CLOSED_LOOP_CONTROL",
             "HOLD", "TORQUE", 0x2000, "MOTOR_OVER_TEMP", True),
    KindCase("cia402", {1: (1, 2), 2: (3, 4), 3: (5, 6), 4: (7, 8)}, "operation enabled",
             "CYCLIC_SYNC_POSITION", "CYCLIC_SYNC_TORQUE", 0x4310,
             "0x4310 excess temperature drive", True),
]  # fmt: skip


def rows(doc: dict[str, Any]) -> dict[tuple[int, str], dict[str, Any]]:
    return {(a["module"], a["axis"]): a for a in doc["axes"]}


@pytest.mark.parametrize("case", CASES, ids=[c.kind for c in CASES])
def test_configured_alive_then_a_fault_named(case: KindCase, tmp_path: Path) -> None:
    robot = tmp_path / "robot.yaml"
    robot.write_text(f"drives: {case.kind}\n")
    with sim_service(tmp_path, robot_config=robot) as sim:
        c, rt = sim.client, sim.rt
        # before any run: the config's drives, nothing watched (the simulator's time
        # stands still between runs), no fault
        idle = c.get("/drives").json()
        assert idle["kind"] == case.kind and idle["driver"] == "inactive"
        assert idle["bus"] == f"virtual:{rt.can_channel}" and idle["fault_cause"] is None
        assert idle["watched"] is False and idle["axis_detail"] is case.axis_detail
        assert [(a["module"], a["axis"], a["node"]) for a in idle["axes"]] == [
            (m, axis, case.nodes[m][i]) for m in (1, 2, 3, 4)
            for i, axis in enumerate(("steer", "wheel"))
        ]  # fmt: skip
        assert all(a["alive"] is None and not a["fault"] for a in idle["axes"])
        assert all(a["error"] == 0 and a["error_name"] == "none" for a in idle["axes"])
        assert "swpc drives scan, with the service stopped" in idle["scan"]

        # a run's bring-up: every drive alive, its heartbeat fresh, the steering homed
        run_id = start(c, SHORT)
        wait_spinning(c, run_id, guard=120)
        live = c.get("/drives").json()
        assert live["driver"] == "active" and live["watched"] is True
        loss = rt.drives.config.loss_after_s if rt.drives is not None else 0.0
        ages = [a["heartbeat_age_s"] for a in live["axes"]]
        assert all(a["alive"] is True and a["state"] == case.running for a in live["axes"])
        assert all(0.0 <= age < loss for age in ages), (ages, loss)
        assert all(a["heartbeats"] > 0 for a in live["axes"])
        by = rows(live)
        assert [by[m, "steer"]["homed"] for m in (1, 2, 3, 4)] == [True] * 4
        assert [by[m, "wheel"]["homed"] for m in (1, 2, 3, 4)] == [None] * 4
        # spinning about module 1: its wheel held, the others' driven by torque
        assert by[1, "wheel"]["mode"] == case.held and by[2, "wheel"]["mode"] == case.driven
        print(f"\n{case.kind}: heartbeat ages during the spin {min(ages):.3f}-{max(ages):.3f} s "
              f"(lost after {loss:.3f} s)")  # fmt: skip

        # a drive's fault: named on its axis, and the run stopped on it
        assert rt.simulator is not None
        rt.simulator.inject_fault(2, Axis.WHEEL, ErrorFlag.OVER_TEMPERATURE)
        st = wait_state(c, run_id, {"FAILED", "ABORTED", "DONE"}, timeout=60)
        assert st["state"] == "FAILED" and "module 2" in st["reason"], st
        after = c.get("/drives").json()
        assert after["driver"] == "inactive" and after["fault_cause"] in st["reason"]
        by = rows(after)
        wheel = by[2, "wheel"]
        assert (wheel["node"], wheel["error"], wheel["error_name"], wheel["fault"]) == (
            case.nodes[2][1], case.error, case.error_name, True
        )
        others = [a for k, a in by.items() if k != (2, "wheel")]
        assert all(a["error"] == 0 and not a["fault"] for a in others)


def test_without_a_robot_the_configured_drives_only(tmp_path: Path) -> None:
    """A service not connected to a robot (no bus): the config's drives, nothing known of
    them."""
    from fastapi.testclient import TestClient

    from tests.service_rig import app_without_robot

    with TestClient(app_without_robot(tmp_path)) as c:
        doc = c.get("/drives").json()
    assert (doc["kind"], doc["driver"], doc["watched"], doc["axis_detail"]) == (
        "swpc", "not open", False, False
    )
    assert [(a["module"], a["axis"], a["node"]) for a in doc["axes"]] == [
        (m, axis, m) for m in (1, 2, 3, 4) for axis in ("steer", "wheel")
    ]
    assert all(a["alive"] is None and a["state"] is None for a in doc["axes"])
