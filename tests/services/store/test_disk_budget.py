"""The disk budget (services/store/disk.py) and the data dir's room: old runs' recordings
pruned to make room for a run, then 507 when nothing is left; 507 on a nearly full file
system or one with no inodes left, 503 when the data dir cannot keep a run's files, each
before any frame and leaving nothing half-made; health warns when a run would not find its
room and names what is wrong.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import textwrap
import time
from pathlib import Path

import pytest

from tests.service_rig import (
    AUTH,
    ROOT,
    SHORT_STEPS,
    send,
    sim_service,
)
from tests.tmpfs_rig import no_unshare, run_in_tmpfs

MIB = 1 << 20


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
        r = send(client, json.dumps(SHORT_STEPS))
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
        r = send(client, json.dumps(SHORT_STEPS))
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
        r = send(sim.client, json.dumps(SHORT_STEPS))
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
        r = send(sim.client, json.dumps(SHORT_STEPS))
        assert r.status_code == 507 and r.json()["detail"].startswith("disk nearly full: ")
        assert sim.host_frames() == []


def test_a_data_dir_that_cannot_keep_a_run_refuses_it_and_leaves_nothing(
    tmp_path: Path,
) -> None:
    """runs/ unusable after the service started: POST /calibrations was a 500, the run
    stayed PENDING for ever, every later start and install a 409, an abort changed nothing
    and /health blamed "no heartbeat".  Now: 503 before any frame, nothing half-made,
    /health names the data dir, and the next start once it is fixed runs."""
    with sim_service(tmp_path / "data") as sim:
        client, rt = sim.client, sim.rt
        runs = rt.data_dir / "runs"
        if runs.exists():
            shutil.rmtree(runs)
        runs.write_text("not a directory\n")  # what a root-owned, unwritable runs/ is to us
        sim.host_frames()
        r = send(client, json.dumps(SHORT_STEPS))
        assert r.status_code == 503, r.text
        assert "cannot keep a run" in r.json()["detail"] and str(runs) in r.json()["detail"]
        assert sim.host_frames() == []  # not one command frame
        assert client.get("/calibrations").json() == [] and rt.current is None
        health = client.get("/health").json()
        assert any(f"{runs} is not a directory" in p for p in health["problems"]), health
        assert not any("heartbeat" in p for p in health["problems"]), health
        runs.unlink()
        r = send(client, json.dumps(SHORT_STEPS))
        assert r.status_code == 202, r.text
        run_id = r.json()["id"]
        assert client.post(f"/calibrations/{run_id}/abort", headers=AUTH).status_code == 200
        assert sim.wait(run_id, {"ABORTED", "FAILED", "DONE"})["state"] == "ABORTED"


NO_INODES = textwrap.dedent(
    """
    import json, sys, uuid
    from pathlib import Path
    sys.path.insert(0, {root!r})
    from tests.service_rig import AUTH, SHORT_STEPS, send, sim_service

    d = Path(sys.argv[1])
    with sim_service(d / "data") as sim:
        filler = d / "filler"
        filler.mkdir()
        n = 0
        try:  # every inode left, after the service has started
            while True:
                (filler / str(n)).touch()
                n += 1
        except OSError:
            pass
        r = send(sim.client, json.dumps(SHORT_STEPS))
        out = {{"status": r.status_code, "detail": r.json().get("detail"),
                "runs": sim.client.get("/calibrations").json(), "frames": len(sim.host_frames()),
                "health": sim.client.get("/health").json()["problems"]}}
        for p in list(filler.iterdir())[:50]:
            p.unlink()
        r = send(sim.client, json.dumps(SHORT_STEPS))
        out["then"] = r.status_code
        if r.status_code == 202:
            run_id = r.json()["id"]
            sim.client.post(f"/calibrations/{{run_id}}/abort", headers=AUTH)
            out["end"] = sim.wait(run_id, {{"ABORTED", "FAILED", "DONE"}})["state"]
    print(json.dumps(out))
    """
)


@no_unshare
def test_no_inodes_left_refuses_a_run_with_507_and_health_says_why(tmp_path: Path) -> None:
    """A real exhaustion of inodes: a tmpfs of 400 inodes in a user + mount namespace,
    filled once the service has started."""
    out = run_in_tmpfs(
        tmp_path, NO_INODES.format(root=str(ROOT)), "size=2g,nr_inodes=400", timeout=240
    )
    assert out["status"] == 507 and "no room for the run's files" in out["detail"], out
    assert out["runs"] == [] and out["frames"] == 0, out
    assert any("no inodes left" in h for h in out["health"]), out
    assert out["then"] == 202 and out["end"] == "ABORTED", out
