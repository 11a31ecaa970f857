"""Calibration without motion capture (issue 20): identifiability, accuracy, honesty.

1. **Fisher information** of the default protocol (4 modules, 45/165 deg, Table-4 robot,
   rests and a 4 m straight drive; 2^17-count encoders, gyro 0.005 deg/s/sqrt(Hz) with a
   1e-4 deg/s/sqrt(s) bias walk, references 0.5 mm): rank, null space, condition number
   and the std devs of what odometry needs, for the encoders alone, with the gyro, with
   each kind of reference and with the chosen set
   (:mod:`swpc_hw.calibration.plan.identifiability`).
2. **Accuracy and honesty** over seeds, default gyro (bias 0.1 deg/s, scale error 0.3 %)
   and references (0.5 mm): truth = Table 4 (every seed other noise), and random robots
   with the paper's spread (P_s +-30 %, beta +-30 deg, b and r +-10 %, robot.yaml the
   design).  Frame-free figures (differences of beta, b, distances between steering
   axes, r): worst and RMS error; z = error / std dev of those and of x_s, y_s, beta in
   the design-fit frame against the truth expressed in it, and of the gyro's scale.
3. The motion-capture solver on the mocap dataset of the same runs (poses 0.5 mm /
   0.05 deg at 100 Hz), the first half of the Table-4 runs: the same frame-free errors.

``SWPC_BENCH_SEEDS`` sets the seeds per family (default 20).  Figures in
``docs/imu.md``; ``python -m benchmarks imu`` reproduces them.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import os
import time

import numpy as np

from simulators.offline.datagen_imu import (
    IMU_PROTOCOL,
    ReferenceOptions,
    fisher_setup,
    generate_imu_experiment,
)
from simulators.offline.random_robots import random_robots
from swpc_hw.calibration.gyro.solver import solve_imu
from swpc_hw.calibration.mocap.solver import solve
from swpc_hw.calibration.plan.identifiability import analyse
from swpc_hw.calibration.result import CalibrationResult
from swpc_hw.files.references import AxisDistance, WheelRadius
from swpc_hw.robot.frames import design_fit_transform, transform_parameters
from swpc_hw.robot.model import RobotParams
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED, PAPER_NOMINAL
from swpc_hw.sensors.gyro import GyroOptions

DEG = 180.0 / math.pi
FREE = ("d_beta", "b", "distance", "r")
"""Frame-free figures: unit factor (deg, mm) and requirement."""
UNIT = {"d_beta": (DEG, "deg", 0.05), "b": (1e3, "mm", 0.2), "distance": (1e3, "mm", 0.5),
        "r": (1e3, "mm", 0.05)}
Z_KINDS = ("d_beta", "b", "distance", "r", "x_s", "y_s", "beta", "gyro scale")
RUN = dataclasses.replace(
    IMU_PROTOCOL, pose_sigma_xy=0.5e-3, pose_sigma_yaw=math.radians(0.05)
)


def as_array(p: RobotParams) -> np.ndarray:
    a = p.arrays()
    return np.column_stack([a.P_s, a.beta, a.b, a.r])


def frame_free(X: np.ndarray) -> dict[str, list[tuple[float, np.ndarray]]]:
    """Every frame-free figure of (N, 5) parameters with its gradient (flat, 5N)."""
    n = X.shape[0]
    out: dict[str, list[tuple[float, np.ndarray]]] = {k: [] for k in FREE}
    for j in range(1, n):
        g = np.zeros(5 * n)
        g[5 * j + 2], g[2] = 1.0, -1.0
        out["d_beta"].append((X[j, 2] - X[0, 2], g))
    for j in range(n):
        for name, col in (("b", 3), ("r", 4)):
            g = np.zeros(5 * n)
            g[5 * j + col] = 1.0
            out[name].append((X[j, col], g))
    for j, k in itertools.combinations(range(n), 2):
        d = X[j, :2] - X[k, :2]
        L = float(np.linalg.norm(d))
        g = np.zeros(5 * n)
        g[5 * j : 5 * j + 2], g[5 * k : 5 * k + 2] = d / L, -d / L
        out["distance"].append((L, g))
    return out


def errors_and_z(
    res: CalibrationResult, truth: RobotParams, eps: float
) -> tuple[dict[str, list[float]], dict[str, list[float]]]:
    """Frame-free errors, and z of every kind (module docstring) of an IMU result."""
    X, T = as_array(res.params), as_array(truth)
    phi, t = design_fit_transform(T[:, :2], res.nominal.arrays().P_s)
    T_df = transform_parameters(T, phi, t)
    C = res.covariance if res.covariance is not None else np.full((X.size, X.size), np.nan)
    err: dict[str, list[float]] = {k: [] for k in FREE}
    z: dict[str, list[float]] = {k: [] for k in Z_KINDS}
    fx, ft = frame_free(X), frame_free(T)
    for k in FREE:
        for (est, g), (tru, _) in zip(fx[k], ft[k], strict=True):
            err[k].append(est - tru)
            z[k].append((est - tru) / math.sqrt(float(g @ C @ g)))
    std = res.stddev_array()
    for name, col in (("x_s", 0), ("y_s", 1), ("beta", 2)):
        z[name] += list((X[:, col] - T_df[:, col]) / std[:, col])
    q = res.imu
    if q is not None and q.gyro_scale_error_std:
        z["gyro scale"].append((q.gyro_scale_error - eps) / q.gyro_scale_error_std)
    return err, z


def mocap_errors(res: CalibrationResult, truth: RobotParams) -> dict[str, list[float]]:
    X, T = as_array(res.params), as_array(truth)
    return {
        k: [a - b for (a, _), (b, _) in zip(frame_free(X)[k], frame_free(T)[k], strict=True)]
        for k in FREE
    }


def family(
    name: str,
    truths: list[RobotParams],
    gyro: GyroOptions,
    mocap: int,
    references: ReferenceOptions | None = None,
) -> None:
    """Solve every truth's run; print accuracy and honesty, and the motion-capture solver's
    accuracy on the first ``mocap`` of the same runs."""
    err: dict[str, list[float]] = {k: [] for k in FREE}
    merr: dict[str, list[float]] = {k: [] for k in FREE}
    z: dict[str, list[float]] = {k: [] for k in Z_KINDS}
    times, failed = [], []
    for i, truth in enumerate(truths):
        opts = dataclasses.replace(RUN, seed=7000 + i)
        run = generate_imu_experiment(
            truth, opts, gyro, references=references, nominal=PAPER_NOMINAL
        )
        t0 = time.perf_counter()
        try:
            res = solve_imu(run.imu_dataset)
        except Exception as exc:  # a refusal is a finding, not a crash of the benchmark
            failed.append(f"seed {i}: {exc}")
            continue
        times.append(time.perf_counter() - t0)
        e, zz = errors_and_z(res, truth, gyro.scale_error)
        for k in FREE:
            err[k] += e[k]
        for k in Z_KINDS:
            z[k] += zz[k]
        if i < mocap:
            for k, v in mocap_errors(solve(run.mocap_dataset), truth).items():
                merr[k] += v
    n = len(truths)
    print(f"\n[{name}] {n} seeds, {len(times)} solved, median solve {np.median(times):.2f} s")
    for f in failed:
        print(f"[{name}] REFUSED/FAILED {f}")
    head = f"[{name}] {'figure':<9} {'unit':<4} {'worst':>8} {'RMS':>8} {'goal':>6} {'met':>4}"
    if mocap:
        head += f" {'mocap worst':>11} {'mocap RMS':>9} (first {mocap} runs)"
    print(head)
    for k in FREE:
        f, unit, goal = UNIT[k]
        a = np.abs(np.array(err[k])) * f
        line = (
            f"[{name}] {k:<9} {unit:<4} {a.max():8.4f} {np.sqrt(np.mean(a**2)):8.4f} "
            f"{goal:6.2f} {'yes' if a.max() <= goal else 'NO':>4}"
        )
        if mocap:
            m = np.abs(np.array(merr[k])) * f
            line += f" {m.max():11.4f} {np.sqrt(np.mean(m**2)):9.4f}"
        print(line)
    print(f"[{name}] {'z of':<10} {'n':>4} {'RMS z':>6} {'cover95':>8} {'mean z':>7}")
    for k in Z_KINDS:
        v = np.array(z[k])
        if v.size == 0:
            continue
        print(
            f"[{name}] {k:<10} {v.size:4d} {np.sqrt(np.mean(v**2)):6.2f} "
            f"{np.mean(np.abs(v) <= 1.96):8.3f} {v.mean():+7.2f}"
        )


def fisher_table() -> None:
    """Identifiability of the default protocol, every reference kind (module docstring)."""
    run, x = fisher_setup(
        PAPER_CALIBRATED, references=ReferenceOptions(wheel_radius_modules=(1, 2, 3, 4))
    )
    p = run.problem
    axes = [r for r in p.refs if isinstance(r, AxisDistance)]
    radii = [r for r in p.refs if isinstance(r, WheelRadius)]
    long_side = [r for r in axes if r.modules == (1, 4)]
    enc = {"settled", "spin", "locked_angle"}
    gyro = enc | {"gyro", "rest"}
    drive = {"drive", "straight_drive"}
    ax = {"axis_distance"}
    rows = [
        ("encoders only", enc, [], ()),
        ("+ gyro", gyro, [], ()),
        ("+ gyro, scale known", gyro, [], (p.layout.scale,)),
        ("+ gyro + axis_distance 1-4", gyro | ax, long_side, ()),
        ("+ gyro + 6 axis_distance", gyro | ax, axes, ()),
        ("+ gyro + 4 wheel_radius", gyro | {"wheel_radius"}, radii, ()),
        ("+ gyro + straight_drive", gyro | drive, [], ()),
        ("chosen: gyro, drive, 6 axes", gyro | drive | ax, axes, ()),
        ("chosen, every axis taped twice", gyro | drive | ax, axes + axes, ()),
        ("the same without the gyro", enc | drive | ax, axes, ()),
    ]
    print(
        "\n[fisher] default protocol, Table-4 robot: 2^17-count encoders, gyro 0.005 "
        "deg/s/sqrt(Hz), references 0.5 mm"
    )
    print(
        f"[fisher] {'experiment':<28} {'unknowns':>8} {'rank':>4} {'cond':>8}  null space "
        "(named) | std dev: r, length scale (ppm), beta_2-beta_1 (mdeg), b_1 (um), "
        "gyro scale (ppm)"
    )

    def fmt(v: float, f: float) -> str:
        return "free" if math.isinf(v) else ("-" if math.isnan(v) else f"{v * f:.3g}")

    for name, blocks, refs, known in rows:
        res = analyse(p.with_blocks(blocks).with_refs(refs), x, known=known)
        null = ", ".join(res.null) + (f" +{res.unexplained} more" if res.unexplained else "")
        s = res.std
        print(
            f"[fisher] {name:<28} {res.size:8d} {res.rank:4d} {res.condition:8.2g}  "
            f"{null or '-'} | {fmt(s['r'], 1e6)}, {fmt(s['length scale'], 1e6)}, "
            f"{fmt(s['beta difference'], 1e3)}, {fmt(s['b'], 1e3)}, "
            f"{fmt(s['gyro scale'], 1e6)}"
        )


def main() -> None:
    seeds = int(os.environ.get("SWPC_BENCH_SEEDS", "20"))
    t0 = time.perf_counter()
    fisher_table()
    print(f"[fisher] ({time.perf_counter() - t0:.1f} s)")
    gyro = GyroOptions()
    print(
        "\n[runs] gyro: bias 0.1 deg/s, walk 1e-4 deg/s/sqrt(s), scale error 0.3 %, "
        "0.005 deg/s/sqrt(Hz) at 200 Hz; 6 axis distances and a 4 m straight drive, 0.5 mm; "
        "2^17-count encoders; mocap solver: poses 0.5 mm / 0.05 deg at 100 Hz"
    )
    family("table4", [PAPER_CALIBRATED] * seeds, gyro, mocap=max(3, seeds // 2))
    robots = random_robots(seeds, np.random.default_rng(2020), PAPER_NOMINAL)
    family("random", [robots.robot(i, PAPER_NOMINAL.ids) for i in range(seeds)], gyro, 0)
    # the length scale is the tape's: every distance read twice (12 readings) halves its
    # variance (docs/imu.md, "The cheapest reference set")
    pairs = tuple(itertools.combinations(PAPER_NOMINAL.ids, 2)) * 2
    family("table4-taped-twice", [PAPER_CALIBRATED] * seeds, gyro, 0,
           ReferenceOptions(axis_pairs=pairs))
    print(
        "\n[runs] Table 4: one truth, so the encoders' quantization errors repeat in every "
        "seed; the random robots' z are the independent ones."
    )


if __name__ == "__main__":
    main()
