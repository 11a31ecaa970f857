"""An always-on service, the rows of issue 21 that need an open runtime or a real server.

Health and metrics on a runtime opened on python-can's virtual bus with no robot on it
(every node lost) and zenoh on loopback with no motion capture; the service on the
in-process simulator (a robot that would move: a run it started would put the host's
commands on the virtual bus, which a test bus on the same channel sees) for health
``ok`` / ``degraded``, refusals before any frame (422, 503, 507), the disk budget and an
unwritable run store; idle connections against the real HTTP server (uvicorn with
:class:`services.http.server.GuardedH11`, in a thread, on a free loopback port); every
endpoint fed non-standard JSON.  The rest of the issue's rows are in
``tests/test_hardening.py``.
"""

from __future__ import annotations

import json
import logging
import math
import os
import socket
import threading
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import httpx
import pytest
from fastapi.testclient import TestClient
from prometheus_client.parser import text_string_to_metric_families
from pydantic import SecretStr

from firmware_protocol import codec
from services.config.robot import MotionLimits, RobotConfig, Tolerances
from services.config.settings import ServiceSettings
from services.http.app import create_app
from services.runtime.runtime import Runtime
from swpc_hw.zenoh_session import free_tcp_endpoint
from tests.test_hardening import AUTH, PRE_MOTION_REFUSALS, TOKEN, app_without_robot

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


@pytest.fixture(scope="module")
def lost(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[TestClient, Runtime]]:
    """The service opened on a virtual CAN channel no controller answers on, and a zenoh
    endpoint no motion capture publishes to."""
    settings = ServiceSettings(
        data_dir=tmp_path_factory.mktemp("lost"),
        token=SecretStr(TOKEN),
        can_interface="virtual",
        can_channel=f"swpc-lost-{uuid.uuid4().hex[:8]}",
        zenoh_listen=[free_tcp_endpoint()],
    )
    app = create_app(settings, runtime_factory=lambda s: Runtime(s).open())
    with TestClient(app) as client:
        yield client, app.state.runtime


def test_health_is_failing_with_every_node_lost_and_no_motion_capture(
    lost: tuple[TestClient, Runtime],
) -> None:
    client, _ = lost
    r = client.get("/health")
    doc = r.json()
    # was 200 "ok"
    assert r.status_code == 503 and doc["status"] == "failing", doc
    for m in (1, 2, 3, 4):
        assert f"module {m} (node {m}): no heartbeat" in doc["problems"], doc["problems"]
    assert "motion capture stale: no pose yet" in doc["problems"]
    assert doc["nodes"]["1"]["alive"] is False and doc["mocap_stale"] is True
    # and no run starts: PRECHECK would refuse it after 5 s; the service says so at once
    assert not doc["running"]
    # a lab without motion capture (SWPC_METROLOGY): the gyro is judged instead, or both
    rt = lost[1]
    try:
        for metrology, stale in (
            ("imu", {"gyro stale: no sample yet"}),
            ("both", {"gyro stale: no sample yet", "motion capture stale: no pose yet"}),
        ):
            rt.settings.metrology = metrology  # type: ignore[assignment]
            doc = client.get("/health").json()
            assert {p for p in doc["problems"] if " stale: " in p} == stale, doc["problems"]
            assert doc["gyro_age_s"] is None and doc["gyro_stale"] is True
    finally:
        rt.settings.metrology = "mocap"  # type: ignore[assignment]


def families(text: str) -> dict[str, Any]:
    return {f.name: f for f in text_string_to_metric_families(text)}


