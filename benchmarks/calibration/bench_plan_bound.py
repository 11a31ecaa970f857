"""How far the planner is from issue 34's goal: at most half the default protocol's robot
time at equal or better worst-case std devs (docs/plan.md, *Measured*).

On the paper's robot (nominal: the design), with the prediction of ``swpc plan``
(``services.plan.predict``, mocap 0.5 mm / 0.05 deg, white):

1. **The default protocol** (45 and 165 deg, 360 deg sweeps, settle 3 s, stop 1.5 s,
   align 1 s, at the config's spin torque): its robot time and worst predicted std dev
   per kind at 100 Hz: the targets of the rest (no square path: the targets alone).
2. **(a) The planner** as ``swpc plan`` searches (the check's pauses, the config's spin
   torque and the fastest within the limits), and the same at the config's spin torque
   only (the planner before it chose the speed).
3. **(b) A lower bound**: every pause idealised to 0.05 s (settle, stop, align, re-steer;
   not 0: the generator's phases need a length; the casters still settle, in the
   prediction, as long as they need), the spin at the fastest the limit allows
   (``limits.max_yaw_rate`` itself, no margin) and at the planner's fastest, sweeps up to
   1440 deg; and the same at 150 Hz.
4. **(c) The mocap rate** at which (a) reaches half the default's robot time, the
   targets still the default's at 100 Hz (the default at the faster rate gains as much:
   with white noise every std dev scales as ``1 / sqrt(rate)``, shown for 200 Hz).

``SWPC_BENCH_PLAN_RATES`` (default ``150 200 250 300 350 400``): the rates of (c), up to
the first that reaches half.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import replace

from benchmarks.calibration.bench_plan import default_protocol
from services.config.robot import RobotConfig
from services.plan.planner import pauses, time_model
from services.plan.predict import predicted_covariance
from swpc_hw.calibration.plan.plan import (
    SWEEPS,
    Candidate,
    FloatArray,
    MocapNoise,
    Plan,
    PlanError,
    Requirement,
    Targets,
    TimeModel,
    plan,
    robot_time,
    spin_torques,
    stddevs,
    worst_per_kind,
)
from swpc_hw.robot.paper_robot import PAPER_NOMINAL

LONG_SWEEPS = (*SWEEPS, *(720.0 + 90.0 * k for k in range(1, 9)))
"""The planner's sweeps and longer ones, up to 1440 deg (the bound's)."""
IDEAL_PAUSE = 0.05
"""s: the bound's settle, stop, align and re-steer times."""


def worst(cov: FloatArray) -> str:
    w = worst_per_kind(stddevs(cov))
    return (f"position {w['position'] * 1e3:.5f} mm, beta {math.degrees(w['beta']):.5f} deg, "
            f"radius {w['radius'] * 1e3:.5f} mm")  # fmt: skip


def search(
    label: str, requirement: Requirement, pause: Candidate, tm: TimeModel,
    torques: tuple[float, ...], noise: MocapNoise, sweeps: tuple[float, ...], default_time: float,
) -> Plan | None:  # fmt: skip
    """One plan, printed: its design, robot time, share of the default's and std devs."""
    t0 = time.perf_counter()

    def predict(c: Candidate) -> FloatArray:
        return predicted_covariance(PAPER_NOMINAL, c, noise, tm)

    try:
        p = plan(predict, requirement, PAPER_NOMINAL.ids, pause, tm, sweeps=sweeps,
                 torques=torques, max_spin_time=60.0)  # fmt: skip
    except PlanError as exc:
        print(f"  {label}: none ({exc}) [{time.perf_counter() - t0:.0f} s]", flush=True)
        return None
    n = sum(e.covariance is not None for e in p.tried)
    print(f"  {label}: {p.candidate.label()} ({p.yaw_rate:.3f} rad/s), {p.robot_time:.1f} s "
          f"= {p.robot_time / default_time:.1%} of the default; {worst(p.covariance)} "
          f"[{n} predicted, {time.perf_counter() - t0:.0f} s]", flush=True)  # fmt: skip
    return p


def main() -> None:
    rates = os.environ.get("SWPC_BENCH_PLAN_RATES", "150 200 250 300 350 400").split()
    cfg = RobotConfig(nominal=PAPER_NOMINAL)
    lim = cfg.limits
    tm = time_model(cfg)
    d = default_protocol(cfg)
    d_time = robot_time(d, 4, tm)
    d_cov = predicted_covariance(PAPER_NOMINAL, d, MocapNoise(), tm)
    w = worst_per_kind(stddevs(d_cov))
    req = Requirement(Targets(w["position"], w["beta"], w["radius"]))
    print(f"[plan bound] paper's robot; the default protocol: {d_time:.1f} s at "
          f"{d.spin_torque:g} N.m; worst predicted sd (100 Hz) {worst(d_cov)}: the targets; "
          f"half its robot time: {d_time / 2:.1f} s")  # fmt: skip
    d200 = predicted_covariance(PAPER_NOMINAL, d, replace(MocapNoise(), rate=200.0), tm)
    print(f"  the default at 200 Hz: {worst(d200)}")
    torques = spin_torques(lim.spin_torque, lim.max_wheel_torque, lim.max_yaw_rate, tm)
    print("(a) the planner (the check's pauses, spin torques "
          f"{', '.join(f'{t:g}' for t in torques)} N.m):")  # fmt: skip
    search("100 Hz", req, pauses(cfg), tm, torques, MocapNoise(), SWEEPS, d_time)
    search(f"100 Hz, {lim.spin_torque:g} N.m only", req, pauses(cfg), tm, (lim.spin_torque,),
           MocapNoise(), SWEEPS, d_time)  # fmt: skip
    fastest = math.floor(lim.max_yaw_rate / tm.rate_per_torque * 100 + 1e-9) / 100
    print(f"(b) the bound: pauses {IDEAL_PAUSE:g} s, sweeps up to {LONG_SWEEPS[-1]:g} deg:")
    for tau, rate in ((fastest, 100.0), (torques[0], 100.0), (fastest, 150.0)):
        ideal = Candidate((), 0.0, *(IDEAL_PAUSE,) * 4, tau)
        noise = replace(MocapNoise(), rate=rate)
        search(f"{rate:g} Hz, {tau:g} N.m", req, ideal, tm, (tau,), noise, LONG_SWEEPS, d_time)
    print("(c) the planner (as (a)) with a faster mocap, the targets the default's at 100 Hz:")
    for rate in map(float, rates):
        p = search(f"{rate:g} Hz", req, pauses(cfg), tm, torques, replace(MocapNoise(), rate=rate),
                   SWEEPS, d_time)  # fmt: skip
        if p is not None and p.robot_time <= d_time / 2:
            break


if __name__ == "__main__":
    main()
