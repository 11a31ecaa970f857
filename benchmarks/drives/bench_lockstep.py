"""What a second of simulated robot time costs in lockstep (issue 41: the suite's time).

Every whole run of ``make test``, the console's browser tests and ``make demo`` runs the
in-process simulator as fast as the host allows, so their wall time is CPU time.

1. The physics step (:meth:`RobotPhysics.step`), microseconds per step: a spin (module 1
   pinned, the three others' wheels at a torque, their casters trailing) and a drive
   (two modules steered and driven, two free).
2. One calibration through the service on the in-process simulator (the short protocol of
   the test suite's whole runs: 45 deg spins, 1 s settles, the fast part first): robot
   time, wall time, the process's CPU and the simulator thread's, the physics steps and
   frames, and robot seconds per CPU second.  ``SWPC_BENCH_LOCKSTEP_RUNS`` runs (default 2,
   the first pays the imports).

``python -m benchmarks.drives.bench_lockstep``; part 2 takes about 15 s a run here.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from tempfile import TemporaryDirectory

from fastapi.testclient import TestClient
from pydantic import SecretStr

from benchmarks.services.bench_soak import AUTH, TOKEN
from benchmarks.services.bench_soak import PROTOCOL as SHORT
from services.config.settings import ServiceSettings
from services.http.app import create_app
from simulators.physics.robot import ModuleDrive, RobotPhysics, SteerDrive, WheelDrive


def physics_step_us(drives: list[ModuleDrive], steps: int = 3000) -> float:
    p = RobotPhysics(theta0=[0.3, -0.2, 1.0, 2.0])
    t0 = time.perf_counter()
    for _ in range(steps):
        p.step(0.01, drives)
    return (time.perf_counter() - t0) / steps * 1e6


def one_run() -> dict[str, float]:
    with TemporaryDirectory() as d:
        settings = ServiceSettings(
            data_dir=Path(d), token=SecretStr(TOKEN), allowed_hosts=["testserver"]
        )
        app = create_app(settings)
        with TestClient(app) as client:
            rt = app.state.runtime
            w0, c0 = time.monotonic(), time.process_time()
            r = client.post("/calibrations", json={"overrides": {"protocol": SHORT}},
                            headers=AUTH)  # fmt: skip
            r.raise_for_status()
            rid = r.json()["id"]
            while (st := client.get(f"/calibrations/{rid}").json())["state"] not in {
                "DONE", "FAILED", "ABORTED"
            }:
                time.sleep(0.05)
            wall, cpu = time.monotonic() - w0, time.process_time() - c0
            sim = rt.simulator
            stats = sim.stats()
            return {
                "state_done": float(st["state"] == "DONE"),
                "robot_s": float(st["elapsed_s"]),
                "wall_s": wall,
                "cpu_s": cpu,
                "sim_cpu_s": stats.cpu_time,
                "steps": float(sim.robot.steps),
                "frames": float(stats.frames_tx + stats.frames_rx),
            }


def main() -> None:
    spin = [ModuleDrive(SteerDrive.RATE, 0.0, WheelDrive.BRAKE, 0.0)] + [
        ModuleDrive(SteerDrive.PASSIVE, 0.0, WheelDrive.TORQUE, 0.6)
    ] * 3
    drive = [ModuleDrive(SteerDrive.RATE, 0.5, WheelDrive.RATE, 1.0)] * 2 + [
        ModuleDrive(SteerDrive.PASSIVE, 0.0, WheelDrive.PASSIVE, 0.0)
    ] * 2
    print(f"physics step: spin {physics_step_us(spin):.0f} us, "
          f"drive {physics_step_us(drive):.0f} us")  # fmt: skip
    for i in range(int(os.environ.get("SWPC_BENCH_LOCKSTEP_RUNS", "2"))):
        r = one_run()
        print(
            f"run {i + 1}: {'DONE' if r['state_done'] else 'NOT DONE'}, {r['robot_s']:.1f} s "
            f"of robot time in {r['wall_s']:.1f} s wall, {r['cpu_s']:.1f} s CPU (simulator "
            f"thread {r['sim_cpu_s']:.1f} s); {r['steps']:.0f} physics steps, "
            f"{r['frames']:.0f} frames; {r['robot_s'] / r['cpu_s']:.2f} robot s per CPU s"
        )


if __name__ == "__main__":
    main()
