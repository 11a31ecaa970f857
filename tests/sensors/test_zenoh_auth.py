"""Only authenticated peers publish the robot's poses and gyro: zenoh's own user-password
authentication and access control (swpc_hw/sensors/zenoh_session.py), on loopback, as the
service, its in-process simulator and the deploy configs set them up."""

from __future__ import annotations

import json
import os
import stat
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from services.runtime.runtime import ZENOH_USERS_FILE
from swpc_hw.sensors.mocap import PoseSample, encode_native
from swpc_hw.sensors.zenoh_session import ZenohAuth, free_tcp_endpoint, open_session, publishers_acl
from tests.service_rig import Sim

KEY = "mocap/swpc/pose"


def deliveries(publish: Callable[[], None], got: list[Any], within: float = 2.0) -> int:
    """Publish every 50 ms for ``within`` s (a guard: links take a moment); how many of
    them arrived."""
    n0 = len(got)
    deadline = time.monotonic() + within
    while time.monotonic() < deadline:
        publish()
        time.sleep(0.05)
    return len(got) - n0


def test_only_the_named_publishers_put_on_the_sensor_keys(tmp_path: Path) -> None:
    users = tmp_path / "users"
    users.write_text("mocap:mocap-secret-0123\nviewer:viewer-secret-0123\n")
    ep = free_tcp_endpoint()
    service = open_session(
        listen=[ep], auth=ZenohAuth(users_file=str(users)), acl=publishers_acl([KEY], ["mocap"])
    )
    got: list[bytes] = []
    service.declare_subscriber(KEY, lambda s: got.append(s.payload.to_bytes()))
    peers = {
        "mocap": ZenohAuth("mocap", "mocap-secret-0123"),
        "viewer": ZenohAuth("viewer", "viewer-secret-0123"),  # known, not a publisher
        "wrong password": ZenohAuth("mocap", "guessed"),
        "anonymous": None,
    }
    arrived = {}
    try:
        for name, auth in peers.items():
            peer = open_session(connect=[ep], auth=auth)
            try:
                arrived[name] = deliveries(lambda p=peer, n=name: p.put(KEY, n.encode()), got)
            finally:
                peer.close()
    finally:
        service.close()
    assert arrived["mocap"] > 0, arrived
    assert arrived["viewer"] == arrived["wrong password"] == arrived["anonymous"] == 0, arrived


def test_a_local_process_cannot_feed_the_service_poses(sim: Sim) -> None:
    """Any local process could connect to the service's zenoh port and publish poses on the
    robot's key.  Against the in-process simulator only the simulator may: its credential
    is made for this run of the service, in a file of the data dir no one else reads."""
    rt = sim.rt
    users = rt.data_dir / ZENOH_USERS_FILE
    assert stat.S_IMODE(users.stat().st_mode) == 0o600
    (ep,) = rt.zenoh_endpoints
    _, cursor = rt.mocap.samples_since(0)
    rogue = open_session(connect=[ep])
    try:
        n = deliveries(
            lambda: rogue.put(KEY, encode_native(PoseSample.planar(time.time(), 9.0, 9.0, 0.0))),
            [],
            within=1.0,
        )
        assert n == 0
    finally:
        rogue.close()
    # not one of its poses reached the ingest (the simulator's own, in flight on a busy
    # host, may: they are not at x = 9 m)
    rows, _ = rt.mocap.samples_since(cursor)
    assert not (rows[:, 3] == 9.0).any(), rows


