"""Everything a run can be refused for is refused before any CAN frame: overrides that loosen
a limit, runs with the IMU metrology that cannot succeed, operator answers to a run that
does not wait for them, the simulator's tape against a robot, non-standard JSON on every
endpoint (never a 5xx).
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import yaml
from fastapi.testclient import TestClient

from services.config.robot import MotionLimits, RobotConfig, Tolerances
from swpc_hw.files.kinematic_file import kinematics_document
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED
from tests.service_rig import (
    AUTH,
    PRE_MOTION_REFUSALS,
    SHORT_STEPS,
    Sim,
    app_without_robot,
    send,
)

#: every kind of non-standard JSON Python's parser accepts (or chokes on)
NON_STANDARD = [
    '{"overrides":{"limits":{"watchdog_ms":Infinity}}}',
    '{"overrides":{"protocol":{"sweep_deg":NaN}}}',
    '{"overrides":{"limits":{"max_yaw_rate":-Infinity}}}',
    '{"overrides":{"limits":{"max_yaw_rate":1e400}}}',
    '{"install":' + "9" * 5000 + "}",
    '{"overrides":' + "[" * 5000 + "]" * 5000 + "}",
    "NaN",
    "[" * 100_000,
]


def loosened() -> list[tuple[str, str, str]]:
    """``(overrides as JSON, install, words of the refusal)``: every safety limit and
    tolerance loosened (doubled), removed (1e308, Infinity) or made NaN."""
    base = RobotConfig()
    out = []
    for group, model in (("limits", MotionLimits), ("tolerances", Tolerances)):
        install = "always" if group == "tolerances" else "if-within-tolerance"
        for name in model.model_fields:
            value = getattr(getattr(base, group), name)
            for bad, words in (
                (json.dumps(value * 2), f"{group}.{name}"),
                ("1e308", name),
                ("Infinity", "Infinity"),
                ("-Infinity", "Infinity"),
                ("NaN", "NaN"),
            ):
                out.append((f'{{"{group}":{{"{name}":{bad}}}}}', install, words))
    return out


def test_every_refused_override_is_a_422_before_any_can_frame(sim: Sim) -> None:
    """Through HTTP, to a robot that would move: each pre-motion check and each loosened
    safety limit is a 422 naming it, with no command on the bus (the run was accepted,
    the robot moved for 15-60 s, then FAILED; Infinity removed the limit)."""
    client = sim.client
    runs_before = len(client.get("/calibrations").json())
    sim.host_frames()
    cases = [(json.dumps(doc), "if-within-tolerance", why) for doc, why in PRE_MOTION_REFUSALS]
    cases += loosened()
    assert len(cases) == 8 + 14 * 5  # 11 limits and 3 tolerances, 5 ways each
    for overrides, install, words in cases:
        r = send(client, overrides, install)
        assert r.status_code == 422, (overrides, r.status_code, r.text)
        said = " ".join(f"{'.'.join(map(str, d['loc']))}: {d['msg']}" for d in r.json()["detail"])
        assert words in said, (overrides, said)
        assert sim.host_frames() == [], overrides  # not one frame
    assert len(client.get("/calibrations").json()) == runs_before
    # the control: what the bus shows of a run that is accepted (then aborted at once)
    r = send(client, json.dumps(SHORT_STEPS))
    assert r.status_code == 202, r.text
    client.post(f"/calibrations/{r.json()['id']}/abort", headers=AUTH)
    assert sim.wait(r.json()["id"], {"ABORTED", "FAILED", "DONE"})["state"] == "ABORTED"
    assert len(sim.host_frames()) > 0


AXES = [{"kind": "axis_distance", "modules": [1, 2], "value": 0.25, "stddev": 5e-4}]

#: ``(request body, words of the refusal)``: runs without motion capture refused before
#: any motion
DRIVE = {"kind": "straight_drive", "value": 4.0, "stddev": 5e-4}

TWO_KEYS = {"kind": "wheel_radius", "module": 1, "value": 0.05, "stddev": 1e-4, "modules": [1]}

LONG = {"protocol": {"drive_length": 15}, "limits": {"step_timeout": 30}}

IMU_REFUSALS: list[tuple[dict[str, Any], str]] = [
    ({"metrology": "imu"}, "no axis_distance: nothing fixes the length scale"),
    (
        {"metrology": "imu", "references": AXES, "overrides": {"protocol": {"drive_length": 0}}},
        "protocol.drive_length is 0 and no wheel_radius",
    ),
    (
        {"metrology": "imu", "references": [{**AXES[0], "modules": [1, 9]}]},
        "module 9 is not in robot.yaml",
    ),
    ({"metrology": "imu", "references": [{**AXES[0], "stddev": 0}]}, "must be > 0"),
    ({"metrology": "imu", "references": [DRIVE]}, "the run has not driven yet"),
    ({"metrology": "imu", "references": [TWO_KEYS]}, "unknown key(s) modules"),
    (
        {"metrology": "imu", "references": AXES, "overrides": {"protocol": {"rest_time": 0.2}}},
        "protocol.rest_time: 0.2 s is shorter than 1 s",
    ),
    (
        {"metrology": "imu", "references": AXES, "overrides": {"protocol": {"drive_length": 25}}},
        "less than or equal to 20",
    ),
    (
        {"metrology": "imu", "references": AXES, "overrides": LONG},
        "takes at least 34.0 s at limits.max_drive_speed 0.5 m/s",
    ),
    ({"metrology": "mocap", "references": AXES}, "references are for metrology imu"),
    ({"metrology": "gps"}, "metrology"),
]


def test_every_refused_run_without_motion_capture_is_a_422_before_any_can_frame(
    sim: Sim,
) -> None:
    """References that cannot fix the scale or the radii, malformed ones, a drive that
    cannot fit the floor or the step timeout: 422 naming it, not one frame, no run."""
    client = sim.client
    runs_before = len(client.get("/calibrations").json())
    sim.host_frames()
    for body, words in IMU_REFUSALS:
        r = client.post("/calibrations", json=body, headers=AUTH)
        assert r.status_code == 422, (body, r.status_code, r.text)
        said = " ".join(f"{'.'.join(map(str, d['loc']))}: {d['msg']}" for d in r.json()["detail"])
        assert words in said, (body, said)
        assert sim.host_frames() == [], body
    assert len(client.get("/calibrations").json()) == runs_before


def test_the_operator_routes_answer_only_a_run_that_waits(sim: Sim) -> None:
    """continue and references: 401 without the token, 404 for no such run, 409 for a run
    with motion capture or one that does not wait, 422 for a malformed measurement; the
    simulator's tape: 404 / 409 unless the run drove.  Nothing reaches the bus."""
    client = sim.client
    ref = {"references": [{"kind": "straight_drive", "value": 4.0, "stddev": 5e-4}]}
    assert client.post("/calibrations/nope/continue").status_code == 401
    assert client.post("/calibrations/nope/references", json=ref).status_code == 401
    assert client.post("/calibrations/nope/continue", headers=AUTH).status_code == 404
    assert client.post("/calibrations/nope/references", json=ref, headers=AUTH).status_code == 404
    bad = {"references": [{"kind": "straight_drive", "value": 4.0}]}  # no stddev
    assert client.post("/calibrations/nope/references", json=bad, headers=AUTH).status_code == 422
    empty = {"references": []}
    r = client.post("/calibrations/nope/references", json=empty, headers=AUTH)
    assert r.status_code == 422
    r = send(client, json.dumps(SHORT_STEPS))
    assert r.status_code == 202, r.text
    run_id = r.json()["id"]
    try:
        r = client.post(f"/calibrations/{run_id}/continue", headers=AUTH)
        assert r.status_code == 409 and "measures with motion capture" in r.text
        r = client.post(f"/calibrations/{run_id}/references", json=ref, headers=AUTH)
        assert r.status_code == 409
        tape = client.get("/simulator/tape-measure", params={"run": run_id})
        assert tape.status_code == 409 and "has not driven straight" in tape.text
    finally:
        client.post(f"/calibrations/{run_id}/abort", headers=AUTH)
    assert sim.wait(run_id, {"ABORTED", "FAILED", "DONE"})["state"] == "ABORTED"
    assert client.get("/simulator/tape-measure", params={"run": "nope"}).status_code == 404
    assert client.get("/simulator/tape-measure").status_code == 422  # which run?


