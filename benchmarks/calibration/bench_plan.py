"""The planner's benchmark (issue 34: the same accuracy in less robot time; docs/plan.md).

For the paper's robot (nominal: the design, truth: Table 4) and ``SWPC_BENCH_PLAN_RANDOM``
random robots (default 3; ``simulators.offline.random_robots`` as the paper's Table 3: ``P_s``
+-30 %, ``beta`` +-30 deg, ``b`` and ``r`` +-10 % of the design; nominal: the truth
rounded as ``simulators.offline.datagen.default_nominal`` does), with the default requirement (the
robot
config's tolerances, the square path within 0.50 mm and 0.016 deg):

1. **The plan**: ``services.plan.planner.plan_for`` on the robot's config, its predicted
   robot time and std devs, and the default protocol's (4 modules x 45 and 165 deg x
   360 deg sweeps, settle 3 s, stop 1.5 s) predicted the same way.
2. **Errors reached, offline**: ``SWPC_BENCH_PLAN_SEEDS`` seeds (default 20) of each
   protocol through the offline generator at the time model's yaw rate, mocap 0.5 mm /
   0.05 deg at 100 Hz, 2^17-count encoders; the truth of each seed the robot's perturbed
   (``P_s`` +-5 %, ``beta`` +-3 deg, ``b`` and ``r`` +-2 %: the encoders' quantization
   differs between seeds as between real runs, as the solver's honesty benchmark).
   Per kind the RMS error, the largest, the RMS of ``z = error / predicted std dev``
   (the plan's honesty: the goal 0.7-1.5) and of the solver's own z; the square path's
   end error the parameter errors cause (``S dp``, CCW and CW: RMS, largest, and RMS z
   against its predicted std dev), and how many seeds end it within the budget (position
   and heading at once, the larger of CCW and CW: the requirement asks 90 %).  With
   sequential stopping, the robot time and the degrees each locked module's spins swept
   before the rule ended them (what a plan of per-module sweeps would plan).
3. **Robot time through the service** (``SWPC_BENCH_PLAN_SERVICE=0`` skips): one
   calibration per protocol on the in-process simulator with the robot as its hidden
   truth: the default (``{}``) and the plan (``{"plan": "auto"}``): robot time, and the
   result against the truth (largest |z| per kind, the square path's error it causes).
"""

from __future__ import annotations

import contextlib
import math
import os
import tempfile
import time
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.calibration.bench_check import TOKEN, start_and_wait
from services.config.robot import RobotConfig
from services.plan.planner import plan_for, stopping_for, time_model
from services.plan.predict import experiment_options, predicted_covariance
from simulators.offline.datagen import generate_experiment
from simulators.offline.random_robots import random_robots
from swpc_hw.calibration.mocap.solver import solve
from swpc_hw.calibration.plan.forecast import Stopping, forecast_covariance, replay
from swpc_hw.calibration.plan.plan import Candidate, MocapNoise, Plan, robot_time, stddevs
from swpc_hw.calibration.plan.square_error import (
    square_path_error,
    square_path_sd,
    square_path_sensitivity,
    square_path_within,
)
from swpc_hw.files.kinematic_file import save_kinematics
from swpc_hw.robot.model import PARAM_NAMES, RobotParams
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED, PAPER_NOMINAL

KINDS = {"position": [0, 1, 3], "beta": [2], "radius": [4]}
SHOW = {"position": (1e3, "mm"), "beta": (180.0 / math.pi, "deg"), "radius": (1e3, "mm")}


def default_protocol(cfg: RobotConfig, imu: bool = False) -> Candidate:
    """The robot config's own protocol as a candidate (``imu``: with its rests and drive)."""
    p = cfg.protocol
    return Candidate(
        tuple(p.angles_deg), p.sweep_deg, p.settle_time, p.stop_time, p.align_time,
        p.resteer_time, cfg.limits.spin_torque, p.rest_time if imu else None,
        p.drive_length if imu else None,
    )  # fmt: skip