def test_metrics_are_counters_and_histograms(lost: tuple[TestClient, Runtime]) -> None:
    client, rt = lost
    before = families(client.get("/metrics").text)
    # was: gauges, and a gauge of the p99 latency
    assert before["swpc_can_frames"].type == "counter"
    assert before["swpc_can_errors"].type == "counter"
    assert before["swpc_poses"].type == "counter"
    assert before["swpc_pose_delay_seconds"].type == "histogram"
    assert before["swpc_run_duration_seconds"].type == "histogram"
    assert {s.labels["outcome"] for s in before["swpc_poses"].samples} >= {"received", "accepted"}
    health = before["swpc_health"].samples[0].value
    assert health == 2.0  # failing

    def rx(fams: dict[str, Any]) -> float:
        return float(
            next(
                s.value
                for s in fams["swpc_can_frames"].samples
                if s.name == "swpc_can_frames_total" and s.labels["direction"] == "rx"
            )
        )

    with can.Bus(interface="virtual", channel=rt.can_channel) as bus:
        for _ in range(5):
            bus.send(can.Message(arbitration_id=0x7F0, data=b"\x01", is_extended_id=False))
    deadline = time.monotonic() + 10
    while rx(families(client.get("/metrics").text)) < rx(before) + 5:
        assert time.monotonic() < deadline, "the rx counter never counted 5 frames"
        time.sleep(0.02)
    bucket = [
        s for s in before["swpc_pose_delay_seconds"].samples if s.name.endswith("_bucket")
    ]
    assert bucket[-1].labels["le"] == "+Inf"


# ------------------------------------------------------------ on the in-process simulator

MIB = 1 << 20
#: a run of the whole protocol with short steps (as tests/test_service.py's quick one)
QUICK = {"protocol": {"sweep_deg": 45, "settle_time": 1.0, "stop_time": 0.5,
                      "align_time": 0.5, "resteer_time": 1.5}}  # fmt: skip


@dataclass
class Sim:
    """The service on the in-process simulator, and a bus of ours on its CAN channel."""

    client: TestClient
    rt: Runtime
    bus: can.BusABC

    def host_frames(self) -> list[can.Message]:
        """The commands a host sent since the last call (drained from our bus's queue: the
        virtual bus hands every frame to every other bus on the channel as it is sent)."""
        out = []
        while (msg := self.bus.recv(0)) is not None:
            if not msg.is_error_frame and codec.split_id(msg.arbitration_id)[1] in (
                codec.HOST_COMMANDS
            ):
                out.append(msg)
        return out

    def wait(self, run_id: str, states: set[str]) -> dict[str, Any]:
        deadline = time.monotonic() + 60  # a guard against a hang, never a judgement
        while True:
            st: dict[str, Any] = self.client.get(f"/calibrations/{run_id}").json()
            if st["state"] in states:
                return st
            assert time.monotonic() < deadline, f"never {states}: {st}"
            time.sleep(0.01)


@contextmanager
def sim_service(data: Path, **settings: Any) -> Iterator[Sim]:
    app = create_app(ServiceSettings(data_dir=data, token=SecretStr(TOKEN), **settings))
    with TestClient(app) as client:
        rt: Runtime = app.state.runtime
        with can.Bus(interface="virtual", channel=rt.can_channel) as bus:
            yield Sim(client, rt, bus)


@pytest.fixture(scope="module")
def sim(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Sim]:
    with sim_service(tmp_path_factory.mktemp("sim")) as s:
        yield s


def health_gauge(client: TestClient) -> float:
    return float(families(client.get("/metrics").text)["swpc_health"].samples[0].value)


def test_health_is_ok_200_then_degraded_200_with_a_corrupt_kinematic_file(sim: Sim) -> None:
    client, rt = sim.client, sim.rt
    r = client.get("/health")
    assert (r.status_code, r.json()["status"], r.json()["problems"]) == (200, "ok", [])
    assert health_gauge(client) == 0.0
    kin = rt.settings.kinematics_file
    kin.write_bytes(b"format: swpc-kinematics/1\nrobot: \xff\xfe\n")
    try:
        r = client.get("/health")
        # it can calibrate (a run writes a new file), but someone must look: 200 degraded
        assert (r.status_code, r.json()["status"]) == (200, "degraded"), r.json()
        (problem,) = r.json()["problems"]
        assert problem.startswith("kinematic file in force unreadable: ") and "0xff" in problem
        assert health_gauge(client) == 1.0
    finally:
        kin.unlink()
    assert client.get("/health").json()["status"] == "ok"


