"""An always-on service, the rows of issue 21 that need an open runtime or a real server.

Health and metrics on a runtime opened on python-can's virtual bus with no robot on it
(every node lost) and zenoh on loopback with no motion capture; idle connections against
the real HTTP server (uvicorn with :class:`services.http_server.GuardedH11`, in a thread,
on a free loopback port); every endpoint fed non-standard JSON.  The rest of the issue's rows are in
``tests/test_hardening.py``.
"""

from __future__ import annotations

import socket
import threading
import time
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import can
import httpx
import pytest
from fastapi.testclient import TestClient
from prometheus_client.parser import text_string_to_metric_families
from pydantic import SecretStr

from services.api import create_app
from services.runtime import Runtime
from services.settings import ServiceSettings
from swpc_hw.zenoh_session import free_tcp_endpoint
from tests.test_hardening import AUTH, TOKEN, app_without_robot

#: every kind of non-standard JSON Python's parser accepts (or chokes on)
NON_STANDARD = [
    '{"overrides":{"limits":{"watchdog_ms":Infinity}}}',
    '{"overrides":{"protocol":{"sweep_deg":NaN}}}',
    '{"overrides":{"limits":{"max_yaw_rate":-Infinity}}}',
    '{"overrides":{"limits":{"max_yaw_rate":1e400}}}',
    '{"install":' + "9" * 5000 + "}",
    '{"overrides":' + "[" * 5000 + "]" * 5000 + "}",
    "NaN",
    "[" * 100_000,
]


@pytest.fixture(scope="module")
def lost(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[TestClient, Runtime]]:
    """The service opened on a virtual CAN channel no controller answers on, and a zenoh
    endpoint no motion capture publishes to."""
    settings = ServiceSettings(
        data_dir=tmp_path_factory.mktemp("lost"),
        token=SecretStr(TOKEN),
        can_interface="virtual",
        can_channel=f"swpc-lost-{uuid.uuid4().hex[:8]}",
        zenoh_listen=[free_tcp_endpoint()],
    )
    app = create_app(settings, runtime_factory=lambda s: Runtime(s).open())
    with TestClient(app) as client:
        yield client, app.state.runtime


def test_health_is_failing_with_every_node_lost_and_no_motion_capture(
    lost: tuple[TestClient, Runtime],
) -> None:
    client, _ = lost
    r = client.get("/health")
    doc = r.json()
    # was 200 "ok"
    assert r.status_code == 503 and doc["status"] == "failing", doc
    for m in (1, 2, 3, 4):
        assert f"module {m} (node {m}): no heartbeat" in doc["problems"], doc["problems"]
    assert "motion capture stale: no pose yet" in doc["problems"]
    assert doc["nodes"]["1"]["alive"] is False and doc["mocap_stale"] is True
    # and no run starts: PRECHECK would refuse it after 5 s; the service says so at once
    assert not doc["running"]


def families(text: str) -> dict[str, Any]:
    return {f.name: f for f in text_string_to_metric_families(text)}


def test_metrics_are_counters_and_histograms(lost: tuple[TestClient, Runtime]) -> None:
    client, rt = lost
    before = families(client.get("/metrics").text)
    # was: gauges, and a gauge of the p99 latency
    assert before["swpc_can_frames"].type == "counter"
    assert before["swpc_can_errors"].type == "counter"
    assert before["swpc_poses"].type == "counter"
    assert before["swpc_pose_delay_seconds"].type == "histogram"
    assert before["swpc_run_duration_seconds"].type == "histogram"
    assert {s.labels["outcome"] for s in before["swpc_poses"].samples} >= {"received", "accepted"}
    health = before["swpc_health"].samples[0].value
    assert health == 2.0  # failing

    def rx(fams: dict[str, Any]) -> float:
        return float(
            next(
                s.value
                for s in fams["swpc_can_frames"].samples
                if s.name == "swpc_can_frames_total" and s.labels["direction"] == "rx"
            )
        )

    with can.Bus(interface="virtual", channel=rt.can_channel) as bus:
        for _ in range(5):
            bus.send(can.Message(arbitration_id=0x7F0, data=b"\x01", is_extended_id=False))
    deadline = time.monotonic() + 10
    while rx(families(client.get("/metrics").text)) < rx(before) + 5:
        assert time.monotonic() < deadline, "the rx counter never counted 5 frames"
        time.sleep(0.02)
    bucket = [
        s for s in before["swpc_pose_delay_seconds"].samples if s.name.endswith("_bucket")
    ]
    assert bucket[-1].labels["le"] == "+Inf"


