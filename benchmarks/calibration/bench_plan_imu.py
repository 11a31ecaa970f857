"""The planner without motion capture (issue 34, ``metrology: imu``; docs/plan.md).

On the paper's robot (nominal: the design, truth: Table 4), the default requirement (the
robot config's tolerances; no square path, docs/plan.md says why):

1. **The plan** (``services.plan.planner.plan_for`` with ``metrology="imu"``), its predicted
   robot time and std devs, and the default protocol's (45 and 165 deg, 360 deg sweeps,
   settle 3 s, stop 1.5 s, rests 2 s, a 4 m drive) predicted the same way.
2. **Honesty, offline**: ``SWPC_BENCH_PLAN_SEEDS`` seeds (default 20) of each protocol
   through ``simulators.offline.datagen_imu`` (the gyro as the service's defaults, two tape
   readings per pair of steering axes and the drive's, 0.5 mm) solved by the IMU
   solver; per kind the RMS error, the RMS of ``z = error / predicted std dev`` (the
   goal 0.7-1.5) and of the solver's own z, in the ``design-fit`` frame (the truth
   re-expressed in it).
3. **Robot time through the service** (``SWPC_BENCH_PLAN_SERVICE=0`` skips): both
   protocols on the in-process simulator with Table 4 as its truth, the operator played
   (the tape's readings from the truth), against the prediction.
"""

from __future__ import annotations

import dataclasses
import math
import os
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.calibration.bench_check import TOKEN
from benchmarks.calibration.bench_plan import KINDS, SHOW, default_protocol
from services.config.robot import RobotConfig
from services.plan.planner import PlanRequest, plan_for, time_model
from services.plan.predict import imu_experiment_options, predicted_imu_covariance, tape_readings
from simulators.offline.datagen_imu import generate_imu_experiment
from swpc_hw.calibration.gyro.solver import solve_imu
from swpc_hw.calibration.plan.plan import Candidate, FloatArray, robot_time, stddevs
from swpc_hw.robot.frames import design_fit_transform, transform_parameters
from swpc_hw.robot.model import RobotParams
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED, PAPER_NOMINAL
from swpc_hw.sensors.gyro import GyroOptions


def in_design_fit(params: RobotParams, nominal: RobotParams) -> FloatArray:
    """(N, 5) parameters re-expressed in their design-fit frame against ``nominal``."""
    a = params.arrays()
    X = np.column_stack([a.P_s, a.beta, a.b, a.r])
    phi, t = design_fit_transform(a.P_s, nominal.arrays().P_s)
    return transform_parameters(X, phi, t)


def offline(
    c: Candidate, cfg: RobotConfig, truth: RobotParams, cov: FloatArray, seeds: int
) -> dict[str, Any]:
    """Per kind: RMS error, RMS z against the prediction and against the solver's own."""
    tm = time_model(cfg)
    nominal = cfg.nominal
    X_true = in_design_fit(truth, nominal)
    sd_pred = stddevs(cov)
    err, z_pred, z_own = [], [], []
    for s in range(seeds):
        opt = dataclasses.replace(imu_experiment_options(c, tm), seed=s)
        ie = generate_imu_experiment(truth, opt, None, tape_readings(nominal.ids), nominal)
        res = solve_imu(ie.imu_dataset)
        a = res.params.arrays()
        X = np.column_stack([a.P_s, a.beta, a.b, a.r])
        e = X - X_true
        e[:, 2] = (e[:, 2] + math.pi) % (2 * math.pi) - math.pi
        assert res.covariance is not None
        own = stddevs(np.asarray(res.covariance)[: e.size, : e.size])
        err.append(e)
        z_pred.append(e / sd_pred)
        z_own.append(e / own)
    E, Zp, Zo = (np.array(v) for v in (err, z_pred, z_own))
    out = {}
    for k, cols in KINDS.items():
        out[k] = (
            float(np.sqrt(np.mean(E[:, :, cols] ** 2))),
            float(np.sqrt(np.mean(Zp[:, :, cols] ** 2))),
            float(np.sqrt(np.mean(Zo[:, :, cols] ** 2))),
            float(np.max(sd_pred[:, cols])),
        )
    return out


