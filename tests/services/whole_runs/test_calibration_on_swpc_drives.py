"""The calibration service through HTTP, against the in-process simulator (lockstep).

The real app, the real CAN driver on python-can's virtual bus, the real simulator, zenoh
on loopback, all on one simulated clock: a busy host slows these tests down and cannot
change their outcome.  A second bus on the same virtual channel records every frame with
its time on that clock, so the fault tests can check that zero-torque (FREE) and DISABLE
frames reached every axis.  Waits on wall time here are only guards against a hang.

The state machine's every transition, fault, abort and timeout is tested on a fake robot
and a virtual clock in ``tests/services/runs/test_state_machine.py``; here the paths that need the
real
driver, simulator and HTTP.  (That the driver reports a fault stop before its event
callbacks run is checked from inside a callback in
``tests/drives/swpc/test_driver_faults.py``; here a
callback held for long would hold the simulated clock itself.)
"""

from __future__ import annotations

import math
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest
from fastapi.testclient import TestClient

from firmware_protocol import codec
from firmware_protocol.codec import ControlMode
from services.runtime.runtime import Runtime
from swpc_hw.calibration.mocap.solver import solve_directory
from swpc_hw.clock import Clock
from swpc_hw.files.dataset import load_dataset
from swpc_hw.files.kinematic_file import load_kinematics, save_kinematics
from swpc_hw.robot.model import PARAM_NAMES
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED, PAPER_NOMINAL
from tests.service_rig import (
    AUTH,
    MID_SPIN,
    QUICK_PROTOCOL,
    SHORT,
    bus_off,
    fault_mid_spin,
    home_and_release,
    sim_service,
    start,
    wait_spinning,
    wait_state,
)

NAMES = PARAM_NAMES


class Recorder(can.Listener):  # type: ignore[misc]
    """Every frame on the bus as ``(clock time, id, data)`` (its bus stamp on the service
    clock): tuples of atomic values, which the garbage collector stops tracking."""

    def __init__(self, clock: Clock) -> None:
        self.clock = clock
        self.frames: list[tuple[float, int, bytes]] = []
        self.lock = threading.Lock()

    def on_message_received(self, msg: can.Message) -> None:
        if msg.is_error_frame:
            return
        t = self.clock.from_wall(msg.timestamp)
        with self.lock:
            self.frames.append((t, msg.arbitration_id, bytes(msg.data)))

    def timed_since(self, t: float) -> list[tuple[float, int, object]]:
        """``(clock time, node, decoded frame)`` of the frames of our protocol sent at or
        after t."""
        with self.lock:
            frames = [f for f in self.frames if f[0] >= t]
        out = []
        for ts, i, data in frames:
            try:
                out.append((ts, codec.split_id(i)[0], codec.parse(i, data)))
            except codec.ProtocolError:
                continue
        return out

    def decoded_since(self, t: float) -> list[tuple[int, object]]:
        """``(node, decoded frame)`` of the frames of our protocol recorded at or after t."""
        return [(node, d) for _, node, d in self.timed_since(t)]

    def stop_frames_after(self, t: float) -> tuple[set[tuple[int, int]], set[tuple[int, int]]]:
        """(node, axis) pairs that got SetControl FREE, and SetAxisState disabled, after t."""
        free, disabled = set(), set()
        for node, d in self.decoded_since(t):
            if isinstance(d, codec.SetControl) and d.mode == ControlMode.FREE:
                free.add((node, int(d.axis)))
            elif isinstance(d, codec.SetAxisState) and not d.enabled:
                disabled.add((node, int(d.axis)))
        return free, disabled


@pytest.fixture(scope="module")
def service(
    tmp_path_factory: pytest.TempPathFactory,
) -> Iterator[tuple[TestClient, Runtime, Recorder]]:
    with sim_service(tmp_path_factory.mktemp("svc")) as sim:
        rt = sim.rt
        rec = Recorder(rt.clock)
        bus = can.Bus(interface="virtual", channel=rt.can_channel)
        notifier = can.Notifier(bus, [rec], timeout=0.05)  # its stop() joins a wait this long
        try:
            yield sim.client, rt, rec
        finally:
            notifier.stop()
            bus.shutdown()


def data_summary(rt: Runtime, run_id: str) -> str:
    """A failed run's recorded segments, for the assertion message: the data behind a
    solver failure is lost with the test's temporary directory (and with a CI clone)."""
    directory = Path(rt.settings.data_dir) / "runs" / run_id / "dataset"
    try:
        ds = load_dataset(directory)
    except Exception as exc:  # a summary: never the test's own failure
        return f"(no dataset: {exc})"
    rows = []
    for sg in ds.segments:
        sel = (ds.poses[:, 0] >= sg.start) & (ds.poses[:, 0] <= sg.end)
        yaw = np.unwrap(ds.poses[sel, 3])
        rot = math.degrees(float(yaw.max() - yaw.min())) if yaw.size else 0.0
        gaps = float(np.diff(ds.poses[sel, 0]).max()) if yaw.size > 1 else float("nan")
        rows.append(
            f"module {sg.static_module} {sg.end - sg.start:.2f} s {int(sel.sum())} poses "
            f"{rot:.1f} deg, longest pose gap {gaps:.3f} s"
        )
    return "; ".join(rows)


