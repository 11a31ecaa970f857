"""What a finished run leaves, and who may read it (SWPC_FILE_GROUP): the installed file's
provenance, the run's MCAP against its Foxglove schemas, one structured log line per run
event, its plot rendered once and then served from disk (also after a restart).
"""

from __future__ import annotations

import grp
import json
import logging
import os
import stat
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient
from pydantic import SecretStr

from services.config.settings import ServiceSettings
from services.runs.state import State
from services.runtime.runtime import Runtime
from swpc_hw.errors import KinematicFileError
from swpc_hw.files.dataset import load_dataset
from swpc_hw.files.kinematic_file import load_kinematics, save_kinematics
from swpc_hw.robot.paper_robot import PAPER_NOMINAL
from tests.mcap_listing import mcap_listing
from tests.run_rig import Rig
from tests.service_rig import (
    TOKEN,
    app_without_robot,
)


class Collect(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


@pytest.fixture(scope="module")
def done_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Rig, Any, list[str]]:
    """One whole run on the fake robot (three modules, three angles), installed, under
    the unit's umask 0027, with its swpc.run log lines."""
    handler = Collect()
    logger = logging.getLogger("swpc.run")
    logger.addHandler(handler)
    level = logger.level
    logger.setLevel(logging.INFO)
    old = os.umask(0o027)
    try:
        rig = Rig(tmp_path_factory.mktemp("done"))
        rig.run_kwargs["mcap"] = True
        run = rig.run()
    finally:
        os.umask(old)
        logger.removeHandler(handler)
        logger.setLevel(level)
    assert run.status.state is State.DONE, run.status.errors
    return rig, run, [r.getMessage() for r in handler.records]


def test_the_installed_file_and_the_dataset_are_readable_by_the_group(
    done_run: tuple[Rig, Any, list[str]],
) -> None:
    rig, run, _ = done_run
    for path in [
        rig.kinematics,
        run.run_dir / "kinematics.yaml",
        *(run.run_dir / "dataset" / n for n in ("robot.yaml", "poses.csv", "encoders.csv")),
        run.run_dir / "run.mcap",
    ]:
        mode = stat.S_IMODE(path.stat().st_mode)
        assert mode == 0o640, (path, oct(mode))  # was 0600: the odometry user could not read


def other_group() -> int | None:
    """A group this process may give its files other than its own (any, as root)."""
    mine = os.getegid()
    if os.geteuid() == 0:
        return next((g.gr_gid for g in grp.getgrall() if g.gr_gid != mine), None)
    return next((g for g in os.getgroups() if g != mine), None)


def test_file_group_gives_the_data_dir_its_group(tmp_path: Path) -> None:
    from services.config.settings import SettingsError

    def serve(data: Path, gid: int) -> os.stat_result:
        data.mkdir()
        save_kinematics(data / "kinematics.yaml", PAPER_NOMINAL)
        os.chmod(data / "kinematics.yaml", 0o600)
        group = grp.getgrgid(gid).gr_name
        Runtime(ServiceSettings(data_dir=data, token=SecretStr(TOKEN), file_group=group)).close()
        kin = (data / "kinematics.yaml").stat()
        assert kin.st_gid == gid and kin.st_mode & 0o040, oct(kin.st_mode)
        return data.stat()

    # the unit's case: the group is the service's own (Group=), new files get it anyway:
    # no setgid bit, which the unit's RestrictSUIDSGID= would refuse
    st = serve(tmp_path / "own", os.getegid())
    assert st.st_gid == os.getegid() and st.st_mode & 0o050 == 0o050
    assert not st.st_mode & stat.S_ISGID
    # another group (a supplementary one): the setgid bit makes new files inherit it
    gid = other_group()
    if gid is not None:
        st = serve(tmp_path / "other", gid)
        assert st.st_gid == gid and st.st_mode & stat.S_ISGID and st.st_mode & 0o050 == 0o050
        (tmp_path / "other" / "new").write_text("x")
        assert (tmp_path / "other" / "new").stat().st_gid == gid
    with pytest.raises(SettingsError, match="no group named"):
        Runtime(ServiceSettings(data_dir=tmp_path / "d2", file_group="no-such-group-xyz"))


