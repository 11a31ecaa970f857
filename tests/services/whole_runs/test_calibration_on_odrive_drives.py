"""The calibration service on ODrive drives: the fault tests of the swpc drives, on ODrive.

The real app, the real ODrive driver on python-can's virtual bus, the virtual robot with
virtual ODrives (firmware 0.5.x here: the line whose watchdog any frame feeds; the demo
runs 0.6.x), zenoh on loopback, all on one simulated clock.  A second bus records every
frame with its time on that clock: every fault must reach every axis with a stop
(``Set_Axis_State`` IDLE), and each test prints how long after the fault the first stop
frame went out (robot time): the fault table of docs/drives.md.

Stale motion capture and a step timeout are judged by the state machine on any drives
(``tests/services/runs/test_state_machine.py``); they stop the robot through the same
``stop_all()``.
"""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import can
import pytest
import yaml
from fastapi.testclient import TestClient
from pydantic import SecretStr

from firmware_protocol.codec import Axis, ErrorFlag
from firmware_protocol.odrive import can_simple as cs
from services.config.robot import RobotConfig
from services.config.settings import ServiceSettings
from services.http.app import create_app
from services.runtime.runtime import Runtime
from swpc_hw.clock import Clock
from swpc_hw.drives.odrive.config import ODriveDrives
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED
from tests.service_rig import (
    AUTH,
    MID_SPIN,
    QUICK_PROTOCOL,
    SHORT,
    TOKEN,
    abort,
    bus_off,
    fault_mid_spin,
    start,
    wait_spinning,
    wait_state,
)

LINE = "0.5"
NAMES = ("x_s", "y_s", "beta", "b", "r")


class Recorder(can.Listener):  # type: ignore[misc]
    def __init__(self, clock: Clock) -> None:
        self.clock = clock
        self.frames: list[tuple[float, int, bytes, bool]] = []
        self.lock = threading.Lock()

    def on_message_received(self, msg: can.Message) -> None:
        if msg.is_error_frame:
            return
        with self.lock:
            self.frames.append(
                (self.clock.from_wall(msg.timestamp), msg.arbitration_id, bytes(msg.data),
                 bool(msg.is_remote_frame))
            )  # fmt: skip

    def decoded_since(self, t: float) -> list[tuple[float, Any]]:
        c = cs.can_simple(LINE)
        with self.lock:
            frames = [f for f in self.frames if f[0] >= t]
        out = []
        for ts, i, data, remote in frames:
            try:
                out.append((ts, c.decode(i, data, remote)))
            except cs.ProtocolError:
                continue
        return out


@pytest.fixture(scope="module")
def service(
    tmp_path_factory: pytest.TempPathFactory,
) -> Iterator[tuple[TestClient, Runtime, Recorder]]:
    data = tmp_path_factory.mktemp("svc-odrive")
    doc = RobotConfig().to_document()
    doc["drives"] = {"kind": "odrive", "firmware": LINE, "homing": "index", "modules": {
        m: {"steer": {"node": 2 * i + 10, "gear_ratio": 8.0},
            "wheel": {"node": 2 * i + 11, "gear_ratio": 4.0}}
        for i, m in enumerate(PAPER_CALIBRATED.ids)}}  # fmt: skip
    path = data / "robot.yaml"
    path.write_text(yaml.safe_dump(doc))
    settings = ServiceSettings(data_dir=data, token=SecretStr(TOKEN), robot_config=path)
    app = create_app(settings)
    with TestClient(app) as client:
        rt: Runtime = app.state.runtime
        rec = Recorder(rt.clock)
        bus = can.Bus(interface="virtual", channel=rt.can_channel)
        notifier = can.Notifier(bus, [rec], timeout=0.05)  # its stop() joins a wait this long
        try:
            yield client, rt, rec
        finally:
            notifier.stop()
            bus.shutdown()


def axis_nodes(rt: Runtime) -> set[int]:
    assert isinstance(rt.config.drives, ODriveDrives)
    return set(rt.config.drives.nodes())