def robots(n_random: int) -> list[tuple[str, RobotParams, RobotParams]]:
    """(name, nominal, truth): the paper's robot and ``n_random`` random ones."""
    out = [("paper's robot (Table 4)", PAPER_NOMINAL, PAPER_CALIBRATED)]
    batch = random_robots(n_random, np.random.default_rng(34), PAPER_NOMINAL)
    for i in range(n_random):
        truth = batch.robot(i, PAPER_NOMINAL.ids)
        out.append((f"random robot {i + 1}", rounded(truth), truth))
    return out


def rounded(truth: RobotParams) -> RobotParams:
    """A random robot's nominal: :func:`simulators.offline.datagen.default_nominal`'s rounding
    (``beta = 0``, ``P_s`` to 5 mm, ``b`` and ``r`` to 1 mm), whatever its ids."""
    a = truth.arrays()
    return RobotParams.from_arrays(
        a.ids, np.round(a.P_s / 0.005) * 0.005, np.zeros(a.n), np.round(a.b, 3),
        np.round(a.r, 3),
    )  # fmt: skip


def seed_truths(truth: RobotParams, n: int, salt: int) -> list[RobotParams]:
    batch = random_robots(
        n, np.random.default_rng(salt), truth, pos_frac=0.05, beta_max=math.radians(3.0),
        br_frac=0.02,
    )  # fmt: skip
    return [batch.robot(i, truth.ids) for i in range(n)]


def as_matrix(p: RobotParams) -> np.ndarray:
    return np.array([[getattr(m, k) for k in PARAM_NAMES] for m in p.modules])


def offline(
    c: Candidate, nominal: RobotParams, truths: list[RobotParams], cov: np.ndarray,
    cfg: RobotConfig, stopping: Stopping | None = None,
) -> dict[str, Any]:  # fmt: skip
    """Errors, z and the square path's error over the seeds of protocol ``c`` whose
    predicted covariance is ``cov``.  The square path's z: its end position's error (CCW
    and CW each) over its predicted std dev ``sqrt(var x + var y)``, its heading's over
    ``sqrt(var yaw)``.  With ``stopping``: every spin recorded to its most sweep and cut
    where sequential stopping ends it (:func:`swpc_hw.calibration.plan.forecast.replay`); the
    z then against each seed's final forecast, and ``robot_time`` the seeds' robot times
    (the plan's, less the sweep not spun at the time model's yaw rate)."""
    tm = time_model(cfg)
    S = square_path_sensitivity(nominal)
    err, z_pred, z_solver, sq_pos, sq_head, zsq_pos, zsq_head = [], [], [], [], [], [], []
    times, within = [], 0
    swept: dict[int, list[float]] = {}  # sequential stopping: the locked module's spins' sweeps
    for i, truth in enumerate(truths):
        if stopping is None:
            opts = experiment_options(c, MocapNoise(), tm, 1000 + i)
            res = solve(generate_experiment(truth, opts, nominal).dataset)
            seed_cov = cov
        else:
            longest = replace(c, sweep_deg=stopping.extension * c.sweep_deg + 5.0)
            opts = experiment_options(longest, MocapNoise(), tm, 1000 + i)
            ds = generate_experiment(truth, opts, nominal).dataset
            cut, got = replay(ds, stopping)
            res = solve(replace(ds, segments=cut))
            seed_cov = forecast_covariance(stopping.spins, got)
            unspun = sum(s.sweep - g.sweep for s, g in zip(stopping.spins, got, strict=True))
            for s, g in zip(stopping.spins, got, strict=True):
                swept.setdefault(s.module, []).append(math.degrees(g.sweep))
            times.append(robot_time(c, len(nominal.ids), tm) - unspun / tm.yaw_rate(c.spin_torque))
        predicted = stddevs(seed_cov)
        E_sq = S @ seed_cov @ S.T
        e = as_matrix(res.params) - as_matrix(truth)
        e[:, 2] = (e[:, 2] + math.pi) % (2 * math.pi) - math.pi
        err.append(e)
        z_pred.append(e / predicted)
        z_solver.append(e / res.stddev_array())
        d = S @ e.ravel()
        within += square_path_within(square_path_error(S, e.ravel()))
        for row in (0, 3):  # CCW, CW
            sq_pos.append(math.hypot(d[row], d[row + 1]))
            sq_head.append(abs(d[row + 2]))
            zsq_pos.append(sq_pos[-1] ** 2 / (E_sq[row, row] + E_sq[row + 1, row + 1]))
            zsq_head.append(sq_head[-1] ** 2 / E_sq[row + 2, row + 2])
    predicted = stddevs(cov)
    E, Zp, Zs = np.array(err), np.array(z_pred), np.array(z_solver)
    out: dict[str, Any] = {}
    for kind, cols in KINDS.items():
        out[kind] = {
            "rms": float(np.sqrt(np.mean(E[:, :, cols] ** 2))),
            "max": float(np.max(np.abs(E[:, :, cols]))),
            "z_pred": float(np.sqrt(np.mean(Zp[:, :, cols] ** 2))),
            "z_solver": float(np.sqrt(np.mean(Zs[:, :, cols] ** 2))),
            "sd_pred": float(np.max(predicted[:, cols])),
        }
    out["square"] = (
        float(np.sqrt(np.mean(np.square(sq_pos)))), float(np.max(sq_pos)),
        float(np.sqrt(np.mean(np.square(sq_head)))), float(np.max(sq_head)),
        float(np.sqrt(np.mean(zsq_pos))), float(np.sqrt(np.mean(zsq_head))),
    )  # fmt: skip
    out["robot_time"] = times
    out["swept"] = swept
    out["within"] = (within, len(truths))
    return out