def print_offline(label: str, t_pred: float, stats: dict[str, Any]) -> None:
    print(f"  {label}: predicted robot time {t_pred:.1f} s")
    for k, (rms, zp, zo, sd) in stats.items():
        f, unit = SHOW[k]
        print(f"    {k:<8} worst predicted sd {sd * f:.5f} {unit}, RMS error {rms * f:.5f} "
              f"{unit}, RMS z {zp:.2f} (against the solver's own sd {zo:.2f})")  # fmt: skip


def through_service(truth: RobotParams, body: dict[str, Any]) -> tuple[str, float]:
    """One calibration without motion capture on the in-process simulator (``truth``
    hidden), the operator played: its final state and robot time."""
    from fastapi.testclient import TestClient
    from pydantic import SecretStr

    from services.config.settings import ServiceSettings
    from services.http.app import create_app
    from swpc_hw.files.kinematic_file import save_kinematics

    auth = {"Authorization": f"Bearer {TOKEN}"}
    a = truth.arrays()
    refs = [
        {"kind": "axis_distance", "modules": [truth.ids[i], truth.ids[j]],
         "value": float(np.linalg.norm(a.P_s[i] - a.P_s[j])), "stddev": 0.5e-3}
        for i in range(len(truth.ids)) for j in range(i + 1, len(truth.ids))
    ] * 2  # fmt: skip
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "truth.yaml"
        save_kinematics(path, truth)
        settings = ServiceSettings(
            data_dir=Path(d) / "data", token=SecretStr(TOKEN), sim_truth=path,
            allowed_hosts=["testserver"],
        )  # fmt: skip
        with TestClient(create_app(settings)) as client:
            req = {"metrology": "imu", "references": refs, "install": "never", **body}
            deadline = time.monotonic() + 600
            while True:
                r = client.post("/calibrations", json=req, headers=auth)
                if r.status_code != 409 or time.monotonic() > deadline:
                    break
                time.sleep(0.2)  # the plan is being made
            assert r.status_code == 202, r.text
            rid = r.json()["id"]
            while True:
                st: dict[str, Any] = client.get(f"/calibrations/{rid}").json()
                if st["state"] in ("DONE", "FAILED", "ABORTED"):
                    return st["state"], float(st["elapsed_s"])
                assert time.monotonic() < deadline, st
                if st["state"] == "MARK":
                    client.post(f"/calibrations/{rid}/continue", headers=auth)
                elif st["state"] == "MEASURE":
                    tape = client.get("/simulator/tape-measure", params={"run": rid}).json()
                    ref = {k: tape[k] for k in ("kind", "value", "stddev")}
                    client.post(f"/calibrations/{rid}/references", json={"references": [ref]},
                                headers=auth)  # fmt: skip
                time.sleep(0.02)


def main() -> None:
    import logging

    logging.getLogger("swpc").setLevel(logging.ERROR)
    seeds = int(os.environ.get("SWPC_BENCH_PLAN_SEEDS", "20"))
    with_service = os.environ.get("SWPC_BENCH_PLAN_SERVICE", "1") != "0"
    cfg = RobotConfig(nominal=PAPER_NOMINAL)
    t0 = time.perf_counter()
    p = plan_for(cfg, PlanRequest(metrology="imu", budget=None))
    n_pred = sum(e.covariance is not None for e in p.tried)
    print(f"[plan_imu] paper's robot, default requirement (tolerances), {seeds} seeds; plan "
          f"{p.candidate.label()} ({time.perf_counter() - t0:.1f} s to plan, {n_pred} "
          "candidates predicted)")  # fmt: skip
    d = default_protocol(cfg, imu=True)
    tm = time_model(cfg)
    d_cov = predicted_imu_covariance(PAPER_NOMINAL, d, GyroOptions(), tm)
    print_offline("default", robot_time(d, 4, tm), offline(d, cfg, PAPER_CALIBRATED, d_cov, seeds))
    print_offline("planned", p.robot_time, offline(p.candidate, cfg, PAPER_CALIBRATED,
                                                   p.covariance, seeds))  # fmt: skip
    if with_service:
        for label, body, t_pred in (
            ("default", {}, robot_time(d, 4, tm)),
            ("planned", {"plan": "auto"}, p.robot_time),
        ):
            state, t = through_service(PAPER_CALIBRATED, body)
            print(f"  through the service, {label}: {state}, {t:.1f} s of robot time "
                  f"(predicted {t_pred:.1f} s)", flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
