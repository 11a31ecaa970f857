"""Square-path validation benchmark: the paper's Table 5 in simulation.

1. Calibrated file: the seed experiment simulated on the paper's Table 4 robot with the
   in-process default mocap noise (0.5 mm / 0.05 deg at 100 Hz, encoders 2**17 counts/turn,
   :func:`simulators.offline.datagen.generate_experiment`), solved offline
   (:func:`swpc_hw.calibration.solve`); nominal = :data:`swpc_hw.robot.paper_robot.PAPER_NOMINAL`.
2. The validation drive (:mod:`swpc_hw.validation`) on the in-process simulator (truth =
   Table 4): 2.5 m square, CW and CCW, 4 runs each, 0.2 m/s, each file used for control and
   odometry; prints the per-run errors and the Table-5-like comparison, writes
   ``out/validation/`` (table, JSON, Figure-13-like PNG, the solved kinematic file).

``python -m benchmarks validation``.  The full test is ~1520 s of robot time, in simulated
time (lockstep: a loaded host slows it down and cannot change it).
``SWPC_BENCH_VALIDATION_SIDE`` / ``_RUNS`` change it.
"""

from __future__ import annotations

import json
import math
import os
import time
from pathlib import Path

from swpc_hw.robot.model import RobotParams

OUT = Path("out/validation")


def offline_calibrated(seed: int = 0) -> RobotParams:
    """Table 4 robot, seed experiment with the in-process default noise, solved offline."""
    from simulators.offline.datagen import ExperimentOptions, generate_experiment
    from swpc_hw.calibration import solve
    from swpc_hw.robot.paper_robot import PAPER_CALIBRATED, PAPER_NOMINAL

    opt = ExperimentOptions(
        pose_rate=100.0, pose_sigma_xy=0.5e-3, pose_sigma_yaw=math.radians(0.05), seed=seed
    )
    exp = generate_experiment(PAPER_CALIBRATED, opt, PAPER_NOMINAL)
    return solve(exp.dataset).params


def main() -> None:
    from services.cli.offline.validate import run_in_process
    from swpc_hw.files.kinematic_file import save_kinematics
    from swpc_hw.robot.paper_robot import PAPER_NOMINAL
    from swpc_hw.validation import SquareOptions

    side = float(os.environ.get("SWPC_BENCH_VALIDATION_SIDE", "2.5"))
    runs = int(os.environ.get("SWPC_BENCH_VALIDATION_RUNS", "4"))
    OUT.mkdir(parents=True, exist_ok=True)
    calibrated = offline_calibrated()
    save_kinematics(OUT / "kinematics-offline.yaml", calibrated,
                    extra={"note": "offline solve of a simulated run, in-process default noise"})
    t0 = time.perf_counter()
    report = run_in_process(
        [("nominal", PAPER_NOMINAL), ("calibrated", calibrated)],
        SquareOptions(side=side, runs=runs),
        log=lambda m: print(m, flush=True),
    )
    wall = time.perf_counter() - t0
    report.files = {"nominal": "swpc_hw.robot.paper_robot.PAPER_NOMINAL",
                    "calibrated": str(OUT / "kinematics-offline.yaml")}
    table = report.table()
    print()
    print(table)
    red = report.reduction() or {}
    print(f"\npaper (hardware): 467.4 mm -> 165.5 mm (64.6 %), 9.67 deg -> 1.92 deg (80.15 %); "
          f"here: {red.get('position', math.nan) * 100:.1f} % / "
          f"{red.get('heading', math.nan) * 100:.1f} % (goal >= 95 %)")
    print(f"{len(report.results)} squares of {side:g} m in {wall:.0f} s wall (in-process "
          "simulator, lockstep)")
    (OUT / "validation.txt").write_text(table + "\n", encoding="utf-8")
    (OUT / "validation.json").write_text(json.dumps(report.to_document(), indent=2) + "\n",
                                         encoding="utf-8")
    report.plot(str(OUT / "validation.png"))
    print(f"wrote {OUT}/validation.txt, validation.json, validation.png")


if __name__ == "__main__":
    main()
