"""GET /health and GET /metrics: failing with every node lost and no motion capture, ok then
degraded with a corrupt kinematic file, counters and histograms, and an unwritable run
store said everywhere.
"""

from __future__ import annotations

import json
import platform
import time
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import can
import pytest
from fastapi.testclient import TestClient
from pydantic import SecretStr

from services.config.settings import ServiceSettings
from services.http.app import create_app
from services.runtime.runtime import Runtime
from services.store.provenance import tool_version
from swpc_hw.sensors.zenoh_session import free_tcp_endpoint
from tests.service_rig import (
    AUTH,
    SHORT_STEPS,
    TOKEN,
    Sim,
    families,
    send,
)


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
    # which build answers: swpc_build_info{python="3.11.2",version="0.1.0"} 1.0
    (build,) = before["swpc_build_info"].samples
    assert before["swpc_build_info"].type == "gauge" and build.name == "swpc_build_info"
    assert build.labels == {"version": tool_version(), "python": platform.python_version()}
    assert build.value == 1.0 and tool_version() != "unknown"

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
    bucket = [s for s in before["swpc_pose_delay_seconds"].samples if s.name.endswith("_bucket")]
    assert bucket[-1].labels["le"] == "+Inf"


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
    r = send(client, json.dumps(SHORT_STEPS))
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
        r = send(client, json.dumps(SHORT_STEPS))
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
    r = send(client, json.dumps(SHORT_STEPS))
    assert r.status_code == 202, r.text
    client.post(f"/calibrations/{r.json()['id']}/abort", headers=AUTH)
    sim.wait(r.json()["id"], {"ABORTED", "FAILED", "DONE"})


def test_factory_cia402_drives_are_brought_up_once_and_watched_between_runs(
    tmp_path: Path,
) -> None:
    """CiA 402 drives from the factory say nothing until the host sets 0x1017: without a
    first contact /health said "no heartbeat" for ever between runs (and a lab's script
    waiting for the nodes never started its run).  The service brings them up once at
    start (nothing enabled) and then watches them."""
    from simulators.options import SimOptions
    from simulators.virtual_robot import VirtualRobot
    from swpc_hw.drives.cia402.config import Cia402Drives
    from swpc_hw.robot.paper_robot import PAPER_CALIBRATED

    ch = f"swpc-contact-{uuid.uuid4().hex[:8]}"
    cfg = Cia402Drives().for_modules(PAPER_CALIBRATED.ids)
    sim = VirtualRobot.open(PAPER_CALIBRATED, channel=ch, options=SimOptions(drives=cfg))
    sim.start()  # powered before the service: booted, silent
    robot = tmp_path / "robot.yaml"
    robot.write_text("drives: cia402\n")
    settings = ServiceSettings(
        data_dir=tmp_path / "data", token=SecretStr(TOKEN), can_interface="virtual",
        can_channel=ch, zenoh_listen=[free_tcp_endpoint()], robot_config=robot,
    )  # fmt: skip
    app = create_app(settings, runtime_factory=lambda s: Runtime(s).open())
    try:
        with TestClient(app) as client:
            deadline = time.monotonic() + 30.0
            while True:
                doc = client.get("/health").json()
                if all(n["alive"] for n in doc["nodes"].values()):
                    break
                assert time.monotonic() < deadline, doc
                time.sleep(0.1)
            assert not any("no heartbeat" in p for p in doc["problems"]), doc["problems"]
            rt: Runtime = app.state.runtime
            assert rt._contact is not None
            rt._contact.join(30.0)  # set up and started (its NMT start after every set-up)
            for d in sim.drives:
                for a in d.axes:  # type: ignore[attr-defined]
                    assert a.node.nmt.state == "OPERATIONAL", a.config.node
                    assert a.axis_model().state.value != "enabled"  # nothing enabled
    finally:
        sim.stop()
