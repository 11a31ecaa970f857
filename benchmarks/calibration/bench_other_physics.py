"""The joint solver's covariance on data from other physics (issue 44, item 2).

The covariance had been checked only on this project's own kinematic simulators (rigid,
no slip).  Here the same calibration is played on a force-based physics with tyres
(:mod:`simulators.physics.tyres`, :mod:`simulators.offline.datagen_tyres`: tyre
compliance and friction, casters with inertia and friction, wheels driven by torque) and
the result is weighed by its own covariance against the hidden truth.

``SWPC_BENCH_OTHER_PHYSICS_RUNS`` truths (default 20): the paper's Table 4 robot perturbed
per truth as :mod:`benchmarks.calibration.bench_honesty` does (``P_s`` +-5 %, ``beta``
+-3 deg, ``b`` and ``r`` +-2 %; the same truths), a noise seed per truth, the nominal the
paper's design, mocap 0.5 mm / 0.05 deg at 100 Hz, 2^17-count encoders, the default
protocol (45 and 165 deg, 360 deg per spin at ~0.5 rad/s).  Per physics
(``SWPC_BENCH_OTHER_PHYSICS_VARIANTS``, comma-separated, default all):

* ``kinematic``: :func:`simulators.offline.datagen.generate_experiment` (the reference);
* ``tyres``: the tyre physics at its defaults (:class:`~simulators.physics.tyres.TyreOptions`);
* ``soft``: the same with a lateral stiffness 5x lower (``K_y`` 2e4 N/m);
* ``stiff``: towards the model: both stiffnesses 10x higher and no Coulomb friction on
  the steering (with it, casters on tyres that stiff shimmy);

and per physics: the NEES ``e' C^+ e / k`` over the whole covariance (mean, median, range,
the share of runs above the 95 % point of ``chi2(k) / k``), per kind (position ``x_s,
y_s, b``; ``beta``; radius ``r``) the RMS of ``z = e / sd`` and the largest error, per
parameter column the RMS error against the RMS std dev, and what the physics did (the
locked tread point's largest drift in a window, the yaw rates).

``python -m benchmarks.calibration.bench_other_physics`` (or ``python -m benchmarks
other_physics``).  About 8 s of one core per run on the tyre physics (~0.3 M steps of
0.5 ms), 0.1 s on the kinematic one: ~10 minutes for the default set.
"""

from __future__ import annotations

import dataclasses
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from benchmarks.calibration.bench_honesty import whole_and_kinds
from benchmarks.calibration.bench_plan import as_matrix, seed_truths
from simulators.offline import datagen, datagen_tyres
from simulators.physics.tyres import TyreOptions
from swpc_hw.calibration.mocap.solver import solve
from swpc_hw.calibration.plan.square_error import (
    AgainstTruth,
    against_truth,
    square_path_sensitivity,
)
from swpc_hw.errors import CalibrationError
from swpc_hw.files.dataset import Dataset
from swpc_hw.robot.model import PARAM_KINDS, PARAM_NAMES, RobotParams
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED, PAPER_NOMINAL

SIGMA_XY = 0.5e-3
SIGMA_YAW = math.radians(0.05)
PHYSICS: dict[str, TyreOptions] = {
    "tyres": TyreOptions(),
    "soft": dataclasses.replace(TyreOptions(), stiffness_y=2.0e4),
    "stiff": dataclasses.replace(TyreOptions(), steer_coulomb=0.0).stiffer(10.0),
}
"""The tyre physics' variants (``kinematic`` is datagen's)."""
DISPLAY = {"position": (1e3, "mm"), "beta": (180.0 / math.pi, "deg"), "radius": (1e3, "mm")}


Made = tuple[Dataset, float, tuple[float, float]]
"""A run's dataset, the locked tread point's largest drift (m) and the yaw rates' range."""


@dataclass
class Run:
    """One calibration against its truth."""

    against: AgainstTruth
    error: np.ndarray  # (N, 5) result - truth, beta wrapped
    sd: np.ndarray  # (N, 5) the reported std devs
    drift: float  # m, the locked tread point's largest drift in a window (0: kinematic)
    yaw_rates: tuple[float, float]  # rad/s, the windows' least and largest


def kinematic(truth: RobotParams, seed: int) -> Made:
    """The reference: datagen's rigid no-slip experiment with the same protocol and noise."""
    tyre = datagen_tyres.TyreExperimentOptions()
    opt = datagen.ExperimentOptions(
        yaw_rate=tyre.yaw_rate, spin_duration=tyre.sweep / tyre.yaw_rate,
        pose_sigma_xy=SIGMA_XY, pose_sigma_yaw=SIGMA_YAW, seed=seed,
    )  # fmt: skip
    ds = datagen.generate_experiment(truth, opt, PAPER_NOMINAL).dataset
    return ds, 0.0, (tyre.yaw_rate, tyre.yaw_rate)


def on_tyres(physics: TyreOptions) -> Callable[[RobotParams, int], Made]:
    """The experiment on the tyre physics ``physics``, noise as :func:`kinematic`'s."""

    def make(truth: RobotParams, seed: int) -> Made:
        opt = datagen_tyres.TyreExperimentOptions(
            physics=physics, pose_sigma_xy=SIGMA_XY, pose_sigma_yaw=SIGMA_YAW, seed=seed
        )
        ex = datagen_tyres.generate_experiment(truth, opt, PAPER_NOMINAL)
        rates = [s.yaw_rate for s in ex.spins]
        return ex.dataset, max(s.tread_drift for s in ex.spins), (min(rates), max(rates))

    return make


