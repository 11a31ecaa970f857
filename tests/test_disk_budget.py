"""The disk budget (services/store/disk.py): old runs' recordings pruned to make room for a
run, then 507 when nothing is left; 507 on a nearly full file system; health warns when a
run would not find its room.
"""

from __future__ import annotations

import json
import logging
import os
import time
from pathlib import Path

import pytest

from tests.service_rig import (
    AUTH,
    SHORT_STEPS,
    send,
    sim_service,
)

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
