"""The planner without motion capture (``metrology: imu``, docs/plan.md): the time model
against the service's robot time, the prediction against a solve, the search, and a
planned run through the service on the in-process simulator."""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Any

import numpy as np
import pytest

from services.config.robot import RobotConfig
from services.plan.planner import MIN_IMU_WINDOW, PlanRequest, plan_for, time_model
from services.plan.predict import (
    imu_experiment_options,
    predicted_imu_covariance,
    tape_readings,
)
from simulators.offline.datagen_imu import fisher_setup, generate_imu_experiment
from swpc_hw.calibration.gyro.solver import solve_imu
from swpc_hw.calibration.plan.identifiability import gauge_directions
from swpc_hw.calibration.plan.plan import Candidate, Targets, TimeModel, robot_time, stddevs
from swpc_hw.calibration.plan.square_error import (
    SQUARE_BUDGET,
    square_path_sd,
    square_path_sensitivity,
)
from swpc_hw.robot.paper_robot import PAPER_NOMINAL
from swpc_hw.sensors.gyro import GyroOptions
from tests.service_rig import AUTH, Sim
from tests.services.whole_runs.test_calibration_without_mocap import axis_distances, play_operator

DEFAULT = Candidate((45.0, 165.0), 360.0, 3.0, 1.5, 1.0, 2.5, 0.6, 2.0, 4.0)
"""The robot config's default protocol without motion capture."""
SHORT = Candidate((45.0, 165.0), 90.0, 1.5, 1.0, 0.5, 2.5, 0.6, 1.0, 1.0)


def test_the_imu_time_model_takes_the_robot_time_the_service_measured() -> None:
    tm = TimeModel()
    # through the service on the in-process simulator (docs/plan.md): 168.8 s and 67.0 s
    # before the gyro's fast part (2026-11-30), whose four probes took 13.1-15.6 s since
    assert robot_time(DEFAULT, 4, tm) == pytest.approx(168.8 + 4 * tm.probe, abs=1.0)
    assert robot_time(SHORT, 4, tm) == pytest.approx(67.0 + 4 * tm.probe, abs=1.0)
    # the mocap protocol's time plus 11 rests (8 spins, after the last, around the drive);
    # both start with the fast part (four modules)
    mocap = dataclasses.replace(SHORT, rest_time=None, drive_length=None)
    assert robot_time(SHORT, 4, tm) - robot_time(mocap, 4, tm) == pytest.approx(
        11 * 1.0 + 1.0 / 0.325 + 1.85
    )
    # a robot of three modules (9 rests) has no fast part with the gyro alone
    assert robot_time(SHORT, 3, tm) - robot_time(mocap, 3, tm) == pytest.approx(
        9 * 1.0 + 1.0 / 0.325 + 1.85 - 3 * tm.probe
    )
    # a 3 m drive took 6.07 s more than the 1 m one (the service: 11.97 s and 5.89 s)
    longer = dataclasses.replace(SHORT, drive_length=3.0)
    assert robot_time(longer, 4, tm) - robot_time(SHORT, 4, tm) == pytest.approx(6.08, abs=0.1)


def test_the_prediction_is_a_solves_covariance_in_design_fit() -> None:
    tm = TimeModel()
    c = dataclasses.replace(SHORT, spin_torque=1.03)
    cov = predicted_imu_covariance(PAPER_NOMINAL, c, GyroOptions(), tm)
    opt = dataclasses.replace(imu_experiment_options(c, tm), seed=3)
    ie = generate_imu_experiment(PAPER_NOMINAL, opt, None, tape_readings(PAPER_NOMINAL.ids))
    res = solve_imu(ie.imu_dataset)
    assert res.params.frame == "design-fit" and res.covariance is not None
    solved = stddevs(np.asarray(res.covariance)[:20, :20])
    np.testing.assert_allclose(stddevs(cov), solved, rtol=0.05)
    # the tape: x_s 0.076 mm whatever the robot does; r 0.027 mm from a 1 m drive
    assert np.max(stddevs(cov)[:, 0]) == pytest.approx(0.0764e-3, rel=0.02)
    assert np.max(stddevs(cov)[:, 4]) == pytest.approx(0.0275e-3, rel=0.05)


