"""An always-on service: safe overrides, bounded resources, honest state, clear errors.

Each test here is one row of the issue "An always-on robot service" and fails on the code
before it.  Fast: the state machine on the fake robot (``tests/fake_robot.py``), the real
app and runtime not connected to a robot (no simulator), the real filesystem, SQLite and
python-can's virtual bus; the tests that need another process run a child one (one that
holds the data dir's lock; one killed with ``kill -9``; one in a user + mount namespace
with a small tmpfs: a full file system).
The rows that need an open runtime (health, metrics, refusals before any CAN frame, the
disk budget, an unwritable run store on the in-process simulator) or the real server
(uvicorn, idle connections, non-standard JSON on every endpoint) are in
``tests/test_hardening_server.py``; schemathesis fuzzes the real ``swpc serve`` in
``tests/test_api_schema.py``, and the paths through the real driver and simulator are in
``tests/test_service.py``.
"""

from __future__ import annotations

import asyncio
import grp
import json
import logging
import math
import os
import re
import shutil
import stat
import subprocess
import sys
import textwrap
import uuid
from pathlib import Path
from typing import Any

import can
import pytest
from fastapi.testclient import TestClient
from pydantic import SecretStr, ValidationError

from services.config.robot import ConfigOverrides, MotionLimits, RobotConfig, Tolerances
from services.config.settings import ServiceSettings
from services.http.app import create_app
from services.runs.protocol import State
from services.runtime.runtime import Runtime
from swpc_hw.can.recording import Recorder
from swpc_hw.dataset import load_dataset
from swpc_hw.errors import KinematicFileError
from swpc_hw.kinematic_file import load_kinematics, save_kinematics
from swpc_hw.paper_robot import PAPER_NOMINAL
from tests.test_state_machine import Rig

ROOT = Path(__file__).resolve().parents[1]
TOKEN = "hardening-token-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


def overrides(doc: dict[str, Any]) -> dict[str, Any]:
    return ConfigOverrides.model_validate(doc).document()


# ------------------------------------------------------------ overrides only tighten


@pytest.mark.parametrize(
    ("group", "name"),
    [("limits", n) for n in MotionLimits.model_fields]
    + [("tolerances", n) for n in Tolerances.model_fields],
)
def test_every_safety_limit_in_an_override_can_only_tighten(group: str, name: str) -> None:
    from services.config.robot import RUN_FIXED_LIMITS, OverrideError

    base = RobotConfig()
    value = getattr(getattr(base, group), name)
    # a run may not loosen it, by any amount, nor remove it with Infinity
    with pytest.raises(OverrideError, match=rf"{group}\.{name}") as exc:
        base.for_run(overrides({group: {name: value * 2 if value else 1}}))
    assert all(f"{group}.{name}" in p for p in exc.value.problems), exc.value.problems
    with pytest.raises(ValidationError):
        overrides({group: {name: math.inf}})
    with pytest.raises(ValidationError):
        overrides({group: {name: math.nan}})
    # tightening is accepted and is what the run gets (the watchdog is the service's only)
    tighter = type(value)(value * 0.5) if not (group == "limits" and name == "spin_torque") else 0.3
    if name in RUN_FIXED_LIMITS:
        with pytest.raises(OverrideError, match="not per run"):
            base.for_run(overrides({group: {name: tighter}}))
    else:
        run = base.for_run(overrides({group: {name: tighter}}))
        assert getattr(getattr(run, group), name) == tighter < value


#: overrides that cannot succeed, each with the words of its refusal (before any motion)
PRE_MOTION_REFUSALS: list[tuple[dict[str, Any], str]] = [
    ({"protocol": {"modules": [1]}}, "modules [2, 3, 4] are never locked"),
    ({"protocol": {"angles_deg": [0, 360]}}, "modulo 360"),
    ({"protocol": {"angles_deg": [1e300, -1e300]}}, "within +-360 deg"),
    (
        {"protocol": {"sweep_deg": 1440}, "limits": {"max_yaw_rate": 0.3}},
        "takes at least 86.8 s at limits.max_yaw_rate 0.3 rad/s",
    ),
    ({"protocol": {"settle_time": 61}}, "settle_time: 61 s is not shorter"),
    ({"limits": {"step_timeout": 2}}, "resteer_time: 2.5 s is not shorter"),
    ({"robot": "other"}, "not this service's robot"),
    ({"nodes": {1: 4, 2: 3, 3: 2, 4: 1}}, "CAN node map"),
]