def runs(name: str, truths: list[RobotParams], S: np.ndarray) -> tuple[list[Run], int]:
    """Every truth on physics ``name``: the runs solved and how many the solver refused."""
    make = kinematic if name == "kinematic" else on_tyres(PHYSICS[name])
    out: list[Run] = []
    refused = 0
    for i, truth in enumerate(truths):
        t0 = time.perf_counter()
        ds, drift, rates = make(truth, 1 + i)
        t1 = time.perf_counter()
        try:
            res = solve(ds)
        except CalibrationError as exc:
            refused += 1
            print(f"  {name} truth {i}: refused ({exc})", flush=True)
            continue
        if res.covariance is None:
            refused += 1
            print(f"  {name} truth {i}: no covariance", flush=True)
            continue
        a = against_truth(res.params, res.covariance, truth, PAPER_NOMINAL, S)
        e = as_matrix(res.params) - as_matrix(truth)
        e[:, 2] = (e[:, 2] + math.pi) % (2.0 * math.pi) - math.pi
        out.append(Run(a, e, res.stddev_array(), drift, rates))
        z = ", ".join(f"{k} {a.rms_z[k]:.2f}" for k in PARAM_KINDS)
        print(f"  {name} truth {i}: NEES {a.nees:.2f}, RMS z {z}, locked tread drift "
              f"{drift * 1e6:.1f} um, data {t1 - t0:.1f} s + solve "
              f"{time.perf_counter() - t1:.1f} s", flush=True)  # fmt: skip
    return out, refused


def summary(name: str, rs: list[Run], refused: int) -> list[str]:
    if not rs:
        return [f"{name}: no run solved ({refused} refused)"]
    nees, dof, above, kinds = whole_and_kinds([r.against for r in rs])
    largest = ", ".join(
        f"{k} {max(r.against.largest[k] for r in rs) * DISPLAY[k][0]:.4f} {DISPLAY[k][1]}"
        for k in PARAM_KINDS
    )
    E = np.stack([r.error for r in rs])  # (runs, N, 5)
    SD = np.stack([r.sd for r in rs])
    scale = np.array([1e3, 1e3, 180.0 / math.pi, 1e3, 1e3])
    unit = ("mm", "mm", "deg", "mm", "mm")
    cols = ", ".join(
        f"{PARAM_NAMES[c]} {math.sqrt(float(np.mean(E[..., c] ** 2))) * scale[c]:.4f}/"
        f"{math.sqrt(float(np.mean(SD[..., c] ** 2))) * scale[c]:.4f} {unit[c]} (z "
        f"{math.sqrt(float(np.mean((E[..., c] / SD[..., c]) ** 2))):.2f}, mean error "
        f"{float(np.mean(E[..., c])) * scale[c]:+.4f})"
        for c in range(5)
    )
    drift = np.array([r.drift for r in rs]) * 1e6
    lo, hi = min(r.yaw_rates[0] for r in rs), max(r.yaw_rates[1] for r in rs)
    return [
        f"{name} ({len(rs)} runs, {refused} refused): NEES mean {nees.mean():.2f} (median "
        f"{np.median(nees):.2f}, {nees.min():.2f}-{nees.max():.2f}, {above:.0%} above the "
        f"chi2({dof}) 95 % point); RMS z {kinds}; largest errors {largest}",
        f"  per column, RMS error / RMS std dev: {cols}",
        f"  locked tread point's largest drift in a window: median {np.median(drift):.1f} um, "
        f"largest {drift.max():.1f} um; windows' yaw rates {lo:.3f}-{hi:.3f} rad/s",
    ]


def main() -> None:
    import logging

    logging.getLogger("swpc").setLevel(logging.ERROR)
    n = int(os.environ.get("SWPC_BENCH_OTHER_PHYSICS_RUNS", "20"))
    names = [
        s.strip()
        for s in os.environ.get(
            "SWPC_BENCH_OTHER_PHYSICS_VARIANTS", ",".join(["kinematic", *PHYSICS])
        ).split(",")
    ]
    truths = seed_truths(PAPER_CALIBRATED, n, 4400)
    S = square_path_sensitivity(PAPER_NOMINAL)
    print(f"[other physics] {n} truths (Table 4 +-5 % / 3 deg / 2 %, bench_honesty's), "
          "mocap 0.5 mm / 0.05 deg, 2^17 counts, the default protocol, joint solver")  # fmt: skip
    for name in names:
        if name in PHYSICS:
            print(f"[other physics] {name}: {PHYSICS[name].describe()}")
    lines: list[str] = []
    for name in names:
        t0 = time.perf_counter()
        rs, refused = runs(name, truths, S)
        block = summary(name, rs, refused)
        block[0] += f" [{time.perf_counter() - t0:.0f} s]"
        print("\n".join(block), flush=True)
        lines += block
    print("\n".join(["", "[other physics] summary", *lines]))


if __name__ == "__main__":
    main()
