"""A planned calibration through the service (docs/plan.md): ``POST /calibrations
{"plan": "auto"}`` on the in-process simulator, and its refusals; ``swpc plan``."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from services.cli import main as swpc
from services.config.robot import RobotConfig
from services.runs.plan import plan_for
from tests.service_rig import AUTH, Sim, start, wait_state


def test_a_planned_calibration_runs_the_plan_in_the_robot_time_it_predicted(sim: Sim) -> None:
    rid = start(sim.client, plan="auto")
    st = wait_state(sim.client, rid, {"DONE", "FAILED", "ABORTED"})
    assert st["state"] == "DONE", st["reason"]
    p = plan_for(RobotConfig())  # the same plan (its prediction is kept)
    assert st["angles_total"] == len(p.candidate.angles_deg)
    assert st["segments"] == 4 * len(p.candidate.angles_deg)
    # the default protocol takes 133 s; the plan about half of it, as predicted
    assert st["elapsed_s"] == pytest.approx(p.robot_time, rel=0.05)
    assert st["elapsed_s"] < 0.6 * 133.1
    ds = sim.rt.runs[rid].dataset()
    for seg in ds.segments:  # every window sweeps the plan's sweep
        poses = ds.poses[(ds.poses[:, 0] >= seg.start) & (ds.poses[:, 0] <= seg.end)]
        yaw = np.unwrap(poses[:, 3])
        swept = abs(math.degrees(float(yaw[-1] - yaw[0])))
        assert swept == pytest.approx(p.candidate.sweep_deg, abs=3.0)
    res = sim.client.get(f"/calibrations/{rid}/result").json()
    assert st["installed"] is True, res
    # GET /plan: the plan before Start, as swpc plan --json gives it
    doc = sim.client.get("/plan").json()
    assert doc["protocol"] == p.candidate.protocol()
    assert doc["robot_time_s"] == round(p.robot_time, 1)
    assert [row["module"] for row in doc["predicted"]] == [1, 2, 3, 4]


def test_a_plan_that_cannot_be_made_is_refused_with_its_reason(sim: Sim) -> None:
    before = len(sim.client.get("/calibrations").json())

    def post(body: dict[str, object]) -> tuple[int, str]:
        r = sim.client.post("/calibrations", json=body, headers=AUTH)
        return r.status_code, r.text

    code, text = post({"plan": "auto", "overrides": {"protocol": {"sweep_deg": 90}}})
    assert code == 422 and "plan auto chooses protocol.sweep_deg" in text
    code, text = post({"plan": "auto", "metrology": "imu"})
    assert code == 422 and "motion capture" in text
    code, text = post({"targets": {"beta": 0.001}})
    assert code == 422 and "targets are for a planned run" in text
    code, text = post({"plan": "auto", "targets": {"beta": -1}})
    assert code == 422 and "greater than 0" in text
    code, text = post({"plan": "auto", "targets": {"position": 1e-9}})
    assert code == 422 and "no candidate protocol reaches the requirement" in text
    assert "closest" in text
    assert len(sim.client.get("/calibrations").json()) == before  # nothing started


def test_swpc_plan_prints_the_plan(capsys: pytest.CaptureFixture[str]) -> None:
    assert swpc(["plan", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    p = plan_for(RobotConfig())
    assert doc["protocol"] == p.candidate.protocol()
    assert doc["robot_time_s"] == round(p.robot_time, 1)
    assert doc["ratio"] <= 1.0
    assert doc["square_position_mm"] <= 0.5 and doc["square_heading_deg"] <= 0.016
    assert swpc(["plan"]) == 0
    out = capsys.readouterr().out
    assert f"robot time: {p.robot_time:.1f} s (predicted)" in out
    assert "square path within 0.5 mm, 0.016 deg" in out
    assert swpc(["plan", "--target-position-mm", "0.000001"]) == 2
    assert "no candidate protocol reaches the requirement" in capsys.readouterr().err
