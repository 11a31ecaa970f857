"""Checks through the service (docs/check.md): POST /checks against the in-process
simulator, the verdict, what a check never does (install), the history, the refusals, the
store's kinds, and ``swpc check``."""

from __future__ import annotations

import hashlib
import sqlite3
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from services.cli import main as swpc
from services.store.runs import RunStore
from swpc_hw.files.kinematic_file import save_kinematics
from swpc_hw.robot.model import RobotParams
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED
from tests.service_rig import (
    AUTH,
    MID_SPIN,
    TOKEN,
    Sim,
    sim_service,
    start,
    wait_spinning,
    wait_state,
    watch,
)

DONE = {"DONE", "FAILED", "ABORTED"}


def worn(module: int, dr: float) -> RobotParams:
    """The simulator's truth (Table 4) with one wheel's radius off by ``dr``: as a file
    in force, a robot whose wheel has changed since it was written."""
    return PAPER_CALIBRATED.model_copy(update={"modules": [
        m.model_copy(update={"r": m.r + dr}) if m.id == module else m
        for m in PAPER_CALIBRATED.modules
    ]})  # fmt: skip


def run_check(client: TestClient, body: dict[str, Any] | None = None) -> dict[str, Any]:
    r = client.post("/checks", json=body or {}, headers=AUTH)
    assert r.status_code == 202, r.text
    cid = r.json()["id"]
    assert r.headers["Location"] == f"/checks/{cid}" and r.json()["kind"] == "check"
    st = wait_check(client, cid)
    assert st["state"] == "DONE", st["reason"]
    return st


def wait_check(client: TestClient, cid: str) -> dict[str, Any]:
    return watch(client, cid, lambda st: st["state"] in DONE, path="/checks")


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_no_check_without_a_file_in_force(sim: Sim) -> None:
    kin = sim.rt.settings.kinematics_file
    assert not kin.exists()
    r = sim.client.post("/checks", json={}, headers=AUTH)
    assert r.status_code == 409 and "no kinematic file in force" in r.text
    assert sim.client.post("/checks", json={}).status_code == 401
    r = sim.client.post("/checks", json={"metrology": "imu"}, headers=AUTH)
    assert r.status_code == 409 and "no kinematic file in force" in r.text
    # a check does not drive (nothing to measure the drive with); overrides only tighten
    r = sim.client.post(
        "/checks", json={"metrology": "imu", "overrides": {"protocol": {"drive_length": 2}}},
        headers=AUTH,
    )  # fmt: skip
    assert r.status_code == 422 and "a check does not drive" in r.text
    r = sim.client.post(
        "/checks", json={"overrides": {"limits": {"max_yaw_rate": 9}}}, headers=AUTH
    )
    assert r.status_code == 422 and "would loosen" in r.text


@dataclass(frozen=True)
class AfterCheck:
    """What the disk and the API said right after a check: the file in force's sha256
    and bytes, its backups, the checks listed and the file's changes."""

    sha: str
    kin: bytes
    backups: list[Path]
    checks: list[str]
    changes: list[Any]


@dataclass(frozen=True)
class MocapChecks:
    """Two checks with motion capture on a fresh service of their own (nothing else runs
    on it): ``unchanged`` of the simulator's truth exactly (the file's sha256 ``before``
    it, :class:`AfterCheck` ``after`` it), then ``worn`` of a file whose wheel 2 has 0.3 mm
    more than the wheel.  The unchanged check is the worn one's point before: the
    history's trend needs two.  ``design_fit``: the answer to a check of a file in frame
    design-fit, before both."""

    sim: Sim
    design_fit: tuple[int, str]
    before: str
    unchanged: dict[str, Any]
    after: AfterCheck
    worn: dict[str, Any]


