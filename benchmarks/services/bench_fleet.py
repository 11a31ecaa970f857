"""The fleet with 100 robots (issue 40, item 2): every robot publishing through one router.

The fleet service is the router, in this process, as ``swpc fleet --zenoh-mode router``
runs it: the shipped ``deploy/zenoh/fleet-router.json5`` and a users file of
``SWPC_BENCH_FLEET_ROBOTS`` robots (default 100), so every message passes their access
control.  The robots are peers in a child process, each with its own credentials and
liveliness token, publishing a state document (a history of 8 calibrations of 4 modules,
about 7 kB) every ``SWPC_BENCH_FLEET_PERIOD`` s (default 1), a new calibration every 10th.
For ``SWPC_BENCH_FLEET_S`` s (default 60) ``GET /robots`` is read every 0.5 s, as the page
polls it.  Printed: ``/robots`` p50 / p99 / max (ms), the fleet process's CPU share (the
router and the service: one process) and its RSS before the robots and at the end, the
store (documents, MiB), and the CPU share of the 100 robots' process.
``python -m benchmarks fleet``; the figures are in docs/figures.md.
"""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from tempfile import TemporaryDirectory

import numpy as np
from fastapi.testclient import TestClient

from services.config.fleet import FleetSettings
from services.fleet.service import FleetService, open_fleet_session
from services.http.fleet.app import create_fleet_app
from services.store.fleet import FleetStore
from swpc_hw.sensors.zenoh_session import free_tcp_endpoint

ROOT = Path(__file__).resolve().parents[1]
ROUTER_FILE = ROOT / "deploy" / "zenoh" / "fleet-router.json5"

ROBOTS = textwrap.dedent(
    """
    import json, sys, time
    sys.path.insert(0, {root!r})
    from services.config.fleet import alive_key, state_key
    from swpc_hw.sensors.zenoh_session import ZenohAuth, open_session

    ep, n, period, seconds = sys.argv[1], int(sys.argv[2]), float(sys.argv[3]), float(sys.argv[4])

    def calibration(k, i):
        mods = [{{"id": m, "x_s": 0.215, "y_s": 0.125, "beta": 0.001 * i, "b": 0.02,
                  "r": 0.055 - 1e-6 * i * k,
                  "stddev": {{"x_s": 2e-4, "y_s": 2e-4, "beta": 1e-3, "b": 1e-4, "r": 2e-5}}}}
                for m in (1, 2, 3, 4)]
        return {{"run": f"r{{k}}-{{i}}", "time": f"2026-01-{{1 + i % 28:02d}}T10:00:00Z",
                 "modules": mods}}

    def document(k, cals):
        return json.dumps({{"format": "swpc-fleet-state/2", "robot": f"robot{{k}}",
            "fleet_period_s": period, "time": time.time(), "version": "bench",
            "file_in_force": {{"created": "2026-01-01T00:00:00Z", "run": f"r{{k}}-{{cals - 1}}",
                               "modules": calibration(k, cals - 1)["modules"]}},
            "last_check": None, "health": {{"status": "ok", "problems": []}},
            "history": {{"calibrations": [calibration(k, i) for i in range(cals)]}}}}).encode()

    sessions, tokens = [], []
    for k in range(1, n + 1):
        s = open_session(connect=[ep], auth=ZenohAuth(f"robot{{k}}", f"secret-{{k:04d}}"))
        sessions.append(s)
        tokens.append(s.liveliness().declare_token(alive_key(f"robot{{k}}")))
    print("ready", flush=True)
    start, sent = time.monotonic(), 0
    while time.monotonic() - start < seconds:
        tick = time.monotonic()
        for k, s in enumerate(sessions, start=1):
            cals = 8 + sent // (10 * n)  # a new calibration every 10th period
            s.put(state_key(f"robot{{k}}"), document(k, cals))
            sent += 1
        time.sleep(max(0.0, period - (time.monotonic() - tick)))
    for t in tokens:
        t.undeclare()
    for s in sessions:
        s.close()
    print(json.dumps({{"sent": sent}}), flush=True)
    """
)


def rss_mib() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def main() -> None:
    n = int(os.environ.get("SWPC_BENCH_FLEET_ROBOTS", "100"))
    period = float(os.environ.get("SWPC_BENCH_FLEET_PERIOD", "1"))
    seconds = float(os.environ.get("SWPC_BENCH_FLEET_S", "60"))
    with TemporaryDirectory() as tmp:
        users = Path(tmp) / "fleet-users.txt"
        users.write_text("".join(f"robot{k}:secret-{k:04d}\n" for k in range(1, n + 1)))
        ep = free_tcp_endpoint()
        s = FleetSettings(mode="router", listen=[ep], config_file=str(ROUTER_FILE),
                          users_file=users, data_dir=Path(tmp))  # fmt: skip
        fleet = FleetService(FleetStore(Path(tmp) / "fleet.sqlite"))
        session = open_fleet_session(s)
        fleet.subscribe(session)
        script = Path(tmp) / "robots.py"
        script.write_text(ROBOTS.format(root=str(ROOT)))
        rss0 = rss_mib()
        child = subprocess.Popen(
            [sys.executable, str(script), ep, str(n), str(period), str(seconds)],
            stdout=subprocess.PIPE, text=True,
        )  # fmt: skip
        try:
            assert child.stdout is not None
            assert child.stdout.readline().strip() == "ready", "the robots did not connect"
            c0, t0 = cpu_s(), time.monotonic()
            lat: list[float] = []
            with TestClient(create_fleet_app(fleet)) as client:
                while child.poll() is None:
                    q = time.perf_counter()
                    r = client.get("/robots")
                    lat.append(time.perf_counter() - q)
                    assert r.status_code == 200, r.text
                    time.sleep(0.5)
                rows = client.get("/robots").json()
            wall, cpu = time.monotonic() - t0, cpu_s() - c0
            out = json.loads(child.stdout.read().strip().splitlines()[-1])
            child_cpu = resource.getrusage(resource.RUSAGE_CHILDREN)
        finally:
            if child.poll() is None:
                child.kill()
            child.wait()
            fleet.close()
            session.close()
        ms = np.array(lat) * 1e3
        st = fleet.store
        print(
            f"[fleet] {n} robots through one router (the fleet service, their ACL), a "
            f"~7 kB state each every {period:g} s for {wall:.0f} s: {out['sent']} sent, "
            f"{fleet.received} received, {fleet.rejected} rejected; {len(rows)} robots listed"
        )
        print(
            f"[fleet] GET /robots ({len(ms)} reads): p50 {np.percentile(ms, 50):.1f} ms, "
            f"p99 {np.percentile(ms, 99):.1f} ms, max {ms.max():.1f} ms"
        )
        print(
            f"[fleet] fleet process (router + service): CPU {100 * cpu / wall:.1f} % of a core, "
            f"RSS {rss0:.0f} MiB before the robots, {rss_mib():.0f} MiB at the end; store "
            f"{sum(r.documents for r in st.robots())} documents, {st.bytes / (1 << 20):.1f} MiB"
        )
        print(
            f"[fleet] the {n} robots' process: CPU "
            f"{100 * (child_cpu.ru_utime + child_cpu.ru_stime) / wall:.1f} % of a core"
        )
        st.close()


if __name__ == "__main__":
    main()
