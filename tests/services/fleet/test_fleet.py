"""The fleet view (docs/fleet.md): five robots' services publish their state through a
zenoh router on loopback; ``swpc fleet``'s core keeps it, shows each robot live or stale
and the drift of its parameters, and loses nothing when it restarts.

The robots are real services' runtimes (:class:`Runtime`, each on its own data dir with a
run store holding real result documents of three calibrations, and a kinematic file in
force) with the real publisher; the router, the robots' sessions and the fleet's are real
zenoh sessions on ``tcp/127.0.0.1:<free port>``, multicast scouting off.  Staleness is
judged on an injected clock; the only waits are for zenoh's deliveries, with a deadline.
"""

from __future__ import annotations

import contextlib
import json
import math
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from pydantic import ValidationError

from services.config.fleet import FleetNameError, state_key
from services.config.robot import RobotConfig
from services.config.settings import ServiceSettings
from services.fleet.service import DocumentError, FleetService, check_document
from services.fleet.view import drift, status
from services.http.app import create_app
from services.http.fleet.app import create_fleet_app
from services.runs.install import result_document
from services.runs.state import RunStatus, State
from services.runtime.fleet import FleetPublisher, fleet_document
from services.runtime.runtime import Runtime
from services.store.fleet import FleetStore
from services.store.runs import RunStore
from swpc_hw.calibration.result import CalibrationResult
from swpc_hw.clock import VirtualClock
from swpc_hw.files.kinematic_file import save_kinematics
from swpc_hw.robot.model import ModuleStddev, RobotParams
from swpc_hw.robot.paper_robot import PAPER_NOMINAL
from swpc_hw.sensors.zenoh_session import free_tcp_endpoint, open_session

ROBOTS = [f"robot{i}" for i in range(1, 6)]
ROUTER_FILE = Path(__file__).resolve().parents[3] / "deploy" / "zenoh" / "fleet-router.json5"
DAYS = ["2026-01-01T10:00:00.000Z", "2026-01-15T10:00:00.000Z", "2026-01-29T10:00:00.000Z"]
WEAR = 0.05e-3
"""Wheel radius lost per week by robot<k>'s module 1, times k (m)."""
STD = ModuleStddev(x_s=0.2e-3, y_s=0.2e-3, beta=0.001, b=0.1e-3, r=0.02e-3)


def until(what: str, cond: Callable[[], Any], timeout: float = 15.0) -> Any:
    """Wait for a zenoh delivery (``cond`` true), with a deadline."""
    deadline = time.monotonic() + timeout
    while not (got := cond()):
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.01)
    return got


def calibrated(k: int, week: int) -> RobotParams:
    """robot<k>'s parameters ``week`` weeks on: module 1's wheel worn by k x WEAR a week;
    robot3's module 2 steering axis re-homed (+2 deg) before its last calibration."""
    mods = []
    for m in PAPER_NOMINAL.modules:
        upd: dict[str, Any] = {"stddev": STD}
        if m.id == 1:
            upd["r"] = m.r - k * WEAR * week
        if k == 3 and m.id == 2 and week == 4:
            upd["beta"] = m.beta + math.radians(2.0)
        mods.append(m.model_copy(update=upd))
    return PAPER_NOMINAL.model_copy(update={"modules": mods})


def result(params: RobotParams) -> CalibrationResult:
    return CalibrationResult(
        params=params, nominal=PAPER_NOMINAL, segments=[], time_offset=0.0,
        time_offset_std=None, time_offset_mode="given", poses_used=0, poses_rejected=0,
        increments_used=0, increments_rejected=0, reduced_chi2=None,
    )  # fmt: skip


def add_calibration(store: RunStore, kin: Path, k: int, i: int, when: str) -> None:
    """robot<k>'s calibration ``i`` (week 2 i), DONE at ``when`` and installed."""
    rid = f"r{k}-cal{i}"
    params = calibrated(k, 2 * i)
    st = RunStatus(id=rid, created=when, state=State.DONE, finished=when, installed=True)
    store.upsert(rid, when, st.to_dict())
    store.set_result(rid, result_document(
        rid, result(params), RobotConfig(), run_dir=kin.parent / "runs" / rid,
        kinematics_path=kin, within=True, installed=True,
    ))  # fmt: skip
    save_kinematics(kin, params, created=when, extra={"provenance": {"run": rid}})


