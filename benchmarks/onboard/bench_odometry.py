"""Odometry update rate on one core, 4 modules (goal >= 20 kHz: 500 Hz feedback < 2.5 % of a core).

Readings: the paper's calibrated robot on an arc (v = 0.2 m/s, omega = 0.3 rad/s) sampled at
500 Hz and quantized to 2^17 counts/rev; variants with steering that keeps changing and with
one wheel slipping 30 % (more IRLS iterations).  ``python -m benchmarks odometry``.
"""

from __future__ import annotations

import math
import os
import time

import numpy as np
from numpy.typing import NDArray

from swpc_hw.onboard.odometry import Odometry, OdometryOptions
from swpc_hw.onboard.twist_controller import settled_steering, settled_wheel_rates
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED

FloatArray = NDArray[np.float64]
N_UPDATES = 10000
RATE = 500.0


def _readings(kind: str) -> tuple[list[float], list[list[float]], list[list[float]]]:
    a = PAPER_CALIBRATED.arrays()
    tw = (0.2, 0.0, 0.3)
    t = np.arange(N_UPDATES) / RATE
    th = np.tile(settled_steering(a, tw), (t.size, 1))
    ps = np.outer(t, settled_wheel_rates(a, tw))
    if kind == "steering":  # steering keeps moving (not a consistent drive; cost only)
        th = th + 0.3 * np.sin(np.outer(t, [1.0, 1.3, 1.7, 2.1]))
    if kind == "slip":
        ps[:, 0] *= 1.3
    q = 2.0 * math.pi / 2**17
    th = np.round(th / q) * q
    ps = np.round(ps / q) * q
    return t.tolist(), th.tolist(), ps.tolist()


def _run(opts: OdometryOptions, t: list[float], th: list[list[float]] | FloatArray,
         ps: list[list[float]] | FloatArray) -> int:
    """Feed all readings through one Odometry; returns the last update's solve count."""
    odo = Odometry(PAPER_CALIBRATED, options=opts)
    upd = odo.update
    for k in range(len(t)):
        upd(t[k], th[k], ps[k])
    last = odo.last
    return last.iterations if last is not None else 0


def main() -> None:
    try:  # measure on one core
        cpu = min(os.sched_getaffinity(0))
        os.sched_setaffinity(0, {cpu})
        where = f"pinned to CPU {cpu}"
    except (AttributeError, OSError):
        where = "not pinned"
    print(f"odometry update rate, 4 modules, {N_UPDATES} updates per run, best of 3 ({where})")
    print(f"{'readings':<10} {'robust':<7} {'input':<6} {'rate kHz':>9} {'us/update':>10} "
          f"{'solves':>7} {'core % @500 Hz':>15}")
    for kind in ("arc", "steering", "slip"):
        t, th, ps = _readings(kind)
        inputs: dict[str, tuple[list[list[float]] | FloatArray, list[list[float]] | FloatArray]]
        inputs = {"list": (th, ps), "numpy": (np.array(th), np.array(ps))}
        for robust in ("geman", "none"):
            opts = OdometryOptions(robust="geman" if robust == "geman" else "none")
            for inp, (th_in, ps_in) in inputs.items():
                best = math.inf
                solves = 0
                for _ in range(3):
                    t0 = time.perf_counter()
                    solves = _run(opts, t, th_in, ps_in)
                    best = min(best, time.perf_counter() - t0)
                per = best / N_UPDATES
                print(f"{kind:<10} {robust:<7} {inp:<6} {1e-3 / per:9.1f} {per * 1e6:10.1f} "
                      f"{solves:7d} {100 * per * RATE:14.2f}%")


if __name__ == "__main__":
    main()
