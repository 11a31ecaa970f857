"""Abort under load (issue 40, item 1): an abort's latency with the service crowded by
other clients, against the same with the service left alone.

``swpc serve``'s real HTTP server (uvicorn with GuardedH11, the default caps: 128
connections, 32 event streams, 4 per client without the token) on a loopback port, the
in-process simulator paced at real time (the robot's case).  ``SWPC_BENCH_ABORT_TRIALS``
runs (default 20) are started, each aborted once the robot is commanded, by a new
connection with the token: the latency is wall time from the request to its answer (the
run then ABORTED: every axis was stopped before the answer).

The load comes from another process and address (:data:`LOAD_ADDRESS`), as another
client would: ``SWPC_BENCH_STREAMS``
connections (default 500) each asking ``GET /events`` without the token and opened again
as soon as the server closes them, and ``SWPC_BENCH_PLANS`` threads (default 50) asking
for the plan without pause (``GET /plan``; the plan is made before, as an operator's
first look at it would: the service makes a plan in its own process, and while it does
that takes the interpreter from every request, abort included).  The load pauses while
each run is started (the start is no control route: behind 50 plan requests it waits its
turn) and is in full swing again for 2 s before the abort.  Run it as it is and beside
``busy-host 2`` (docs/figures.md says which).
"""

from __future__ import annotations

import contextlib
import multiprocessing as mp
import os
import socket
import threading
import time
from pathlib import Path
from tempfile import TemporaryDirectory
from typing import Any

import httpx
import numpy as np
from pydantic import SecretStr

from benchmarks.services.bench_service import StopWatch
from services.config.settings import ServiceSettings
from services.http.app import create_app
from services.http.edge.server import server as http_server
from swpc_hw.sensors.zenoh_session import free_tcp_endpoint

TOKEN = "bench-token-0123456789"
LOAD_ADDRESS = "127.0.0.2"
"""The other clients' address (loopback: another client, as another host would be)."""
AUTH = {"Authorization": f"Bearer {TOKEN}"}


def _streams(port: int, n: int, stop: Any, go: Any, opened: Any) -> None:
    """``n`` connections asking for an event stream, each opened again once closed."""
    req = b"GET /events HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n"
    socks: list[socket.socket | None] = [None] * n
    while not stop.is_set():
        go.wait(1.0)
        for i in range(n):
            s = socks[i]
            if s is not None:
                try:
                    s.setblocking(False)
                    if s.recv(65536) != b"":
                        continue  # still open (events, or a 429 left idle)
                except BlockingIOError:
                    continue
                except OSError:
                    pass
                s.close()
            try:
                s = socket.create_connection(("127.0.0.1", port), 5, (LOAD_ADDRESS, 0))
                s.sendall(req)
                socks[i] = s
                with opened.get_lock():
                    opened.value += 1
            except OSError:
                socks[i] = None
        time.sleep(0.05)
    for s in socks:
        if s is not None:
            s.close()


