"""Commissioning against a miswired robot, on every drive kind (issue 43's table).

For each drive kind (swpc, cia402, odrive) and each miswiring of :data:`CASES` (and three
combinations), on the in-process simulator built from the robot config (its hidden truth
miswired: ``SWPC_SIM_WIRING``, a steering zero off in ``SWPC_SIM_TRUTH``):

1. **found**: a commissioning says the robot is not right;
2. **named**: its findings are exactly the miswiring's (what, module, axis);
3. **corrected**: the service restarted on the corrected robot config (the simulator
   still built from the original, ``SWPC_SIM_ROBOT_CONFIG``), a second commissioning
   says it is right; a fix the config cannot hold (the sensor's, swpc's one node per
   module) is "-" and the row ends there;
4. **DONE**: a calibration (QUICK protocol) on the corrected config ends DONE.

Then on a right robot, commissionings in a row (``--right N``): the refusals (a right
robot said miswired), the robot time and the largest motion of each; and calibrations
through their fast part (``--prechecks N``, each aborted at its first lock; with
``--metrology imu`` the gyro alone): the refusals and the fast part's robot time.
Robot time is the simulator's; wall time is printed for what it costs here.

``python -m benchmarks.drives.bench_commission [--kinds swpc,cia402] [--right 50]
[--prechecks 50 [--metrology imu]] [--cases ...]``
(``make bench``: every case on every kind, about half an hour here).
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import os
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import yaml
from fastapi.testclient import TestClient
from pydantic import SecretStr

from benchmarks.services.bench_soak import PROTOCOL as QUICK
from services.config.settings import ServiceSettings
from services.http.app import create_app
from swpc_hw.files.kinematic_file import kinematics_document
from swpc_hw.robot.model import ModuleParams, RobotParams
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED

TOKEN = "bench-commission-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
Expected = set[tuple[str, int | None, str]]

CASES: dict[str, tuple[dict[str, Any], dict[int, float], Expected]] = {
    # name: (wiring, steering zeros off (module: deg), the findings (what, module, axis))
    "crossed 1-2": ({"crossed": {1: 2, 2: 1}}, {},
                    {("crossed", 1, "module"), ("crossed", 2, "module")}),
    "swapped 3": ({"swapped": [3]}, {}, {("swapped", 3, "module")}),
    "wheel 2 inverted": ({"inverted": [{"module": 2, "axis": "wheel"}]}, {},
                         {("polarity", 2, "wheel")}),
    "steering 3 inverted": ({"inverted": [{"module": 3, "axis": "steer"}]}, {},
                            {("polarity", 3, "steer")}),
    "steering 1 ratio x1.5": ({"ratio": [{"module": 1, "axis": "steer", "factor": 1.5}]}, {},
                              {("ratio", 1, "steer")}),
    "wheel 4 ratio x2": ({"ratio": [{"module": 4, "axis": "wheel", "factor": 2.0}]}, {},
                         {("ratio", 4, "wheel")}),
    "zero 2 +90 deg": ({}, {2: 90.0}, {("zero", 2, "steer")}),
    "zero 4 180 deg": ({}, {4: 180.0}, {("zero", 4, "steer")}),
    "mocap body 90 deg": ({"mocap_yaw_deg": 90}, {}, {("mocap_yaw", None, "sensor")}),
    "mocap Y-up": ({"mocap_y_up": True}, {}, {("not_seen", None, "sensor")}),
    "A: crossed 1-3, wheel 2 inverted": (
        {"crossed": {1: 3, 3: 1}, "inverted": [{"module": 2, "axis": "wheel"}]}, {},
        {("crossed", 1, "module"), ("crossed", 3, "module"), ("polarity", 2, "wheel")}),
    "B: steering 2 inverted, wheel 3 x2": (
        {"inverted": [{"module": 2, "axis": "steer"}],
         "ratio": [{"module": 3, "axis": "wheel", "factor": 2.0}]}, {},
        {("polarity", 2, "steer"), ("ratio", 3, "wheel")}),
    "C: crossed 2-4, zero 1 180, wheel 3 inverted": (
        {"crossed": {2: 4, 4: 2}, "inverted": [{"module": 3, "axis": "wheel"}]}, {1: 180.0},
        {("crossed", 2, "module"), ("crossed", 4, "module"), ("zero", 1, "steer"),
         ("polarity", 3, "wheel")}),
}  # fmt: skip


@contextmanager
def service(data: Path, **settings: Any) -> Iterator[TestClient]:
    app = create_app(ServiceSettings(data_dir=data, token=SecretStr(TOKEN), **settings))
    with TestClient(app) as client:
        yield client


def follow(client: TestClient, path: str, run_id: str, timeout: float = 600.0) -> dict[str, Any]:
    deadline = time.monotonic() + timeout
    while True:
        st: dict[str, Any] = client.get(f"{path}/{run_id}").json()
        if st["state"] in ("DONE", "FAILED", "ABORTED"):
            return st
        if time.monotonic() > deadline:
            raise TimeoutError(f"{path}/{run_id} still {st['state']}")
        time.sleep(0.05)


def commission(client: TestClient) -> dict[str, Any]:
    r = client.post("/commissions", headers=AUTH)
    if r.status_code != 202:
        raise RuntimeError(f"POST /commissions: {r.status_code} {r.text}")
    return follow(client, "/commissions", r.json()["id"])


def truth_with_zeros(zeros: dict[int, float]) -> RobotParams:
    mods = [
        ModuleParams(id=m.id, x_s=m.x_s, y_s=m.y_s, b=m.b, r=m.r,
                     beta=m.beta + math.radians(zeros.get(m.id, 0.0)))
        for m in PAPER_CALIBRATED.modules
    ]  # fmt: skip
    return RobotParams(robot="swpc", frame="R", modules=mods)


def one(kind: str, name: str, work: Path) -> dict[str, Any]:
    wiring, zeros, expected = CASES[name]
    work.mkdir(parents=True)
    (work / "wiring.yaml").write_text(yaml.safe_dump(wiring))
    (work / "truth.yaml").write_text(yaml.safe_dump(kinematics_document(truth_with_zeros(zeros))))
    robot = work / "robot.yaml"
    robot.write_text(yaml.safe_dump({"drives": {"kind": kind}}))
    built = work / "robot-built.yaml"
    built.write_text(robot.read_text())
    sim = {"sim_wiring": work / "wiring.yaml", "sim_truth": work / "truth.yaml",
           "sim_robot_config": built}  # fmt: skip
    row: dict[str, Any] = {"kind": kind, "case": name}
    t = time.monotonic()
    with service(work / "data", robot_config=robot, **sim) as client:
        st = commission(client)
        if st["state"] != "DONE":
            return {**row, "found": f"FAILED: {st['reason']}"}
        res = st["result"]
        got = {(f["what"], f["module"], f["axis"]) for f in res["findings"]}
        row.update(found=not res["right"], named=got == expected, findings=sorted(map(str, got)),
                   robot_time_s=res["robot_time_s"], stops=res["stops"],
                   largest_turn_deg=res["largest_turn_deg"])  # fmt: skip
        if res["not_in_config"] or not res["diff"]:
            row["corrected"] = "-"
            return row
        a = client.post(f"/commissions/{st['id']}/accept", headers=AUTH)
        if a.status_code != 200:
            return {**row, "corrected": f"accept {a.status_code}: {a.text}"}
    with service(work / "data2", robot_config=robot, **sim) as client:
        again = commission(client)
        row["corrected"] = again["state"] == "DONE" and again["result"]["right"]
        if not row["corrected"]:
            row["again"] = again.get("reason") or [f["text"] for f in again["result"]["findings"]]
            return row
        r = client.post("/calibrations", json={"overrides": {"protocol": QUICK}}, headers=AUTH)
        cal = follow(client, "/calibrations", r.json()["id"])
        row["calibration"] = cal["state"] if cal["state"] == "DONE" else cal["reason"]
    row["wall_s"] = round(time.monotonic() - t, 1)
    return row


def right_runs(kind: str, n: int, work: Path) -> None:
    robot = work / "robot.yaml"
    work.mkdir(parents=True)
    robot.write_text(yaml.safe_dump({"drives": {"kind": kind}}))
    refusals, times, turns, moves = 0, [], [], []
    with service(work / "data", robot_config=robot, sim_seed=7) as client:
        for _ in range(n):
            st = commission(client)
            res = st["result"] if st["state"] == "DONE" else None
            if res is None or not res["right"]:
                refusals += 1
                print(f"  refused: {st.get('reason') or [f['text'] for f in res['findings']]}")
            if res is not None:
                times.append(res["robot_time_s"])
                turns.append(res["largest_turn_deg"])
                moves.append(res["largest_move_mm"])
    print(f"{kind}: {n} commissionings of a right robot: {refusals} refusals; robot time "
          f"{min(times):.1f}-{max(times):.1f} s; largest motion {max(turns):.1f} deg, "
          f"{max(moves):.0f} mm")  # fmt: skip


def axis_distances() -> list[dict[str, Any]]:
    """The six distances between the true steering axes (a run with the gyro needs them;
    the fast part comes before they are used)."""
    a = PAPER_CALIBRATED.arrays()
    out = []
    for i, j in itertools.combinations(range(a.n), 2):
        d = float(math.hypot(*(a.P_s[i] - a.P_s[j])))
        ids = [PAPER_CALIBRATED.ids[i], PAPER_CALIBRATED.ids[j]]
        out.append({"kind": "axis_distance", "modules": ids, "value": d, "stddev": 0.5e-3})
    return out


def prechecks(kind: str, n: int, work: Path, metrology: str = "mocap") -> None:
    """``n`` calibrations of a right robot through their fast part (each aborted once it
    locks for its first spin), with motion capture or the gyro alone (``imu``): the
    refusals, the fast part's robot time.  The simulator's seed differs per run (its
    sensors' noise, the drives' timing)."""
    robot = work / "robot.yaml"
    work.mkdir(parents=True)
    robot.write_text(yaml.safe_dump({"drives": {"kind": kind}}))
    refusals, times = 0, []
    body: dict[str, Any] = {"overrides": {"protocol": QUICK}}
    if metrology == "imu":
        protocol = {**QUICK, "rest_time": 1.0, "drive_length": 1.0}
        body = {"metrology": "imu", "references": axis_distances(),
                "overrides": {"protocol": protocol}}  # fmt: skip
    for seed in range(11, 11 + n):
        with service(work / f"data{seed}", robot_config=robot, sim_seed=seed) as client:
            r = client.post("/calibrations", json=body, headers=AUTH)
            assert r.status_code == 202, r.text
            rid = r.json()["id"]
            deadline = time.monotonic() + 300
            while True:
                st = client.get(f"/calibrations/{rid}").json()
                if st["state"] in ("LOCK", "DONE", "FAILED", "ABORTED"):
                    break
                assert time.monotonic() < deadline, st
                time.sleep(0.02)
            if st["state"] != "LOCK":
                refusals += 1
                print(f"  refused (seed {seed}): {st['reason']}", flush=True)
            else:
                times.append(st["elapsed_s"])
                client.post(f"/calibrations/{rid}/abort", headers=AUTH)
                follow(client, "/calibrations", rid)
    print(f"{kind} ({metrology}): {n} fast parts of a right robot: {refusals} refusals; robot "
          f"time to the first lock {min(times):.1f}-{max(times):.1f} s")  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--kinds", default="swpc,cia402,odrive")
    p.add_argument("--cases", default=";".join(CASES), help="case names, separated by ;")
    p.add_argument("--right", type=int, default=0, help="commissionings of a right robot")
    p.add_argument("--prechecks", type=int, default=0, help="fast parts of a right robot")
    p.add_argument("--metrology", default="mocap", choices=["mocap", "imu"],
                   help="the prechecks' metrology")  # fmt: skip
    p.add_argument("--json", help="also write the rows to this file")
    args = p.parse_args([] if argv is None else argv)
    os.environ.setdefault("SWPC_ALLOWED_HOSTS", '["testserver"]')
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-commission-") as tmp:
        for kind in args.kinds.split(","):
            if args.right or args.prechecks:
                if args.right:
                    right_runs(kind, args.right, Path(tmp) / f"{kind}-right")
                if args.prechecks:
                    work = Path(tmp) / f"{kind}-prechecks"
                    prechecks(kind, args.prechecks, work, args.metrology)
                continue
            for i, name in enumerate(args.cases.split(";")):
                row = one(kind, name, Path(tmp) / f"{kind}-{i}")
                rows.append(row)
                print(json.dumps(row), flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