def test_file_group_already_right_makes_no_chown(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Under the unit every chown fails (SystemCallFilter=~@privileged: EPERM, even one that
    changes nothing; the VM's robot-install step runs the real filter): the service starts
    when systemd's StateDirectory= and the unit's Group= already gave the data dir its group,
    and says why when they did not."""
    from services.config.settings import SettingsError

    def refused(*args: object) -> None:
        raise PermissionError(1, "Operation not permitted", str(args[0]))

    data = tmp_path / "state"
    data.mkdir(mode=0o750)
    os.chmod(data, 0o750)
    save_kinematics(data / "kinematics.yaml", PAPER_NOMINAL)
    os.chmod(data / "kinematics.yaml", 0o640)
    group = grp.getgrgid(os.getegid()).gr_name
    monkeypatch.setattr(os, "chown", refused)
    Runtime(ServiceSettings(data_dir=data, token=SecretStr(TOKEN), file_group=group)).close()
    assert stat.S_IMODE(data.stat().st_mode) == 0o750
    gid = other_group()
    if gid is not None:  # a group it lacks: the chown is needed, refused, and said so
        with pytest.raises(SettingsError, match=r"cannot give .*state the group"):
            Runtime(
                ServiceSettings(
                    data_dir=data, token=SecretStr(TOKEN), file_group=grp.getgrgid(gid).gr_name
                )
            )


def test_the_installed_file_says_where_it_came_from(
    done_run: tuple[Rig, Any, list[str]], tmp_path: Path
) -> None:
    from services.store.provenance import config_sha256, dataset_sha256, git_commit, tool_version

    rig, run, _ = done_run
    k = load_kinematics(rig.kinematics)
    raw = rig.kinematics.read_text()
    assert "units:\n  length: m\n  angle: rad" in raw
    prov = k.extra["provenance"]
    assert prov["tool"] == "swpc service" and prov["version"] == tool_version()
    assert prov["commit"] == git_commit() and (prov["commit"] is None or len(prov["commit"]) == 40)
    assert prov["dataset_sha256"] == dataset_sha256(run.run_dir / "dataset")
    assert prov["config_sha256"] == config_sha256(rig.config.to_document())
    assert prov["run"] == run.id and prov["units"] == {"length": "m", "angle": "rad", "time": "s"}
    # a file in other units is refused, one without units still loads
    with pytest.raises(KinematicFileError, match=r"units\.length"):
        bad = tmp_path / "mm.yaml"
        bad.write_text(raw.replace("length: m", "length: mm"))
        load_kinematics(bad)


def test_the_run_mcap_is_foxglove_json_that_matches_its_schemas(
    done_run: tuple[Rig, Any, list[str]],
) -> None:
    """Every message of a finished run's MCAP is standard JSON valid against its channel's
    JSON schema (Foxglove's own for poses, transforms and logs), one per recorded row."""
    import jsonschema_rs
    from mcap.reader import make_reader

    _, run, lines = done_run
    ds = load_dataset(run.run_dir / "dataset")
    with (run.run_dir / "run.mcap").open("rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        assert summary is not None  # finished: the summary is written
        schemas = {c.topic: summary.schemas[c.schema_id] for c in summary.channels.values()}
        validators = {
            t: jsonschema_rs.validator_for(json.loads(s.data)) for t, s in schemas.items()
        }
        counts: dict[str, int] = {}
        docs: dict[str, Any] = {}
        for _schema, channel, message in reader.iter_messages():
            doc = json.loads(message.data, parse_constant=lambda c: pytest.fail(c))
            errors = [e.message for e in validators[channel.topic].iter_errors(doc)]
            assert errors == [], (channel.topic, doc, errors)
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
            docs[channel.topic] = doc
        attachments = {a.name for a in reader.iter_attachments()}
        metadata = {m.name for m in reader.iter_metadata()}
    assert schemas["/mocap/pose"].name == "foxglove.PoseInFrame"
    assert schemas["/tf"].name == "foxglove.FrameTransform"
    assert schemas["/calibration/events"].name == "foxglove.Log"
    assert counts["/mocap/pose"] == counts["/tf"] == ds.poses.shape[0]
    for m, rows in ds.encoders.items():
        assert counts[f"/module{m}/encoders"] == rows.shape[0]
    assert counts["/calibration/segments"] == len(ds.segments)
    # the frame tree to base_link, the robot, and each spin's fitted circle in W: the path
    # of R's origin in that spin, within 2 mm of every pose of it
    assert counts["/tf_static"] == counts["/robot_description"] == 1
    topics, edges, listing = mcap_listing(run.run_dir / "run.mcap")
    print(f"\nmotion-capture run's MCAP:\n{listing}")
    assert {("W", "R"), ("R", "base_link"), ("base_link", "steer_1_link")} <= edges, edges
    assert topics["/module1/encoders"][0] == "sensor_msgs/msg/JointState"
    assert schemas["/calibration/circles"].name == "foxglove.SceneUpdate"
    entities = docs["/calibration/circles"]["entities"]
    assert len(entities) == len(ds.segments)
    for seg, ent in zip(ds.segments, entities, strict=True):
        pts = np.array([[p["x"], p["y"]] for p in ent["lines"][0]["points"]])
        centre, radius = pts.mean(axis=0), float(np.linalg.norm(pts[0] - pts.mean(axis=0)))
        sel = (ds.poses[:, 0] >= seg.start) & (ds.poses[:, 0] <= seg.end)
        off = np.linalg.norm(ds.poses[sel, 1:3] - centre, axis=1) - radius
        assert ent["frame_id"] == "W" and np.abs(off).max() < 2e-3, (seg, np.abs(off).max())
    # every run event as a log too, from the recordings' opening (after run.start) to the
    # last before DONE (the outcome metadata has the end)
    assert lines[0].startswith("event=run.start ") and "state=DONE" in lines[-1]
    assert counts["/calibration/events"] == len(lines) - 2
    assert {"kinematics.yaml", "result.json"} <= attachments
    assert {"robot-config", "provenance", "outcome"} <= metadata


def test_every_run_event_is_a_structured_log_line(
    done_run: tuple[Rig, Any, list[str]], tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    rig, run, lines = done_run
    entered = [line for line in lines if line.startswith("event=run.state ")]
    # one line per state entered, each naming the run and the state
    assert [line.split(" state=")[1].split(" ")[0] for line in entered] == [
        str(s) for s in rig.states[1:]
    ]
    assert all(f"run={run.id}" in line for line in lines)
    assert sum(line.startswith("event=run.segment ") for line in lines) == run.status.segments
    assert any(line.startswith("event=run.start ") for line in lines)
    assert any(line.startswith("event=run.install ") and "path=" in line for line in lines)
    # a failure is an ERROR line with its reason
    caplog.set_level(logging.INFO, logger="swpc.run")
    rig = Rig(tmp_path, faults=["module 2 (node 2): no heartbeat for 0.300 s"])
    failed = rig.run()
    ends = [r for r in caplog.records if r.getMessage().startswith("event=run.end ")]
    assert failed.status.state is State.FAILED and len(ends) == 1
    assert ends[0].levelno == logging.ERROR and "reason=" in ends[0].getMessage()


def test_the_plot_after_a_restart_is_rendered_once_and_served_from_disk(
    done_run: tuple[Any, Any, list[str]],
) -> None:
    _, run, _ = done_run
    data = run.run_dir.parent.parent
    app = app_without_robot(data)
    with TestClient(app) as client:
        # the finished run, as the service that ran it saved it (this "restart" has none
        # of it in memory)
        app.state.runtime.store.upsert(run.id, run.status.created, run.status.to_dict())
        assert client.get(f"/calibrations/{run.id}").json()["state"] == "DONE"
        r = client.get(f"/calibrations/{run.id}/plot.png")  # was 409 "no result in memory"
        assert r.status_code == 200 and r.content[:8] == b"\x89PNG\r\n\x1a\n", r.text
        cached = run.run_dir / "plot.png"
        assert cached.read_bytes() == r.content
        stamp = cached.stat().st_mtime_ns
        again = client.get(f"/calibrations/{run.id}/plot.png")
        assert again.content == r.content and cached.stat().st_mtime_ns == stamp  # not redrawn
        assert client.get("/calibrations/nope/plot.png").status_code == 404


def mcap_log_times(path: Path, topic: str | None = None) -> list[float]:
    """Epoch s of the messages of a run's MCAP (of ``topic``), in file order."""
    from mcap.reader import make_reader

    with path.open("rb") as fh:
        return [
            m.log_time / 1e9
            for _s, c, m in make_reader(fh).iter_messages(log_time_order=False)
            if topic is None or c.topic == topic
        ]


def test_the_mcap_lines_up_with_the_api_and_two_runs_never_overlap(
    done_run: tuple[Rig, Any, list[str]], tmp_path: Path
) -> None:
    """A run's MCAP starts at the API's ``started`` (the fake robot's clock, like the
    in-process simulator's, has its own epoch: 2001 here, and races through a run in
    milliseconds of host time), and a next run's log times start where the previous
    run's ended, although it started in the API a few milliseconds later."""
    import datetime as dt

    def epoch(iso: str | None) -> float:
        assert iso is not None
        return dt.datetime.fromisoformat(iso.replace("Z", "+00:00")).timestamp()

    rig, first, _ = done_run
    assert abs(rig.clock.wall() - dt.datetime.now(dt.UTC).timestamp()) > 3.0e8  # 2001
    times = mcap_log_times(first.run_dir / "run.mcap")
    events = mcap_log_times(first.run_dir / "run.mcap", "/calibration/events")
    started = epoch(first.status.started)
    assert abs(events[0] - started) < 0.5  # the first event, as the run opened its files
    assert min(times) >= started - 1.0 - 0.5  # samples from 1 s before the start
    span = max(times) - min(times)
    assert span > 30.0  # robot time, which the fake robot ran through in host ms
    end = first.journal.log_end()
    # MCAP log times are integer ns; back in float seconds near 1.8e9 they are good to a
    # float's resolution there (2.4e-7 s), so compared to one microsecond
    assert end is not None and end >= max(times) - 1e-6

    rig2 = Rig(tmp_path)
    rig2.run_kwargs.update(mcap=True, log_after=end)
    second = rig2.run()
    assert second.status.state is State.DONE, second.status.errors
    times2 = mcap_log_times(second.run_dir / "run.mcap")
    assert epoch(second.status.started) < max(times)  # it started before run 1's log ended
    assert min(times2) >= max(times) - 1e-6  # and its log begins after it
    assert min(times2) - max(times) < 2.0