@pytest.mark.parametrize("method", ["GET", "POST", "PUT", "DELETE"])
def test_every_endpoint_answers_non_standard_json_below_500(tmp_path: Path, method: str) -> None:
    app = app_without_robot(tmp_path)
    with TestClient(app) as client:
        spec = client.get("/openapi.json").json()
        paths = [p.replace("{run_id}", "abc123") for p in spec["paths"]]
        paths += ["/docs", "/redoc", "/metrics", "/health", "/openapi.json", "/nope"]
        statuses = set()
        for path in paths:
            for headers in (AUTH, {}):
                for body in NON_STANDARD:
                    r = client.request(
                        method,
                        path,
                        content=body,
                        headers={**headers, "content-type": "application/json"},
                    )
                    assert r.status_code < 500, (method, path, body[:40], r.status_code, r.text)
                    statuses.add(r.status_code)
    if method == "POST":
        assert {401, 422} <= statuses, statuses  # refused, named, never parsed into a 500


# ------------------------------------------------------------ the real server


@pytest.fixture()
def server(tmp_path: Path) -> Iterator[tuple[str, int]]:
    from services.http_server import server as make_server

    app = create_app(
        ServiceSettings(data_dir=tmp_path, token=SecretStr(TOKEN)), runtime_factory=Runtime
    )
    port = int(free_tcp_endpoint().rsplit(":", 1)[1])
    srv = make_server(
        app, host="127.0.0.1", port=port, header_timeout=0.5, max_connections=8,
        log_level="warning",
    )  # fmt: skip
    thread = threading.Thread(target=srv.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while not srv.started:
        assert thread.is_alive() and time.monotonic() < deadline, "server did not start"
        time.sleep(0.01)
    try:
        yield "127.0.0.1", port
    finally:
        srv.should_exit = True
        thread.join(10)


def closed_by_peer(sock: socket.socket, within: float) -> bool:
    """The server closed ``sock`` within ``within`` host seconds (a guard: it may well
    be sooner)."""
    sock.settimeout(within)
    try:
        return sock.recv(1) == b""
    except TimeoutError:
        return False
    except ConnectionResetError:
        return True


def test_idle_connections_are_closed_and_health_still_answers(server: tuple[str, int]) -> None:
    host, port = server
    # 3 times the connection cap, silent or sending half a request head: each one held a
    # file descriptor for ever (256 of them: /health unanswered for 50 s)
    idle = []
    for i in range(24):
        s = socket.create_connection((host, port))
        if i % 2:
            s.sendall(b"GET /health HTTP/1.1\r\nHost: x\r\n")  # never finished
        idle.append(s)
    r = httpx.get(f"http://{host}:{port}/health", timeout=20)
    assert r.status_code == 503  # answered (no robot here: failing)
    # every one of them is closed: the head timeout (0.5 s) or the cap (8)
    assert all(closed_by_peer(s, 20.0) for s in idle)
    for s in idle:
        s.close()
    # a client that sends its request in time is served, on a kept-alive connection too
    with httpx.Client(base_url=f"http://{host}:{port}", timeout=20) as c:
        assert c.get("/health").status_code == 503
        assert c.get("/kinematics").status_code == 404