@pytest.fixture(scope="module")
def mocap_checks(tmp_path_factory: pytest.TempPathFactory) -> Iterator[MocapChecks]:
    """A whole check is expensive: the two with motion capture run once, judged by the
    unchanged robot's test and the worn wheel's."""
    with sim_service(tmp_path_factory.mktemp("mocap-checks")) as sim:
        kin = sim.rt.settings.kinematics_file
        save_kinematics(kin, PAPER_CALIBRATED.model_copy(update={"frame": "design-fit"}))
        r = sim.client.post("/checks", json={}, headers=AUTH)
        design_fit = (r.status_code, r.text)
        save_kinematics(kin, PAPER_CALIBRATED)  # the simulator's truth, exactly
        before = sha(kin)
        unchanged = run_check(sim.client)
        after = AfterCheck(
            sha(kin), kin.read_bytes(), sorted(kin.parent.glob("kinematics.*.yaml")),
            [c["id"] for c in sim.client.get("/checks").json()],
            sim.client.get("/kinematics/changes").json(),
        )  # fmt: skip
        save_kinematics(kin, worn(2, +0.3e-3))  # the file says 0.3 mm more than the wheel has
        # without the fast part (the unchanged check had it): what is judged is the same
        worn_check = run_check(sim.client, {"overrides": {"protocol": {"precheck": False}}})
        yield MocapChecks(sim, design_fit, before, unchanged, after, worn_check)


def test_an_unchanged_robot_is_consistent_and_nothing_is_installed(
    mocap_checks: MocapChecks,
) -> None:
    sim, st, after = mocap_checks.sim, mocap_checks.unchanged, mocap_checks.after
    code, text = mocap_checks.design_fit
    assert code == 409 and "in frame 'design-fit'" in text
    assert st["verdict"] == "consistent" and st["installed"] is None
    res = st["result"]
    assert res["verdict"] == "consistent" and res["action"] == "none"
    assert len(res["table"]) == 20 and len(res["modules"]) == 4
    assert all(not m["drifted"] for m in res["modules"])
    assert "taken as exact" in res["notes"][0]  # no covariance, no std dev in the file
    # one spin about every module (21-23 s of robot time) after the fast part (4 probes
    # of 3.1-3.8 s)
    assert st["segments"] == 4 and st["angles_total"] == 1 and st["elapsed_s"] <= 40
    assert after.sha == mocap_checks.before and after.backups == []
    run_dir = sim.rt.data_dir / "runs" / st["id"]
    assert (run_dir / "file-in-force.yaml").read_bytes() == after.kin
    assert not (run_dir / "kinematics.yaml").exists()
    # a check is no calibration: not listed, not found, not installable
    cid = st["id"]
    assert after.checks == [cid]
    assert cid not in [r["id"] for r in sim.client.get("/calibrations").json()]
    assert sim.client.get("/calibrations").json() == []
    assert sim.client.get(f"/calibrations/{cid}").status_code == 404
    assert sim.client.get(f"/calibrations/{cid}/result").status_code == 404
    assert sim.client.post(f"/calibrations/{cid}/install", headers=AUTH).status_code == 404
    assert sim.client.get("/checks/nope").status_code == 404
    assert after.changes == [] and sim.client.get("/kinematics/changes").json() == []


