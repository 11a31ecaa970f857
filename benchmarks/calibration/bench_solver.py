"""Solver benchmarks (issue: foundation and solver).

1. The paper's Table 3, noiseless: 10,000 random robots (P_s within +-30 % of design,
   beta within +-30 deg, b and r within +-10 %), exact rotation data from
   ``simulators.offline.random_robots``, solved by the closed-form geometry vectorised over all
   trials.
   Plus the full joint solver on generator runs of a subset of those robots.
2. Noisy accuracy, truth = paper Table 4: mocap 0.5 mm / 0.05 deg at 100 Hz, encoders
   2^17 counts/rev, 20 seeds: RMSE of the paper's literal procedure and of the joint
   solver, side by side, with the ratio.
3. The same with 20 % pose dropouts, 1 % outlier poses (5 cm) and wheel slip bursts on
   the dynamic wheels: growth of the joint solver's RMSE versus the clean case.
4. Wall time of one full run (4 modules, 2 angles, 12 s per spin).
5. Honesty of the std devs: z = error / reported std dev of every parameter kind (and of
   the clock offset, estimated in these runs) over the seeds, with white and with AR(1)
   (rho 0.8) mocap noise: RMS z (1 when the std devs are right) and the share with
   |z| <= 1.96 (0.95 when right); and of the whole covariance, each run's NEES
   ``e' C^-1 e / 20`` (1 when its correlations are right too).  Truth: Table 4 perturbed
   per seed (P_s +-5 %, beta +-3 deg, b and r +-2 %), so that the encoders' quantization
   errors differ between seeds as between real runs; a true clock offset uniform in
   +-100 ms per seed.
6. The clock offset alone, default noise: true offsets 0, +-30 and +-200 ms; and a
   dataset of steady spins only (poses and encoders inside the segments), where it is not
   observable.
7. Slow slip: one wheel (module 2) slipping 0.4 % in 2 of its 6 rolling segments, over
   the whole segment, its last half or a quarter of it (and no slip, for the false
   alarms), default noise: increments cut out in and outside the slipping segments, and
   z of every parameter kind.

``SWPC_BENCH_SEEDS`` and ``SWPC_BENCH_TRIALS`` shrink the run for a quick look.
"""

from __future__ import annotations

import dataclasses
import math
import os
import time

import numpy as np

from simulators.offline.datagen import ExperimentOptions, PartialSlip, generate_experiment
from simulators.offline.random_robots import batch_experiment, random_robots
from swpc_hw.calibration import geometry as geo
from swpc_hw.calibration.mocap.baseline import solve_paper
from swpc_hw.calibration.mocap.solver import CalibrationResult, SolverOptions, solve
from swpc_hw.files.dataset import Dataset
from swpc_hw.robot.model import PARAM_NAMES, RobotParams
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED, PAPER_NOMINAL

NAMES = PARAM_NAMES
DISPLAY = np.array([1e3, 1e3, 180.0 / math.pi, 1e3, 1e3])  # mm, mm, deg, mm, mm
UNITS = ("mm", "mm", "deg", "mm", "mm")


def params_array(p: RobotParams) -> np.ndarray:
    return np.array([[getattr(m, k) for k in NAMES] for m in p.modules])


def result_array(r: CalibrationResult) -> np.ndarray:
    return params_array(r.params)


