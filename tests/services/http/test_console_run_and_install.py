"""The console's endpoints through the real app (TestClient) on one real run: every state
of it pushed on ``GET /events?run=<id>``, install and roll back with dated backups (and
their log lines), no install while a run goes, the comparison, the run's geometry, files
and what its MCAP holds, its elapsed and remaining robot time, no start while ``/health``
fails; and a run that installs itself compared with the file it replaced.

The run behind them is a real one: the state machine on the fake robot of
``tests/services/runs/test_state_machine.py`` (a virtual clock: a whole run in about a
second), started through the runtime's own ``on_change`` (the store, the event bus), while
a client follows it on ``GET /events?run=<id>`` (the rig:
:mod:`tests.services.http.console_rig`).  The tests on the module's ``svc`` share that run
and the service's kinematic file, in order.  The browser drives the same endpoints in
``tests/browser`` (``make test-browser``).
"""

from __future__ import annotations

import io
import json
import logging
import math
import threading
import time
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from mcap.exceptions import McapError
from mcap.writer import Writer

from services.http.app import create_app
from services.http.console.router import mcap_summary
from services.runs.mcap import MODULE_COLOURS
from services.runs.protocol import CalibrationRun
from services.runtime.runtime import Runtime
from swpc_hw.files.kinematic_file import load_kinematics, save_kinematics
from tests.service_rig import AUTH
from tests.services.http.console_rig import NOMINAL, TRUTH, bare_runtime, new_check, new_run


def parse_sse(text: str) -> list[tuple[str, Any]]:
    """``(event, data)`` of every event in a text/event-stream body."""
    out = []
    for block in text.split("\n\n"):
        fields = dict(line.split(": ", 1) for line in block.splitlines() if ": " in line)
        if "event" in fields:
            out.append((fields["event"], json.loads(fields["data"])))
    return out