def test_a_worn_wheel_is_found_and_named(
    mocap_checks: MocapChecks, capsys: pytest.CaptureFixture[str]
) -> None:
    sim, st = mocap_checks.sim, mocap_checks.worn
    kin = sim.rt.settings.kinematics_file
    res = st["result"]
    assert st["verdict"] == "drifted" and res["drifted_modules"] == [2], res["summary"]
    assert res["action"] == "recalibrate module 2"
    assert res["modules"][1]["parameters"] == ["r"]
    row = next(r for r in res["table"] if r["module"] == 2 and r["param"] == "r")
    assert row["unit"] == "mm" and row["drifted"] and row["change"] == pytest.approx(-0.3, abs=0.05)
    assert res["file"]["sha256"] == sha(kin)[:16] and res["file"]["frame"] == "R"
    # the same verdict offline, from what the check kept
    run_dir = sim.rt.data_dir / "runs" / st["id"]
    assert swpc(["check", "--offline", str(run_dir)]) == 1
    out = capsys.readouterr().out
    assert out.startswith("drifted: recalibrate module 2") and "DRIFTED r" in out
    # the history: both checks, per module and parameter, and the last check
    h = sim.client.get("/history").json()
    assert [r["run"] for r in h["runs"]] == [mocap_checks.unchanged["id"], st["id"]]
    assert {r["kind"] for r in h["runs"]} == {"check"} and h["runs"][-1]["run"] == st["id"]
    assert h["last_check"]["id"] == st["id"] and h["last_check"]["verdict"] == "drifted"
    assert h["last_check"]["action"] == "recalibrate module 2"
    # what the robot publishes to the fleet (docs/fleet.md) says the same
    from services.runtime.fleet import fleet_document

    doc = fleet_document(sim.rt)
    assert doc["last_check"]["id"] == st["id"] and doc["last_check"]["verdict"] == "drifted"
    assert doc["last_check"]["drifted_modules"] == [2]
    assert [(c["check"], c["verdict"]) for c in doc["history"]["checks"]][-1] == (
        st["id"], "drifted")
    assert doc["history"]["calibrations"] == []  # checks are no calibrations
    p = next(q for q in h["parameters"] if q["module"] == 2 and q["param"] == "r")
    in_r = [q for q in p["points"] if q["frame"] == "R"]  # the two checks, nothing else
    assert p["unit"] == "mm" and len(in_r) == 2 and p["tolerance"] == pytest.approx(0.2)
    assert p["reference"] == pytest.approx((PAPER_CALIBRATED.module(2).r + 0.3e-3) * 1e3)
    # two checks minutes apart: no slope (trend.MIN_SPAN: a slope per week of two points
    # minutes apart is their noise times thousands); the frames' part of the trend is
    # tests/services/http/test_frames_across_methods.py's, over days
    assert p["trend"] is None
    assert sim.client.get("/history", params={"since": "2999-01-01T00:00:00Z"}).json()[
        "runs"
    ] == []
    assert sim.client.get("/history", params={"since": "yesterday"}).status_code == 422


@dataclass(frozen=True)
class GyroChecks:
    """Two checks with the gyro on a fresh service of their own (nothing else runs on
    it): ``consistent`` of the simulator's truth in frame design-fit, then one of a file
    whose wheel 3 has 0.3 mm more than the wheel, started and followed by ``swpc check``
    over HTTP (its HTTP client the test's, over the app): its exit status ``code``, what
    it printed ``out``, and the check's status ``drifted``."""

    sim: Sim
    consistent: dict[str, Any]
    code: int
    out: str
    drifted: dict[str, Any]


@pytest.fixture(scope="module")
def gyro_checks(tmp_path_factory: pytest.TempPathFactory) -> Iterator[GyroChecks]:
    """A whole check is expensive: the two with the gyro run once, judged by the gyro's
    test and by ``swpc check``'s."""
    import contextlib
    import io

    import httpx

    with sim_service(tmp_path_factory.mktemp("gyro-checks")) as sim:
        kin = sim.rt.settings.kinematics_file
        save_kinematics(kin, PAPER_CALIBRATED.model_copy(update={"frame": "design-fit"}))
        consistent = run_check(sim.client, {"metrology": "imu"})
        save_kinematics(kin, worn(3, +0.3e-3))  # in R: the frame does not matter either
        out = io.StringIO()
        with pytest.MonkeyPatch.context() as mp, contextlib.redirect_stdout(out):
            mp.setenv("SWPC_TOKEN", TOKEN)
            mp.setattr(
                httpx, "Client", lambda **kw: contextlib.nullcontext(sim.client)
            )  # the service answers at the test client's address
            code = swpc(["check", "--url", "http://testserver", "--metrology", "imu"])
        printed = out.getvalue()
        cid = printed.split("check ", 1)[1].split(" started", 1)[0]
        assert [c["id"] for c in sim.client.get("/checks").json()] == [consistent["id"], cid]
        drifted = sim.client.get(f"/checks/{cid}").json()
        assert drifted["state"] == "DONE", drifted["reason"]
        yield GyroChecks(sim, consistent, code, printed, drifted)


