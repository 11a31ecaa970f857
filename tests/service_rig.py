"""The real service as the tests open it: its token, a service on the in-process simulator
with a bus of ours on its CAN channel (:class:`Sim`), one not connected to any robot
(:func:`app_without_robot`), and the requests and readings the tests share.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
from fastapi.testclient import TestClient
from prometheus_client.parser import text_string_to_metric_families
from pydantic import SecretStr

from firmware_protocol import codec
from services.config.robot import ConfigOverrides
from services.config.settings import ServiceSettings
from services.http.app import create_app
from services.runtime.runtime import Runtime

ROOT = Path(__file__).resolve().parents[1]
"""The repository's root."""
TOKEN = "test-token-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


def overrides(doc: dict[str, Any]) -> dict[str, Any]:
    return ConfigOverrides.model_validate(doc).document()


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


def app_without_robot(tmp_path: Path, **settings: Any) -> Any:
    """The real app on a real runtime that is not connected to a robot (no bus, no
    simulator): what the API does before and after a run."""
    cfg = ServiceSettings(data_dir=tmp_path, token=SecretStr(TOKEN), **settings)
    return create_app(cfg, runtime_factory=Runtime)


def families(text: str) -> dict[str, Any]:
    return {f.name: f for f in text_string_to_metric_families(text)}


QUICK_PROTOCOL = {
    "sweep_deg": 45, "settle_time": 1.0, "stop_time": 0.5, "align_time": 0.5, "resteer_time": 1.5
}
"""The whole protocol with short spins (as make test-vcan): a real result, quickly."""
SPINS_ONLY = {**QUICK_PROTOCOL, "precheck": False}
""":data:`QUICK_PROTOCOL` without the fast part (``protocol.precheck``, 14 s of robot time
before the first lock): for a test of what comes after it.  The fast part itself is
tested by the whole calibration on each drive kind, the commissioning and the miswired
robot's tests."""
SHORT_STEPS = {"protocol": SPINS_ONLY}
SHORT = {"protocol": {"sweep_deg": 1440, "precheck": False}}
"""A long first spin (about module 1), no fast part before it: the faults a test injects
land in it."""
MID_SPIN = {"protocol": {"sweep_deg": 1440, "settle_time": 1.0, "precheck": False}}
""":data:`SHORT` with :data:`QUICK_PROTOCOL`'s 1 s settle: the same long first spin for a
fault, reached 2 s of robot time sooner (the sweep :func:`wait_spinning` waits for is
counted once the settle is over)."""


@dataclass
class Sim:
    """The service on the in-process simulator, and (once asked) a bus of ours on its CAN
    channel."""

    client: TestClient
    rt: Runtime
    bus: can.BusABC | None = None

    def host_frames(self) -> list[can.Message]:
        """The commands a host sent since the last call (drained from our bus's queue: the
        virtual bus hands every frame to every other bus on the channel as it is sent).
        The first call opens that bus and returns nothing: a bus nobody reads would be
        handed a copy of every frame of every run (CPU of the simulation, and a queue
        that only grows)."""
        if self.bus is None:
            self.bus = can.Bus(interface="virtual", channel=self.rt.can_channel)
            return []
        out = []
        while (msg := self.bus.recv(0)) is not None:
            if not msg.is_error_frame and codec.split_id(msg.arbitration_id)[1] in (
                codec.HOST_COMMANDS
            ):
                out.append(msg)
        return out

    def wait(self, run_id: str, states: set[str]) -> dict[str, Any]:
        return wait_state(self.client, run_id, states, timeout=60.0)


@contextmanager
def sim_service(data: Path, **settings: Any) -> Iterator[Sim]:
    app = create_app(ServiceSettings(data_dir=data, token=SecretStr(TOKEN), **settings))
    with TestClient(app) as client:
        rt: Runtime = app.state.runtime
        sim = Sim(client, rt)
        try:
            yield sim
        finally:
            if sim.bus is not None:
                sim.bus.shutdown()


def send(client: TestClient, overrides: str, install: str = "if-within-tolerance") -> Any:
    """POST /calibrations with ``overrides`` as written (NaN and Infinity included)."""
    body = f'{{"overrides":{overrides},"install":"{install}"}}'
    return client.post(
        "/calibrations", content=body, headers={**AUTH, "content-type": "application/json"}
    )


def _run_state(client: TestClient, run_id: str) -> str | None:
    """The run's state as the service holds it in memory (no request), None when the
    client's service has no such run in this process (then only HTTP says)."""
    app = getattr(client, "app", None)  # an httpx client to a service process: None
    rt = None if app is None else getattr(app.state, "runtime", None)
    run = None if rt is None else rt.runs.get(run_id)
    return None if run is None else str(run.status.state)


def watch(
    client: TestClient,
    run_id: str,
    until: Callable[[dict[str, Any]], bool],
    timeout: float = 240.0,
    path: str = "/calibrations",
) -> dict[str, Any]:
    """The run's status over HTTP (``GET {path}/{run_id}``) once ``until`` holds for it.

    A GET through the TestClient costs ~10 ms of CPU (the portal's event loop, the
    middleware), taken from the run's simulation: polled every 50 ms over a whole run, a
    sixth of the test's CPU.  So between GETs this watches the run's state in the
    service's memory (an attribute read, every 10 ms) and asks HTTP only when it changed;
    HTTP still answers what the test judges.  ``timeout`` (wall s) is a guard against a
    hang, never a judgement of speed."""
    deadline = time.monotonic() + timeout
    seen: str | None = ""
    st: dict[str, Any] = {}
    while True:
        now = _run_state(client, run_id)
        if now is None or now != seen:
            st = client.get(f"{path}/{run_id}").json()
            seen = now
            if until(st):
                return st
        assert time.monotonic() < deadline, f"run {run_id} never got there: {st}"
        time.sleep(0.01)