def first_stop(rec: Recorder, since: float, rt: Runtime) -> float:
    """Robot time from ``since`` to the first IDLE request; asserts every axis got one."""
    want = axis_nodes(rt)
    deadline = time.monotonic() + 5.0
    while time.monotonic() < deadline:
        idle = [(ts, d.node) for ts, d in rec.decoded_since(since)
                if isinstance(d, cs.SetAxisState) and d.state == cs.AxisState.IDLE]  # fmt: skip
        if want <= {n for _, n in idle}:
            return min(ts for ts, _ in idle) - since
        time.sleep(0.01)
    raise AssertionError(f"IDLE missing for nodes {sorted(want - {n for _, n in idle})}")


def test_a_whole_calibration_on_odrive_05(service: tuple[TestClient, Runtime, Recorder]) -> None:
    """Short spins, every module: DONE on ODrive drives, near the truth and within the
    solver's own std devs; the watchdog was proven and the encoders never polled."""
    client, _, rec = service
    run_id = start(client, {"protocol": QUICK_PROTOCOL})
    st = wait_state(client, run_id, {"DONE", "FAILED", "ABORTED"})
    assert st["state"] == "DONE", st
    res = client.get(f"/calibrations/{run_id}/result").json()
    truth = {m.id: m for m in PAPER_CALIBRATED.modules}
    for m in res["modules"]:
        for k in NAMES:
            err, sd = m[k] - getattr(truth[m["id"]], k), m["stddev"][k]
            assert abs(err) < (0.3e-3 if k != "beta" else math.radians(0.05)), (m["id"], k, err)
            assert abs(err) < 4 * sd, (m["id"], k, err, sd)
    frames = rec.decoded_since(0.0)
    assert not any(isinstance(d, cs.Poll) for _, d in frames)
    index = {d.node for _, d in frames if isinstance(d, cs.SetAxisState)
             and d.state == cs.AxisState.ENCODER_INDEX_SEARCH}  # fmt: skip
    assert index == {10, 12, 14, 16}  # the steering axes, once each


def test_abort_mid_spin_stops_every_axis(service: tuple[TestClient, Runtime, Recorder]) -> None:
    client, rt, rec = service
    st, t = fault_mid_spin(client, rt, abort(client))
    assert st["state"] == "ABORTED"
    dt = first_stop(rec, t, rt)
    print(f"\nfault table (odrive {LINE}): abort -> first IDLE after {dt * 1e3:.1f} ms")


def test_heartbeat_loss_mid_spin(service: tuple[TestClient, Runtime, Recorder]) -> None:
    client, rt, rec = service
    sim = rt.simulator
    assert sim is not None
    st, t = fault_mid_spin(client, rt, lambda _: sim.mute(3), undo=lambda: sim.mute(3, False))
    assert st["state"] == "FAILED" and "no heartbeat" in st["reason"], st
    assert "module 3" in st["reason"]
    dt = first_stop(rec, t, rt)
    loss = rt.timing.heartbeat_loss
    assert dt <= loss + rt.timing.heartbeat_period + 0.05, dt
    print(f"\nfault table (odrive {LINE}): heartbeat lost -> first IDLE after {dt * 1e3:.1f} ms "
          f"(loss window {loss:g} s)")  # fmt: skip


def test_an_axis_error_mid_spin(service: tuple[TestClient, Runtime, Recorder]) -> None:
    client, rt, rec = service
    sim = rt.simulator
    assert sim is not None
    over_temperature = ErrorFlag.OVER_TEMPERATURE
    st, t = fault_mid_spin(client, rt, lambda _: sim.inject_fault(2, Axis.WHEEL, over_temperature))
    assert st["state"] == "FAILED" and "axis error OVER_TEMP" in st["reason"], st
    assert "module 2" in st["reason"] and "wheel" in st["reason"]
    dt = first_stop(rec, t, rt)
    assert dt <= rt.timing.heartbeat_period + 0.05, dt  # reported by the next heartbeat
    print(f"\nfault table (odrive {LINE}): axis error -> first IDLE after {dt * 1e3:.1f} ms "
          "(the next heartbeat)")


