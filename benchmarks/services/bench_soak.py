"""Soak: calibrations back to back through the HTTP API, with aborts and faults mixed in.

One service on the in-process simulator (simulated time, as fast as the host allows) runs
``SWPC_BENCH_SOAK_RUNS`` calibrations (default 100) of a short protocol, one after the
other, as an operator's script would: every 7th is aborted mid-spin, every 11th loses a
module's heartbeat mid-spin (the drives stop, the run fails), the rest end DONE and are
installed.  After every 10 it prints what an always-on service must not grow without
bound: resident memory, open file descriptors, threads, the data dir's size (its budget
set to 96 MiB), how many backups of the kinematic file and runs in memory are kept, and
the rows of the pose and encoder-feedback rings (bounded by their capacities: they fill,
then keep the newest).
``python -m benchmarks soak``; the figures are in docs/figures.md.
"""

from __future__ import annotations

import os
import shutil
import threading
import time
from pathlib import Path
from tempfile import TemporaryDirectory

from fastapi.testclient import TestClient
from pydantic import SecretStr

from services.config.settings import ServiceSettings
from services.http.app import create_app
from services.runs.install import backups
from services.runtime.runtime import Runtime

TOKEN = "bench-token-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
PROTOCOL = {"sweep_deg": 45, "settle_time": 1.0, "stop_time": 0.5, "align_time": 0.5,
            "resteer_time": 1.5}  # fmt: skip
TERMINAL = {"DONE", "FAILED", "ABORTED"}
DISK_BUDGET = 96 << 20
"""A small data dir (bytes), so that a hundred runs reach it: the oldest runs' recordings
are then pruned to make room, and the data dir's size must level off under it."""


def rss_mib() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def tree_mib(path: Path) -> float:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file()) / (1 << 20)


def wait(client: TestClient, run_id: str, until: set[str], timeout: float = 600.0) -> str:
    deadline = time.monotonic() + timeout  # a guard against a hang
    while time.monotonic() < deadline:
        state = str(client.get(f"/calibrations/{run_id}").json()["state"])
        if state in until:
            return state
        time.sleep(0.02)
    raise RuntimeError(f"run {run_id} never reached {until}")


def one_run(client: TestClient, rt: Runtime, i: int) -> str:
    r = client.post(
        "/calibrations", json={"overrides": {"protocol": PROTOCOL}, "install": "always"},
        headers=AUTH,
    )  # fmt: skip
    assert r.status_code == 202, r.text
    run_id = r.json()["id"]
    if i % 7 == 6 or i % 11 == 10:
        wait(client, run_id, {"SPIN"} | TERMINAL)
        if i % 7 == 6:
            client.post(f"/calibrations/{run_id}/abort", headers=AUTH)
        else:
            assert rt.simulator is not None
            rt.simulator.mute(2)
            try:
                return wait(client, run_id, TERMINAL)
            finally:
                rt.simulator.mute(2, False)
    return wait(client, run_id, TERMINAL)


def main() -> None:
    runs = int(os.environ.get("SWPC_BENCH_SOAK_RUNS", "100"))
    with TemporaryDirectory() as tmp:
        data = Path(tmp)
        settings = ServiceSettings(
            data_dir=data,
            token=SecretStr(TOKEN),
            allowed_hosts=["testserver"],
            disk_budget=DISK_BUDGET,
            can_log_bytes=DISK_BUDGET // 4,
            min_free=0,
        )
        app = create_app(settings)
        with TestClient(app) as client:
            rt: Runtime = app.state.runtime
            print(f"[soak] {runs} calibrations of a short protocol; every 7th aborted, every "
                  "11th a lost heartbeat; after every 10:")  # fmt: skip
            print(f"{'runs':>5} {'DONE':>5} {'FAILED':>6} {'ABORTED':>7} {'RSS MiB':>8} "
                  f"{'fds':>4} {'threads':>7} {'data MiB':>8} {'backups':>7} {'in mem':>6} "
                  f"{'poses kept':>10} {'feedback kept':>13} {'wall s':>7}")
            counts = dict.fromkeys(sorted(TERMINAL), 0)
            t0 = time.perf_counter()
            for i in range(runs):
                counts[one_run(client, rt, i)] += 1
                if (i + 1) % 10 == 0:
                    fds = len(os.listdir("/proc/self/fd"))
                    kept = len(backups(rt.settings.kinematics_file))
                    assert rt.drives is not None
                    fb = sum(len(rt.drives.history_arrays(m)["t"]) for m in rt.drives.modules())
                    print(
                        f"{i + 1:>5} {counts['DONE']:>5} {counts['FAILED']:>6} "
                        f"{counts['ABORTED']:>7} {rss_mib():>8.1f} {fds:>4} "
                        f"{threading.active_count():>7} {tree_mib(data):>8.1f} {kept:>7} "
                        f"{len(rt.runs):>6} {rt.mocap.samples().shape[0]:>10} {fb:>13} "
                        f"{time.perf_counter() - t0:>7.0f}",
                        flush=True,
                    )
        disk = shutil.disk_usage(data)
        print(f"[soak] data dir file system: {disk.free / (1 << 30):.1f} GiB free at the end")
