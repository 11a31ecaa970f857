"""A fleet only robots can write (issue 40, item 2): each robot connects to the fleet's
router with its own zenoh credentials and may publish under its own name only; every
document is checked (size, nesting, finite and plausible numbers) and a refused one is
counted, logged once and never stored; the store is bounded; ``GET /robots`` is never
broken by what was stored.

Rows of the issue: 2 (a peer without credentials made a robot "live"), 3 (a calibration
published under another robot's key merged into its drift for good), 4 (a document
nested 900 deep broke ``GET /robots`` for everyone, also after a restart), 5 (no bound on
the store; ``heartbeat_s`` = 1e400 an uncaught OverflowError, not counted).
"""

from __future__ import annotations

import json
import logging
import re
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from services.config.fleet import (
    FleetNameError,
    FleetSettings,
    alive_key,
    fleet_acl,
    fleet_users,
    state_key,
)
from services.config.settings import ServiceSettings
from services.fleet.service import (
    MAX_DEPTH,
    DocumentError,
    FleetService,
    check_document,
    open_fleet_session,
)
from services.http.fleet.app import create_fleet_app
from services.runtime.fleet import FleetPublisher
from services.runtime.runtime import Runtime
from services.store.fleet import FleetStore
from swpc_hw.clock import VirtualClock
from swpc_hw.sensors.zenoh_session import ZenohAuth, free_tcp_endpoint, open_session

ROUTER_FILE = Path(__file__).resolve().parents[3] / "deploy" / "zenoh" / "fleet-router.json5"
GOOD = {"format": "swpc-fleet-state/2", "fleet_period_s": 5.0, "file_in_force": None,
        "last_check": None, "history": {"calibrations": []}}  # fmt: skip


def state(robot: str, **more: Any) -> bytes:
    return json.dumps({**GOOD, "robot": robot, **more}).encode()


def calibration(run: str, x_s: float) -> dict[str, Any]:
    mod = {"id": 1, "x_s": x_s, "y_s": 0.125, "beta": 0.0, "b": 0.02, "r": 0.055}
    return {"run": run, "time": "2026-01-01T00:00:00Z", "modules": [mod]}


def nested(depth: int) -> Any:
    v: Any = 1.0
    for _ in range(depth):
        v = {"a": v}
    return v


# ------------------------------------------------------------------ the checks, no zenoh


@pytest.mark.parametrize(
    ("payload", "words"),
    [
        (state("a", health=nested(900)), f"nested more than {MAX_DEPTH} deep"),
        (state("a", health=0).replace(b'"health": 0', b'"health": ' + b'[' * 100_000
                                      + b']' * 100_000), f"nested more than {MAX_DEPTH} deep"),
        (state("a").replace(b'"fleet_period_s": 5.0', b'"fleet_period_s": 1e400'),
         "/fleet_period_s: inf is not a finite number"),
        (state("a", health={"load": 1e400}), "/health/load: inf is not a finite number"),
        (state("a", fleet_period_s=3600.5), "fleet_period_s 3600.5"),
        (state("a", history={"calibrations": [calibration("r1", 1e300)]}),
         "x_s: 1e+300 is not a finite number within"),
        (state("a", history={"calibrations": [calibration("r1", 60.0)]}),
         "x_s: 60.0 outside the plausible [-50.0, 50.0]"),
        (b" " * (1 << 20) + state("a"), "bytes, more than 1048576"),
    ],
)  # fmt: skip
def test_a_document_out_of_shape_is_refused_naming_why(payload: bytes, words: str) -> None:
    with pytest.raises(DocumentError) as exc:
        check_document("a", payload)
    assert words in str(exc.value), str(exc.value)