def print_stats(
    label: str, t_pred: float, stats: dict[str, Any], sq_sd: tuple[float, float]
) -> None:
    sq = stats["square"]
    source = "final forecast" if stats["robot_time"] else "plan's sd"
    if stats["robot_time"]:
        t = stats["robot_time"]
        print(f"  {label}: robot time {np.mean(t):.1f} s on average ({min(t):.1f}-{max(t):.1f})"
              f" of the plan's {t_pred:.1f} s")  # fmt: skip
        per = ", ".join(
            f"{m + 1}: {np.mean(v):.0f} ({min(v):.0f}-{max(v):.0f})"
            for m, v in sorted(stats["swept"].items())
        )
        print(f"  {label}: deg swept per spin by locked module, mean (range): {per}")
    print(f"  {label}: predicted robot time {t_pred:.1f} s; square path predicted sd "
          f"{sq_sd[0] * 1e3:.3f} mm, {math.degrees(sq_sd[1]):.4f} deg; reached (CCW and CW) "
          f"RMS {sq[0] * 1e3:.3f} mm (largest {sq[1] * 1e3:.3f}), {math.degrees(sq[2]):.4f} "
          f"deg (largest {math.degrees(sq[3]):.4f}); RMS z {sq[4]:.2f}, {sq[5]:.2f}; within the "
          f"budget {stats['within'][0]} of {stats['within'][1]} seeds")  # fmt: skip
    for kind in KINDS:
        f, unit = SHOW[kind]
        s = stats[kind]
        print(f"    {kind:<8} worst predicted sd {s['sd_pred'] * f:8.5f} {unit}, error RMS "
              f"{s['rms'] * f:8.5f}, largest {s['max'] * f:8.5f}; RMS z ({source}) "
              f"{s['z_pred']:.2f}, (solver's) {s['z_solver']:.2f}")  # fmt: skip


@contextlib.contextmanager
def service(data: Path, truth: Path, robot_config: Path) -> Iterator[Any]:
    """The service on the in-process simulator (hidden truth ``truth``, the robot config
    ``robot_config``): a client."""
    from fastapi.testclient import TestClient
    from pydantic import SecretStr

    from services.config.settings import ServiceSettings
    from services.http.app import create_app

    s = ServiceSettings(
        data_dir=data, token=SecretStr(TOKEN), sim_truth=truth, sim_seed=1,
        robot_config=robot_config, allowed_hosts=["testserver"],
    )  # fmt: skip
    with TestClient(create_app(s)) as client:
        yield client


