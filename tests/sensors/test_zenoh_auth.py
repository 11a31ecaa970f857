"""Only authenticated peers publish the robot's poses and gyro: zenoh's own user-password
authentication and access control (swpc_hw/sensors/zenoh_session.py), on loopback, as the
service, its in-process simulator and the deploy configs set them up."""

from __future__ import annotations

import json
import os
import stat
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import pytest

from services.runtime.runtime import ZENOH_USERS_FILE
from swpc_hw.sensors.mocap import PoseSample, encode_native
from swpc_hw.sensors.zenoh_session import (
    ZenohAuth,
    free_tcp_endpoint,
    linked_sessions,
    open_session,
    publishers_acl,
)
from tests.service_rig import Sim

KEY = "mocap/swpc/pose"


def deliveries(publish: Callable[[], None], got: list[Any], within: float = 2.0) -> int:
    """Publish every 50 ms for ``within`` s (a window for a negative, after a positive
    control on the same link); how many of them arrived."""
    n0 = len(got)
    deadline = time.monotonic() + within
    while time.monotonic() < deadline:
        publish()
        time.sleep(0.05)
    return len(got) - n0


def publish_until(publish: Callable[[], None], arrived: Callable[[], bool]) -> None:
    """Publish every 50 ms until ``arrived()``: a positive control, waiting for the event
    itself (10 s: a guard against a hang, never a judgement of speed)."""
    deadline = time.monotonic() + 10.0
    while not arrived():
        assert time.monotonic() < deadline, "the positive control never arrived"
        publish()
        time.sleep(0.05)


NEGATIVE_WINDOW_S = 0.3
"""How long a negative keeps publishing once its positive control on the same link (same
loopback endpoint, same key) has arrived: a put that may cross arrives within the 50 ms
tick after it is sent, so 6 rounds of puts, each peer's last ones sent 50 ms before the
window ends, leave every refused put ample time to show up."""


def open_sessions(ep: str, auths: dict[str, ZenohAuth | None]) -> dict[str, Any]:
    """One peer session per name, connected to ``ep``, opened together: zenoh's open waits
    its scouting delay (0.5 s) for a link that never comes when the peer is refused."""
    with ThreadPoolExecutor(len(auths)) as pool:
        futures = {n: pool.submit(open_session, connect=[ep], auth=a) for n, a in auths.items()}
    failed = [e for f in futures.values() if (e := f.exception()) is not None]
    if failed:
        for f in futures.values():
            if f.exception() is None:
                f.result().close()
        raise failed[0]
    return {n: f.result() for n, f in futures.items()}


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
    try:
        sessions = open_sessions(ep, peers)
        try:

            def put_all() -> None:
                for name, peer in sessions.items():
                    peer.put(KEY, name.encode())

            # every peer puts at once: the authorised one's puts arrive (positive control),
            # then a window for the others' (NEGATIVE_WINDOW_S)
            publish_until(put_all, lambda: b"mocap" in got)
            deliveries(put_all, got, within=NEGATIVE_WINDOW_S)
            links = {name: linked_sessions(peer) for name, peer in sessions.items()}
        finally:
            for peer in sessions.values():
                peer.close()
    finally:
        service.close()
    arrived = {name: got.count(name.encode()) for name in peers}
    assert arrived["mocap"] > 0, arrived
    assert arrived["viewer"] == arrived["wrong password"] == arrived["anonymous"] == 0, arrived
    # the viewer is refused by the access control (it has a link), the other two by the
    # authentication (none)
    assert links == {"mocap": 1, "viewer": 1, "wrong password": 0, "anonymous": 0}, links


def test_a_local_process_cannot_feed_the_service_poses(sim: Sim) -> None:
    """Any local process could connect to the service's zenoh port and publish poses on the
    robot's key.  Against the in-process simulator only the simulator may: its credential
    is made for this run of the service, in a file of the data dir no one else reads."""
    rt = sim.rt
    users = rt.data_dir / ZENOH_USERS_FILE
    assert stat.S_IMODE(users.stat().st_mode) == 0o600
    (ep,) = rt.zenoh_endpoints
    _, cursor = rt.mocap.samples_since(0)
    user, password = users.read_text().strip().split(":", 1)
    peers = open_sessions(ep, {"rogue": None, "simulator": ZenohAuth(user, password)})
    try:

        def put(name: str, x: float) -> None:
            peers[name].put(KEY, encode_native(PoseSample.planar(time.time(), x, x, 0.0)))

        def put_both() -> None:
            put("rogue", 9.0)
            put("simulator", 7.0)

        def ingested() -> Any:
            return rt.mocap.samples_since(cursor)[0]

        # positive control on the same endpoint: the simulator's credential is admitted and
        # its poses (x = 7 m) reach the ingest; then a window for the rogue's
        publish_until(put_both, lambda: bool((ingested()[:, 3] == 7.0).any()))
        deliveries(put_both, [], within=NEGATIVE_WINDOW_S)
        rogue_links = linked_sessions(peers["rogue"])
    finally:
        for peer in peers.values():
            peer.close()
    assert rogue_links == 0  # refused by the authentication
    # not one of its poses reached the ingest (the simulator's own, in flight on a busy
    # host, may: they are not at x = 9 m)
    rows = ingested()
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
        peers = open_sessions(ep, {"robot": ZenohAuth("swpc", "robot-secret-0123"), "anon": None})
        robot, anon = peers["robot"], peers["anon"]
        try:
            robot.declare_subscriber(KEY, lambda s: got["robot"].append(s.payload.to_bytes()))
            anon.declare_subscriber(KEY, lambda s: got["anonymous"].append(s.payload.to_bytes()))
            mocap.declare_subscriber(KEY, lambda s: got["mocap"].append(s.payload.to_bytes()))

            def put_both() -> None:
                mocap.put(KEY, b"pose")
                robot.put(KEY, b"spoofed")

            # the poses reach the robot (positive control: the link is up both ways, the
            # robot's subscription crossed it to the mocap PC), then a window for the
            # anonymous peer's poses and the robot's spoofed ones (NEGATIVE_WINDOW_S)
            publish_until(put_both, lambda: b"pose" in got["robot"])
            deliveries(put_both, [], within=NEGATIVE_WINDOW_S)
            anon_links = linked_sessions(anon)
        finally:
            robot.close()
            anon.close()
    finally:
        mocap.close()
    assert b"pose" in got["robot"], got  # (its own puts it hears locally)
    assert got["anonymous"] == [], got
    assert anon_links == 0  # not admitted
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
        # the admitted robot first: the positive control of the mocap PC's listener and
        # its poses, then the refused one's window (NEGATIVE_WINDOW_S)
        for name, password in (("admitted", "robot-secret-0123"), ("refused", "guessed")):
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
                if name == "admitted":
                    publish_until(
                        lambda p=pose: mocap.put(KEY, p),
                        lambda: client.get("/health").json()["mocap_age_s"] is not None,
                    )
                else:
                    deliveries(lambda p=pose: mocap.put(KEY, p), [], within=NEGATIVE_WINDOW_S)
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