def test_a_check_with_the_gyro_judges_the_robots_shape(
    gyro_checks: GyroChecks, capsys: pytest.CaptureFixture[str]
) -> None:
    """Without motion capture: the gyro and the encoders, no references, no drive, no
    operator; the file in any frame (here design-fit: a calibration without motion
    capture); a worn wheel named, relative to the other wheels."""
    sim, st = gyro_checks.sim, gyro_checks.consistent
    res = st["result"]
    assert st["verdict"] == "consistent" and res["verdict"] == "consistent", res["summary"]
    # the fast part (four probes, 13-16 s of robot time) and four spins
    assert st["metrology"] == "imu" and st["segments"] == 4 and st["elapsed_s"] <= 45
    assert any("shape" in n for n in res["notes"])
    assert {e["id"] for e in res["estimate"]} == {1, 2, 3, 4}
    assert max(m["chi2"] for m in res["modules"]) < res["chi2_threshold"]
    st = gyro_checks.drifted  # of worn(3, +0.3e-3), in R: the frame does not matter either
    res = st["result"]
    assert st["metrology"] == "imu" and st["segments"] == 4 and st["elapsed_s"] <= 45
    assert st["verdict"] == "drifted" and res["drifted_modules"] == [3], res["summary"]
    assert res["modules"][2]["parameters"] == ["r"]
    row = next(r for r in res["table"] if r["module"] == 3 and r["param"] == "r")
    assert row["change"] == pytest.approx(-0.3, abs=0.05) and row["drifted"]
    others = [r for r in res["table"] if r["module"] != 3 and r["param"] == "r"]
    assert all(abs(r["change"]) < 0.05 for r in others)  # relative to the unchanged wheels
    # the same verdict offline from what the check kept; the history shows the gyro's
    # checks (frame file-fit) but fits no trend to them
    run_dir = sim.rt.data_dir / "runs" / st["id"]
    assert not (run_dir / "dataset" / "poses.csv").exists()
    assert swpc(["check", "--offline", str(run_dir)]) == 1
    assert capsys.readouterr().out.startswith("drifted: recalibrate module 3")
    h = sim.client.get("/history").json()
    p = next(q for q in h["parameters"] if q["module"] == 3 and q["param"] == "r")
    assert [q["frame"] for q in p["points"]] == ["file-fit", "file-fit"]  # its two checks
    # r is the same in any frame: drawn as it is (the API had dropped these two flags)
    assert [(q["other_frame"], q["re_expressed"]) for q in p["points"]] == [(False, False)] * 2
    assert p["trend"] is None


def test_a_check_is_a_run_one_at_a_time_and_aborts(sim: Sim) -> None:
    save_kinematics(sim.rt.settings.kinematics_file, PAPER_CALIBRATED)  # a file to check
    r = sim.client.post("/checks", json={"overrides": {"protocol": {"sweep_deg": 1440}}},
                        headers=AUTH)  # fmt: skip
    assert r.status_code == 202, r.text
    cid = r.json()["id"]
    r = sim.client.post("/calibrations", json={}, headers=AUTH)
    assert r.status_code == 409 and f"check {cid} is still running" in r.text
    assert sim.client.post("/checks", json={}, headers=AUTH).status_code == 409
    assert sim.client.post(f"/calibrations/{cid}/abort", headers=AUTH).status_code == 404
    r = sim.client.post(f"/checks/{cid}/abort", headers=AUTH)
    assert r.status_code == 200 and r.json()["state"] == "ABORTED"
    assert sim.client.get(f"/checks/{cid}").json()["result"] is None
    # and a calibration aborted by the checks' route is no check's either
    rid = start(sim.client, MID_SPIN)
    wait_spinning(sim.client, rid, 5.0)
    assert sim.client.post(f"/checks/{rid}/abort", headers=AUTH).status_code == 404
    sim.client.post(f"/calibrations/{rid}/abort", headers=AUTH)
    assert wait_state(sim.client, rid, DONE)["state"] == "ABORTED"