def test_the_mocap_pcs_listener_admits_only_robots_and_takes_no_poses_from_them(
    tmp_path: Path,
) -> None:
    """deploy/zenoh/mocap-peer.json5 on loopback: a robot (user swpc) subscribes to its
    poses; an anonymous peer is not admitted; no robot can publish poses into it."""
    import zenoh

    from swpc_hw.sensors.zenoh_session import zenoh_config

    root = Path(__file__).resolve().parents[2]
    users = tmp_path / "zenoh-users.txt"
    users.write_text("swpc:robot-secret-0123\n")
    ep = free_tcp_endpoint()
    mcfg = zenoh_config(config_file=str(root / "deploy" / "zenoh" / "mocap-peer.json5"))
    mcfg.insert_json5("listen/endpoints", json.dumps([ep]))
    mcfg.insert_json5("plugins", "{}")
    mcfg.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(users)))
    mocap = zenoh.open(mcfg)
    got: dict[str, list[bytes]] = {"robot": [], "anonymous": [], "mocap": []}
    try:
        robot = open_session(connect=[ep], auth=ZenohAuth("swpc", "robot-secret-0123"))
        anon = open_session(connect=[ep])
        try:
            robot.declare_subscriber(KEY, lambda s: got["robot"].append(s.payload.to_bytes()))
            anon.declare_subscriber(KEY, lambda s: got["anonymous"].append(s.payload.to_bytes()))
            mocap.declare_subscriber(KEY, lambda s: got["mocap"].append(s.payload.to_bytes()))
            deliveries(lambda: mocap.put(KEY, b"pose"), got["robot"])
            deliveries(lambda: robot.put(KEY, b"spoofed"), got["mocap"], within=1.0)
        finally:
            robot.close()
            anon.close()
    finally:
        mocap.close()
    assert b"pose" in got["robot"], got  # (its own puts it hears locally)
    assert got["anonymous"] == [], got
    assert b"spoofed" not in got["mocap"], got


def test_the_in_process_credential_is_gone_when_the_service_closes(tmp_path: Path) -> None:
    from tests.service_rig import sim_service

    with sim_service(tmp_path) as sim:
        users = sim.rt.data_dir / ZENOH_USERS_FILE
        assert users.exists()
    assert not users.exists() and not os.path.lexists(users)


pytestmark = pytest.mark.timeout(120)


def test_health_names_a_refused_zenoh_link_and_the_right_password_clears_it(
    tmp_path: Path,
) -> None:
    """The service set up as deploy/README.md says (robot-peer.json5 presenting this robot's
    user/password) against the mocap PC's listener (mocap-peer.json5): with a password the
    mocap PC does not know, /health names the link, not only the silent poses; with the
    right one, the link is up and the poses arrive."""
    import uuid

    import zenoh
    from fastapi.testclient import TestClient
    from pydantic import SecretStr

    from services.config.settings import ServiceSettings
    from services.http.app import create_app
    from services.runtime.runtime import Runtime
    from swpc_hw.sensors.zenoh_session import zenoh_config
    from tests.service_rig import TOKEN

    root = Path(__file__).resolve().parents[2]
    users = tmp_path / "robots.txt"
    users.write_text("swpc-robot07:robot-secret-0123\n")
    ep = free_tcp_endpoint()
    mcfg = zenoh_config(config_file=str(root / "deploy" / "zenoh" / "mocap-peer.json5"))
    mcfg.insert_json5("listen/endpoints", json.dumps([ep]))
    mcfg.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(users)))
    mocap = zenoh.open(mcfg)
    template = (root / "deploy" / "zenoh" / "robot-peer.json5").read_text()
    template = template.replace("tcp/192.0.2.10:7447", ep)
    seen: dict[str, dict[str, Any]] = {}
    try:
        for name, password in (("refused", "guessed"), ("admitted", "robot-secret-0123")):
            robot_cfg = tmp_path / f"{name}.json5"
            robot_cfg.write_text(
                template.replace("replace-with-this-robot's-password", password)
            )
            settings = ServiceSettings(
                data_dir=tmp_path / name,
                token=SecretStr(TOKEN),
                can_interface="virtual",
                can_channel=f"swpc-{name}-{uuid.uuid4().hex[:8]}",
                zenoh_config_file=str(robot_cfg),
            )
            app = create_app(settings, runtime_factory=lambda s: Runtime(s).open())
            with TestClient(app) as client:
                rt: Runtime = app.state.runtime
                assert rt.zenoh_connect == [ep]
                pose = encode_native(PoseSample.planar(time.time(), 1.0, 2.0, 0.0))
                deliveries(lambda p=pose: mocap.put(KEY, p), [], within=1.5)
                seen[name] = client.get("/health").json()
    finally:
        mocap.close()
    link = [p for p in seen["refused"]["problems"] if p.startswith("zenoh: no link to ")]
    assert link == [
        f"zenoh: no link to {ep}: check the address, that the peer listens there, and this "
        "robot's zenoh user/password (deploy/README.md, Motion capture over zenoh)"
    ], seen["refused"]["problems"]
    assert seen["refused"]["zenoh_links"] == 0 and seen["refused"]["mocap_age_s"] is None
    assert not [p for p in seen["admitted"]["problems"] if p.startswith("zenoh")]
    assert seen["admitted"]["zenoh_links"] == 1 and seen["admitted"]["mocap_age_s"] is not None