@pytest.mark.parametrize(("doc", "why"), PRE_MOTION_REFUSALS)
def test_each_pre_motion_check_refuses_the_run(doc: dict[str, Any], why: str) -> None:
    from services.config.robot import OverrideError

    with pytest.raises((OverrideError, ValidationError), match=re.escape(why)):
        RobotConfig().for_run(overrides(doc))


def test_a_refused_config_never_moves_the_robot(tmp_path: Path) -> None:
    """Defence in depth: a config that the API would refuse, given to the state machine
    directly, fails before CONNECT with no command sent."""
    rig = Rig(tmp_path, {"protocol": {"modules": [1]}})
    run = rig.run()
    assert run.status.state is State.FAILED and "before any motion" in (run.status.reason or "")
    assert [c[1] for c in rig.robot.log if c[1] not in ("stop_all", "release")] == []


# ------------------------------------------------------------ the HTTP guard (ASGI)


def app_without_robot(tmp_path: Path, **settings: Any) -> Any:
    """The real app on a real runtime that is not connected to a robot (no bus, no
    simulator): what the API does before and after a run."""
    cfg = ServiceSettings(data_dir=tmp_path, token=SecretStr(TOKEN), **settings)
    return create_app(cfg, runtime_factory=Runtime)


def asgi_post(app: Any, path: str, headers: dict[str, str], chunks: int) -> tuple[int, int]:
    """POST ``chunks`` MiB to ``app`` as a streamed body; returns (status, chunks read)."""
    pulled = 0
    status: list[int] = []

    async def receive() -> dict[str, Any]:
        nonlocal pulled
        pulled += 1
        return {"type": "http.request", "body": b"x" * (1 << 20), "more_body": pulled < chunks}

    async def send(msg: dict[str, Any]) -> None:
        if msg["type"] == "http.response.start":
            status.append(msg["status"])

    scope = {
        "type": "http",
        "method": "POST",
        "path": path,
        "raw_path": path.encode(),
        "query_string": b"",
        "headers": [(k.lower().encode(), v.encode()) for k, v in headers.items()],
        "client": ("127.0.0.1", 1),
        "server": ("127.0.0.1", 8080),
        "scheme": "http",
        "http_version": "1.1",
        "root_path": "",
        "app": app,
    }
    asyncio.run(app(scope, receive, send))
    return status[0], pulled


def test_a_body_without_the_token_is_never_read_and_size_is_bounded(tmp_path: Path) -> None:
    app = app_without_robot(tmp_path)
    # 200 MiB with a wrong token: 401, not one chunk of the body read (it was all read and
    # parsed before the token was checked)
    assert asgi_post(app, "/calibrations", {"authorization": "Bearer wrong"}, 200) == (401, 0)
    assert asgi_post(app, "/calibrations", {}, 200) == (401, 0)
    # with the token, chunked: 413 after the first MiB over the 64 KiB limit
    assert asgi_post(app, "/calibrations", AUTH, 200) == (413, 1)
    # by its Content-Length: 413 before reading anything
    sized = {**AUTH, "content-length": str(200 << 20)}
    assert asgi_post(app, "/calibrations", sized, 200) == (413, 0)