def test_a_store_from_before_checks_opens_with_its_runs_as_calibrations(tmp_path: Path) -> None:
    path = tmp_path / "runs.sqlite"
    db = sqlite3.connect(path)
    db.executescript(
        "CREATE TABLE runs (id TEXT PRIMARY KEY, created TEXT NOT NULL, updated TEXT NOT NULL,"
        " state TEXT NOT NULL, status TEXT NOT NULL, result TEXT);"
        "INSERT INTO runs VALUES ('old', '2026-01-01', '2026-01-01', 'DONE',"
        " '{\"id\": \"old\", \"state\": \"DONE\", \"created\": \"2026-01-01\"}', '{}');"
    )
    db.commit()
    db.close()
    store = RunStore(path)
    assert [r["id"] for r in store.list("calibration")] == ["old"]
    assert list(store.list("check")) == []
    store.upsert("c1", "2026-01-02", {"id": "c1", "state": "DONE", "kind": "check"})
    assert [r["id"] for r in store.list("check")] == ["c1"]
    assert [r["id"] for r in store.list()] == ["old", "c1"]
    store.close()


def test_swpc_check_names_a_service_that_is_not_there(capsys: pytest.CaptureFixture[str]) -> None:
    code = swpc(["check", "--url", "http://127.0.0.1:9", "--token-file", "/nonexistent"])
    assert code == 2 and "--token-file" in capsys.readouterr().err


def test_swpc_check_over_http_prints_the_verdict(
    gyro_checks: GyroChecks, capsys: pytest.CaptureFixture[str]
) -> None:
    """``swpc check`` against the service (its HTTP client is the test's, over the app):
    the check's progress, the verdict and the table; exit status 1 for drifted (the gyro's
    check of a worn wheel 3, :func:`gyro_checks`)."""
    out = gyro_checks.out
    assert gyro_checks.code == 1
    assert gyro_checks.drifted["verdict"] == "drifted"
    assert f"check {gyro_checks.drifted['id']} started" in out
    assert "check " in out and "started" in out and "SPIN" in out and "STILL" in out
    assert "drifted: recalibrate module 3" in out and "module 3: chi2" in out
    assert swpc(["check", "--overrides", "{not json"]) == 2
    assert "--overrides: not JSON" in capsys.readouterr().err


def test_the_simulators_truth_is_a_kinematic_file_of_the_robots_modules(tmp_path: Path) -> None:
    """``SWPC_SIM_TRUTH``: the in-process simulator's hidden truth (the benchmark's changed
    robots); a file of other modules is refused when the service opens, naming both."""
    from pydantic import SecretStr

    from services.config.settings import ServiceSettings, SettingsError
    from services.runtime.runtime import Runtime

    two = PAPER_CALIBRATED.model_copy(update={"modules": PAPER_CALIBRATED.modules[:2]})
    save_kinematics(tmp_path / "truth.yaml", two)
    s = ServiceSettings(
        data_dir=tmp_path / "data", token=SecretStr("t" * 20), sim_truth=tmp_path / "truth.yaml"
    )
    with pytest.raises(SettingsError, match=r"SWPC_SIM_TRUTH: .* has modules \[1, 2\]"):
        Runtime(s).open()
    save_kinematics(tmp_path / "truth.yaml", worn(1, -0.3e-3))
    rt = Runtime(s).open()
    try:
        assert rt.simulator is not None
        assert rt.simulator.truth.module(1).r == pytest.approx(PAPER_CALIBRATED.module(1).r - 3e-4)
    finally:
        rt.close()
