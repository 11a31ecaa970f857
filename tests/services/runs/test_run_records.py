"""A run's records hold whatever happens to the service: a state that cannot be saved, a
stopping service, a run that outgrows the disk budget, kill -9 mid-run, a full file
system; the dataset's hash follows every file.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path
from typing import Any

from services.runs.state import State
from swpc_hw.files.dataset import load_dataset
from swpc_hw.files.kinematic_file import save_kinematics
from swpc_hw.robot.paper_robot import PAPER_NOMINAL
from tests.run_rig import Rig
from tests.service_rig import ROOT
from tests.tmpfs_rig import no_unshare, run_in_tmpfs


def test_a_state_that_cannot_be_saved_fails_the_run_and_stops_the_robot(tmp_path: Path) -> None:
    rig = Rig(tmp_path)
    saving = rig._changed

    def flaky(run: Any) -> None:
        saving(run)
        if run.status.state is State.SPIN:
            raise OSError(30, "Read-only file system")

    rig._changed = flaky  # type: ignore[method-assign]
    run = rig.run()
    assert run.status.state is State.FAILED
    assert "cannot save the run's state" in (run.status.reason or "")
    t_spin = rig.entered_at[State.SPIN]
    assert rig.robot.stopped_for_good_after(t_spin)


def test_a_stopping_service_fails_its_run_not_aborted_by_the_operator(tmp_path: Path) -> None:
    rig = Rig(tmp_path)
    rig.hooks[State.SPIN] = lambda run: run.shutdown(
        "the service was stopped (SIGTERM) during the run"
    )
    run = rig.run()
    assert run.status.state is State.FAILED
    assert run.status.reason is not None and run.status.reason.startswith(
        "the service was stopped (SIGTERM)"
    )
    assert "operator" not in run.status.reason
    assert rig.robot.stopped_for_good_after(rig.entered_at[State.SPIN])


def test_a_run_that_outgrows_the_disk_budget_fails_cleanly(tmp_path: Path) -> None:
    from services.runs.recording import SpaceGuard

    kin = tmp_path / "kinematics.yaml"
    save_kinematics(kin, PAPER_NOMINAL, created="2026-01-01T00:00:00Z")
    before = kin.read_bytes()
    rig = Rig(tmp_path)
    rig.run_kwargs["space"] = SpaceGuard(tmp_path, allowed=150_000, min_free=0)
    run = rig.run()
    assert run.status.state is State.FAILED and "disk budget" in (run.status.reason or "")
    assert kin.read_bytes() == before
    assert rig.robot.stopped_for_good_after(0.0)
    assert (run.run_dir / "dataset" / "poses.csv").stat().st_size > 0  # kept, whole lines
    assert (run.run_dir / "dataset" / "poses.csv").read_text().endswith("\n")


KILLED = textwrap.dedent(
    """
    import os, signal, sys
    from pathlib import Path
    sys.path.insert(0, {root!r})
    from tests.run_rig import Rig
    from services.runs.state import State

    rig = Rig(Path(sys.argv[1]))
    rig.run_kwargs["mcap"] = True
    kill_at = []
    runs = []
    rig.hooks[State.SPIN] = runs.append

    def maybe_kill(t):
        if runs and runs[0].status.segments >= 1 and not kill_at:
            kill_at.append(t + 2.0)  # mid-run: after one segment, 2 s of robot time on
        if kill_at and t >= kill_at[0]:
            with open(sys.argv[2], "w") as fh:
                fh.write(repr(t))
            os.kill(os.getpid(), signal.SIGKILL)

    rig.clock.on_sleep.append(maybe_kill)
    rig.run()
    """
)


def test_kill_9_mid_run_keeps_the_recordings_up_to_the_kill(tmp_path: Path) -> None:
    from mcap.exceptions import EndOfFile
    from mcap.records import Channel, Message
    from mcap.stream_reader import StreamReader

    script = tmp_path / "killed.py"
    script.write_text(KILLED.format(root=str(ROOT)))
    stamp = tmp_path / "killed-at"
    p = subprocess.run(
        [sys.executable, str(script), str(tmp_path), str(stamp)], capture_output=True, timeout=120
    )
    assert p.returncode == -9, p.stderr.decode()[-2000:]
    t_kill = float(stamp.read_text())
    (run_dir,) = (tmp_path / "runs").iterdir()
    ds = load_dataset(run_dir / "dataset")  # loads: every file whole
    assert len(ds.segments) >= 1
    # everything up to the kill, within one recording period (0.5 s of robot time)
    assert t_kill - 0.6 <= ds.poses[-1, 0] <= t_kill
    for rows in ds.encoders.values():
        assert t_kill - 0.6 <= rows[-1, 0] <= t_kill
    # the MCAP: no summary, every flushed chunk readable
    topics: dict[int, str] = {}
    counts: dict[str, int] = {}
    last_pose = 0
    try:
        for rec in StreamReader(run_dir.joinpath("run.mcap").open("rb")).records:
            if isinstance(rec, Channel):
                topics[rec.id] = rec.topic
            elif isinstance(rec, Message):
                topic = topics[rec.channel_id]
                counts[topic] = counts.get(topic, 0) + 1
                if topic == "/mocap/pose":
                    last_pose = max(last_pose, rec.log_time)
    except EndOfFile:
        pass
    assert counts["/mocap/pose"] == ds.poses.shape[0]
    assert counts["/calibration/segments"] == len(ds.segments)
    assert counts["/module1/encoders"] == ds.encoders[1].shape[0]
    t0_epoch = last_pose / 1e9 - ds.poses[-1, 0]  # epoch log times: the same instants
    assert t0_epoch > 1e8


DISK_FULL = textwrap.dedent(
    """
    import hashlib, json, sys
    from pathlib import Path
    sys.path.insert(0, {root!r})
    from tests.run_rig import Rig
    from swpc_hw.files.kinematic_file import load_kinematics, save_kinematics
    from swpc_hw.robot.paper_robot import PAPER_NOMINAL

    d = Path(sys.argv[1])
    save_kinematics(d / "kinematics.yaml", PAPER_NOMINAL, created="2026-01-01T00:00:00Z")
    before = hashlib.sha256((d / "kinematics.yaml").read_bytes()).hexdigest()
    rig = Rig(d)
    run = rig.run()
    after = hashlib.sha256((d / "kinematics.yaml").read_bytes()).hexdigest()
    load_kinematics(d / "kinematics.yaml")
    print(json.dumps({{"state": str(run.status.state), "reason": run.status.reason,
                      "same": before == after, "stopped": rig.robot.stopped_for_good_after(0.0),
                      "segments": run.status.segments}}))
    """
)


@no_unshare
def test_a_full_disk_fails_the_run_cleanly_and_keeps_the_kinematic_file(tmp_path: Path) -> None:
    """A real ENOSPC: a 160 KiB tmpfs in a user + mount namespace of a child process."""
    out = run_in_tmpfs(tmp_path, DISK_FULL.format(root=str(ROOT)), "size=160k")
    print(f"\ndisk-full run: {out}")  # the figure docs/history/ records (pytest -s)
    assert out["state"] == "FAILED" and "disk full" in out["reason"], out
    assert "No space left on device" in out["reason"]
    assert out["same"] and out["stopped"], out


def test_dataset_hash_follows_every_file(tmp_path: Path) -> None:
    from services.store.provenance import dataset_sha256

    for name in ("robot.yaml", "poses.csv", "encoders.csv", "segments.csv"):
        (tmp_path / name).write_text("a\n")
    h = dataset_sha256(tmp_path)
    (tmp_path / "poses.csv").write_text("b\n")
    assert dataset_sha256(tmp_path) != h and len(h) == 64
    (tmp_path / "poses.csv").write_text("a\n")
    assert dataset_sha256(tmp_path) == h


PLOT_ON_A_FULL_DISK = textwrap.dedent(
    """
    import json, os, sys
    from pathlib import Path
    sys.path.insert(0, {root!r})
    from fastapi.testclient import TestClient
    from services.http.app import create_app
    from tests.services.http.console_rig import bare_runtime, new_run

    d = Path(sys.argv[1])
    rt = bare_runtime(d / "data")
    with TestClient(create_app(rt.settings, runtime_factory=lambda _: rt)) as client:
        run = new_run(rt)
        run.start()
        run.join(60)
        url = f"/calibrations/{{run.id}}/plot.png"
        with open(d / "filler", "wb") as f:  # the disk fills up
            try:
                while True:
                    f.write(bytes(1 << 16))
                    f.flush()
            except OSError:
                pass
        full = client.get(url)
        os.remove(d / "filler")  # room again
        again = client.get(url)
    print(json.dumps({{"state": str(run.status.state), "full": full.status_code,
                      "full_type": full.headers["content-type"], "full_body": full.text,
                      "again": again.status_code, "again_type": again.headers["content-type"]}}))
    """
)


@no_unshare
def test_a_plot_on_a_full_disk_is_a_507_that_says_why_then_served_once_there_is_room(
    tmp_path: Path,
) -> None:
    """Issue 40 row 13: ``plot.png`` answered 500 and its traceback when the disk was full.
    A real ENOSPC in a 16 MiB tmpfs (a user + mount namespace of a child process): 507
    with the reason; once there is room, the plot."""
    out = run_in_tmpfs(tmp_path, PLOT_ON_A_FULL_DISK.format(root=str(ROOT)), "size=16m")
    assert out["state"] == "DONE", out
    assert out["full"] == 507 and out["full_type"] == "application/json", out
    assert "no room on disk: No space left on device" in out["full_body"], out
    assert "Traceback" not in out["full_body"]
    assert out["again"] == 200 and out["again_type"] == "image/png", out