def _plans(port: int, n: int, stop: Any, go: Any, asked: Any) -> None:
    def ask() -> None:
        transport = httpx.HTTPTransport(local_address=LOAD_ADDRESS)
        base = f"http://127.0.0.1:{port}"
        with httpx.Client(base_url=base, timeout=30, transport=transport) as c:
            while not stop.is_set():
                if not go.wait(1.0):
                    continue
                with contextlib.suppress(httpx.HTTPError):
                    c.get("/plan")
                with asked.get_lock():
                    asked.value += 1

    threads = [threading.Thread(target=ask, daemon=True) for _ in range(n)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()


def _load(
    port: int, streams: int, plans: int, stop: Any, go: Any, opened: Any, asked: Any
) -> None:
    """The other clients, in their own process (paused while ``go`` is clear)."""
    t = threading.Thread(target=_plans, args=(port, plans, stop, go, asked), daemon=True)
    t.start()
    _streams(port, streams, stop, go, opened)
    t.join(10)


def aborts(trials: int, streams: int, plans: int) -> None:
    with TemporaryDirectory() as tmp:
        settings = ServiceSettings(data_dir=Path(tmp), sim_speed=1.0, token=SecretStr(TOKEN))
        app = create_app(settings)
        port = int(free_tcp_endpoint().rsplit(":", 1)[1])
        srv = http_server(
            app, host="127.0.0.1", port=port, header_timeout=settings.header_timeout,
            max_connections=settings.max_connections, log_level="error",
        )  # fmt: skip
        serving = threading.Thread(target=srv.run, daemon=True)
        serving.start()
        while not srv.started:
            time.sleep(0.01)
        base = f"http://127.0.0.1:{port}"
        # the plan made first: a plan is made in the service's process, between runs,
        # and until it is made it takes the interpreter from everything else there
        deadline = time.monotonic() + 600
        while httpx.get(f"{base}/plan", timeout=60).status_code == 202:
            assert time.monotonic() < deadline, "no plan"
            time.sleep(0.5)
        ctx = mp.get_context("spawn")
        stop, go, opened, asked = ctx.Event(), ctx.Event(), ctx.Value("l", 0), ctx.Value("l", 0)
        go.set()
        load = None
        if streams or plans:
            load = ctx.Process(target=_load, args=(port, streams, plans, stop, go, opened, asked))
            load.start()
            deadline = time.monotonic() + 120
            while opened.value < streams or asked.value < plans:  # the load in full swing
                assert load.is_alive() and time.monotonic() < deadline, "no load"
                time.sleep(0.1)
            time.sleep(1.0)
        rt = app.state.runtime
        watch = StopWatch(rt.drives._bus)
        nodes = set(rt.config.drives.node_map().values())
        lat: list[float] = []
        stops: list[float] = []
        health: list[float] = []
        try:
            for _ in range(trials):
                # each request on a new connection, as curl: under the flood a connection
                # kept alive between requests is the first the cap closes
                go.clear()
                time.sleep(0.5 if load else 0.0)
                r = httpx.post(f"{base}/calibrations", json={}, headers=AUTH, timeout=60)
                while r.status_code == 409:  # the previous run's end being written
                    time.sleep(0.05)
                    r = httpx.post(f"{base}/calibrations", json={}, headers=AUTH, timeout=60)
                assert r.status_code == 202, r.text
                rid = r.json()["id"]
                deadline = time.monotonic() + 60
                while rt.status(rid)["state"] not in ("FREE", "SPIN"):
                    assert time.monotonic() < deadline, "run never moved"
                    time.sleep(0.01)
                go.set()
                time.sleep(2.0 if load else 0.0)
                t0 = time.perf_counter()
                r = httpx.post(f"{base}/calibrations/{rid}/abort", headers=AUTH, timeout=60)
                lat.append(time.perf_counter() - t0)
                assert r.status_code == 200 and r.json()["state"] == "ABORTED", r.text
                end = watch.last_stop_after(t0, nodes)
                assert end is not None, "no zero-torque frames"
                stops.append(end - t0)
                t0 = time.perf_counter()
                httpx.get(f"{base}/health", timeout=60)
                health.append(time.perf_counter() - t0)
        finally:
            stop.set()
            if load is not None:
                load.join(30)
                if load.is_alive():
                    load.kill()  # by its PID
            srv.should_exit = True
            serving.join(30)
    a, s, h = (np.array(x) * 1e3 for x in (lat, stops, health))
    what = (
        f"beside {streams} event streams without the token (opened {opened.value} times) and "
        f"{plans} plan clients ({asked.value} requests)"
    ) if load else "the service alone"  # fmt: skip
    print(
        f"[abort-load] {what}, {trials} aborts: request -> last stop frame of 4 nodes x 2 "
        f"axes p50 {np.percentile(s, 50):.1f} ms, p99 {np.percentile(s, 99):.1f} ms, max "
        f"{s.max():.1f} ms; request -> answer (the run ended ABORTED) p50 "
        f"{np.percentile(a, 50):.1f} ms, p99 {np.percentile(a, 99):.1f} ms; /health p99 "
        f"{np.percentile(h, 99):.1f} ms; load average {os.getloadavg()[0]:.1f}"
    )


def main() -> None:
    trials = int(os.environ.get("SWPC_BENCH_ABORT_TRIALS", "20"))
    aborts(trials, 0, 0)
    aborts(
        trials,
        int(os.environ.get("SWPC_BENCH_STREAMS", "500")),
        int(os.environ.get("SWPC_BENCH_PLANS", "50")),
    )


if __name__ == "__main__":
    main()
