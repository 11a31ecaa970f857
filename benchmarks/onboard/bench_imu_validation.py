"""The square path with an IMU calibration (issue 20): is it nearly as good as mocap?

For each robot (the paper's Table 4, then random robots with a real robot's build
deviations: steering axes within 1 % of the design (~2 mm), homing errors within
1.5 deg, offsets and radii within 2 %; nominal = the paper's design):

1. one simulated calibration run with the IMU protocol (rests, spins, a 4 m
   straight drive; :func:`simulators.offline.datagen_imu.generate_imu_experiment`), motion
   capture of the same run at the in-process default noise (0.5 mm / 0.05 deg, 100 Hz),
   the default gyro (bias 0.1 deg/s, scale error 0.3 %, 0.005 deg/s/sqrt(Hz)) and every
   axis distance plus the drive taped with 0.5 mm std dev;
2. two files: the motion-capture solver on the poses (frame R) and the IMU solver
   on the gyro, encoders and tape (frame design-fit);
3. ``swpc validate`` on the in-process simulator with that robot hidden in it: nominal,
   mocap and IMU files, each driving the square CW and CCW and used for odometry.

Printed: each file's mean end-pose errors, its reduction against the nominal file, and
the ratio of the IMU reduction to the mocap one (goal >= 0.90 in position and in
heading).  ``python -m benchmarks imu_validation``; ``SWPC_BENCH_VALIDATION_ROBOTS``
(default 3: Table 4 and two random robots), ``SWPC_BENCH_VALIDATION_SIDE`` (2.5 m),
``SWPC_BENCH_VALIDATION_RUNS`` (1 per direction).  Lockstep simulated time: a loaded host
slows it down, it cannot change the figures.
"""

from __future__ import annotations

import dataclasses
import math
import os
import time

import numpy as np

from swpc_hw.robot.model import RobotParams

DEG = math.pi / 180.0


def robots(count: int) -> list[tuple[str, RobotParams]]:
    """Table 4, then ``count - 1`` random robots with build deviations (module docstring)."""
    from simulators.offline.random_robots import random_robots
    from swpc_hw.robot.paper_robot import PAPER_CALIBRATED, PAPER_NOMINAL

    out = [("table 4", PAPER_CALIBRATED)]
    batch = random_robots(
        max(count - 1, 0), np.random.default_rng(2026), PAPER_NOMINAL,
        pos_frac=0.01, beta_max=1.5 * DEG, br_frac=0.02,
    )
    for i in range(count - 1):
        out.append((f"random {i + 1}", batch.robot(i, PAPER_NOMINAL.ids)))
    return out


def calibrate(truth: RobotParams, seed: int) -> tuple[RobotParams, RobotParams]:
    """The mocap and the IMU calibration of one simulated run of ``truth``."""
    from simulators.offline.datagen_imu import IMU_PROTOCOL, generate_imu_experiment
    from swpc_hw.calibration import solve
    from swpc_hw.calibration.gyro.solver import solve_imu
    from swpc_hw.robot.paper_robot import PAPER_NOMINAL

    opts = dataclasses.replace(
        IMU_PROTOCOL, pose_rate=100.0, pose_sigma_xy=0.5e-3,
        pose_sigma_yaw=0.05 * DEG, seed=seed,
    )
    run = generate_imu_experiment(truth, opts, nominal=PAPER_NOMINAL)
    return solve(run.mocap_dataset).params, solve_imu(run.imu_dataset).params


def main() -> None:
    from services.cli.offline.validate import run_in_process
    from services.config.robot import RobotConfig
    from swpc_hw.robot.paper_robot import PAPER_NOMINAL
    from swpc_hw.validation import SquareOptions

    count = int(os.environ.get("SWPC_BENCH_VALIDATION_ROBOTS", "3"))
    side = float(os.environ.get("SWPC_BENCH_VALIDATION_SIDE", "2.5"))
    runs = int(os.environ.get("SWPC_BENCH_VALIDATION_RUNS", "1"))
    options = SquareOptions(side=side, runs=runs)
    config = RobotConfig()
    print(f"[imu validation] {side:g} m square, CW and CCW, {runs} run(s) each, "
          f"{count} robot(s); goal: IMU reduction >= 0.90 x mocap reduction")
    ratios: dict[str, list[float]] = {"position": [], "heading": []}
    for i, (name, truth) in enumerate(robots(count)):
        t0 = time.perf_counter()
        mocap, free = calibrate(truth, seed=9100 + i)
        report = run_in_process(
            [("nominal", PAPER_NOMINAL), ("mocap", mocap), ("imu", free)],
            options, truth=truth, config=config,
        )
        s, reds = report.summary(), report.reductions()
        for label in report.labels:
            v = s[label]["all"]
            red = reds.get(label)
            extra = (f"  reduction {red['position'] * 100:6.2f} % / {red['heading'] * 100:6.2f} %"
                     if red else "")
            print(f"[imu validation] {name:<9} {label:<11} end error "
                  f"{v['position'] * 1e3:8.2f} mm {math.degrees(v['heading']):7.3f} deg{extra}")
        line = []
        for k in ("position", "heading"):
            ratio = reds["imu"][k] / reds["mocap"][k]
            ratios[k].append(ratio)
            line.append(f"{k} {ratio:.3f}")
        print(f"[imu validation] {name:<9} ratio of reductions (IMU / mocap): "
              f"{', '.join(line)}  ({time.perf_counter() - t0:.0f} s wall)", flush=True)
    worst = {k: min(v) for k, v in ratios.items()}
    met = all(v >= 0.9 for v in worst.values())
    print(f"[imu validation] worst ratio: position {worst['position']:.3f}, heading "
          f"{worst['heading']:.3f} (goal >= 0.90: {'met' if met else 'NOT met'})")


if __name__ == "__main__":
    main()