@pytest.mark.parametrize(
    "body",
    [
        '{"overrides":{"limits":{"watchdog_ms":Infinity}}}',
        '{"overrides":{"protocol":{"sweep_deg":NaN}}}',
        '{"overrides":{"limits":{"max_yaw_rate":-Infinity}}}',
        '{"overrides":{"limits":{"max_yaw_rate":1e400}}}',
        '{"overrides":{"limits":{"watchdog_ms":' + "9" * 5000 + "}}}",
        '{"overrides":' + "[" * 5000 + "]" * 5000 + "}",
    ],
    ids=["inf", "nan", "-inf", "1e400", "5000-digit int", "deep nesting"],
)
def test_non_standard_json_is_a_422_naming_it(tmp_path: Path, body: str) -> None:
    with TestClient(app_without_robot(tmp_path)) as client:
        r = client.post(
            "/calibrations", content=body, headers={**AUTH, "content-type": "application/json"}
        )
    assert r.status_code == 422, r.text
    detail = r.json()["detail"][0]
    assert detail["type"] == "json_invalid" and detail["loc"][0] == "body"
    assert any(w in detail["msg"] for w in ("NaN", "Infinity", "too large", "digits", "nesting"))


def test_a_validation_error_with_non_finite_input_renders(tmp_path: Path) -> None:
    """The service itself never renders NaN: a validation error about a non-finite value
    says what was sent, as a string (it was a 500 while rendering)."""
    from fastapi.exceptions import RequestValidationError

    app = app_without_robot(tmp_path)

    @app.get("/_probe")
    def probe() -> None:
        error = {"loc": ["body"], "msg": "bad", "type": "x", "input": math.inf}
        raise RequestValidationError([error])

    with TestClient(app) as client:
        r = client.get("/_probe")
    assert r.status_code == 422 and r.json()["detail"][0]["input"] == "inf"


# ------------------------------------------------------------ tokens


@pytest.mark.parametrize(
    ("settings", "message"),
    [
        ({"token": SecretStr("change-me")}, "placeholder"),
        ({"token": SecretStr("")}, "empty"),
        ({"token": SecretStr("short-token")}, "at least 16"),
        ({"host": "0.0.0.0"}, "required when binding to 0.0.0.0"),
    ],
)
def test_weak_or_missing_tokens_are_refused(
    tmp_path: Path, settings: dict[str, Any], message: str
) -> None:
    from services.config.settings import SettingsError

    with pytest.raises(SettingsError, match=message):
        create_app(ServiceSettings(data_dir=tmp_path, **settings), runtime_factory=Runtime)


def test_a_generated_token_is_kept_private_and_never_printed(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.DEBUG)
    app = create_app(ServiceSettings(data_dir=tmp_path), runtime_factory=Runtime)
    token = app.state.token
    path = tmp_path / "api-token"
    assert path.read_text().strip() == token and len(token) >= 16
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    out = capsys.readouterr()
    assert token not in out.out + out.err + caplog.text
    # the same token after a restart
    again = create_app(ServiceSettings(data_dir=tmp_path), runtime_factory=Runtime)
    assert again.state.token == token


# ------------------------------------------------------------ one service per data dir / bus


def test_a_second_service_on_the_data_dir_stops_before_touching_it(tmp_path: Path) -> None:
    from services.store.locks import ChannelLock, LockedError

    first = Runtime(ServiceSettings(data_dir=tmp_path, token=SecretStr(TOKEN)))
    try:
        first.store.upsert("live1", "2026-01-01T00:00:00Z", {"id": "live1", "state": "SPIN"})
        with pytest.raises(LockedError, match="in use by swpc serve pid"):
            Runtime(ServiceSettings(data_dir=tmp_path, token=SecretStr(TOKEN)))
        got = first.store.get("live1")
        assert got is not None and got[0]["state"] == "SPIN"  # the first one's run: untouched
        lock = ChannelLock("socketcan", "can7").acquire()
        try:
            with pytest.raises(LockedError, match="socketcan:can7 is in use"):
                ChannelLock("socketcan", "can7").acquire()
        finally:
            lock.release()
        ChannelLock("socketcan", "can7").acquire().release()  # free again
    finally:
        first.close()
    Runtime(ServiceSettings(data_dir=tmp_path, token=SecretStr(TOKEN))).close()  # released


# ------------------------------------------------------------ disk: rolling CAN log