@pytest.fixture(scope="module")
def svc(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    """The app on a runtime whose robot is the fake one; one run followed on the stream."""
    rt = bare_runtime(tmp_path_factory.mktemp("console"))
    settings = rt.settings
    save_kinematics(settings.kinematics_file, NOMINAL, created="2026-01-01T00:00:00Z")
    app = create_app(settings, runtime_factory=lambda _: rt)
    with TestClient(app) as client:
        seen: list[str] = []
        run = new_run(rt, seen=seen)

        def start_when_listened_to() -> None:
            deadline = time.monotonic() + 30
            while rt.events.subscribers == 0 and time.monotonic() < deadline:
                time.sleep(0.01)
            run.start()

        # the run starts once the stream below listens; the stream ends with the run
        threading.Thread(target=start_when_listened_to, daemon=True).start()
        body = client.get(f"/events?run={run.id}").text
        run.join(30)
        yield {"client": client, "rt": rt, "run": run, "events": parse_sse(body), "seen": seen}


def changes(states: list[str]) -> list[str]:
    """``states`` without repeats in a row."""
    return [s for i, s in enumerate(states) if i == 0 or states[i - 1] != s]


def test_the_event_stream_pushes_every_state_of_a_run_and_ends_with_it(
    svc: dict[str, Any],
) -> None:
    events, run = svc["events"], svc["run"]
    assert run.status.state == "DONE", run.status.errors
    kinds = [e for e, _ in events]
    assert kinds[0] == "hello" and kinds[-1] == "run" and "live" in kinds
    hello = events[0][1]
    assert [m["id"] for m in hello["modules"]] == [1, 2, 3]
    assert hello["protocol"]["angles_deg"] == [30, 150]
    pushed = [d["state"] for e, d in events if e == "run"]
    # the state when the stream began (the run starts once it listens), then every change
    # the state machine made after it, in its order, nothing after the end
    told = changes(svc["seen"])
    assert told[0] == "PENDING" and told[-1] == "DONE"
    assert changes(pushed) == told[len(told) - len(changes(pushed)) :], (pushed, told)
    assert pushed[-1] == "DONE" and pushed.count("DONE") == 1
    for a, b in [("CONNECT", "PRECHECK"), ("LOCK", "ALIGN"), ("SPIN", "STOP"),
                 ("STOP", "RESTEER"), ("RELEASE", "SOLVE"), ("SOLVE", "WRITE")]:  # fmt: skip
        assert pushed.index(a) < pushed.index(b), pushed
    assert pushed.count("SPIN") == 6 and pushed.count("LOCK") == 3
    spins = [d for e, d in events if e == "run" and d["state"] == "SPIN"]
    assert [(d["module_index"], d["angle_index"], d["angle_deg"]) for d in spins] == [
        (k, i, a) for k in (1, 2, 3) for i, a in ((1, 30.0), (2, 150.0))
    ]
    live = [d for e, d in events if e == "live"]
    assert live[0]["nodes"] == [] and live[0]["can"] is None  # no bus: none shown
    # a finished run's stream: its last state, then the end
    again = parse_sse(svc["client"].get(f"/events?run={run.id}").text)
    assert [e for e, _ in again] == ["hello", "run"] and again[1][1]["state"] == "DONE"
    assert svc["client"].get("/events?run=nope").status_code == 404


def test_install_and_roll_back_with_dated_backups(svc: dict[str, Any]) -> None:
    client, rt, run = svc["client"], svc["rt"], svc["run"]
    path: Path = rt.settings.kinematics_file
    nominal_bytes = path.read_bytes()
    files = client.get("/kinematics/files").json()
    assert files["in_force"]["run"] is None and files["backups"] == []
    # never installed: against the file in force (the nominal design), what an install
    # would replace; one verdict per parameter
    cmp = client.get(f"/calibrations/{run.id}/comparison").json()
    assert cmp["reference"] == "file in force" and not cmp["is_in_force"]
    assert cmp["replaced"] is None and cmp["reference_why"] is None
    assert not cmp["installed"] and len(cmp["rows"]) == 15
    rows = {(r["module"], r["param"]): r for r in cmp["rows"]}
    x = rows[(1, "x_s")]
    assert x["unit"] == "mm" and x["reference_value"] == pytest.approx(215.0)
    assert x["change"] == pytest.approx(x["calibrated"] - 215.0)
    assert x["calibrated"] == pytest.approx(TRUTH.module(1).x_s * 1e3, abs=0.05)
    assert x["significant"] is True and x["within_tolerance"] is True  # 1.3 mm, sd ~0.01
    assert rows[(2, "beta")]["unit"] == "deg"
    # install: the token, then the run's file in force, the nominal kept as a backup
    assert client.post(f"/calibrations/{run.id}/install").status_code == 401
    r = client.post(f"/calibrations/{run.id}/install", headers=AUTH)
    assert r.status_code == 200, r.text
    backup = r.json()["backup"]
    assert r.json()["in_force"]["run"] == run.id
    assert (path.parent / backup).read_bytes() == nominal_bytes
    assert load_kinematics(path).extra["provenance"]["run"] == run.id
    # installed: still against the file it replaced (it compared with itself: all 0)
    after = client.get(f"/calibrations/{run.id}/comparison").json()
    assert after["is_in_force"] and after["reference"] == "replaced file"
    assert after["replaced"]["replaced"] == backup and after["replaced"]["action"] == "install"
    assert after["rows"] == cmp["rows"]
    changes = client.get("/kinematics/changes").json()
    c = changes[0]
    assert (c["action"], c["run"], c["replaced"], c["replaced_run"]) == (
        "install", run.id, backup, None
    )
    # roll back to the nominal design: the run's file kept as a backup in turn
    assert client.post("/kinematics/rollback", json={"backup": backup}).status_code == 401
    for bad in ("runs.sqlite", "../kinematics.yaml", "kinematics.yaml"):
        r = client.post("/kinematics/rollback", json={"backup": bad}, headers=AUTH)
        assert r.status_code == 404, (bad, r.text)
    r = client.post("/kinematics/rollback", json={"backup": backup}, headers=AUTH)
    assert r.status_code == 200, r.text
    assert path.read_bytes() == nominal_bytes
    files = client.get("/kinematics/files").json()
    assert [b["run"] for b in files["backups"]] == [run.id, None]  # newest first
    # the roll-back is a change of its own, newest first; the run is still compared with
    # the file its install replaced
    rolled = client.get("/kinematics/changes").json()[0]
    assert (rolled["action"], rolled["run"], rolled["file"]) == ("rollback", None, backup)
    assert rolled["replaced_run"] == run.id and rolled["replaced"] == files["backups"][0]["name"]
    assert client.get(f"/calibrations/{run.id}/comparison").json()["rows"] == cmp["rows"]
    assert files["backups"][0]["backup_time"].endswith("Z")
    # a corrupt backup installs nothing
    bad = path.with_name("kinematics.20200101T000000000000Z.yaml")
    bad.write_text("format: nope\n")
    r = client.post("/kinematics/rollback", json={"backup": bad.name}, headers=AUTH)
    assert r.status_code == 422 and path.read_bytes() == nominal_bytes
    listed = {b["name"]: b for b in client.get("/kinematics/files").json()["backups"]}
    assert listed[bad.name]["valid"] is False
    bad.unlink()


def kinematics_lines(caplog: pytest.LogCaptureFixture) -> list[tuple[str, str]]:
    """``(level, message)`` of every ``kinematics.*`` log line captured."""
    return [
        (r.levelname, r.getMessage())
        for r in caplog.records
        if r.name == "swpc.service" and r.getMessage().startswith("event=kinematics.")
    ]


def test_install_and_roll_back_are_structured_log_lines(
    svc: dict[str, Any], caplog: pytest.LogCaptureFixture
) -> None:
    """Every change of the file in force, and every refusal, is in the journal: which
    file, from which run or backup, the backup kept, who asked (it logged nothing)."""
    import hashlib
    import resource

    client, rt, run = svc["client"], svc["rt"], svc["run"]
    path: Path = rt.settings.kinematics_file
    caplog.set_level(logging.INFO, logger="swpc.service")
    r = client.post(f"/calibrations/{run.id}/install", headers=AUTH)
    assert r.status_code == 200, r.text
    kept = r.json()["backup"]
    sha = hashlib.sha256(path.read_bytes()).hexdigest()[:16]
    assert kinematics_lines(caplog) == [
        ("INFO", f"event=kinematics.install run={run.id} path={path} sha256={sha} "
                 f"source_run={run.id} backup={kept} client=testclient"),
    ]  # fmt: skip
    caplog.clear()
    r = client.post("/kinematics/rollback", json={"backup": kept}, headers=AUTH)
    assert r.status_code == 200, r.text
    sha = hashlib.sha256(path.read_bytes()).hexdigest()[:16]
    assert kinematics_lines(caplog) == [
        ("INFO", f"event=kinematics.rollback restored={kept} path={path} sha256={sha} "
                 f"backup={r.json()['backup']} client=testclient"),
    ]  # fmt: skip
    # refused: a corrupt backup (422), a run going on (409); nothing changed
    before = path.read_bytes()
    bad = path.with_name("kinematics.20200101T000000000000Z.yaml")
    bad.write_text("format: nope\n")
    caplog.clear()
    try:
        assert client.post("/kinematics/rollback", json={"backup": bad.name},
                           headers=AUTH).status_code == 422  # fmt: skip
    finally:
        bad.unlink()
    pending = new_run(rt)
    try:
        assert client.post(f"/calibrations/{run.id}/install", headers=AUTH).status_code == 409
    finally:
        rt.current = run
        del rt.runs[pending.id]
    (refused_bad, refused_running) = kinematics_lines(caplog)
    assert refused_bad[0] == "WARNING" and refused_bad[1].startswith(
        f"event=kinematics.install_refused action=rollback restored={bad.name} "
        'client=testclient reason="'
    ) and f"{bad}: missing key 'robot'" in refused_bad[1], refused_bad
    assert refused_running == (
        "WARNING",
        f"event=kinematics.install_refused action=install run={run.id} client=testclient "
        'reason="a calibration is running: the file is not changed"',
    )
    # a write that fails (here: a file-size limit of 512 bytes, EFBIG): a JSON 500 that
    # says the file in force is untouched, and an ERROR line
    caplog.clear()
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    resource.setrlimit(resource.RLIMIT_FSIZE, (512, hard))
    try:
        r = client.post(f"/calibrations/{run.id}/install", headers=AUTH)
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
    assert r.status_code == 500 and r.headers["content-type"] == "application/json"
    assert r.json()["detail"].startswith("not installed: cannot write the kinematic file: ")
    assert r.json()["detail"].endswith("(the file in force is untouched)")
    assert path.read_bytes() == before
    ((level, line),) = kinematics_lines(caplog)
    assert level == "ERROR" and line.startswith(
        f"event=kinematics.install_failed action=install run={run.id} client=testclient "
        f"path={path} status=500 error="
    ), line
    assert "File too large" in line


def test_no_install_while_a_run_is_going_nor_of_an_unfinished_run(svc: dict[str, Any]) -> None:
    client, rt, done = svc["client"], svc["rt"], svc["run"]
    before = rt.settings.kinematics_file.read_bytes()
    pending = new_run(rt)  # made, not started: running as far as anyone can tell
    try:
        r = client.post(f"/calibrations/{done.id}/install", headers=AUTH)
        assert r.status_code == 409 and "running" in r.text
        r = client.post(f"/calibrations/{pending.id}/install", headers=AUTH)
        assert r.status_code == 409
        assert client.get(f"/calibrations/{pending.id}/comparison").status_code == 409
        assert client.post("/calibrations/nope/install", headers=AUTH).status_code == 404
    finally:
        rt.current = done
    assert rt.settings.kinematics_file.read_bytes() == before


def test_a_runs_geometry_and_files(svc: dict[str, Any]) -> None:
    client, run = svc["client"], svc["run"]
    geo = client.get(f"/calibrations/{run.id}/geometry").json()
    assert [m["id"] for m in geo["nominal"]] == [1, 2, 3] and len(geo["spins"]) == 6
    cal = {m["id"]: m for m in geo["calibrated"]}
    for s in geo["spins"]:
        m = cal[s["module"]]
        # each fixed point is the locked module's contact point: on its caster circle
        d = math.hypot(s["c_r"][0] - m["x_s"], s["c_r"][1] - m["y_s"])
        assert d == pytest.approx(m["b"], abs=0.1e-3)
        assert s["radius"] == pytest.approx(math.hypot(*s["c_r"]))
        assert len(s["path"]) >= 10
    listed = {f["name"]: f for f in client.get(f"/calibrations/{run.id}/files").json()}
    assert {"run.mcap", "kinematics.yaml", "dataset.zip"} <= set(listed)
    z = client.get(listed["dataset.zip"]["url"])
    assert z.status_code == 200 and z.headers["content-type"] == "application/zip"
    names = zipfile.ZipFile(io.BytesIO(z.content)).namelist()
    assert f"{run.id}/dataset/poses.csv" in names
    k = client.get(f"/calibrations/{run.id}/files/kinematics.yaml")
    assert k.status_code == 200 and b"swpc-kinematics/1" in k.content
    mcap = client.get(f"/calibrations/{run.id}/files/run.mcap")
    assert mcap.status_code == 200 and mcap.content[:5] == b"\x89MCAP"
    assert client.get(f"/calibrations/{run.id}/files/runs.sqlite").status_code == 422
    assert client.get("/calibrations/nope/files").status_code == 404
    assert client.get("/calibrations/nope/geometry").status_code == 404
    # the console page itself, and only its own assets
    page = client.get("/")
    assert page.status_code == 200 and "/console/console.js" in page.text
    assert "http" not in page.text.replace("http-equiv", "")  # nothing from elsewhere
    assert client.get("/console/console.js").headers["content-type"].startswith("text/javascript")
    # one module, one colour: the page's are the run plot's (served, not copied)
    palette = client.get("/console/palette.js")
    assert palette.headers["content-type"].startswith("text/javascript")
    assert palette.text == f"const COLORS = {json.dumps(list(MODULE_COLOURS))};\n"
    assert "const COLORS" not in client.get("/console/console.js").text
    assert page.text.index("/console/palette.js") < page.text.index("/console/console.js")
    assert client.get("/console/..%2Fapi.py").status_code == 404
    # the endless stream stays out of the schema (a schema fuzzer would wait on it for ever)
    paths = client.get("/openapi.json").json()["paths"]
    assert "/events" not in paths and "/" not in paths and "/kinematics/rollback" in paths


def test_what_a_runs_mcap_holds(svc: dict[str, Any], tmp_path: Path) -> None:
    client, rt, run = svc["client"], svc["rt"], svc["run"]
    s = client.get(f"/calibrations/{run.id}/mcap").json()
    assert s["indexed"] and s["size"] > 1000
    chans = {c["topic"]: c for c in s["channels"]}
    poses = (rt.data_dir / "runs" / run.id / "dataset" / "poses.csv").read_text().splitlines()
    assert chans["/mocap/pose"]["messages"] == len(poses) - 1  # the file's header line
    assert chans["/mocap/pose"]["schema_name"] == "foxglove.PoseInFrame"
    assert chans["/mocap/pose"]["native"] and not chans["/calibration/segments"]["native"]
    assert sum(c["messages"] for c in s["channels"]) > len(poses)
    assert s["start_ns"] <= s["end_ns"]
    assert client.get("/calibrations/nope/mcap").status_code == 404
    # what Foxglove knows, the time base, metadata and attachments, from a file's summary
    path = tmp_path / "x.mcap"
    with path.open("wb") as fh:
        w = Writer(fh)
        w.start()
        t0 = 1_764_000_000 * 10**9
        for i, name in enumerate(["foxglove.PoseInFrame", "geometry_msgs/msg/PoseStamped",
                                  "swpc.Segment"]):  # fmt: skip
            sid = w.register_schema(name=name, encoding="jsonschema", data=b"{}")
            ch = w.register_channel(topic=f"/c{i}", message_encoding="json", schema_id=sid)
            for k in range(i + 1):
                w.add_message(channel_id=ch, log_time=t0 + k, publish_time=t0 + k, data=b"{}")
        w.add_metadata("robot-config", {"robot": "swpc"})
        w.add_attachment(0, 0, "result.json", "application/json", b"{}")
        w.finish()  # type: ignore[no-untyped-call]  # mcap: untyped
    got = mcap_summary("x", path)
    assert [(c.topic, c.messages, c.native) for c in got.channels] == [
        ("/c0", 1, True), ("/c1", 2, True), ("/c2", 3, False)
    ]  # fmt: skip
    assert got.epoch_times and got.start_ns == t0 and got.end_ns == t0 + 2
    assert got.metadata == ["robot-config"] and got.attachments == ["result.json"]
    # a recording cut short (no summary) says so; what is not an MCAP is an error
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    assert mcap_summary("x", path).indexed is False
    path.write_bytes(b"not an mcap file at all")
    with pytest.raises(McapError):
        mcap_summary("x", path)


def test_a_runs_elapsed_and_remaining_robot_time(svc: dict[str, Any]) -> None:
    """Every status pushed carries the robot time since the start and the estimate of
    what the plan's steps left take: from the start, each spin as the planner's time model
    predicts it (issue 45 item 3: there was none until a spin had ended), within 35 % of
    what the run took (the fake robot spins slower than the model's simulator); once a
    spin has ended, within 1.5 s (each step as long as the same state's mean so far: the
    first lock, after the fast part, steers from where its probe left the caster).  The
    progress is the share of that time done: never
    backwards, 1 at the end."""
    pushed = [d for e, d in svc["events"] if e == "run" and d["started"] is not None]
    elapsed = [d["elapsed_s"] for d in pushed]
    assert elapsed == sorted(elapsed) and elapsed[0] is not None
    total = pushed[-1]["elapsed_s"]
    assert pushed[-1]["state"] == "DONE" and 25 < total < 40, total
    assert pushed[-1]["remaining_s"] is None
    first_stop = next(i for i, d in enumerate(pushed) if d["state"] == "STOP")
    early = [d for d in pushed[:first_stop] if d["state"] not in ("PENDING", "CONNECT")]
    assert early and all(d["remaining_s"] is not None for d in early)
    for d in early:
        assert abs(d["elapsed_s"] + d["remaining_s"] - total) < 0.35 * total, d
    progress = [d["progress"] for d in pushed]
    assert progress == sorted(progress) and progress[-1] == 1.0
    last_release = max(i for i, d in enumerate(pushed) if d["state"] == "RELEASE")
    planned = pushed[first_stop : last_release + 1]
    assert len(planned) == 23
    for d in planned:
        assert d["remaining_s"] >= 0 and abs(d["elapsed_s"] + d["remaining_s"] - total) < 1.5, (
            d["state"], d["elapsed_s"], d["remaining_s"], total,
        )  # fmt: skip
    assert planned[0]["remaining_s"] > 20 and planned[-1]["remaining_s"] == 0.0
    # past the plan (solving, writing): not estimated
    assert all(d["remaining_s"] is None for d in pushed[last_release + 1 :])


def test_no_start_while_health_fails_and_the_reason_is_said(svc: dict[str, Any]) -> None:
    """``POST /calibrations`` was accepted while ``/health`` failed; the run then failed at
    CONNECT.  Now 409 with the health's reason, and nothing is started."""
    client, rt = svc["client"], svc["rt"]
    health = client.get("/health")
    assert health.status_code == 503 and "CAN driver not open" in health.json()["problems"]
    runs = client.get("/calibrations").json()
    r = client.post("/calibrations", json={}, headers=AUTH)
    assert r.status_code == 409, r.text
    assert r.json()["detail"] == "not started: GET /health is failing: CAN driver not open"
    assert client.get("/calibrations").json() == runs and not rt.running()
    # bad input is still told first (422), then the token (401)
    bad = client.post("/calibrations", json={"install": "sometimes"}, headers=AUTH)
    assert bad.status_code == 422
    assert client.post("/calibrations", json={}).status_code == 401


def installed_run(data: Path, in_force: bool) -> tuple[Runtime, TestClient, CalibrationRun]:
    """A run of the fake robot with the default install, to DONE, installed; ``in_force``:
    the nominal design's file is in force before it."""
    rt = bare_runtime(data)
    if in_force:
        save_kinematics(rt.settings.kinematics_file, NOMINAL, created="2026-01-01T00:00:00Z")
    client = TestClient(create_app(rt.settings, runtime_factory=lambda _: rt))
    run = new_run(rt, install="if-within-tolerance")
    run.start()
    run.join(30)
    assert run.status.state == "DONE" and run.status.installed, run.status.errors
    return rt, client, run


def test_a_run_that_installs_itself_is_compared_with_the_file_it_replaced(
    tmp_path: Path,
) -> None:
    """After the default install (if within tolerance) the result compared the run with
    itself: every change 0.000, never significant, although beta moved 0.6-1.5 deg.  Now
    with the file in force before its install, or, none, nominal (said so); the install
    is in the changes' history."""
    truth = math.degrees(TRUTH.module(2).beta)
    assert abs(truth) > 0.5
    for in_force in (True, False):
        rt, client, run = installed_run(tmp_path / str(in_force), in_force)
        with client:
            cmp = client.get(f"/calibrations/{run.id}/comparison").json()
            changes = client.get("/kinematics/changes").json()
        assert cmp["is_in_force"] and cmp["replaced"]["action"] == "run"
        rows = {(r["module"], r["param"]): r for r in cmp["rows"]}
        beta, x = rows[(2, "beta")], rows[(1, "x_s")]
        assert beta["change"] == pytest.approx(beta["calibrated"] - beta["nominal"])
        assert beta["change"] == pytest.approx(truth, abs=0.05) and beta["significant"]
        assert x["change"] == pytest.approx(x["calibrated"] - 215.0) and x["significant"]
        assert len(changes) == 1 and changes[0]["run"] == run.id
        assert changes[0]["file"] == f"runs/{run.id}/kinematics.yaml"
        if in_force:
            assert cmp["reference"] == "replaced file" and cmp["reference_why"] is None
            backup = cmp["replaced"]["replaced"]
            assert backup.startswith("kinematics.") and backup == changes[0]["replaced"]
            assert (rt.settings.kinematics_file.parent / backup).is_file()
            assert beta["reference_value"] == 0.0 and x["reference_value"] == 215.0
        else:
            assert cmp["reference"] == "nominal" and cmp["replaced"]["replaced"] is None
            assert cmp["reference_why"] == "no file was in force when it was installed"
            assert beta["reference_value"] is None


def test_a_checks_id_is_found_only_under_checks(svc: dict[str, Any]) -> None:
    """A check keeps a dataset, an MCAP and its file in force in its run directory, yet it
    is no calibration: none of the calibration's file routes serves them (they answered
    200 with the check's files)."""
    client, rt = svc["client"], svc["rt"]
    check = new_check(rt)  # (the fake robot's check may fail: its files are there either way)
    check.start()
    check.join(30)
    assert check.status.state in ("DONE", "FAILED") and check.status.kind == "check"
    cid = check.id
    kept = {p.name for p in (rt.data_dir / "runs" / cid).iterdir()}
    assert {"run.mcap", "dataset"} <= kept, kept
    assert client.get(f"/checks/{cid}").status_code == 200
    for path in (
        "", "/result", "/files", "/files/dataset.zip", "/files/run.mcap", "/files/can.log",
        "/files/kinematics.yaml", "/mcap", "/geometry", "/plot.png", "/comparison",
        "/export?to=kinematics",
    ):  # fmt: skip
        r = client.get(f"/calibrations/{cid}{path}")
        assert r.status_code == 404, (path, r.status_code, r.text[:200])
        assert "no calibration" in r.json()["detail"], (path, r.text[:200])