# ---------------------------------------------------------------------- happy path


def test_full_calibration_through_http(service: tuple[TestClient, Runtime, Recorder]) -> None:
    """Every module, two angles each, short spins (the whole default protocol is what
    ``make demo`` runs): DONE, accurate, installed, reproducible offline, recorded."""
    client, rt, _ = service
    assert client.get("/health").json()["in_process_simulator"] is True
    # between runs the simulated time stands still: nothing is late, ok (200); and once
    # it flows (robot time passes while this thread waits on it), every node is up
    h = client.get("/health")
    assert h.status_code == 200 and h.json()["status"] == "ok", h.json()
    rt.clock.sleep(1.0)
    h = client.get("/health")
    assert all(n["alive"] for n in h.json()["nodes"].values()), h.json()
    assert h.status_code == 200 and h.json()["problems"] == [], h.json()
    assert client.get("/kinematics").status_code == 404
    t0 = time.monotonic()
    run_id = start(client, {"protocol": QUICK_PROTOCOL})
    assert client.get(f"/calibrations/{run_id}/result").status_code == 409
    st = wait_state(client, run_id, {"DONE", "FAILED", "ABORTED"})
    wall = time.monotonic() - t0
    assert st["state"] == "DONE", st["errors"]
    assert st["progress"] == 1.0 and st["segments"] == 8 and st["installed"] is True
    res = client.get(f"/calibrations/{run_id}/result").json()
    truth = {m.id: m for m in PAPER_CALIBRATED.modules}
    for m in res["modules"]:
        t = truth[m["id"]]
        for k in NAMES:
            err, sd = m[k] - getattr(t, k), m["stddev"][k]
            # near the truth (the nominal is 0.3-2 mm and 0.6-1.5 deg off), and within
            # what the solver says of itself
            assert abs(err) < (0.3e-3 if k != "beta" else math.radians(0.05)), (m["id"], k, err)
            assert abs(err) < 4 * sd, (m["id"], k, err, sd)
        assert m["nominal"]["x_s"] == PAPER_NOMINAL.module(m["id"]).x_s
    assert len(res["table"]) == 20
    # against the simulator's truth: the largest errors as computed here, the whole
    # covariance's NEES and the square path beside its forecast and the budget
    got = client.get("/simulator/reached", params={"run": run_id}).json()
    kinds = {k["kind"]: k for k in got["kinds"]}
    err = {n: [abs(m[n] - getattr(truth[m["id"]], n)) for m in res["modules"]] for n in NAMES}
    assert kinds["radius"]["largest"] == pytest.approx(max(err["r"]) * 1e3, abs=1e-9)
    assert kinds["beta"]["largest"] == pytest.approx(math.degrees(max(err["beta"])), abs=1e-9)
    assert got["frame"] == "R" and got["dof"] == 20 and 0.1 < got["nees"] < 4.0, got
    assert 0 < got["square_position_mm"] < 3 * got["forecast_position_mm"], got
    assert got["budget_position_mm"] == 0.5
    # the 90 % bound by the same covariance: 1.5-2.2 std devs; within the budget or not
    assert 1.5 < got["bound_position_mm"] / got["forecast_position_mm"] < 2.2, got
    assert got["share_percent"] == 90
    assert got["within_budget"] == (
        got["square_position_mm"] <= 0.5 and got["square_heading_deg"] <= 0.016
    )
    print(f"\nagainst the truth: NEES {got['nees']:.2f}; square path "
          f"{got['square_position_mm']:.3f} mm, forecast {got['forecast_position_mm']:.3f} mm")
    # the kinematic file in force is the result, and loads
    k = load_kinematics(rt.settings.kinematics_file)
    got = np.array([[getattr(m, n) for n in NAMES] for m in k.params.modules])
    api = np.array([[m[n] for n in NAMES] for m in res["modules"]])
    np.testing.assert_allclose(got, api, rtol=0, atol=1e-12)
    assert client.get("/kinematics").json()["modules"][0]["id"] == 1
    # offline `swpc solve` of the recorded dataset gives the same result
    offline = solve_directory(res["dataset_dir"])
    off = np.array([[getattr(m, n) for n in NAMES] for m in offline.params.modules])
    np.testing.assert_allclose(off, api, rtol=0, atol=1e-15)
    # the run's raw CAN traffic, decoded by cantools with our DBC
    log = Path(res["dataset_dir"]) / "can.log"
    out = subprocess.run(
        [sys.executable, "-m", "cantools", "decode", "firmware_protocol/swpc.dbc"],
        stdin=log.open("rb"),
        capture_output=True,
        check=True,
        timeout=120,
    ).stdout.decode()
    assert "N1_FeedbackPosition(" in out and "N4_SetControl(" in out
    # the same data as MCAP (Foxglove)
    from mcap.reader import make_reader

    with (Path(res["dataset_dir"]).parent / "run.mcap").open("rb") as fh:
        reader = make_reader(fh)
        topics = {ch.topic for ch in reader.get_summary().channels.values()}  # type: ignore[union-attr]
        count = sum(1 for _ in reader.iter_messages(topics=["/calibration/segments"]))
    assert {"/mocap/pose", "/module1/encoders", "/calibration/segments"} <= topics
    assert count == 8
    # plot, listing, metrics
    png = client.get(f"/calibrations/{run_id}/plot.png")
    assert png.status_code == 200 and png.content[:4] == b"\x89PNG"
    assert any(r["id"] == run_id for r in client.get("/calibrations").json())
    metrics = client.get("/metrics").text
    assert 'swpc_runs{state="DONE"} 1.0' in metrics
    assert "swpc_pose_rate_hz" in metrics and 'swpc_can_frames_total{direction="rx"}' in metrics
    print(f"\nend-to-end calibration through HTTP: {wall:.1f} s wall, "
          f"{rt.clock.now():.1f} s of robot time so far")