def test_the_square_path_is_frame_free_but_tape_bound_without_motion_capture() -> None:
    S = square_path_sensitivity(PAPER_NOMINAL)
    run, x = fisher_setup(PAPER_NOMINAL, imu_experiment_options(DEFAULT, TimeModel()))
    g = gauge_directions(run.problem, x)
    for name in ("translation x", "translation y", "rotation"):  # the design-fit frame's
        assert np.max(np.abs(S @ g[name][:20])) < 1e-6
    assert np.max(np.abs(S @ g["length scale"][:20])) > 1.0  # what only the tape fixes
    cov = predicted_imu_covariance(PAPER_NOMINAL, DEFAULT, GyroOptions(), TimeModel())
    pos, head = square_path_sd(S, cov)
    assert pos > 8 * SQUARE_BUDGET[0] and head > 8 * SQUARE_BUDGET[1]  # 4.19 mm, 0.136 deg


def test_the_plan_without_motion_capture_is_the_fastest_that_meets_the_targets() -> None:
    cfg = RobotConfig()
    p = plan_for(cfg, PlanRequest(metrology="imu", budget=None))
    c = p.candidate
    assert (c.angles_deg, c.sweep_deg, c.spin_torque) == ((45.0, 165.0), 75.0, 1.03)
    assert (c.rest_time, c.drive_length) == (1.0, 1.0)
    assert time_model(cfg).window(c) >= MIN_IMU_WINDOW  # 60 deg would be 1.03 s
    # 55.9 s before the fast part; the planned run through the service takes 70.2 s
    assert p.robot_time == pytest.approx(69.5, abs=0.1) and p.ratio <= 1.0
    assert c.overrides()["protocol"]["rest_time"] == 1.0
    # r within 0.015 mm needs a longer drive (1 m: 0.0275 mm)
    tight = Targets(cfg.tolerances.position, cfg.tolerances.beta, 0.015e-3)
    q = plan_for(cfg, PlanRequest(metrology="imu", budget=None, targets=tight))
    assert q.candidate.drive_length == 2.0 and np.max(q.stddev[:, 4]) <= 0.015e-3


def test_a_planned_calibration_without_motion_capture_runs_to_done(sim: Sim) -> None:
    body: dict[str, Any] = {
        "plan": "auto", "metrology": "imu", "references": axis_distances() * 2,
        "install": "never",
    }  # fmt: skip
    client = sim.client
    deadline = time.monotonic() + 600  # a guard against a hang, never a judgement
    while (r := client.post("/calibrations", json=body, headers=AUTH)).status_code == 409:
        # the plan is being made in the background (a second or two of CPU): every 0.1 s,
        # a POST without a pause (270 of them) took the GIL from it and doubled its time
        assert "being made" in r.text and time.monotonic() < deadline, r.text
        time.sleep(0.1)
    assert r.status_code == 202, r.text
    predicted = client.get("/plan", params={"metrology": "imu"}).json()
    st = play_operator(client, r.json()["id"], {})
    assert st["state"] == "DONE", st["errors"]
    assert st["segments"] == 8
    assert st["elapsed_s"] == pytest.approx(predicted["robot_time_s"], abs=1.5)
    res = client.get(f"/calibrations/{st['id']}/result").json()
    worst = max(m["stddev"]["x_s"] for m in res["modules"])
    assert worst == pytest.approx(predicted["predicted"][0]["x_s_mm"] * 1e-3, rel=0.1)
    # what the plan chooses may not be set too
    again = dict(body, overrides={"protocol": {"rest_time": 2.0}})
    r = client.post("/calibrations", json=again, headers=AUTH)
    assert r.status_code == 422 and "plan auto chooses protocol.rest_time" in r.text
    assert math.isfinite(predicted["ratio"]) and predicted["ratio"] <= 1.0