def test_bus_off_mid_spin(service: tuple[TestClient, Runtime, Recorder]) -> None:
    client, rt, rec = service
    st, t = fault_mid_spin(client, rt, bus_off(rt))
    assert st["state"] == "FAILED" and "bus-off" in st["reason"], st
    dt = first_stop(rec, t, rt)
    print(f"\nfault table (odrive {LINE}): bus-off -> first IDLE after {dt * 1e3:.1f} ms")


def test_stale_motion_capture_mid_spin(service: tuple[TestClient, Runtime, Recorder]) -> None:
    client, rt, rec = service
    sim = rt.simulator
    assert sim is not None
    run_id = start(client, MID_SPIN)
    wait_spinning(client, run_id)
    t = rt.clock.now()
    before = sim.mocap.options
    sim.mocap.options = dataclasses.replace(before, dropout=1.0)  # every pose lost
    try:
        st = wait_state(client, run_id, {"FAILED", "ABORTED", "DONE"}, timeout=60)
    finally:
        sim.mocap.options = before
    assert st["state"] == "FAILED" and "motion capture stale" in st["reason"], st
    dt = first_stop(rec, t, rt)
    assert dt <= rt.timing.mocap_stale + 0.1, dt
    print(f"\nfault table (odrive {LINE}): motion capture stale -> first IDLE after "
          f"{dt * 1e3:.1f} ms (stale after {rt.timing.mocap_stale:g} s)")  # fmt: skip


def test_a_spin_that_outlasts_the_step_timeout(
    service: tuple[TestClient, Runtime, Recorder],
) -> None:
    """A 180 deg spin within a 4 s step timeout (the pre-motion check's least: settle
    1 s + 3.1 rad at 1.2 rad/s) at 0.6 N.m, which turns the robot far slower than that
    (6.3 s): the first spin's step times out."""
    client, rt, rec = service
    timeout = 4.0
    t = rt.clock.now()
    spin = {"sweep_deg": 180, "settle_time": 1.0}
    run_id = start(client, {"protocol": spin, "limits": {"step_timeout": timeout}})
    st = wait_state(client, run_id, {"FAILED", "ABORTED", "DONE"}, timeout=120)
    assert st["state"] == "FAILED" and st["reason"].startswith("step timeout: "), st
    assert "spinning about module 1 (1/2) took longer than 4 s" in st["reason"], st["reason"]
    # the spin alone took 4 s: the stop of the timeout is the first after that
    at = timeout + first_stop(rec, t + timeout, rt)
    print(f"\nfault table (odrive {LINE}): step timeout -> every axis IDLE {at:.1f} s after "
          f"the run started ({st['reason']})")


def test_a_host_that_stops_refreshing_is_stopped_by_every_axis_watchdog(
    service: tuple[TestClient, Runtime, Recorder],
) -> None:
    """The drive's own dead-man: the driver's I/O step (receive, supervise, refresh) taken
    off the clock mid-spin, as a hung service: every axis' watchdog disarms it within
    W of the last frame the host sent it (and its heartbeat says so within T_hb)."""
    client, rt, rec = service
    drv = rt.drives
    assert drv is not None
    run_id = start(client, MID_SPIN)
    wait_spinning(client, run_id)
    hook = drv._io_hook  # type: ignore[attr-defined]
    rt.clock.remove_hook(hook)  # type: ignore[attr-defined]
    t = rt.clock.now()
    try:
        rt.clock.sleep(1.0)  # robot time flows while this thread waits on it
    finally:
        t_back = rt.clock.now()  # the I/O step's first frame after this is at t_back or later
        rt.clock.add_hook(hook)  # type: ignore[attr-defined]
    client.post(f"/calibrations/{run_id}/abort", headers=AUTH)
    wait_state(client, run_id, {"ABORTED", "FAILED", "DONE"})
    frames = rec.decoded_since(t - 1.0)
    c = cs.can_simple(LINE)
    w = rt.timing.watchdog
    worst = 0.0
    for node in axis_nodes(rt):
        last_tx = max(ts for ts, d in frames
                      if not isinstance(d, cs.Heartbeat | cs.EncoderEstimates)
                      and getattr(d, "node", None) == node and ts < t_back)  # fmt: skip
        expired = min(ts for ts, d in frames if isinstance(d, cs.Heartbeat) and d.node == node
                      and d.axis_error & c.watchdog_bit and ts > last_tx)  # fmt: skip
        assert expired - last_tx <= w + rt.timing.heartbeat_period + 1e-6, (node, expired - last_tx)
        worst = max(worst, expired - last_tx)
    print(f"\nfault table (odrive {LINE}): host silent -> every axis' watchdog reported "
          f"within {worst * 1e3:.0f} ms of its last frame (W {w * 1e3:.0f} ms + T_hb)")