# ---------------------------------------------------------------------- faults


@pytest.fixture()
def installed(service: tuple[TestClient, Runtime, Recorder]) -> Iterator[bytes]:
    """A kinematic file in force whose bytes must survive every failed run."""
    _, rt, _ = service
    path = rt.settings.kinematics_file
    path.parent.mkdir(parents=True, exist_ok=True)
    save_kinematics(path, PAPER_NOMINAL, created="2026-01-01T00:00:00Z")
    before = path.read_bytes()
    yield before
    assert path.read_bytes() == before, "a failed run touched the kinematic file"


def assert_stopped(rec: Recorder, since: float, rt: Runtime) -> None:
    nodes = set(rt.config.drives.node_map().values())
    want = {(n, a) for n in nodes for a in (0, 1)}
    deadline = time.monotonic() + 2.0
    while time.monotonic() < deadline:
        free, disabled = rec.stop_frames_after(since)
        if want <= free and want <= disabled:
            return
        time.sleep(0.01)
    raise AssertionError(
        f"zero-torque frames missing: free {sorted(free)}, disabled {sorted(disabled)}"
    )


def test_abort_mid_spin(service: tuple[TestClient, Runtime, Recorder], installed: bytes) -> None:
    client, rt, rec = service
    run_id = start(client, MID_SPIN)
    wait_spinning(client, run_id)
    t = rt.clock.now()
    assert client.post("/calibrations", json={}).status_code == 401  # a start needs the token
    r = client.post(f"/calibrations/{run_id}/abort")  # a stop never does (docs/operating.md)
    assert r.status_code == 200
    st = wait_state(client, run_id, {"ABORTED", "FAILED", "DONE"})
    assert st["state"] == "ABORTED" and st["reason"].startswith("aborted by the operator")
    assert_stopped(rec, t, rt)
    assert client.post(f"/calibrations/{run_id}/abort", headers=AUTH).status_code == 409
    assert client.get(f"/calibrations/{run_id}/result").status_code == 409


def test_motion_rates_are_least_squares_slopes() -> None:
    from services.runs.metrology.pose_motion import motion_rates

    rng = np.random.default_rng(3)
    t = np.sort(rng.uniform(10.0, 10.5, 60))
    x = 1.0 + 0.03 * (t - 10) + rng.normal(0, 1e-4, t.size)
    y = -2.0 - 0.04 * (t - 10) + rng.normal(0, 1e-4, t.size)
    yaw = np.angle(np.exp(1j * (3.1 + 0.5 * (t - 10))))  # wraps through +-pi
    speed, rate = motion_rates(t, x, y, yaw)
    assert speed == pytest.approx(0.05, abs=2e-3) and rate == pytest.approx(0.5, abs=1e-9)
    still = np.full(t.size, 0.7)
    assert motion_rates(t, still, still, still) == pytest.approx((0.0, 0.0), abs=1e-15)
    with pytest.raises(ValueError, match="two distinct times"):
        motion_rates(np.full(3, 1.0), still[:3], still[:3], still[:3])
    with pytest.raises(ValueError, match="two distinct times"):
        motion_rates(t[:0], t[:0], t[:0], t[:0])