def send(client: TestClient, overrides: str, install: str = "if-within-tolerance") -> Any:
    """POST /calibrations with ``overrides`` as written (NaN and Infinity included)."""
    body = f'{{"overrides":{overrides},"install":"{install}"}}'
    return client.post(
        "/calibrations", content=body, headers={**AUTH, "content-type": "application/json"}
    )


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
    r = send(client, json.dumps(QUICK))
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
    r = send(client, json.dumps(QUICK))
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


def read_only(rt: Runtime, on: bool) -> None:
    """The run store's database refuses every write (SQLite's own ``query_only``: each
    write fails "attempt to write a readonly database"), or takes them again."""
    with rt.store._lock:
        rt.store._db.execute(f"PRAGMA query_only = {'ON' if on else 'OFF'}")


def metric(text: str, name: str, **labels: str) -> float:
    fam = families(text)[name]
    return float(next(s.value for s in fam.samples if s.labels == labels))


def test_an_unwritable_run_store_fails_the_run_and_says_so_everywhere(sim: Sim) -> None:
    """The store refuses writes during SPIN: the run ends FAILED (robot stopped), and the
    runs list, the metrics and the health say so; they showed SPIN for ever."""
    client, rt = sim.client, sim.rt
    r = send(client, json.dumps(QUICK))
    assert r.status_code == 202, r.text
    rid = r.json()["id"]
    sim.wait(rid, {"SPIN"})
    read_only(rt, True)
    try:
        st = sim.wait(rid, {"FAILED", "ABORTED", "DONE"})
        assert st["state"] == "FAILED", st
        assert st["reason"].startswith(
            "cannot save the run's state: OperationalError: attempt to write a readonly database"
        ), st
        saved = rt.store.get(rid)
        assert saved is not None and saved[0]["state"] not in ("FAILED", "DONE")  # stale
        listed = {x["id"]: x for x in client.get("/calibrations").json()}
        assert listed[rid]["state"] == "FAILED" and listed[rid]["reason"] == st["reason"]
        text = client.get("/metrics").text
        assert metric(text, "swpc_runs", state="FAILED") >= 1
        for state in ("PENDING", "CONNECT", "PRECHECK", "LOCK", "ALIGN", "SPIN", "STOP"):
            assert metric(text, "swpc_runs", state=state) == 0, state
        assert metric(text, "swpc_health") == 2.0
        h = client.get("/health")
        assert h.status_code == 503 and h.json()["status"] == "failing"
        assert (
            "run store not writable: OperationalError: attempt to write a readonly database"
            in h.json()["problems"]
        )
        # no run starts while its state cannot be saved: 503, no frame (it was a 500, and
        # the unsaved run then blocked every next start with 409)
        sim.host_frames()
        r = send(client, json.dumps(QUICK))
        assert r.status_code == 503, r.text
        assert r.json()["detail"].startswith("run store not writable: ")
        assert sim.host_frames() == []
        assert [x["id"] for x in client.get("/calibrations").json()].count(rid) == 1
    finally:
        read_only(rt, False)
    # the store takes writes again: the run's end is saved, the service is healthy
    assert client.get("/health").status_code == 200
    saved = rt.store.get(rid)
    assert saved is not None and saved[0]["state"] == "FAILED"
    r = send(client, json.dumps(QUICK))
    assert r.status_code == 202, r.text
    client.post(f"/calibrations/{r.json()['id']}/abort", headers=AUTH)
    sim.wait(r.json()["id"], {"ABORTED", "FAILED", "DONE"})