def test_activation_refuses_an_axis_without_a_watchdog(
    service: tuple[TestClient, Runtime, Recorder],
) -> None:
    client, rt, _ = service
    sim = rt.simulator
    assert sim is not None
    ax = sim.drives[0].axes[1]  # type: ignore[attr-defined]
    ax.watchdog_timeout = 0.0  # enable_watchdog = False on module 1's wheel axis
    try:
        run_id = start(client, SHORT)
        st = wait_state(client, run_id, {"FAILED", "ABORTED", "DONE"}, timeout=60)
    finally:
        ax.watchdog_timeout = rt.timing.watchdog
    assert st["state"] == "FAILED", st
    assert "module 1 (node 11) axis 1 (wheel): still armed" in st["reason"], st["reason"]
    assert "enable_watchdog" in st["reason"]


def test_a_drive_whose_time_lags_the_hosts_gets_the_watchdog_window_it_is_owed(
    service: tuple[TestClient, Runtime, Recorder],
) -> None:
    """The activation's watchdog proof judges ``W + L`` on each drive's own time (its
    heartbeats) as well as the host's: a drive whose time lags the host's (as a simulator
    that cannot keep up in an emulated machine) is proven, not refused as "still armed".

    Its watchdog is three times as long on the host's clock, its heartbeat twice: as slow
    as the heartbeat loss ``L`` lets a heartbeat be with a period to spare (a heartbeat
    three times as slow is ``L`` itself, lost on the first late one: a run that failed,
    rightly, on a busy CI host)."""
    client, rt, _ = service
    sim = rt.simulator
    assert sim is not None
    ax = sim.drives[0].axes[1]  # type: ignore[attr-defined]
    period, w, window = ax.heartbeat_period, rt.timing.watchdog, rt.timing.watchdog + (
        rt.timing.heartbeat_loss
    )
    slow = 3.0  # its expiry 3 W after the last frame, past W + L on the host's clock
    beat = 2.0  # its heartbeat: a period short of the loss L
    assert slow * w > window, (w, window)
    assert (beat + 1) * period <= rt.timing.heartbeat_loss + 1e-9, (period, rt.timing)
    ax.watchdog_timeout, ax.heartbeat_period = slow * w, beat * period
    try:
        run_id = start(client, SHORT)
        wait_spinning(client, run_id)
        client.post(f"/calibrations/{run_id}/abort", headers=AUTH)
        st = wait_state(client, run_id, {"FAILED", "ABORTED", "DONE"}, timeout=60)
    finally:
        ax.watchdog_timeout, ax.heartbeat_period = rt.timing.watchdog, period
    assert st["state"] == "ABORTED", st


def test_config_file_with_odrive_drives_round_trips(tmp_path: Path) -> None:
    doc: dict[str, Any] = {"drives": {"kind": "odrive", "firmware": "0.5", "homing": "absolute"}}
    cfg = RobotConfig.model_validate(doc)
    assert isinstance(cfg.drives, ODriveDrives) and cfg.drives.nodes() == list(range(8))
    again = RobotConfig.model_validate(cfg.to_document())
    assert again.drives == cfg.drives
    with pytest.raises(ValueError, match="firmware"):
        RobotConfig.model_validate({"drives": {"kind": "odrive", "firmware": "0.4"}})