def closed_form_batch(exp: object) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Vectorised closed-form calibration of every trial: returns P_s, beta, b, r."""
    e = exp
    C_R, _ = geo.fixed_point(e.poses)  # type: ignore[attr-defined]  # (T, N, M, 2)
    angles = e.static_theta_hat  # type: ignore[attr-defined]  # (T, N, M)
    P_s, b, beta = geo.steering_circle_fit(C_R, angles)  # (T, N, 2), (T, N), (T, N)
    T, N, M = angles.shape
    # r: eq. (4) with D from the settled right angle, median over the 2(N-1) observations
    Pj = P_s[:, None, None, :, :]  # (T, 1, 1, N, 2)
    D = geo.rolling_distance_perpendicular(Pj, b[:, None, None, :], C_R[:, :, :, None, :])
    with np.errstate(divide="ignore", invalid="ignore"):  # static module: dpsi = 0, masked
        r_obs = geo.radius_from_rotation(D, e.dpsi, e.dyaw[..., None])  # type: ignore[attr-defined]
    mask = ~np.eye(N, dtype=bool)[None, :, None, :].repeat(T, 0).repeat(M, 2)
    r_obs = np.where(mask, r_obs, np.nan)
    r = np.nanmedian(r_obs.transpose(0, 3, 1, 2).reshape(T, N, -1), axis=-1)
    return P_s, beta, b, r


def table3(n_trials: int) -> None:
    rng = np.random.default_rng(2023)
    t0 = time.perf_counter()
    robots = random_robots(n_trials, rng)
    exp = batch_experiment(robots.P_s, robots.beta, robots.b, robots.r, seed=1)
    t1 = time.perf_counter()
    P_s, beta, b, r = closed_form_batch(exp)
    t2 = time.perf_counter()
    mae = {
        "P_s (m)": float(np.mean(np.linalg.norm(P_s - robots.P_s, axis=-1))),
        "beta (rad)": float(np.mean(np.abs(np.angle(np.exp(1j * (beta - robots.beta)))))),
        "b (m)": float(np.mean(np.abs(b - robots.b))),
        "r (m)": float(np.mean(np.abs(r - robots.r))),
    }
    print(f"[table3] {n_trials} random robots, 4 modules, 2 angles, noiseless")
    print(f"[table3] data {t1 - t0:.2f} s + closed-form solve {t2 - t1:.2f} s = {t2 - t0:.2f} s")
    e = generate_experiment(PAPER_CALIBRATED)
    print(f"[datagen] one default experiment (paper robot): {e.generation_seconds:.2f} s")
    for k, v in mae.items():
        print(f"[table3] MAE {k:<11} {v:.3e}   (paper Table 3: ~1e-16..1e-13; goal <= 1e-9)")
    # the joint solver on full generator runs of a subset of the same robots
    n_full = min(20, n_trials)
    errs = []
    t3 = time.perf_counter()
    for i in range(n_full):
        truth = robots.robot(i)
        ex = generate_experiment(truth, ExperimentOptions(counts_per_rev=None, seed=i))
        errs.append(np.abs(result_array(solve(ex.dataset)) - params_array(truth)))
    E = np.array(errs)
    print(
        f"[table3] joint solver on {n_full} full generator runs (trailing casters integrated): "
        + ", ".join(f"MAE {k} {E[..., i].mean():.1e}" for i, k in enumerate(NAMES))
        + f"  ({time.perf_counter() - t3:.1f} s)"
    )


def accuracy(seeds: int, robust: bool) -> tuple[np.ndarray, np.ndarray, float]:
    truth = PAPER_CALIBRATED
    X = params_array(truth)
    ej, ep = [], []
    times = []
    for seed in range(seeds):
        opts = ExperimentOptions(
            pose_sigma_xy=0.5e-3,
            pose_sigma_yaw=math.radians(0.05),
            counts_per_rev=2**17,
            seed=1000 + seed,
        )
        if robust:
            opts = dataclasses.replace(
                opts,
                dropout_fraction=0.20,
                outlier_fraction=0.01,
                outlier_magnitude=0.05,
                slip_burst_rate=0.2,
            )
        ds = generate_experiment(truth, opts).dataset
        t0 = time.perf_counter()
        ej.append(result_array(solve(ds)) - X)
        times.append(time.perf_counter() - t0)
        ep.append(result_array(solve_paper(ds)) - X)
    rmse_j = np.sqrt(np.mean(np.array(ej) ** 2, axis=(0, 1))) * DISPLAY
    rmse_p = np.sqrt(np.mean(np.array(ep) ** 2, axis=(0, 1))) * DISPLAY
    return rmse_p, rmse_j, float(np.median(times))


MOCAP = ExperimentOptions(pose_sigma_xy=0.5e-3, pose_sigma_yaw=math.radians(0.05))


NEES: list[float] = []
"""``e' C^-1 e / n`` of each run of :func:`z_statistics` (its whole covariance, the
clock offset's left out): about 1 when the covariance is honest, correlations and all."""


