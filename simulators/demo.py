"""``make demo``: a whole calibration on the embedded default, offline.

Generates a simulated calibration run of the paper's robot (truth = Table 4 calibrated
values, prior = nominal design) with realistic sensor noise, writes it as a dataset
directory, solves it with ``swpc solve`` and prints nominal / calibrated / true values.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

from simulators.datagen import ExperimentOptions, generate_experiment
from swpc_hw.cli import main as swpc_main
from swpc_hw.reference import PAPER_CALIBRATED


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="out/demo", help="output directory (default out/demo)")
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    opts = ExperimentOptions(
        pose_sigma_xy=0.5e-3,
        pose_sigma_yaw=math.radians(0.05),
        counts_per_rev=2**17,
        dropout_fraction=0.05,
        outlier_fraction=0.005,
        slip_burst_rate=0.1,
        seed=args.seed,
    )
    t0 = time.perf_counter()
    exp = generate_experiment(PAPER_CALIBRATED, opts)
    dataset = out / "dataset"
    exp.save(dataset)
    print(
        f"simulated run: {len(exp.dataset.segments)} spins, {exp.dataset.poses.shape[0]} poses, "
        f"{exp.duration:.0f} s of robot time -> {dataset} ({time.perf_counter() - t0:.2f} s)\n"
        f"noise: mocap 0.5 mm / 0.05 deg, 5 % dropouts, 0.5 % outliers, wheel slip bursts\n"
    )
    kin = out / "kinematics.yaml"
    return swpc_main(
        ["solve", str(dataset), "-o", str(kin), "--truth", str(dataset / "truth.yaml")]
    )


if __name__ == "__main__":
    sys.exit(main())