def test_the_rolling_can_log_stays_within_its_bytes_across_restarts(tmp_path: Path) -> None:
    from swpc_hw.can.recording import ROLLING_FILES, rolling_files

    base = tmp_path / "can" / "can.log"
    base.parent.mkdir()
    total = 512 << 10  # 512 KiB over all its files: 64 KiB each
    msg = can.Message(arbitration_id=0x123, data=bytes(range(8)), timestamp=1.0)
    frames = 0
    for _restart in range(3):  # the service restarts: the rolling log goes on, bounded
        rec = Recorder(str(base), total_bytes=total)
        for _ in range(6000):  # ~44 bytes a line: 260 KB per start
            rec.write(msg)
            frames += 1
        rec.stop()
        assert rec.error is None
    files = [base, *rolling_files(base)]
    size = sum(f.stat().st_size for f in files)
    assert size <= total and len(files) <= ROLLING_FILES + 1, (size, len(files))
    assert size > total // 2  # and it keeps the newest traffic, not nothing
    lines = sum(f.read_text().count("\n") for f in files)
    assert 0 < lines < frames
    # python-can reads every file back
    assert sum(1 for f in files for _ in can.LogReader(str(f))) == lines


def frame(f: Any, t: float) -> can.Message:
    return can.Message(
        arbitration_id=f.arbitration_id, data=f.data, timestamp=t, is_extended_id=False
    )