def robot_data(data: Path, k: int) -> None:
    """A robot's data dir: three DONE calibrations (weeks 0, 2, 4) in its run store, the
    last one's file in force."""
    store = RunStore(data / "runs.sqlite")
    for i, when in enumerate(DAYS):
        add_calibration(store, data / "kinematics.yaml", k, i, when)
    store.close()


def settings(data: Path, name: str, period: float = 1.0, **more: Any) -> ServiceSettings:
    return ServiceSettings(data_dir=data, fleet_robot=name, fleet_period=period, **more)


# ------------------------------------------------------------------ pure cores, no zenoh


def test_status_is_stale_when_the_token_goes_or_after_k_heartbeats() -> None:
    assert status(100.0, True, 5.0, 114.9, 3) == ("live", None)
    assert status(100.0, None, 5.0, 115.0, 3) == ("live", None)
    st, why = status(100.0, True, 5.0, 115.1, 3)
    assert st == "stale" and why is not None and "no message for 15 s" in why
    st, why = status(100.0, False, 5.0, 100.0, 3)
    assert st == "stale" and why is not None and "liveliness token" in why


def test_drift_merges_calibrations_by_run_and_gives_the_rate_per_week(tmp_path: Path) -> None:
    robot_data(tmp_path, 2)
    rt = Runtime(settings(tmp_path, "robot2"))
    try:
        doc = fleet_document(rt)
    finally:
        rt.close()
    cals = doc["history"]["calibrations"]
    assert [c["run"] for c in cals] == ["r2-cal0", "r2-cal1", "r2-cal2"]
    assert doc["file_in_force"]["run"] == "r2-cal2"
    assert doc["file_in_force"]["created"] == DAYS[2]
    assert doc["last_check"] is None
    r1 = next(d for d in drift(cals) if d["module"] == 1 and d["param"] == "r")
    assert r1["change"] == pytest.approx(-2 * WEAR * 4, abs=1e-12)
    assert r1["per_week"] == pytest.approx(-2 * WEAR, rel=1e-9)
    assert [p["stddev"] for p in r1["points"]] == [STD.r] * 3
    b1 = next(d for d in drift(cals) if d["module"] == 1 and d["param"] == "b")
    assert b1["change"] == 0.0


def test_a_change_is_due_at_once_and_the_heartbeat_after_its_period(tmp_path: Path) -> None:
    robot_data(tmp_path, 1)
    rt = Runtime(settings(tmp_path, "robot1"))
    ep = free_tcp_endpoint()
    session = open_session(listen=[ep])
    clock = VirtualClock()
    pub = FleetPublisher(rt, session, clock=clock)
    try:
        assert pub.due()  # never published
        pub.publish()
        assert not pub.due()
        clock.advance(0.99)
        assert not pub.due()
        clock.advance(0.02)  # a heartbeat period (1 s) gone
        assert pub.due()
        pub.publish()
        kin = rt.settings.kinematics_file
        save_kinematics(kin, calibrated(1, 6), created="2026-02-12T10:00:00Z")
        assert pub.due()  # the file in force changed
        doc = pub.publish()
        assert doc["file_in_force"] == {**doc["file_in_force"], "run": None,
                                        "created": "2026-02-12T10:00:00Z"}  # fmt: skip
        rt.events.publish({"type": "run"})  # a run's state changed
        assert pub.due()
    finally:
        pub.close()
        rt.close()


def test_a_malformed_document_is_skipped_and_counted(tmp_path: Path) -> None:
    fleet = FleetService(FleetStore(tmp_path / "fleet.sqlite"), clock=VirtualClock())
    good = {"format": "swpc-fleet-state/1", "robot": "a", "heartbeat_s": 5,
            "history": {"calibrations": []}, "file_in_force": None, "last_check": None}  # fmt: skip
    bad = [
        (b"not json", "not JSON"),
        (json.dumps({**good, "robot": "b"}).encode(), "published on 'a'"),
        (json.dumps({**good, "format": "other/9"}).encode(), "format 'other/9'"),
        (json.dumps({**good, "heartbeat_s": 0}).encode(), "heartbeat_s 0"),
        (json.dumps({**good, "history": {"calibrations": [{"run": "x", "modules": [
            {"id": 1, "x_s": "big"}]}]}}).encode(), "x_s: 'big' is not a finite number"),
    ]  # fmt: skip
    for payload, words in bad:
        assert not fleet.receive("swpc/fleet/a/state", payload)
        assert fleet.last_rejection is not None and words in fleet.last_rejection
    assert not fleet.receive("swpc/fleet/a/b/state", json.dumps(good).encode())
    assert fleet.store.robots() == []
    assert fleet.receive("swpc/fleet/a/state", json.dumps(good).encode())
    # the heartbeat repeats the state: only last_seen moves
    assert fleet.receive("swpc/fleet/a/state", json.dumps({**good, "time": "later"}).encode())
    assert [r.documents for r in fleet.store.robots()] == [1]
    assert fleet.counts()["rejected"] == 6
    with pytest.raises(FleetNameError, match="one zenoh key chunk"):
        state_key("robot/1")
    with pytest.raises(ValueError, match="not JSON"):
        check_document("a", b"\xff")