def z_statistics(seeds: int, rho: float) -> np.ndarray:
    """(seeds * N, 6) z of x_s, y_s, beta, b, r, offset (offset repeated per module); each
    run's NEES of the parameters to :data:`NEES`."""
    robots = random_robots(
        seeds, np.random.default_rng(22), PAPER_CALIBRATED,
        pos_frac=0.05, beta_max=math.radians(3.0), br_frac=0.02,
    )
    offsets = np.random.default_rng(23).uniform(-0.1, 0.1, seeds)
    rows = []
    for i in range(seeds):
        truth = robots.robot(i, PAPER_CALIBRATED.ids)
        opts = dataclasses.replace(
            MOCAP, pose_noise_rho=rho, clock_offset=float(offsets[i]), seed=4000 + i
        )
        ds = generate_experiment(truth, opts, PAPER_NOMINAL).dataset
        res = solve(ds, SolverOptions(time_offset="auto"))
        z = (result_array(res) - params_array(truth)) / res.stddev_array()
        if res.covariance is not None:
            e = (result_array(res) - params_array(truth)).ravel()
            NEES.append(float(e @ np.linalg.solve(res.covariance, e)) / e.size)
        std = res.time_offset_std if res.time_offset_std is not None else math.nan
        z_off = (res.time_offset - offsets[i]) / std
        rows.append(np.column_stack([z, np.full(z.shape[0], z_off)]))
    return np.vstack(rows)


def honesty(seeds: int) -> None:
    print(
        f"\n[z] z = error / reported std dev, {seeds} seeds x 4 modules, mocap 0.5 mm / "
        "0.05 deg, clock offset estimated (true: uniform +-100 ms)"
    )
    print(
        f"[z] {'param':<7} {'white RMS z':>11} {'cover95':>8} "
        f"{'AR(1) 0.8 RMS z':>16} {'cover95':>8}"
    )
    t0 = time.perf_counter()
    NEES.clear()
    Zw = z_statistics(seeds, 0.0)
    nees_w = np.array(NEES)
    NEES.clear()
    Za = z_statistics(seeds, 0.8)
    nees_a = np.array(NEES)
    for i, k in enumerate((*NAMES, "offset")):
        w, a = Zw[:, i], Za[:, i]
        if k == "offset":  # one value per run
            w, a = w[::4], a[::4]
        print(
            f"[z] {k:<7} {np.sqrt(np.mean(w**2)):11.2f} {np.mean(np.abs(w) <= 1.96):8.3f} "
            f"{np.sqrt(np.mean(a**2)):16.2f} {np.mean(np.abs(a) <= 1.96):8.3f}"
        )
    for name, n in (("white", nees_w), ("AR(1) 0.8", nees_a)):
        print(f"[z] the whole covariance, {name}: NEES e' C^-1 e / {5 * len(PAPER_CALIBRATED.ids)} "
              f"mean {n.mean():.2f}, median {np.median(n):.2f}, {n.min():.2f}-{n.max():.2f} "
              f"over {n.size} runs")  # fmt: skip
    print("[z] goal: RMS z within 0.7-1.5 and cover95 >= 0.9 for every kind, both noises")
    print(f"[z] ({time.perf_counter() - t0:.1f} s)")


def clock_offset(seeds: int) -> None:
    print(
        f"\n[offset] --time-offset auto, mocap 0.5 mm / 0.05 deg, {seeds} seeds per offset "
        "(other seeds for every offset)"
    )
    print(
        f"[offset] {'true':>7} {'max |err|':>10} {'mean std':>9} {'RMS z':>6} {'max |z|':>8}"
    )
    for i, true in enumerate((0.0, 0.03, -0.03, 0.2, -0.2)):
        err, std = [], []
        for seed in range(seeds):
            opts = dataclasses.replace(MOCAP, clock_offset=true, seed=5000 + 100 * i + seed)
            res = solve(generate_experiment(PAPER_CALIBRATED, opts).dataset,
                        SolverOptions(time_offset="auto"))
            err.append(res.time_offset - true)
            std.append(res.time_offset_std if res.time_offset_std is not None else math.nan)
        e, s = np.array(err), np.array(std)
        z = e / s
        print(
            f"[offset] {true * 1e3:5.0f}ms {np.abs(e).max() * 1e3:8.3f}ms {s.mean() * 1e3:7.3f}ms "
            f"{np.sqrt(np.mean(z**2)):6.2f} {np.abs(z).max():8.2f}"
        )
    print("[offset] goal: error <= 1 ms, |z| <= 3")
    ds = generate_experiment(PAPER_CALIBRATED, dataclasses.replace(MOCAP, clock_offset=0.2)).dataset

    def inside(t: np.ndarray) -> np.ndarray:
        return np.any([(t >= s.start) & (t <= s.end) for s in ds.segments], axis=0)

    only = Dataset(
        ds.robot, ds.poses[inside(ds.poses[:, 0])],
        {m: e[inside(e[:, 0] - 0.2)] for m, e in ds.encoders.items()}, ds.segments,
    )
    res = solve(only, SolverOptions(time_offset="auto"))
    print(
        f"[offset] steady spins only (true 200 ms): {res.time_offset_mode}, "
        f"{res.time_offset * 1e3:.1f} ms assumed"
    )


