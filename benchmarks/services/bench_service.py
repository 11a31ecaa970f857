"""Service benchmarks (issue: the calibration service).

1. Abort -> zero torque: a run is started and, once the robot is commanded (dynamic
   modules aligning, locked module held), ``POST /calibrations/{id}/abort`` is sent;
   the latency is wall time from the request to the moment the last of the 16 FREE/DISABLE
   frames left the driver (its bus's ``send`` returned; the bus stamps are simulated
   time).  p50 / p99 over ``SWPC_BENCH_ABORTS`` trials (default 60) with the in-process
   simulator paced at real time (``sim_speed`` 1, the robot's case) and over half as many
   at 4x real time and as fast as the host allows (``sim_speed`` 0: the simulator and the
   driver run flat out in the same interpreter and every thread hand-off waits for the GIL).
2. Pose ingest: a zenoh publisher paced at 1 kHz and 2 kHz for ``SWPC_BENCH_POSE_S``
   seconds (default 5), native and ROS 2 CDR, into :class:`MocapIngest` over loopback:
   sent, accepted, lost, latency p99, ingest CPU share.
3. One end-to-end calibration (the default protocol) through HTTP against the in-process
   simulator as fast as the host allows: wall time, robot time, the parameters' digest
   (skip with ``SWPC_BENCH_E2E=0``).
"""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path
from tempfile import TemporaryDirectory
from typing import Any

import can
import numpy as np
from fastapi.testclient import TestClient
from pydantic import SecretStr

from firmware_protocol import codec
from firmware_protocol.codec import ControlMode
from services.config.settings import ServiceSettings
from services.http.app import create_app
from services.sensors.mocap import MocapIngest
from swpc_hw.sensors.mocap import PoseEncoding, PoseSample, encode_pose
from swpc_hw.sensors.zenoh_session import free_tcp_endpoint, open_session

TOKEN = "bench-token-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


class StopWatch:
    """Wall time at which each FREE / DISABLE frame left the driver, per (node, axis):
    wraps the driver bus's ``send`` (python-can's virtual bus sends synchronously)."""

    def __init__(self, bus: can.BusABC) -> None:
        self.lock = threading.Lock()
        self.events: list[tuple[float, str, int, int]] = []
        self._send = bus.send

        def send(msg: can.Message, timeout: float | None = None) -> None:
            self._send(msg, timeout)
            self.record(time.perf_counter(), msg)

        bus.send = send  # type: ignore[method-assign]

    def record(self, t: float, msg: can.Message) -> None:
        try:
            d = codec.parse(msg.arbitration_id, bytes(msg.data))
        except codec.ProtocolError:
            return
        if isinstance(d, codec.SetControl) and d.mode == ControlMode.FREE:
            kind = "free"
        elif isinstance(d, codec.SetAxisState) and not d.enabled:
            kind = "disable"
        else:
            return
        node, _ = codec.split_id(msg.arbitration_id)
        with self.lock:
            self.events.append((t, kind, node, int(d.axis)))

    def last_stop_after(self, t0: float, nodes: set[int]) -> float | None:
        want = {(k, n, a) for k in ("free", "disable") for n in nodes for a in (0, 1)}
        with self.lock:
            seen: dict[tuple[str, int, int], float] = {}
            for t, k, n, a in self.events:
                if t >= t0 and (k, n, a) not in seen:
                    seen[(k, n, a)] = t
        if not want <= set(seen):
            return None
        return max(seen[w] for w in want)


def abort_latency(trials: int, sim_speed: float) -> None:
    with TemporaryDirectory() as tmp:
        settings = ServiceSettings(data_dir=Path(tmp), sim_speed=sim_speed, token=SecretStr(TOKEN))
        app = create_app(settings)
        with TestClient(app) as client:
            rt = app.state.runtime
            watch = StopWatch(rt.drives._bus)
            nodes = set(rt.config.drives.node_map().values())
            lat: list[float] = []
            for _ in range(trials):
                r = client.post("/calibrations", json={}, headers=AUTH)
                rid = r.json()["id"]
                deadline = time.monotonic() + 60
                while client.get(f"/calibrations/{rid}").json()["state"] not in (
                    "ALIGN",
                    "FREE",
                    "SPIN",
                ):
                    assert time.monotonic() < deadline, "run never moved"
                    time.sleep(0.005)
                t0 = time.perf_counter()
                client.post(f"/calibrations/{rid}/abort", headers=AUTH)
                end = watch.last_stop_after(t0, nodes)
                assert end is not None, "no zero-torque frames"
                lat.append(end - t0)
                st = client.get(f"/calibrations/{rid}").json()
                assert st["state"] == "ABORTED", st
    a = np.array(lat) * 1e3
    pace = {0.0: "as fast as the host allows", 1.0: "real time"}.get(
        sim_speed, f"{sim_speed:g}x real time"
    )
    print(
        f"[abort] in-process simulator at {pace}, {trials} aborts (HTTP request -> last "
        f"FREE/DISABLE frame of 4 nodes x 2 axes sent): "
        f"p50 {np.percentile(a, 50):.2f} ms, p99 {np.percentile(a, 99):.2f} ms, "
        f"max {a.max():.2f} ms (goal p99 <= 20 ms)"
    )