def test_a_refused_document_is_counted_logged_once_and_never_stored(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    fleet = FleetService(FleetStore(tmp_path / "fleet.sqlite"), clock=VirtualClock())
    caplog.set_level(logging.WARNING, logger="swpc.fleet")
    key = state_key("a")
    for _ in range(3):  # a robot stuck on a bad document: one line, three counted
        assert not fleet.receive(key, state("a", health=nested(900)))
    assert not fleet.receive(key, state("a", fleet_period_s=float("nan")))
    assert fleet.receive(key, state("a"))  # right again
    assert not fleet.receive(key, state("a", health={"x": 1e400}))
    lines = [r.getMessage() for r in caplog.records if "fleet.rejected" in r.getMessage()]
    assert len(lines) == 2 and "nested more than" in lines[0], lines
    assert fleet.counts()["rejected"] == 5 and fleet.counts()["documents"] == 1
    with TestClient(create_fleet_app(fleet)) as client:
        assert [r["robot"] for r in client.get("/robots").json()] == ["a"]


def test_the_store_is_bounded_per_robot_and_in_total_oldest_first(tmp_path: Path) -> None:
    store = FleetStore(tmp_path / "fleet.sqlite", max_documents=5, max_bytes=20_000)
    fleet = FleetService(store, clock=VirtualClock())
    pad = "x" * 1000  # about 1.2 kB a document
    for i in range(12):  # robot a changes state 12 times: 5 kept, the newest
        assert fleet.receive(state_key("a"), state("a", version=f"{i}{pad}"))
    docs = store.documents("a")
    assert [d.doc["version"][:2] for d in docs] == ["7x", "8x", "9x", "10", "11"]
    for robot in ("b", "c", "d"):  # 20 documents of 1.2 kB > 20 kB: the oldest go first
        for i in range(5):
            assert fleet.receive(state_key(robot), state(robot, version=f"{i}{pad}"))
    assert store.bytes <= 20_000 and store.pruned > 7
    kept = {r.robot: r.documents for r in store.robots()}
    assert kept == {"a": 2, "b": 5, "c": 5, "d": 5}, kept  # a's, the oldest, went first
    assert [d.doc["version"][:2] for d in store.documents("a")] == ["10", "11"]
    one = len(json.dumps(store.documents("a")[0].doc))
    assert store.bytes + one > 20_000  # no more pruned than the bound needs
    assert store.latest("a") is not None and store.latest("a").doc["version"][:2] == "11"  # type: ignore[union-attr]
    # the robots' newest documents alone over the bound: the robot heard longest ago goes
    small = FleetStore(tmp_path / "small.sqlite", max_documents=5, max_bytes=3_000)
    for robot in ("p", "q", "r"):
        small.record(robot, time.time(), json.loads(state(robot, version=pad)))
    assert [r.robot for r in small.robots()] == ["q", "r"]


def test_what_was_stored_before_the_checks_never_breaks_the_robots_list(
    tmp_path: Path,
) -> None:
    """A store written by a service without today's checks: a document nested 900 deep,
    one with a wheel of 1e300 m.  The fleet opened on it sweeps them (a restart fixes
    it); and a robot whose view fails for any reason is listed with why, not a 500."""
    path = tmp_path / "fleet.sqlite"
    old = FleetStore(path)
    old.record("deep", 1.0, json.loads(state("deep", health=nested(900))))
    old.record("wide", 1.0, json.loads(state("wide", history={"calibrations": [
        calibration("r1", 0.216), calibration("r2", 1e300)]})))  # fmt: skip
    old.record("fine", 1.0, json.loads(state("fine")))
    old.close()
    fleet = FleetService(FleetStore(path), clock=VirtualClock())
    assert fleet.sweep() == 2
    assert [r.robot for r in fleet.store.robots()] == ["fine"]
    fleet.store.record("odd", 2.0, {**GOOD, "robot": "odd", "fleet_period_s": "soon"})
    with TestClient(create_fleet_app(fleet)) as client:
        r = client.get("/robots")
        assert r.status_code == 200, r.text
        rows = {x["robot"]: x for x in r.json()}
        assert rows["fine"]["status"] in ("live", "stale")
        assert rows["odd"]["status"] == "unknown" and "error" in rows["odd"]


# ------------------------------------------------------------------ through the router


def until(cond: Callable[[], Any], timeout: float = 15.0) -> Any:
    deadline = time.monotonic() + timeout
    while not (got := cond()):
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.01)
    return got


