"""Disk: bytes the service writes idle (per hour) and per calibration run.

The service (``create_app`` as ``swpc serve``) on the in-process simulator, with the
controllers' feedback at 200 Hz (a robot's default; the in-process default is 100 Hz),
in simulated time:

1. Idle: ``SWPC_BENCH_IDLE_S`` seconds of robot time (default 120) with no run; the bytes
   every file of the data dir gained (the rolling CAN log, the run store) and the bytes
   the process wrote (``wchar`` of ``/proc/self/io``: every ``write``), scaled to an hour.
   The rolling log never holds more than ``SWPC_CAN_LOG_BYTES`` (64 MiB) on disk: the
   figure per hour is the write rate, the bound is what stays.  Between runs it keeps the
   periodic frames once per ``SWPC_CAN_LOG_IDLE_PERIOD`` (1 s) per CAN id; set it to 0 for
   every frame (the service before it).
2. One calibration with the default protocol (4 modules x 2 angles, 360 deg spins): the
   run's directory file by file (dataset CSVs, raw ``can.log``, ``run.mcap``, kinematic
   file), the rolling log's growth over the run (every frame during a run), and the
   process's writes.

``python -m benchmarks disk`` (skip the run: ``SWPC_BENCH_DISK_RUN=0``).
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from tempfile import TemporaryDirectory

from fastapi.testclient import TestClient
from pydantic import SecretStr

from services.config.settings import ServiceSettings
from services.http.app import create_app
from services.runtime.runtime import Runtime

TOKEN = "bench-token-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
MB = 1e6


def written() -> tuple[int, int]:
    """Bytes this process has passed to ``write`` so far (``wchar`` of ``/proc/self/io``:
    files, pipes, the terminal) and sent to storage (``write_bytes``: what the disk gets)."""
    io = dict(line.split(": ") for line in Path("/proc/self/io").read_text().splitlines())
    return int(io["wchar"]), int(io["write_bytes"])


def rates(w0: tuple[int, int], w1: tuple[int, int], per: float, unit: str) -> str:
    calls, disk = ((b - a) / per / MB for a, b in zip(w0, w1, strict=True))
    return f"process write() {calls:.1f} {unit}, to storage {disk:.1f} {unit}"


def sizes(root: Path) -> dict[str, int]:
    return {
        str(p.relative_to(root)): p.stat().st_size for p in sorted(root.rglob("*")) if p.is_file()
    }


def main() -> None:
    idle_s = float(os.environ.get("SWPC_BENCH_IDLE_S", "120"))
    with TemporaryDirectory() as tmp:
        data = Path(tmp)
        settings = ServiceSettings(data_dir=data, token=SecretStr(TOKEN), feedback_rate=200)
        app = create_app(settings)
        with TestClient(app) as client:
            rt: Runtime = app.state.runtime
            rt.clock.sleep(2.0)  # start-up: nodes up, first poses in
            before, w0, t0 = sizes(data), written(), rt.clock.now()
            rt.clock.sleep(idle_s)
            after, w1, t1 = sizes(data), written(), rt.clock.now()
            dt = t1 - t0
            grown = sum(after.values()) - sum(before.values())
            can_log = sum(v for k, v in after.items() if k.startswith("can/"))
            print(
                f"[idle] {dt:.0f} s of robot time, feedback 200 Hz, SWPC_CAN_LOG_IDLE_PERIOD "
                f"{settings.can_log_idle_period:g} s: "
                f"data dir +{grown / dt / 1e3:.1f} "
                f"kB/s = {grown / dt * 3600 / MB:.0f} MB/hour written (rolling CAN log; "
                f"on disk at most {int(settings.can_log_bytes) / MB:.0f} MB: "
                f"SWPC_CAN_LOG_BYTES); {rates(w0, w1, dt / 3600, 'MB/hour')}; "
                f"rolling log now {can_log / MB:.1f} MB in "
                f"{sum(k.startswith('can/') for k in after)} file(s)"
            )
            if os.environ.get("SWPC_BENCH_DISK_RUN", "1") == "0":
                return
            before, w0, t0 = sizes(data), written(), rt.clock.now()
            r = client.post("/calibrations", json={}, headers=AUTH)
            assert r.status_code == 202, r.text
            rid = r.json()["id"]
            wall0 = time.monotonic()
            while True:
                st = client.get(f"/calibrations/{rid}").json()
                if st["state"] in ("DONE", "FAILED", "ABORTED"):
                    break
                time.sleep(0.2)
            after, w1, t1 = sizes(data), written(), rt.clock.now()
            wall = time.monotonic() - wall0
            run = {k: v for k, v in after.items() if k.startswith(f"runs/{rid}/")}
            rolling = sum(v for k, v in after.items() if k.startswith("can/")) - sum(
                v for k, v in before.items() if k.startswith("can/")
            )
            parts = ", ".join(
                f"{k.split('/', 2)[2]} {v / MB:.2f}" for k, v in sorted(run.items())
            )
            print(
                f"[run] default protocol: {st['state']}, {t1 - t0:.0f} s of robot time "
                f"({wall:.0f} s wall); run dir {sum(run.values()) / MB:.1f} MB ({parts} MB); "
                f"rolling CAN log +{rolling / MB:.1f} MB; {rates(w0, w1, 1.0, 'MB')}"
            )


if __name__ == "__main__":
    main()