def wait_state(
    client: TestClient, run_id: str, states: set[str], timeout: float = 240.0
) -> dict[str, Any]:
    """The run's status once its state is one of ``states`` (:func:`watch`)."""
    return watch(client, run_id, lambda st: st["state"] in states, timeout)


def start(client: TestClient, overrides: dict[str, Any] | None = None, **kw: Any) -> str:
    """POST /calibrations (202): the new run's id."""
    r = client.post("/calibrations", json={"overrides": overrides or {}, **kw}, headers=AUTH)
    assert r.status_code == 202, r.text
    assert r.headers["Location"] == f"/calibrations/{r.json()['id']}"
    return str(r.json()["id"])


def wait_spinning(
    client: TestClient, run_id: str, sweep: float = 20.0, guard: float = 60.0
) -> None:
    """Until the run spins and has swept ``sweep`` deg (``guard`` s against a hang)."""
    deadline = time.monotonic() + guard
    while time.monotonic() < deadline:
        if _run_state(client, run_id) not in ("SPIN", "FAILED", "ABORTED", "DONE", None):
            time.sleep(0.01)  # not spinning yet: nothing to ask HTTP (:func:`watch`)
            continue
        st = client.get(f"/calibrations/{run_id}").json()
        assert st["state"] not in ("FAILED", "ABORTED", "DONE"), st
        if st["state"] == "SPIN" and st["sweep_deg"] >= sweep:
            return
        time.sleep(0.02)
    raise AssertionError("never reached a steady spin")


def fault_mid_spin(
    client: TestClient,
    rt: Runtime,
    fault: Callable[[str], object],
    undo: Callable[[], object] | None = None,
    guard: float = 60.0,
) -> tuple[dict[str, Any], float]:
    """A run with a long first spin (:data:`MID_SPIN`), ``fault(run_id)`` once it spins,
    then its end (``undo()`` after it, whatever happens): ``(final status, the service
    clock's time just before the fault)``, what every drive kind's fault table starts from."""
    run_id = start(client, MID_SPIN)
    wait_spinning(client, run_id, guard=guard)
    t = rt.clock.now()
    try:
        fault(run_id)
        st = wait_state(client, run_id, {"FAILED", "ABORTED", "DONE"}, timeout=60)
    finally:
        if undo is not None:
            undo()
    return st, t


def home_and_release(rt: Runtime) -> None:
    """Home every steering not homed yet, then leave every axis free and disabled (a run
    that follows needs no homing: its CONNECT step is short on any drive kind)."""
    from swpc_hw.drives.robot_io import DrivesRobotIO

    assert rt.drives is not None
    io = DrivesRobotIO(rt.drives)
    try:
        io.activate()
        for m in io.unhomed():
            io.start_homing(m)
        deadline = rt.clock.now() + 10.0  # robot time: the clock moves while we wait on it
        while io.unhomed() and rt.clock.now() < deadline:
            rt.clock.sleep(0.01)
        assert not io.unhomed()
    finally:
        io.release()
        io.close()


def abort(client: TestClient) -> Callable[[str], None]:
    """The operator's abort of a run (200), as a :func:`fault_mid_spin` fault."""

    def fault(run_id: str) -> None:
        assert client.post(f"/calibrations/{run_id}/abort", headers=AUTH).status_code == 200

    return fault


def bus_off(rt: Runtime) -> Callable[[str], None]:
    """A bus-off error frame on the robot's bus, as a :func:`fault_mid_spin` fault."""

    def fault(_run_id: str) -> None:
        with can.Bus(interface="virtual", channel=rt.can_channel) as bus:
            bus.send(can.Message(is_error_frame=True, arbitration_id=0x040, dlc=8))

    return fault


@contextmanager
def served(
    app: Any, *, header_timeout: float = 5.0, max_connections: int = 8
) -> Iterator[tuple[Any, int]]:
    """``app`` behind the real HTTP server (uvicorn with GuardedH11) on a free loopback
    port, in this process: ``(server, port)``; the server is stopped on exit."""
    from services.http.edge.server import server as http_server
    from swpc_hw.sensors.zenoh_session import free_tcp_endpoint

    port = int(free_tcp_endpoint().rsplit(":", 1)[1])
    srv = http_server(
        app, host="127.0.0.1", port=port, header_timeout=header_timeout,
        max_connections=max_connections, log_level="warning",
    )  # fmt: skip
    serving = threading.Thread(target=srv.run, daemon=True)
    serving.start()
    deadline = time.monotonic() + 30
    while not srv.started:
        assert serving.is_alive() and time.monotonic() < deadline, "server did not start"
        time.sleep(0.01)
    try:
        yield srv, port
    finally:
        srv.should_exit = True
        serving.join(10)
        if serving.is_alive():
            srv.force_exit = True
            serving.join(10)
