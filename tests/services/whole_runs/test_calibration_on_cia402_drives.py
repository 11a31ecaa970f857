"""The calibration service on CiA 402 drives, against the in-process simulator (lockstep).

The same service, state machine and simulator as
``tests/services/whole_runs/test_calibration_on_swpc_drives.py``; the robot
config says ``drives: cia402``, so the host is :mod:`swpc_hw.drives.cia402` and the
virtual robot's drives are :mod:`simulators.drives.cia402`.  A whole calibration reaches
DONE, and every fault the swpc tests stop on (heartbeat lost, a drive's fault as EMCY,
bus-off, stale motion capture, abort, a step timeout) stops every axis first: RPDO 1 with
controlword *disable voltage* (0) and target torque 0 to all eight drives.  Each test
prints the time from the fault to the first stopping frame, in robot time.
"""

from __future__ import annotations

import dataclasses
import math
import struct
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import can
import pytest
from fastapi.testclient import TestClient
from pydantic import SecretStr

from firmware_protocol import cia402
from firmware_protocol.codec import Axis, ErrorFlag
from services.config.settings import ServiceSettings
from services.http.app import create_app
from services.runtime.runtime import Runtime
from swpc_hw.clock import Clock
from swpc_hw.files.kinematic_file import save_kinematics
from swpc_hw.robot.model import PARAM_NAMES as NAMES
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED, PAPER_NOMINAL
from tests.service_rig import (
    MID_SPIN,
    QUICK_PROTOCOL,
    TOKEN,
    abort,
    bus_off,
    fault_mid_spin,
    home_and_release,
    start,
    wait_spinning,
    wait_state,
)

RPDO1 = cia402.RPDO_BASE[0]


class Frames(can.Listener):  # type: ignore[misc]
    """Every frame on the bus as ``(clock time, id, data)``."""

    def __init__(self, clock: Clock) -> None:
        self.clock = clock
        self.frames: list[tuple[float, int, bytes]] = []
        self.lock = threading.Lock()

    def on_message_received(self, msg: can.Message) -> None:
        if msg.is_error_frame:
            return
        with self.lock:
            self.frames.append((self.clock.from_wall(msg.timestamp), msg.arbitration_id,
                                bytes(msg.data)))  # fmt: skip

    def rpdo1_since(self, t: float) -> list[tuple[float, int, int, int, int]]:
        """(time, node, controlword, mode, target torque) of every RPDO 1 at or after t."""
        with self.lock:
            frames = [f for f in self.frames if f[0] >= t]
        out = []
        for ts, i, d in frames:
            if RPDO1 < i < RPDO1 + 0x80 and len(d) == 5:
                cw, mode, torque = struct.unpack("<Hbh", d)
                out.append((ts, i - RPDO1, cw, mode, torque))
        return out


@pytest.fixture(scope="module")
def service(
    tmp_path_factory: pytest.TempPathFactory,
) -> Iterator[tuple[TestClient, Runtime, Frames]]:
    data = tmp_path_factory.mktemp("svc-cia402")
    robot = data / "robot.yaml"
    robot.write_text("drives: cia402\n")
    settings = ServiceSettings(data_dir=data, token=SecretStr(TOKEN), robot_config=robot)
    app = create_app(settings)
    with TestClient(app) as client:
        rt: Runtime = app.state.runtime
        rec = Frames(rt.clock)
        bus = can.Bus(interface="virtual", channel=rt.can_channel)
        notifier = can.Notifier(bus, [rec], timeout=0.05)  # its stop() joins a wait this long
        try:
            yield client, rt, rec
        finally:
            notifier.stop()
            bus.shutdown()


@pytest.fixture()
def installed(service: tuple[TestClient, Runtime, Frames]) -> Iterator[bytes]:
    _, rt, _ = service
    path = rt.settings.kinematics_file
    path.parent.mkdir(parents=True, exist_ok=True)
    save_kinematics(path, PAPER_NOMINAL, created="2026-01-01T00:00:00Z")
    before = path.read_bytes()
    yield before
    assert path.read_bytes() == before, "a failed run touched the kinematic file"


def first_stop(rec: Frames, rt: Runtime, since: float, what: str) -> float:
    """Every drive got controlword 0 with torque 0 after ``since``: the first such frame's
    time (printed against ``since``, the fault)."""
    nodes = set(rt.config.drives.nodes())
    deadline = time.monotonic() + 5.0
    while True:
        stops = [(t, n) for t, n, cw, _m, tq in rec.rpdo1_since(since) if cw == 0 and tq == 0]
        if {n for _, n in stops} >= nodes or time.monotonic() > deadline:
            break
        time.sleep(0.01)
    missing = nodes - {n for _, n in stops}
    assert not missing, f"axes without a stop frame: {missing}"
    t = min(t for t, _ in stops)
    last = max(t for t, n in stops if n in nodes and t <= min(t for t, _ in stops) + 1e-3)
    print(f"\ncia402 fault table: {what} -> first stopping frame {t - since:+.3f} s "
          f"(robot time; all 8 axes within {last - t:.3f} s)")  # fmt: skip
    return t


# ---------------------------------------------------------------------- happy path