def slow_slip(seeds: int) -> None:
    """Module 2's wheel slips 0.4 % in segments 1 and 5 (locked modules 1 and 3)."""
    print(
        f"\n[slip] module 2's wheel slipping 0.4 % in 2 of its 6 rolling segments, mocap "
        f"0.5 mm / 0.05 deg, {seeds} seeds per case"
    )
    print(
        f"[slip] {'case':<14} {'cut in slip segs':>16} {'cut elsewhere':>13} "
        + " ".join(f"{'RMS z ' + k:>10}" for k in NAMES)
        + f" {'max |z|':>8}"
    )
    cases = {
        "no slip": None,
        "whole segment": (0.0, 1.0),
        "last half": (0.5, 1.0),
        "a quarter": (0.25, 0.5),
    }
    for name, part in cases.items():
        slips = () if part is None else tuple(PartialSlip(2, s, *part, 0.004) for s in (0, 4))
        cut_in, cut_out, zs = [], [], []
        for seed in range(seeds):
            opts = dataclasses.replace(MOCAP, partial_slips=slips, seed=6000 + seed)
            res = solve(generate_experiment(PAPER_CALIBRATED, opts).dataset)
            rej = {q.row: q.increments_rejected for q in res.segments}
            cut_in.append(rej[0] + rej[4])
            cut_out.append(sum(rej.values()) - rej[0] - rej[4])
            zs.append((result_array(res) - params_array(PAPER_CALIBRATED)) / res.stddev_array())
        Z = np.concatenate(zs)
        print(
            f"[slip] {name:<14} {np.mean(cut_in):16.1f} {np.mean(cut_out):13.1f} "
            + " ".join(f"{np.sqrt(np.mean(Z[:, i] ** 2)):10.2f}" for i in range(5))
            + f" {np.abs(Z).max():8.2f}"
        )
    print(
        "[slip] (mean wheel increments cut per run: 0.1 s each, a 12 s segment has ~120 per "
        "wheel; 'a quarter': 3 s of each 12 s segment)"
    )


def main() -> None:
    trials = int(os.environ.get("SWPC_BENCH_TRIALS", "10000"))
    seeds = int(os.environ.get("SWPC_BENCH_SEEDS", "20"))
    table3(trials)

    p_clean, j_clean, t_clean = accuracy(seeds, robust=False)
    print(
        f"\n[noisy] truth = Table 4, mocap 0.5 mm / 0.05 deg @100 Hz, 2^17 counts, {seeds} seeds"
    )
    print(f"[noisy] {'param':<6} {'unit':<4} {'paper RMSE':>11} {'joint RMSE':>11} {'ratio':>7}")
    for i, k in enumerate(NAMES):
        ratio = p_clean[i] / j_clean[i]
        print(f"[noisy] {k:<6} {UNITS[i]:<4} {p_clean[i]:11.5f} {j_clean[i]:11.5f} {ratio:6.1f}x")
    better = bool(np.all(j_clean < p_clean))
    print(f"[noisy] joint better than the paper on every parameter: {better}")

    p_rob, j_rob, t_rob = accuracy(seeds, robust=True)
    print("\n[robust] + 20 % pose dropouts, 1 % outliers (5 cm), slip bursts (0.2/s per wheel)")
    print(
        f"[robust] {'param':<6} {'unit':<4} {'paper RMSE':>11} {'joint RMSE':>11} "
        f"{'joint clean':>11} {'growth':>7}"
    )
    for i, k in enumerate(NAMES):
        g = j_rob[i] / j_clean[i]
        print(
            f"[robust] {k:<6} {UNITS[i]:<4} {p_rob[i]:11.5f} {j_rob[i]:11.5f} "
            f"{j_clean[i]:11.5f} {g:6.2f}x"
        )
    print(f"[robust] max growth {np.max(j_rob / j_clean):.2f}x (goal <= 2x)")

    print(
        f"\n[timing] one full run (4 modules, 2 angles, 12 s spins): median solve "
        f"{t_clean:.3f} s clean, {t_rob:.3f} s robust (goal <= 1 s)"
    )

    honesty(seeds)
    clock_offset(max(3, seeds // 2))
    slow_slip(max(3, seeds // 2))


if __name__ == "__main__":
    main()