def _in_force(path: Path, modules: list[int], **change: float) -> None:
    doc = kinematics_document(PAPER_CALIBRATED)
    rows = {m["id"]: m for m in doc["modules"]}
    doc["modules"] = [{**rows.get(i, rows[4]), "id": i, **change} for i in modules]  # as is
    path.write_text(yaml.safe_dump(doc))


def test_a_check_against_a_file_in_force_that_is_not_the_robots_is_a_409_before_any_frame(
    sim: Sim,
) -> None:
    """A file in force with modules the robot has not, or lacks, or damaged values, or a
    FIFO in its place: /health says why at once (degraded: a calibration replaces it), a
    check is refused (409) naming it, and not one frame reaches the bus."""
    client, path = sim.client, sim.rt.settings.kinematics_file
    cases: list[tuple[Callable[[], None], str, str]] = [
        (lambda: _in_force(path, [1, 2]), "no module [3, 4]", "does not match the robot"),
        (lambda: _in_force(path, [1, 2, 3, 4, 5]), "modules [5] the robot has not", "match"),
        (lambda: _in_force(path, [1, 2, 3, 4], x_s=1e300), "x_s: must be within", "unreadable"),
        (lambda: os.mkfifo(path), "not a regular file (a FIFO)", "unreadable"),
    ]
    runs_before = len(client.get("/calibrations").json())
    sim.host_frames()
    try:
        for make, reason, health in cases:
            make()
            h = client.get("/health", headers=AUTH).json()
            said = [p for p in h["problems"] if "kinematic file in force" in p]
            assert h["status"] == "degraded" and said and reason in said[0], h["problems"]
            assert health in said[0], said
            r = client.post("/checks", json={}, headers=AUTH)
            assert r.status_code == 409 and reason in r.text, (reason, r.status_code, r.text)
            assert sim.host_frames() == [], reason
            path.unlink()
    finally:
        path.unlink(missing_ok=True)
    assert len(client.get("/calibrations").json()) == runs_before