# ------------------------------------------------------------------ five robots, a router


LAB_PERIOD = 0.25
"""The lab's robots' fleet period (s): the test waits for a heartbeat twice (the fleet
joins after the robots' first publication; after its clock's jump), each a period at
most."""


@pytest.fixture(scope="module")
def lab(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    """The shipped fleet router on loopback, five robots' runtimes publishing through it."""
    ep = free_tcp_endpoint()
    router = open_session(mode="router", listen=[ep], config_file=str(ROUTER_FILE))
    robots: dict[str, tuple[Runtime, FleetPublisher]] = {}
    runtimes: dict[str, Runtime] = {}
    try:
        for k, name in enumerate(ROBOTS, start=1):
            data = tmp_path_factory.mktemp(name)
            robot_data(data, k)
            runtimes[name] = Runtime(settings(data, name, LAB_PERIOD, fleet_connect=[ep]))
        # the publishers' sessions opened together: each open waits zenoh's scouting delay
        # (0.5 s, a peer's)
        with ThreadPoolExecutor(len(runtimes)) as pool:
            opened = {n: pool.submit(FleetPublisher.open, rt) for n, rt in runtimes.items()}
        for name, rt in runtimes.items():
            if opened[name].exception() is None:
                robots[name] = (rt, opened[name].result())
        for f in opened.values():
            f.result()  # raises the first failure
        yield {"endpoint": ep, "robots": robots, "store": tmp_path_factory.mktemp("fleet")}
    finally:
        for _, pub in robots.values():
            pub.close()
        for rt in runtimes.values():
            rt.close()
        router.close()


def open_fleet(lab: dict[str, Any], clock: VirtualClock) -> tuple[FleetService, Any]:
    session = open_session(mode="client", connect=[lab["endpoint"]])
    fleet = FleetService(FleetStore(lab["store"] / "fleet.sqlite"), clock=clock)
    fleet.subscribe(session)
    return fleet, session


def close_fleet(fleet: FleetService, session: Any) -> None:
    fleet.close()
    session.close()
    fleet.store.close()


def test_five_robots_through_a_router_one_killed_and_the_fleet_restarted(
    lab: dict[str, Any],
) -> None:
    clock = VirtualClock(epoch=time.time())
    fleet, session = open_fleet(lab, clock)
    try:
        views = until("five robots live", lambda: (
            v if len(v := fleet.robots()) == 5 and all(r["status"] == "live" for r in v)
            and all(fleet.alive.get(n) for n in ROBOTS) else None
        ))  # fmt: skip
        assert [r["robot"] for r in views] == ROBOTS
        for k, r in enumerate(views, start=1):
            assert r["file_in_force"] == {"created": DAYS[2], "run": f"r{k}-cal2", "error": None}
            assert r["calibrations"] == 3
            assert r["last_check"] is None
            # the service's runtime is not connected to a robot here: its health says so
            assert r["health"]["status"] == "failing"
            r1 = next(d for d in r["drift"] if d["module"] == 1 and d["param"] == "r")
            assert r1["per_week"] == pytest.approx(-k * WEAR, rel=1e-9)
        beta = next(d for d in views[2]["drift"] if d["module"] == 2 and d["param"] == "beta")
        assert math.degrees(beta["change"]) == pytest.approx(2.0)

        # the router routes the fleet's keys only
        other: list[Any] = []
        sub = session.declare_subscriber("mocap/**", lambda smp: other.append(smp))
        _, pub2 = lab["robots"]["robot2"]
        pub2.session.put("mocap/robot2/pose", b"x")
        pub2.session.put(state_key("robot2"), b"{not json")  # routed, then refused
        until("the refusal", lambda: fleet.rejected == 1)
        assert other == []
        sub.undeclare()

        # the HTTP side shows the same
        with TestClient(create_fleet_app(fleet)) as client:
            got = client.get("/robots").json()
            assert [r["robot"] for r in got] == ROBOTS
            one = client.get("/robots/robot3").json()
            assert len(one["drift"][0]["points"]) == 3
            assert one["state"]["robot"] == "robot3"
            assert client.get("/robots/robot9").status_code == 404
            page = client.get("/")
            assert page.status_code == 200 and "/fleet/console.css" in page.text
            assert "--ink" in client.get("/fleet/console.css").text  # the console's own CSS

        # robot2 is calibrated again: published on the change, a new document kept
        rt2, _ = lab["robots"]["robot2"]
        add_calibration(rt2.store, rt2.settings.kinematics_file, 2, 3, "2026-02-12T10:00:00.000Z")
        rt2.events.publish({"type": "run"})  # as a run's end does
        until("robot2's 4th calibration", lambda: fleet.robot("robot2")["calibrations"] == 4)
        r2 = fleet.robot("robot2")["drift"]
        r1 = next(d for d in r2 if d["module"] == 1 and d["param"] == "r")
        assert [p["run"] for p in r1["points"]] == [f"r2-cal{i}" for i in range(4)]
        assert r1["per_week"] == pytest.approx(-2 * WEAR, rel=1e-6)

        # robot1's service stops: its token goes, it is stale at once (no time passes)
        _, pub = lab["robots"]["robot1"]
        t0 = time.monotonic()
        pub.close()
        until("robot1 stale", lambda: fleet.robot("robot1", points=False)["status"] == "stale")
        print(f"\nfleet: robot1 stale {1000 * (time.monotonic() - t0):.1f} ms after its close")
        view = {r["robot"]: r for r in fleet.robots()}
        assert "liveliness token" in view["robot1"]["stale_reason"]
        assert [n for n, r in view.items() if r["status"] == "live"] == ROBOTS[1:]

        # the heartbeats keep the other four live; three missed ones make them stale
        # the fleet's clock jumps 3.5 robots' periods ahead; a heartbeat that lands between
        # the jump and the view (its age 0) makes its robot live again: the clock jumps
        # again then, until a view has none.  robot1's too: its last heartbeat, sent before
        # its close, can land after the jump on a loaded host (the restarted fleet, which
        # never saw its token go, then judged it live by that heartbeat, once)
        for _ in range(20):
            clock.advance(3.5 * LAB_PERIOD)
            view = {r["robot"]: r for r in fleet.robots()}
            if all(view[n]["age_s"] >= 3.5 * LAB_PERIOD for n in ROBOTS):
                break
        assert all(view[n]["age_s"] >= 3.5 * LAB_PERIOD for n in ROBOTS), view
        assert all(view[n]["status"] == "stale" for n in ROBOTS[1:])
        until("a heartbeat after the jump", lambda: all(
            r["status"] == "live" for r in fleet.robots() if r["robot"] != "robot1"))  # fmt: skip
        before = {r.robot: r.documents for r in fleet.store.robots()}
        seen = {r.robot: r.last_seen for r in fleet.store.robots()}
    finally:
        close_fleet(fleet, session)

    # the fleet service restarts on its store: every robot and document is still there
    fleet, session = open_fleet(lab, clock)
    try:
        assert {r.robot: r.documents for r in fleet.store.robots()} == before
        # a document per state (robot2 changed once); a loaded host can add one where the
        # health summary changed between two heartbeats
        assert before["robot2"] >= 2 and all(before[n] >= 1 for n in ROBOTS), before
        assert {r.robot: r.last_seen for r in fleet.store.robots()}["robot1"] == seen["robot1"]
        until("the four tokens again", lambda: all(fleet.alive.get(n) for n in ROBOTS[1:]))
        view = {r["robot"]: r for r in fleet.robots()}
        assert view["robot1"]["calibrations"] == 3  # from the store: robot1 is gone
        assert view["robot1"]["status"] == "stale"  # no token, no message since
        assert view["robot1"]["file_in_force"]["run"] == "r1-cal2"
        print(f"fleet: documents per robot before/after the restart {before} / "
              f"{ {r.robot: r.documents for r in fleet.store.robots()} }")
    finally:
        close_fleet(fleet, session)


def test_the_service_publishes_when_told_to_and_never_otherwise(tmp_path: Path) -> None:
    """``SWPC_FLEET_PUBLISH``: the app's lifespan opens the publisher beside its runtime."""
    ep = free_tcp_endpoint()
    router = open_session(mode="router", listen=[ep])
    fleet, session = None, None
    try:
        fleet = FleetService(FleetStore(tmp_path / "fleet.sqlite"), clock=VirtualClock())
        session = open_session(mode="client", connect=[ep])
        fleet.subscribe(session)
        for publish in (False, True):
            data = tmp_path / f"svc-{publish}"
            robot_data(data, 4)
            cfg = settings(data, f"svc-{publish}".lower(), fleet_connect=[ep],
                           fleet_publish=publish)  # fmt: skip
            with TestClient(create_app(cfg, runtime_factory=Runtime)) as client:
                assert (client.app.state.fleet is not None) == publish  # type: ignore[attr-defined]
                if publish:
                    until("the service's state", lambda: fleet.store.robots())
        names = [r.robot for r in fleet.store.robots()]
        assert names == ["svc-true"]
        until("its token gone", lambda: fleet.alive.get("svc-true") is False)
    finally:
        if fleet is not None:
            fleet.close()
            fleet.store.close()
        with contextlib.suppress(Exception):
            if session is not None:
                session.close()
        router.close()


def test_drift_compares_positions_and_beta_within_one_frame() -> None:
    """A calibration without motion capture (design-fit) between two with it (R): its
    positions and beta differ by the frames' turn, which the fleet's largest drift showed
    as the robot's.  They are compared within the newest calibration's frame; b and r in
    all of them."""

    def cal(run: str, day: int, metrology: str, beta: float, r: float) -> dict[str, Any]:
        mods = [{"id": i, "x_s": 0.2, "y_s": 0.1, "beta": beta, "b": 0.02, "r": r,
                 "stddev": None} for i in (1, 2)]  # fmt: skip
        return {"run": run, "time": f"2026-11-{day:02d}T00:00:00Z", "metrology": metrology,
                "installed": True, "modules": mods}  # fmt: skip

    turn = math.radians(3.0)
    cals = [cal("a", 1, "mocap", 0.0, 0.05), cal("g", 8, "imu", turn, 0.0499),
            cal("b", 15, "mocap", 1e-4, 0.0498)]  # fmt: skip
    by = {(d["module"], d["param"]): d for d in drift(cals)}
    beta, r = by[(1, "beta")], by[(1, "r")]
    assert [p["run"] for p in beta["points"]] == ["a", "b"] and beta["frame"] == "R"
    assert beta["change"] == pytest.approx(1e-4)  # not the 3 deg turn of run g
    assert [p["run"] for p in r["points"]] == ["a", "g", "b"] and r["frame"] == "any"
    # the newest without motion capture: its frame's calibrations only (one: no change)
    gyro_last = drift([*cals, cal("h", 22, "imu", turn + 2e-4, 0.0497)])
    beta = next(d for d in gyro_last if d["module"] == 1 and d["param"] == "beta")
    assert [p["run"] for p in beta["points"]] == ["g", "h"] and beta["frame"] == "design-fit"
    assert beta["change"] == pytest.approx(2e-4)
    # two calibrations an hour apart: a change, but no rate per week (less than a day)
    close = drift([cal("a", 1, "mocap", 0.0, 0.05), {**cal("b", 1, "mocap", 1e-4, 0.05),
                   "time": "2026-11-01T01:00:00Z"}])  # fmt: skip
    b1 = next(d for d in close if d["module"] == 1 and d["param"] == "beta")
    assert b1["change"] == pytest.approx(1e-4) and b1["per_week"] is None


def test_each_robot_links_to_its_own_console(tmp_path: Path) -> None:
    """Issue 45 item 8: the fleet page had no way from a robot to its console.  The robot
    publishes where the lab reaches it (``SWPC_FLEET_CONSOLE_URL``), the fleet keeps it in
    the robot's view; anything but an http(s) address is refused, naming the field."""
    url = "http://robot2.lab:8080/"
    rt = Runtime(settings(tmp_path, "robot2", fleet_console_url=url))
    try:
        doc = fleet_document(rt)
    finally:
        rt.close()
    assert doc["console_url"] == url
    assert check_document("robot2", json.dumps(doc).encode())["console_url"] == url
    for bad in ("javascript:alert(1)", "http://a b/", "ftp://robot2/", "http://" + "x" * 500):
        with pytest.raises(DocumentError, match="console_url"):
            check_document("robot2", json.dumps({**doc, "console_url": bad}).encode())
    with pytest.raises(ValidationError):
        settings(tmp_path, "robot2", fleet_console_url="javascript:alert(1)")