def idle_bus(seconds: int) -> list[can.Message]:
    """What an idle 4-module robot sends (heartbeats 10 Hz, encoder feedback 200 Hz, one
    other device at 100 Hz), with node 2 reporting an error from 3.5 s to 6 s, a fault
    report at 5 s, a host command at 6.5 s and an error frame at 7 s."""
    from firmware_protocol import codec
    from firmware_protocol.codec import AxisState, ControlMode

    out = []
    for k in range(seconds * 200):
        t = k / 200
        for n in (1, 2, 3, 4):
            if k % 20 == 0:
                errors = (0, 4) if n == 2 and 3.5 <= t < 6.0 else (0, 0)
                states = (AxisState.DISABLED, AxisState.DISABLED)
                modes = (ControlMode.FREE, ControlMode.FREE)
                hb = codec.make_heartbeat(n, states, modes, errors, True, False, k // 20 % 256)
                out.append(frame(hb, t))
            out.append(frame(codec.make_feedback_position(n, 0.1, 0.2, k % 256), t))
            vt = codec.make_feedback_velocity_torque(n, 0.0, 0.0, 0.0, 0.0, k % 256)
            out.append(frame(vt, t))
        if k % 2 == 0:
            out.append(can.Message(arbitration_id=0x18FF0001, data=b"\x01", timestamp=t))
        if k == 1000:
            fault = codec.make_fault_report(2, codec.Axis.WHEEL, 4, 4, AxisState.FAULT)
            out.append(frame(fault, t))
        if k == 1300:
            cmd = codec.make_set_control(1, codec.Axis.WHEEL, ControlMode.FREE)
            out.append(frame(cmd, t))
        if k == 1400:
            out.append(can.Message(is_error_frame=True, arbitration_id=0x040, timestamp=t))
    return out


def test_between_runs_the_rolling_log_keeps_a_sample_and_every_event(tmp_path: Path) -> None:
    """An idle robot's traffic, 10 s: once a second per CAN id, and every event at once
    (it was every frame: 100 kB/s, 360 MB an hour of writes for a log that forgets)."""
    from firmware_protocol.codec import Command, frame_id

    frames = idle_bus(10)
    assert len(frames) == 17_403
    rec = Recorder(str(tmp_path / "idle.log"), sample_period_s=1.0)
    for msg in frames:
        rec.write(msg, sample=True)
    rec.stop()
    kept = list(can.LogReader(str(tmp_path / "idle.log")))
    by_id: dict[int, list[float]] = {}
    for msg in kept:
        by_id.setdefault(msg.arbitration_id, []).append(round(msg.timestamp, 3))
    seconds = [float(t) for t in range(10)]
    for n in (1, 3, 4):
        assert by_id[frame_id(n, Command.HEARTBEAT)] == seconds  # heartbeat: one a second
    # node 2's heartbeat also when its errors come (3.5 s) and go (6 s)
    changes = [0.0, 1.0, 2.0, 3.0, 3.5, 4.5, 5.5, 6.0, 7.0, 8.0, 9.0]
    assert by_id[frame_id(2, Command.HEARTBEAT)] == changes
    feedback = (Command.FEEDBACK_POSITION, Command.FEEDBACK_VELOCITY_TORQUE)
    for n in (1, 2, 3, 4):
        assert [by_id[frame_id(n, c)] for c in feedback] == [seconds, seconds]
    assert by_id[0x18FF0001] == seconds  # another device's frames: sampled too
    # events: every one
    assert by_id[frame_id(2, Command.FAULT_REPORT)] == [5.0]
    assert by_id[frame_id(1, Command.SET_CONTROL)] == [6.5]
    assert [m.timestamp for m in kept if m.is_error_frame] == [7.0]
    assert len(kept) == 41 + 80 + 10 + 3
    # written without sampling (a run's recording, or the setting 0): every frame
    every = Recorder(str(tmp_path / "all.log"), sample_period_s=0.0)
    for msg in frames[:5000]:
        every.write(msg, sample=True)
    every.stop()
    assert sum(1 for _ in can.LogReader(str(tmp_path / "all.log"))) == 5000


def test_the_driver_logs_every_frame_only_while_it_records_a_run(tmp_path: Path) -> None:
    import time
    import uuid

    from firmware_protocol import codec
    from firmware_protocol.codec import AxisState, ControlMode
    from swpc_hw.can import CanConfig, CanDriver

    channel = f"swpc-idle-{uuid.uuid4().hex[:8]}"
    rolling = tmp_path / "can.log"
    driver = CanDriver(
        CanConfig(channel=channel, log_path=str(rolling), log_total_bytes=1 << 20,
                  log_idle_period_s=1.0)
    )  # fmt: skip
    driver.configure()
    t0 = time.time()
    off = (AxisState.DISABLED, AxisState.DISABLED), (ControlMode.FREE, ControlMode.FREE)

    def burst(bus: can.BusABC, start: float, sent: int) -> int:
        """50 heartbeats of node 1, 10 ms apart from ``start`` (their own stamps)."""
        for k in range(50):
            hb = codec.make_heartbeat(1, *off, (0, 0), True, False, k)
            bus.send(frame(hb, t0 + start + k * 0.01))
        deadline = time.monotonic() + 30  # a guard: the driver's thread takes them in
        while driver.stats().rx_frames < sent + 50:
            assert time.monotonic() < deadline, driver.stats()
            time.sleep(0.005)
        return sent + 50

    with can.Bus(interface="virtual", channel=channel, preserve_timestamps=True) as bus:
        sent = burst(bus, 0.0, 0)  # idle: one kept
        driver.start_recording(str(tmp_path / "run.log"))
        sent = burst(bus, 0.5, sent)  # a run: every one
        assert driver.stop_recording() is None
        sent = burst(bus, 1.2, sent)  # idle again: one
    driver.shutdown()
    stamps = [round(m.timestamp - t0, 2) for m in can.LogReader(str(rolling))]
    assert stamps == [0.0] + [round(0.5 + k * 0.01, 2) for k in range(50)] + [1.2]
    assert sum(1 for _ in can.LogReader(str(tmp_path / "run.log"))) == 50


def test_a_can_log_that_cannot_write_stops_and_says_why(tmp_path: Path) -> None:
    rec = Recorder(str(tmp_path / "x.log"))
    rec.logger.file.close()  # type: ignore[attr-defined]  # the file is gone from under it
    rec.write(can.Message(arbitration_id=1, data=b"\x00"))
    assert rec.closed and rec.error is not None and "x.log" in rec.error


# ------------------------------------------------------------ file modes and group


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


# ------------------------------------------------------------ provenance, logs, state


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
        for _schema, channel, message in reader.iter_messages():
            doc = json.loads(message.data, parse_constant=lambda c: pytest.fail(c))
            errors = [e.message for e in validators[channel.topic].iter_errors(doc)]
            assert errors == [], (channel.topic, doc, errors)
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
        attachments = {a.name for a in reader.iter_attachments()}
        metadata = {m.name for m in reader.iter_metadata()}
    assert schemas["/mocap/pose"].name == "foxglove.PoseInFrame"
    assert schemas["/tf"].name == "foxglove.FrameTransform"
    assert schemas["/calibration/events"].name == "foxglove.Log"
    assert counts["/mocap/pose"] == counts["/tf"] == ds.poses.shape[0]
    for m, rows in ds.encoders.items():
        assert counts[f"/module{m}/encoders"] == rows.shape[0]
    assert counts["/calibration/segments"] == len(ds.segments)
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


# ------------------------------------------------------------ crash: kill -9 keeps the data

KILLED = textwrap.dedent(
    """
    import os, signal, sys
    from pathlib import Path
    sys.path.insert(0, {root!r})
    from tests.test_state_machine import Rig
    from services.runs.protocol import State

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
    from tests.test_state_machine import Rig
    from swpc_hw.kinematic_file import load_kinematics, save_kinematics
    from swpc_hw.paper_robot import PAPER_NOMINAL

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


@pytest.mark.skipif(shutil.which("unshare") is None, reason="no unshare(1)")
def test_a_full_disk_fails_the_run_cleanly_and_keeps_the_kinematic_file(tmp_path: Path) -> None:
    """A real ENOSPC: a 160 KiB tmpfs in a user + mount namespace of a child process."""
    script = tmp_path / "full.py"
    script.write_text(DISK_FULL.format(root=str(ROOT)))
    mnt = tmp_path / "mnt"
    mnt.mkdir()
    probe = subprocess.run(
        ["unshare", "--user", "--map-root-user", "--mount", "true"], capture_output=True
    )
    if probe.returncode != 0:
        pytest.skip(f"no user namespaces here: {probe.stderr.decode().strip()}")
    cmd = (
        f"mount -t tmpfs -o size=160k tmpfs {mnt} && "
        f"exec {sys.executable} {script} {mnt}"
    )
    p = subprocess.run(
        ["unshare", "--user", "--map-root-user", "--mount", "sh", "-c", cmd],
        capture_output=True,
        timeout=120,
    )
    assert p.returncode == 0, p.stderr.decode()[-3000:]
    out = json.loads(p.stdout.decode().strip().splitlines()[-1])
    print(f"\ndisk-full run: {out}")  # the figure docs/history/ records (pytest -s)
    assert out["state"] == "FAILED" and "disk full" in out["reason"], out
    assert "No space left on device" in out["reason"]
    assert out["same"] and out["stopped"], out


# ------------------------------------------------------------ after a restart, corrupt files


def test_corrupt_kinematic_file_is_a_clear_error_and_degraded_health(tmp_path: Path) -> None:
    """A file in force that does not load is a fault of the server's data, not of the
    request: a JSON 500 (not 503, which /health keeps for "cannot calibrate") that says
    why and which backup to roll back to; /health names it (degraded on a service that
    can calibrate: tests/test_hardening_server.py).  It was a bare 500."""
    kin = tmp_path / "kinematics.yaml"
    good = tmp_path / "kinematics.20260101T000000000000Z.yaml"
    save_kinematics(good, PAPER_NOMINAL, created="2026-01-01T00:00:00Z")
    (tmp_path / "kinematics.20260201T000000000000Z.yaml").write_text("format: nope\n")
    kin.write_bytes(b"format: swpc-kinematics/1\nrobot: \xff\xfe\n")
    with TestClient(app_without_robot(tmp_path)) as client:
        r = client.get("/kinematics")
        health = client.get("/health").json()
        files = client.get("/kinematics/files").json()
        assert r.status_code == 500 and r.headers["content-type"] == "application/json"
        body = r.json()
        reason = f"{kin}: not UTF-8 text (byte 0xff at offset 33): a damaged or foreign file"
        assert body == {
            "detail": f"the kinematic file in force cannot be loaded: {reason}; roll back to "
            f'a backup: POST /kinematics/rollback {{"backup": "{good.name}"}} '
            "(GET /kinematics/files lists them)",
            "path": str(kin),
            "reason": reason,
            "backups": [good.name],  # the newer backup does not load: not offered
        }
        assert f"kinematic file in force unreadable: {reason}" in health["problems"]
        assert files["in_force"]["valid"] is False and files["in_force"]["error"] == reason
        # what it says to do works
        r = client.post("/kinematics/rollback", json={"backup": good.name}, headers=AUTH)
        assert r.status_code == 200, r.text
        assert client.get("/kinematics").json()["modules"][0]["id"] == 1
        # a directory or a dangling link where the file should be: the same, not a 404
        # "none installed" (and /kinematics/files was a bare 500 on the directory)
        kin.unlink()
        kin.mkdir()
        r = client.get("/kinematics")
        assert r.status_code == 500 and r.json()["reason"] == f"{kin}: cannot read: Is a directory"
        assert client.get("/kinematics/files").json()["in_force"]["sha256"] is None
        kin.rmdir()
        kin.symlink_to(tmp_path / "gone.yaml")
        r = client.get("/kinematics")
        assert r.status_code == 500 and r.json()["reason"].endswith("No such file or directory")
        assert client.get("/kinematics/files").json()["in_force"]["valid"] is False


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


def test_docs_are_served_without_internet(tmp_path: Path) -> None:
    with TestClient(app_without_robot(tmp_path)) as client:
        for page, asset in (("/docs", "swagger-ui-bundle.js"), ("/redoc", "redoc.standalone.js")):
            html = client.get(page).text
            urls = [u for u in html.split('"') if u.startswith(("http://", "https://", "//"))]
            assert urls == [], urls  # nothing from a CDN (or fonts from Google)
            assert f"/docs/assets/{asset}" in html
            js = client.get(f"/docs/assets/{asset}")
            assert js.status_code == 200 and len(js.content) > 500_000
        assert client.get("/docs/assets/swagger-ui.css").status_code == 200
        lic = client.get("/docs/assets/LICENSE").text
        assert "Apache License 2.0" in lic and "Permission is hereby granted" in lic


# ------------------------------------------------------------ CLI


def test_cli_errors_are_one_line_with_a_nonzero_exit(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from services.cli import main
    from services.store.provenance import tool_version

    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0 and capsys.readouterr().out.startswith(f"swpc {tool_version()}")
    cases = [
        (["serve", "--env-file", str(tmp_path / "none.env")], "--env-file", 2),
        (["sim", "--channel", "swpcnone0", "--duration", "0.1"], "cannot open CAN interface", 2),
        (["can", "monitor", "--channel", "swpc-none", "--duration", "0.4", "--plain"],
         "no heartbeat from module 1 (node 1)", 1),
    ]  # fmt: skip
    for argv, what, code in cases:
        assert main(argv) == code, argv
        err = capsys.readouterr().err.strip().splitlines()
        mine = [line for line in err if line.startswith("swpc ")]
        assert len(mine) == 1 and what in mine[0], err  # one line, no traceback
        assert not any("Traceback" in line for line in err)
    with pytest.raises(SystemExit):
        main(["validate", "--help"])
    text = capsys.readouterr().out
    assert "``" not in text and ":mod:" not in text and "square" in text


HOLD_LOCK = textwrap.dedent(
    """
    import sys
    from pathlib import Path
    sys.path.insert(0, {root!r})
    from services.store.locks import DataDirLock

    DataDirLock(Path(sys.argv[1])).acquire()
    print("held", flush=True)
    sys.stdin.read()  # until the test closes our stdin
    """
)


@pytest.fixture()
def swpc_log_state() -> Any:
    """``swpc serve`` configures the ``swpc`` logger (a stderr handler, no propagation):
    put it back as it was for the tests after this one."""
    lg = logging.getLogger("swpc")
    saved = (list(lg.handlers), lg.propagate, lg.level)
    yield
    lg.handlers[:], lg.propagate, lg.level = saved[0], saved[1], saved[2]


def serve_error(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    """Run ``swpc serve`` in this process: it must return 2 with one line on stderr, the
    error (it was uvicorn's 29-50 line traceback and exit status 3)."""
    from services.cli import main

    assert main(["serve", "--port", "0", "--log-level", "warning", *argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("swpc serve: error: "), err
    return err[0]


@pytest.mark.usefixtures("swpc_log_state")
def test_serve_on_a_data_dir_held_by_another_process_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("SWPC_TOKEN", TOKEN)
    monkeypatch.delenv("SWPC_CAN_INTERFACE", raising=False)
    data = tmp_path / "data"
    script = tmp_path / "hold.py"
    script.write_text(HOLD_LOCK.format(root=str(ROOT)))
    holder = subprocess.Popen(
        [sys.executable, str(script), str(data)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout is not None and holder.stdout.readline() == "held\n"
        line = serve_error(["--data-dir", str(data)], capsys)
        assert f"{data}: the data dir is in use by swpc serve pid {holder.pid}" in line
        # it stopped before writing anything there: no store, no token, no CAN log
        assert sorted(p.name for p in data.iterdir()) == [".lock"]
    finally:
        assert holder.stdin is not None
        holder.stdin.close()
        holder.wait(10)


@pytest.mark.usefixtures("swpc_log_state")
def test_serve_with_a_can_interface_that_cannot_be_opened_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    from services.store.locks import ChannelLock, DataDirLock

    channel = f"swpc{uuid.uuid4().hex[:8]}"  # no such interface (its lock is host-wide)
    monkeypatch.setenv("SWPC_TOKEN", TOKEN)
    monkeypatch.setenv("SWPC_CAN_INTERFACE", "socketcan")
    monkeypatch.setenv("SWPC_CAN_CHANNEL", channel)
    line = serve_error(["--data-dir", str(tmp_path)], capsys)
    # no such interface here (or no CAN in the kernel): python-can's reason, on one line
    assert f"cannot open CAN bus interface='socketcan' channel='{channel}': " in line
    # what it had taken is given back: the data dir's lock and the channel's
    DataDirLock(tmp_path).acquire().release()
    ChannelLock("socketcan", channel).acquire().release()


@pytest.mark.usefixtures("swpc_log_state")
def test_serve_on_a_port_or_zenoh_endpoint_in_use_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    import socket

    monkeypatch.setenv("SWPC_TOKEN", TOKEN)
    monkeypatch.delenv("SWPC_CAN_INTERFACE", raising=False)
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        line = serve_error(["--data-dir", str(tmp_path / "a"), "--port", str(port)], capsys)
        assert f"cannot listen on 127.0.0.1:{port}: Address already in use" in line
        monkeypatch.setenv("SWPC_ZENOH_LISTEN", f'["tcp/127.0.0.1:{port}"]')
        line = serve_error(["--data-dir", str(tmp_path / "b")], capsys)
        assert f"cannot open the zenoh session (listen=['tcp/127.0.0.1:{port}']): " in line
        assert "Address already in use" in line and ".rs:" not in line
    from services.store.locks import DataDirLock

    DataDirLock(tmp_path / "b").acquire().release()


def test_the_paper_method_table_has_no_nan_and_one_turn_angles() -> None:
    from swpc_hw.calibration.report import format_table
    from swpc_hw.calibration.solver import CalibrationResult, SegmentQuality

    seg = SegmentQuality(0, 1, math.radians(405.0), 100, 0, math.nan, (0.0, 0.0), math.nan)
    res = CalibrationResult(
        params=PAPER_NOMINAL, nominal=PAPER_NOMINAL, segments=[seg], time_offset=0.0,
        time_offset_std=None, time_offset_mode="given", poses_used=100, poses_rejected=0,
        increments_used=0, increments_rejected=0, reduced_chi2=math.nan, method="paper",
    )  # fmt: skip
    text = format_table(res)
    assert "nan" not in text.lower() and "at   45.00 deg" in text, text


def test_dataset_hash_follows_every_file(tmp_path: Path) -> None:
    from services.store.provenance import dataset_sha256

    for name in ("robot.yaml", "poses.csv", "encoders.csv", "segments.csv"):
        (tmp_path / name).write_text("a\n")
    h = dataset_sha256(tmp_path)
    (tmp_path / "poses.csv").write_text("b\n")
    assert dataset_sha256(tmp_path) != h and len(h) == 64
    (tmp_path / "poses.csv").write_text("a\n")
    assert dataset_sha256(tmp_path) == h