def test_the_simulators_tape_does_not_exist_against_a_robot(tmp_path: Path) -> None:
    """With a CAN interface (a robot, or an external simulator) there is no tape route."""
    app = app_without_robot(tmp_path, can_interface="socketcan", can_channel="vcan9")
    with TestClient(app) as client:
        assert "/simulator/tape-measure" not in client.get("/openapi.json").json()["paths"]
        r = client.get("/simulator/tape-measure", params={"run": "x"})
        assert r.status_code == 404 and r.json() == {"detail": "Not Found"}
    app = app_without_robot(tmp_path / "in-process")
    with TestClient(app) as client:
        assert "/simulator/tape-measure" in client.get("/openapi.json").json()["paths"]


@pytest.mark.parametrize("method", ["GET", "POST", "PUT", "DELETE"])
def test_every_endpoint_answers_non_standard_json_below_500(tmp_path: Path, method: str) -> None:
    app = app_without_robot(tmp_path)
    with TestClient(app) as client:
        spec = client.get("/openapi.json").json()
        paths = [p.replace("{run_id}", "abc123") for p in spec["paths"]]
        paths += ["/docs", "/redoc", "/metrics", "/health", "/openapi.json", "/nope"]
        statuses: dict[int, int] = {}
        for path in paths:
            for headers in (AUTH, {}):
                for body in NON_STANDARD:
                    r = client.request(
                        method,
                        path,
                        content=body,
                        headers={**headers, "content-type": "application/json"},
                    )
                    assert r.status_code < 500, (method, path, body[:40], r.status_code, r.text)
                    statuses[r.status_code] = statuses.get(r.status_code, 0) + 1
    # the figure docs/history/ records (pytest -s)
    codes = dict(sorted(statuses.items()))
    print(f"\nnon-standard JSON, {method}: {sum(statuses.values())} calls, status codes {codes}")
    if method == "POST":
        assert {401, 422} <= statuses.keys(), statuses  # refused, named, never a 500