def old_run(data: Path, name: str, age_s: float, recordings: int, csv: int = 1000) -> Path:
    """A past run's directory: ``recordings`` bytes of raw recordings (can.log 2/3,
    run.mcap 1/3), a dataset CSV and a kinematic file; modified ``age_s`` ago."""
    d = data / "runs" / name
    (d / "dataset").mkdir(parents=True)
    (d / "dataset" / "can.log").write_bytes(b"c" * (recordings * 2 // 3))
    (d / "run.mcap").write_bytes(b"m" * (recordings - recordings * 2 // 3))
    (d / "dataset" / "poses.csv").write_bytes(b"p" * csv)
    (d / "kinematics.yaml").write_text("k\n")
    t = time.time() - age_s
    os.utime(d, (t, t))
    return d


def test_old_recordings_are_pruned_for_a_run_then_507_when_nothing_is_left(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Budget 8 MiB: a run needs 2 MiB of room (a quarter).  The oldest runs' raw
    recordings go first, their CSVs and results stay; with nothing left to prune, 507
    and not one frame."""
    from services.store.disk import tree_bytes

    caplog.set_level(logging.INFO, logger="swpc.service")
    data = tmp_path / "data"
    runs = [old_run(data, f"old{i}", age_s=300 - 100 * i, recordings=3 * MIB) for i in range(3)]
    with sim_service(data, disk_budget=8 * MIB, can_log_bytes=0, min_free=0) as sim:
        client = sim.client
        assert tree_bytes(data) > 9 * MIB
        r = send(client, json.dumps(QUICK))
        assert r.status_code == 202, r.text
        client.post(f"/calibrations/{r.json()['id']}/abort", headers=AUTH)
        sim.wait(r.json()["id"], {"ABORTED", "FAILED", "DONE"})
        # the two oldest runs' recordings: 9 MiB -> 3 MiB, within 8 - 2 MiB
        pruned = [m.getMessage() for m in caplog.records if "event=disk.pruned" in m.getMessage()]
        assert pruned == [
            f"event=disk.pruned path={runs[i] / rel}"
            for i in (0, 1)
            for rel in ("dataset/can.log", "run.mcap")
        ]
        for d in runs[:2]:
            assert not (d / "run.mcap").exists() and not (d / "dataset" / "can.log").exists()
            assert (d / "dataset" / "poses.csv").stat().st_size == 1000
            assert (d / "kinematics.yaml").read_text() == "k\n"
        assert (runs[2] / "run.mcap").exists() and (runs[2] / "dataset" / "can.log").exists()
        # what cannot be pruned (a dataset) fills the budget: the rest is pruned, then 507
        (runs[2] / "dataset" / "poses.csv").write_bytes(b"p" * (7 * MIB))
        listed = len(client.get("/calibrations").json())
        sim.host_frames()
        r = send(client, json.dumps(QUICK))
        assert r.status_code == 507, r.text
        detail = r.json()["detail"]
        assert detail.startswith("disk budget: the data dir holds 7.") and detail.endswith(
            "MiB of SWPC_DISK_BUDGET 8.0 MiB, and a run needs 2.0 MiB (nothing left to prune)"
        ), detail
        assert not (runs[2] / "run.mcap").exists()
        assert (runs[2] / "dataset" / "poses.csv").stat().st_size == 7 * MIB
        assert sim.host_frames() == [] and len(client.get("/calibrations").json()) == listed
        assert tree_bytes(data) < 8 * MIB


def test_a_file_system_nearly_full_refuses_a_run_with_507(tmp_path: Path) -> None:
    free = os.statvfs(tmp_path)
    above = free.f_bavail * free.f_frsize + 64 * MIB  # more than is free: "nearly full"
    with sim_service(tmp_path, can_log_bytes=0, min_free=above) as sim:
        sim.host_frames()
        r = send(sim.client, json.dumps(QUICK))
        assert r.status_code == 507, r.text
        assert r.json()["detail"].startswith("disk nearly full: ")
        assert f"above SWPC_MIN_FREE {above / MIB:.1f} MiB" in r.json()["detail"]
        assert sim.host_frames() == []
        h = sim.client.get("/health")
        assert h.status_code == 503 and h.json()["problems"][0].startswith("disk nearly full")


def test_health_warns_when_a_run_would_not_find_its_room(tmp_path: Path) -> None:
    """Free space above SWPC_MIN_FREE but below it plus a run's reserve: POST refuses the
    run (507), so /health says so between runs (degraded: pruning may still make room)."""
    free = os.statvfs(tmp_path)
    below = free.f_bavail * free.f_frsize - 64 * MIB  # 64 MiB above the floor; reserve 256
    with sim_service(tmp_path, can_log_bytes=0, min_free=below) as sim:
        sim.host_frames()
        h = sim.client.get("/health")
        assert h.status_code == 200 and h.json()["status"] == "degraded", h.json()
        assert any("a run needs 256.0 MiB above SWPC_MIN_FREE" in p for p in h.json()["problems"])
        r = send(sim.client, json.dumps(QUICK))
        assert r.status_code == 507 and r.json()["detail"].startswith("disk nearly full: ")
        assert sim.host_frames() == []


def test_a_second_runtime_on_the_can_channel_stops_and_lets_go(tmp_path: Path) -> None:
    """Two services, one bus: the second one's Runtime.open() stops at the channel's lock
    and gives back what it took (its data dir's lock)."""
    from services.store.locks import LockedError

    channel = f"swpc-lock-{uuid.uuid4().hex[:8]}"

    def runtime(name: str) -> Runtime:
        return Runtime(
            ServiceSettings(
                data_dir=tmp_path / name,
                token=SecretStr(TOKEN),
                can_interface="virtual",
                can_channel=channel,
                zenoh_listen=[free_tcp_endpoint()],
            )
        )

    first = runtime("a").open()
    try:
        with pytest.raises(LockedError, match=f"CAN virtual:{channel} is in use"):
            runtime("b").open()
        runtime("b").close()  # its data dir is free again
    finally:
        first.close()
    second = runtime("b").open()  # the channel too, once the first has stopped
    assert second.drives is not None and math.isfinite(second.clock.now())
    second.close()


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


# ------------------------------------------------------------ the real server


@pytest.fixture()
def server(tmp_path: Path) -> Iterator[tuple[str, int]]:
    from services.http.server import server as make_server

    app = create_app(
        ServiceSettings(data_dir=tmp_path, token=SecretStr(TOKEN)), runtime_factory=Runtime
    )
    port = int(free_tcp_endpoint().rsplit(":", 1)[1])
    srv = make_server(
        app, host="127.0.0.1", port=port, header_timeout=0.5, max_connections=8,
        log_level="warning",
    )  # fmt: skip
    thread = threading.Thread(target=srv.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while not srv.started:
        assert thread.is_alive() and time.monotonic() < deadline, "server did not start"
        time.sleep(0.01)
    try:
        yield "127.0.0.1", port
    finally:
        srv.should_exit = True
        thread.join(10)


def closed_by_peer(sock: socket.socket, within: float) -> bool:
    """The server closed ``sock`` within ``within`` host seconds (a guard: it may well
    be sooner)."""
    sock.settimeout(within)
    try:
        return sock.recv(1) == b""
    except TimeoutError:
        return False
    except ConnectionResetError:
        return True


def test_idle_connections_are_closed_and_health_still_answers(server: tuple[str, int]) -> None:
    host, port = server
    # 3 times the connection cap, silent or sending half a request head: each one held a
    # file descriptor for ever (256 of them: /health unanswered for 50 s)
    idle = []
    for i in range(24):
        s = socket.create_connection((host, port))
        if i % 2:
            s.sendall(b"GET /health HTTP/1.1\r\nHost: x\r\n")  # never finished
        idle.append(s)
    r = httpx.get(f"http://{host}:{port}/health", timeout=20)
    assert r.status_code == 503  # answered (no robot here: failing)
    # every one of them is closed: the head timeout (0.5 s) or the cap (8)
    assert all(closed_by_peer(s, 20.0) for s in idle)
    for s in idle:
        s.close()
    # a client that sends its request in time is served, on a kept-alive connection too
    with httpx.Client(base_url=f"http://{host}:{port}", timeout=20) as c:
        assert c.get("/health").status_code == 503
        assert c.get("/kinematics").status_code == 404