def pose_ingest(rate: float, seconds: float, encoding: PoseEncoding) -> None:
    ep = free_tcp_endpoint()
    pub_s = open_session(listen=[ep])
    sub_s = open_session(connect=[ep])
    ing = MocapIngest(encoding=encoding)
    try:
        ing.subscribe(sub_s, "mocap/bench/pose")
        pub = pub_s.declare_publisher("mocap/bench/pose")
        deadline = time.monotonic() + 5
        while ing.counters.accepted == 0 and time.monotonic() < deadline:
            pub.put(
                encode_pose(PoseSample.planar(-1.0 + time.monotonic() * 1e-9, 0, 0, 0), encoding)
            )
            time.sleep(0.01)
        base = ing.counters.received
        n = int(rate * seconds)
        payloads = [
            encode_pose(PoseSample.planar(i / rate, 0.001 * i, 0.0, 0.001 * i, i), encoding)
            for i in range(n)
        ]
        cpu0 = time.process_time()
        t0 = time.monotonic()
        for i, p in enumerate(payloads):
            target = t0 + i / rate
            while (now := time.monotonic()) < target:
                time.sleep(min(target - now, 0.0005))
            pub.put(p)
        wall = time.monotonic() - t0
        time.sleep(0.5)
        cpu = time.process_time() - cpu0
        got = ing.counters.received - base
        st = ing.stats()
        print(
            f"[ingest] {encoding.value:<8} {rate:6.0f} Hz for {seconds:g} s: sent {n}, received "
            f"{got}, accepted {ing.counters.accepted - 1 if ing.counters.accepted else 0}, "
            f"lost {n - got}, achieved {n / wall:.0f} Hz, latency p99 "
            f"{st.get('latency_p99_s', float('nan')) * 1e3:.2f} ms (relative to the fastest), "
            f"process CPU {100 * cpu / (wall + 0.5):.0f} % of a core (publisher + ingest)"
        )
    finally:
        ing.close()
        pub_s.close()
        sub_s.close()


def end_to_end() -> None:
    with TemporaryDirectory() as tmp:
        settings = ServiceSettings(data_dir=Path(tmp), token=SecretStr(TOKEN))
        app = create_app(settings)
        with TestClient(app) as client:
            clock = app.state.runtime.clock
            t0 = time.monotonic()
            rid = client.post("/calibrations", json={}, headers=AUTH).json()["id"]
            st: dict[str, Any] = {}
            while time.monotonic() - t0 < 300:
                st = client.get(f"/calibrations/{rid}").json()
                if st["state"] in ("DONE", "FAILED", "ABORTED"):
                    break
                time.sleep(0.1)
            wall = time.monotonic() - t0
            robot = clock.now()
            res = client.get(f"/calibrations/{rid}/result").json() if st["state"] == "DONE" else {}
    from swpc_hw.robot.paper_robot import PAPER_CALIBRATED

    worst_mm, worst_deg = 0.0, 0.0
    for m in res.get("modules", []):
        t = PAPER_CALIBRATED.module(m["id"])
        worst_mm = max(
            worst_mm, *(abs(m[k] - getattr(t, k)) * 1e3 for k in ("x_s", "y_s", "b", "r"))
        )
        worst_deg = max(worst_deg, abs(m["beta"] - t.beta) * 180 / np.pi)
    from services.demo import parameters_digest

    print(
        f"[e2e] full calibration through HTTP (4 modules x 2 angles, 360 deg spins, in-process "
        f"simulator): {st['state']} in {wall:.1f} s wall for {robot:.1f} s of robot time "
        f"({robot / wall:.1f}x); worst error {worst_mm:.4f} mm / {worst_deg:.4f} deg; "
        f"parameters digest {parameters_digest(res) if res else '-'}"
    )


def main() -> None:
    trials = int(os.environ.get("SWPC_BENCH_ABORTS", "60"))
    # real time is the robot's case; flat out shows the in-process simulator sharing the GIL
    abort_latency(trials, 1.0)
    abort_latency(max(trials // 2, 5), 4.0)
    abort_latency(max(trials // 2, 5), 0.0)
    secs = float(os.environ.get("SWPC_BENCH_POSE_S", "5"))
    for enc in (PoseEncoding.NATIVE, PoseEncoding.CDR):
        for rate in (1000.0, 2000.0):
            pose_ingest(rate, secs, enc)
    if os.environ.get("SWPC_BENCH_E2E", "1") != "0":
        end_to_end()


if __name__ == "__main__":
    main()