@pytest.fixture()
def router(tmp_path: Path) -> Iterator[tuple[FleetService, str, Path]]:
    """The fleet service as the router (the shipped config), with two robots' users."""
    users = tmp_path / "fleet-users.txt"
    users.write_text("robot1:robot1-secret-0123\nrobot2:robot2-secret-0123\n")
    ep = free_tcp_endpoint()
    s = FleetSettings(mode="router", listen=[ep], config_file=str(ROUTER_FILE),
                      users_file=users, data_dir=tmp_path / "fleet")  # fmt: skip
    fleet = FleetService(FleetStore(tmp_path / "fleet.sqlite"))
    session = open_fleet_session(s)
    fleet.subscribe(session)
    try:
        yield fleet, ep, users
    finally:
        fleet.close()
        session.close()
        fleet.store.close()


def test_each_robot_writes_under_its_own_name_only(
    router: tuple[FleetService, str, Path], tmp_path: Path
) -> None:
    fleet, ep, _ = router
    # robot1 as its service publishes: SWPC_FLEET_PASSWORD, its fleet name as the user
    rt = Runtime(ServiceSettings(data_dir=tmp_path / "r1", fleet_robot="robot1",
                                 fleet_period=0.25, fleet_connect=[ep],
                                 fleet_password="robot1-secret-0123"))  # fmt: skip
    pub = FleetPublisher.open(rt)
    rogues = {
        "anonymous": open_session(connect=[ep]),
        "wrong password": open_session(connect=[ep], auth=ZenohAuth("robot2", "guessed")),
        "robot2 as robot1": open_session(connect=[ep],
                                         auth=ZenohAuth("robot2", "robot2-secret-0123")),
    }  # fmt: skip
    try:
        # the positive control: robot1 is heard, live, its token seen
        until(lambda: fleet.robot("robot1", points=False) and fleet.alive.get("robot1"))
        received = fleet.received
        # then the rogues: a robot that does not exist, robot1's key from robot2, a token;
        # and robot2 writing its own key beside them, until it is heard (a peer's put is
        # dropped at its source until it knows the router's subscriber: the link proven)
        tokens = [s.liveliness().declare_token(alive_key("robot7")) for s in rogues.values()]

        def forge() -> None:
            for session in rogues.values():
                session.put(state_key("robot7"), state("robot7"))
                session.put(state_key("robot1"), state("robot1", history={"calibrations": [
                    calibration("forged", 9.99)]}))  # fmt: skip

        deadline = time.monotonic() + 15.0
        while not fleet.robot("robot2", points=False):
            assert time.monotonic() < deadline, "robot2 never heard"
            forge()
            rogues["robot2 as robot1"].put(state_key("robot2"), state("robot2"))
            time.sleep(0.05)
        for _ in range(5):  # the forgeries go on after the positive control, 0.25 s more
            forge()
            time.sleep(0.05)
        time.sleep(0.5)  # and robot1's next publications (every 0.25 s) too
        assert {r["robot"] for r in fleet.robots()} == {"robot1", "robot2"}
        assert "robot7" not in fleet.alive
        assert fleet.robot("robot1")["calibrations"] == 0  # type: ignore[index]
        assert fleet.rejected == 0 and fleet.received > received
        del tokens
    finally:
        for session in rogues.values():
            session.close()
        pub.close()
        rt.close()


def test_the_acl_names_each_robot_and_no_key_outside_the_fleet(tmp_path: Path) -> None:
    acl = fleet_acl(fleet_users(ROUTER_FILE.parent / "fleet-users.example.txt"))
    own = {r["id"]: r["key_exprs"] for r in acl["rules"] if r["id"].startswith("own-")}
    assert own == {"own-robot1": ["swpc/fleet/robot1/**"], "own-robot2": ["swpc/fleet/robot2/**"]}
    assert all(k.startswith(("swpc/fleet/", "@/")) for r in acl["rules"] for k in r["key_exprs"])
    assert acl["default_permission"] == "deny"
    bad = tmp_path / "users.txt"
    for text, words in (("robot1\n", ":1: not a user:password line"),
                        ("robot/1:pw\n", ":1: fleet robot name 'robot/1'"), ("\n", "no user")):
        bad.write_text(text)
        with pytest.raises(FleetNameError, match=re.escape(words)):
            fleet_users(bad)