def through_service(nominal: RobotParams, truth: RobotParams) -> list[str]:
    """One calibration with the default protocol and one with ``plan: auto`` on the robot:
    per run its state, robot time and its result against the truth (largest |z| per kind
    with the run's own std devs, and the square path's end error ``S dp``)."""
    from swpc_hw.files.kinematic_file import load_kinematics

    S = square_path_sensitivity(nominal)
    out = []
    with tempfile.TemporaryDirectory() as tmp:
        data = Path(tmp)
        save_kinematics(data / "truth.yaml", truth)
        save_kinematics(data / "nominal.yaml", nominal)
        (data / "robot.yaml").write_text("nominal: nominal.yaml\n", encoding="utf-8")
        for label, body in (("default", {}), ("planned (sequential stopping)", {"plan": "auto"})):
            with service(data, data / "truth.yaml", data / "robot.yaml") as client:
                while body and client.get("/plan").status_code == 202:  # being made
                    time.sleep(0.1)
                st = start_and_wait(client, "calibrations", {**body, "install": "never"})
            if st["state"] != "DONE":
                out.append(f"{label}: {st['state']} ({st['reason']})")
                continue
            kf = load_kinematics(data / "runs" / st["id"] / "kinematics.yaml")
            e = as_matrix(kf.params) - as_matrix(truth)
            e[:, 2] = (e[:, 2] + math.pi) % (2 * math.pi) - math.pi
            sd = np.array([[getattr(m.stddev, k) for k in PARAM_NAMES] for m in kf.params.modules])
            z = np.abs(e / sd)
            zs = ", ".join(f"{k} {float(z[:, c].max()):.2f}" for k, c in KINDS.items())
            d = S @ e.ravel()
            pos = max(math.hypot(d[0], d[1]), math.hypot(d[3], d[4]))
            head = max(abs(d[2]), abs(d[5]))
            out.append(
                f"{label}: {st['elapsed_s']:.1f} s of robot time, largest |z| {zs}; square "
                f"path {pos * 1e3:.3f} mm, {math.degrees(head):.4f} deg"
            )
    return out


def main() -> None:
    import logging

    logging.getLogger("swpc").setLevel(logging.ERROR)
    seeds = int(os.environ.get("SWPC_BENCH_PLAN_SEEDS", "20"))
    n_random = int(os.environ.get("SWPC_BENCH_PLAN_RANDOM", "3"))
    with_service = os.environ.get("SWPC_BENCH_PLAN_SERVICE", "1") != "0"
    print(
        f"[plan] default requirement (tolerances; square path within 0.50 mm, 0.016 deg in "
        f"90 % of runs); "
        f"{seeds} seeds per protocol offline; mocap 0.5 mm / 0.05 deg at 100 Hz"
    )
    for r, (name, nominal, truth) in enumerate(robots(n_random)):
        cfg = RobotConfig(nominal=nominal)
        t0 = time.perf_counter()
        p: Plan = plan_for(cfg)
        t_plan = time.perf_counter() - t0
        c = p.candidate
        n_pred = sum(e.covariance is not None for e in p.tried)
        print(f"\n{name}: plan {c.label()}, settle {c.settle_time:g} s, stop {c.stop_time:g} "
              f"s, align {c.align_time:g} s ({t_plan:.0f} s to plan, {n_pred} candidates "
              "predicted)")  # fmt: skip
        d = default_protocol(cfg)
        tm = time_model(cfg)
        d_cov = predicted_covariance(nominal, d, MocapNoise(), tm)
        S = square_path_sensitivity(nominal)
        truths = seed_truths(truth, seeds, 100 + r)
        d_stats = offline(d, nominal, truths, d_cov, cfg)
        p_stats = offline(c, nominal, truths, p.covariance, cfg)
        print_stats("default", robot_time(d, 4, tm), d_stats, square_path_sd(S, d_cov))
        print_stats("planned", p.robot_time, p_stats, square_path_sd(S, p.covariance))
        stopping = stopping_for(cfg, p)
        s_stats = offline(c, nominal, truths, p.covariance, cfg, stopping)
        print_stats("planned, sequential stopping", p.robot_time, s_stats,
                    square_path_sd(S, p.covariance))  # fmt: skip
        if with_service:
            for line in through_service(nominal, truth):
                print(f"  through the service, {line}", flush=True)


if __name__ == "__main__":
    main()
