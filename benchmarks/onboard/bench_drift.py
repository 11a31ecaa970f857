"""Calibration suspect: metres of normal driving until a drifted module is flagged, and false
alarms per hour on a correct robot (``python -m benchmarks drift``).

The paper's calibrated robot is the kinematic file; the true robot is that file with one
module's wheel radius -0.3 mm (or its homing error +0.3 deg), the module taking turns over
the seeds.  The path: :func:`simulators.offline.drift_path.mixed_segments` (straights, arcs,
strafes, spins, stops at several speeds) read at 200 Hz (the robot config's feedback
rate) with 2^17-count encoders, slip noise 0.2 % and a slip burst (5 %, 0.3 s) per wheel a
minute (:class:`simulators.offline.drift_path.PathNoise`).  Detection runs stop at the first
suspect raised (cap: 20 min of driving); "right" is the drifted module and parameter.
"""

from __future__ import annotations

import math
import statistics
import time

from simulators.offline.drift_path import mixed_segments, observe_drive, with_error
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED

SEEDS = 10
CAP_S = 1200.0
FA_SEEDS = 6
FA_S = 1800.0


def _detect(label: str, parameter: str, dr: float, dbeta: float) -> None:
    ids = PAPER_CALIBRATED.ids
    metres: list[float] = []
    right = 0
    missed = 0
    for seed in range(1, SEEDS + 1):
        module = ids[(seed - 1) % len(ids)]
        truth = with_error(PAPER_CALIBRATED, module, dr=dr, dbeta=dbeta)
        run = observe_drive(truth, PAPER_CALIBRATED, mixed_segments(CAP_S, seed), seed=seed,
                            stop_at_first=True)
        raised = [c.suspect for c in run.changes if c.raised]
        if not raised:
            missed += 1
            continue
        s = raised[0]
        metres.append(s.metres)
        right += s.module == module and s.parameter == parameter
    med = statistics.median(metres) if metres else math.nan
    worst = max(metres) if metres else math.nan
    print(f"{label:<22} {SEEDS:>5} {med:>10.1f} {worst:>10.1f} {right:>6} {missed:>7}")


def main() -> None:
    t0 = time.process_time()
    print(f"drift detection, {SEEDS} seeds (drifted module: seed's turn), cap "
          f"{CAP_S / 60:.0f} min of driving")
    print(f"{'true robot':<22} {'seeds':>5} {'median m':>10} {'worst m':>10} {'right':>6} "
          f"{'missed':>7}")
    _detect("r -0.3 mm, one wheel", "r", -0.3e-3, 0.0)
    _detect("beta +0.3 deg, one", "beta", 0.0, math.radians(0.3))
    alarms = 0
    seconds = 0.0
    metres = 0.0
    for seed in range(101, 101 + FA_SEEDS):
        run = observe_drive(PAPER_CALIBRATED, PAPER_CALIBRATED, mixed_segments(FA_S, seed),
                            seed=seed)
        alarms += sum(c.raised for c in run.changes)
        seconds += run.seconds
        metres += run.metres
    hours = seconds / 3600.0
    print(f"correct robot: {alarms} false alarms in {hours:.1f} h ({metres / 1000:.1f} km, "
          f"{FA_SEEDS} seeds): {alarms / hours:.2f} per hour")
    print(f"CPU {time.process_time() - t0:.0f} s")


if __name__ == "__main__":
    main()