def yaw_rate(rt: Runtime, t0: float, t1: float) -> float:
    """Yaw rate (rad/s) from the mocap poses sampled in [t0, t1] (clock time): the slope of
    a straight line through them."""
    p = rt.mocap.samples(since_host=t0)
    p = p[p[:, 2] <= t1]
    assert p.shape[0] >= 5, p.shape
    return float(np.polyfit(p[:, 2], np.unwrap(p[:, 5]), 1)[0])


def test_a_pushed_robot_is_braked_to_rest_before_a_module_is_locked(
    service: tuple[TestClient, Runtime, Recorder], installed: bytes
) -> None:
    """Someone pushes the robot (or it coasts from an aborted spin) as a run starts: every
    wheel is braked first and the lock only comes once mocap shows it still.  Without the
    REST step the wheels were braked with the lock, on a turning robot (mocap read 0.17-0.20
    rad/s over the 0.5 s before it); in make test, a robot coasting from the previous test's
    aborted spin once dragged the locked steering 24 deg ("the static module is not
    locked")."""
    client, rt, rec = service
    sim = rt.simulator
    assert sim is not None
    node = rt.config.drives.node_map()[1]
    window = 0.5  # s of robot time
    home_and_release(rt)  # (homing steers the modules, which would stop the robot too)
    sim.push(torque=2.0)  # turns the free robot at 0.24 rad/s
    try:
        rt.clock.sleep(4 * window)  # robot time passes while this thread waits on it
        t = rt.clock.now()
        run_id = start(client, MID_SPIN)
        wait_spinning(client, run_id, sweep=1.0)
    finally:
        sim.push()
    client.post(f"/calibrations/{run_id}/abort", headers=AUTH)
    assert wait_state(client, run_id, {"ABORTED", "FAILED", "DONE"})["state"] == "ABORTED"

    frames = rec.timed_since(t)

    def first(pred: Callable[[int, Any], bool]) -> float:
        found = next((ts for ts, n, d in frames if pred(n, d)), None)
        assert found is not None, "no such frame"
        return found

    t_lock = first(
        lambda n, d: n == node and isinstance(d, codec.SetControl)
        and d.axis == codec.Axis.STEER and d.mode == ControlMode.POSITION
    )
    wheels_braked = max(
        first(
            lambda n, d, m=m: n == m and isinstance(d, codec.SetControl)
            and d.axis == codec.Axis.WHEEL and d.mode == ControlMode.HOLD
        )
        for m in rt.config.drives.node_map().values()
    )
    assert wheels_braked < t_lock
    # pushed until braked: 0.24 rad/s
    assert yaw_rate(rt, wheels_braked - 2 * window, wheels_braked) > 0.2
    # still over the last 0.5 s (robot time) before the lock
    assert abs(yaw_rate(rt, t_lock - window, t_lock)) < rt.config.limits.rest_yaw_rate


def test_heartbeat_loss_mid_spin(
    service: tuple[TestClient, Runtime, Recorder], installed: bytes
) -> None:
    client, rt, rec = service
    sim = rt.simulator
    assert sim is not None
    st, t = fault_mid_spin(client, rt, lambda _: sim.mute(3), undo=lambda: sim.mute(3, False))
    assert st["state"] == "FAILED" and "no heartbeat" in st["reason"] and "module 3" in st["reason"]
    assert_stopped(rec, t, rt)


def test_bus_off_mid_spin(service: tuple[TestClient, Runtime, Recorder], installed: bytes) -> None:
    client, rt, rec = service
    st, t = fault_mid_spin(client, rt, bus_off(rt))
    assert st["state"] == "FAILED" and "bus-off" in st["reason"], st
    assert_stopped(rec, t, rt)


def test_second_start_conflicts_and_auth_and_bad_config(
    service: tuple[TestClient, Runtime, Recorder], installed: bytes
) -> None:
    client, _rt, _ = service
    assert client.post("/calibrations", json={}).status_code == 401
    bad = client.post("/calibrations", json={}, headers={"Authorization": "Bearer wrong"})
    assert bad.status_code == 401
    r = client.post(
        "/calibrations", json={"overrides": {"limits": {"spin_torque": "fast"}}}, headers=AUTH
    )
    assert r.status_code == 422 and "spin_torque" in r.text
    r = client.post(
        "/calibrations", json={"overrides": {"protocol": {"angles_deg": [45]}}}, headers=AUTH
    )
    assert r.status_code == 422
    run_id = start(client, SHORT)
    r = client.post("/calibrations", json={}, headers=AUTH)
    assert r.status_code == 409 and run_id in r.text
    client.post(f"/calibrations/{run_id}/abort", headers=AUTH)
    assert wait_state(client, run_id, {"ABORTED", "FAILED", "DONE"})["state"] == "ABORTED"
    assert client.get("/calibrations/nope").status_code == 404
