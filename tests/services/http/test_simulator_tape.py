"""The in-process simulator's tape between the steering axes (``GET
/simulator/axis-distances``): the twelve readings a run without motion capture starts with,
what the console's "Read the simulator's tape" and the demo use."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
from fastapi.testclient import TestClient

from swpc_hw.robot.paper_robot import PAPER_CALIBRATED
from tests.service_rig import app_without_robot, sim_service


def test_every_pair_read_twice_near_the_truth_and_seeded(tmp_path: Path) -> None:
    with sim_service(tmp_path / "sim") as sim:
        got = sim.client.get("/simulator/axis-distances").json()
        again = sim.client.get("/simulator/axis-distances").json()
        other = sim.client.get("/simulator/axis-distances", params={"seed": 7}).json()
        tight = sim.client.get("/simulator/axis-distances", params={"stddev": 1e-5}).json()
        assert sim.client.get("/simulator/axis-distances", params={"stddev": 0}).status_code == 422
    refs = got["references"]
    P = PAPER_CALIBRATED.arrays().P_s
    pairs = list(itertools.combinations(PAPER_CALIBRATED.ids, 2))
    assert sorted(tuple(r["modules"]) for r in refs) == sorted(pairs * 2)
    for r in refs + tight["references"]:
        a, b = r["modules"]
        true = float(np.linalg.norm(P[PAPER_CALIBRATED.index(a)] - P[PAPER_CALIBRATED.index(b)]))
        assert r["kind"] == "axis_distance"
        assert abs(r["value"] - true) < 6 * r["stddev"], (r, true)  # 0.5 mm by default
    assert {r["stddev"] for r in refs} == {0.5e-3}
    assert again == got and other != got  # seeded: the same readings for the same seed
    values = [r["value"] for r in refs]
    assert len(set(values)) == 12  # each reading its own error


def test_no_simulator_no_tape(tmp_path: Path) -> None:
    with TestClient(app_without_robot(tmp_path)) as client:
        assert client.get("/simulator/axis-distances").status_code == 404
        assert client.get("/simulator/reached", params={"run": "x"}).status_code == 404