def test_full_calibration_on_cia402_drives(service: tuple[TestClient, Runtime, Frames]) -> None:
    client, rt, _ = service
    assert rt.config.drives.kind == "cia402"
    run_id = start(client, {"protocol": QUICK_PROTOCOL})
    st = wait_state(client, run_id, {"DONE", "FAILED", "ABORTED"}, timeout=600)
    assert st["state"] == "DONE", st["errors"]
    assert st["segments"] == 8 and st["installed"] is True
    res = client.get(f"/calibrations/{run_id}/result").json()
    truth = {m.id: m for m in PAPER_CALIBRATED.modules}
    for m in res["modules"]:
        t = truth[m["id"]]
        for k in NAMES:
            err, sd = m[k] - getattr(t, k), m["stddev"][k]
            assert abs(err) < (0.3e-3 if k != "beta" else math.radians(0.05)), (m["id"], k, err)
            assert abs(err) < 4 * sd, (m["id"], k, err, sd)
    # the run's CAN log holds the CANopen traffic: SYNC, TPDOs of every drive, RPDOs
    log = (Path(res["dataset_dir"]) / "can.log").read_text()
    for frame in ("080#", "181#", "288#", "201#", "77F#05"):
        assert f" {frame}" in log, frame
    h = client.get("/health").json()
    assert all(n["alive"] and n["homed"] for n in h["nodes"].values()), h


# ---------------------------------------------------------------------- faults


def test_abort_mid_spin(service: tuple[TestClient, Runtime, Frames], installed: bytes) -> None:
    client, rt, rec = service
    st, t = fault_mid_spin(client, rt, abort(client), guard=120)
    assert st["state"] == "ABORTED"
    first_stop(rec, rt, t, "abort")


def test_heartbeat_loss_mid_spin(
    service: tuple[TestClient, Runtime, Frames], installed: bytes
) -> None:
    client, rt, rec = service
    sim = rt.simulator
    assert sim is not None
    st, t = fault_mid_spin(
        client, rt, lambda _: sim.mute(3), undo=lambda: sim.mute(3, False), guard=120
    )
    assert st["state"] == "FAILED" and "no heartbeat" in st["reason"], st
    assert "module 3" in st["reason"]
    first_stop(rec, rt, t, "heartbeat lost (module 3 muted; loss after 0.3 s)")


def test_drive_fault_as_emcy_mid_spin(
    service: tuple[TestClient, Runtime, Frames], installed: bytes
) -> None:
    client, rt, rec = service
    sim = rt.simulator
    assert sim is not None
    over_temperature = ErrorFlag.OVER_TEMPERATURE
    st, t = fault_mid_spin(
        client, rt, lambda _: sim.inject_fault(2, Axis.WHEEL, over_temperature), guard=120
    )
    assert st["state"] == "FAILED", st
    assert "module 2 wheel (node 4): EMCY 0x4310 excess temperature drive" in st["reason"], st
    first_stop(rec, rt, t, "drive fault (EMCY 0x4310, module 2 wheel)")


def test_bus_off_mid_spin(service: tuple[TestClient, Runtime, Frames], installed: bytes) -> None:
    client, rt, rec = service
    st, t = fault_mid_spin(client, rt, bus_off(rt), guard=120)
    assert st["state"] == "FAILED" and "bus-off" in st["reason"], st
    first_stop(rec, rt, t, "bus-off")


def test_stale_motion_capture_mid_spin(
    service: tuple[TestClient, Runtime, Frames], installed: bytes
) -> None:
    client, rt, rec = service
    sim = rt.simulator
    assert sim is not None
    run_id = start(client, MID_SPIN)
    wait_spinning(client, run_id, guard=120)
    with sim._lock:
        before = sim.mocap.options
        sim.mocap.options = dataclasses.replace(before, dropout=1.0)
        t = rt.clock.now()
    try:
        st = wait_state(client, run_id, {"FAILED", "ABORTED", "DONE"}, timeout=60)
    finally:
        with sim._lock:
            sim.mocap.options = before
    assert st["state"] == "FAILED" and "motion capture stale" in st["reason"], st
    first_stop(rec, rt, t, "stale motion capture (stale after 0.5 s)")


def test_step_timeout(service: tuple[TestClient, Runtime, Frames], installed: bytes) -> None:
    """A spin too slow for its step (a weak spin torque): the step's timeout fails it.
    3 s: what the pre-motion check allows a 90 deg sweep after a 1 s settle (2.3 s at
    limits.max_yaw_rate) and the protocol's 2.5 s re-steer.  The robot is homed first, as
    the file's first run leaves it: homing these drives takes 8 s, which the run's own
    step timeout would stop."""
    client, rt, rec = service
    home_and_release(rt)
    t = rt.clock.now()
    run_id = start(client, {"limits": {"spin_torque": 0.05, "step_timeout": 3.0},
                            "protocol": {"settle_time": 1.0, "sweep_deg": 90}})  # fmt: skip
    st = wait_state(client, run_id, {"FAILED", "ABORTED", "DONE"}, timeout=120)
    assert st["state"] == "FAILED", st
    assert "spinning about module 1 (1/2) took longer than 3 s" in st["reason"], st
    spins = [ts for ts, _n, cw, mode, tq in rec.rpdo1_since(t)
             if mode == 10 and tq != 0 and cw == 0x0F]  # fmt: skip
    assert spins, rec.rpdo1_since(t)[-40:]
    t_spin = max(spins)
    first_stop(rec, rt, t_spin, "step timeout (limits.step_timeout 3 s from the spin's torque)")
