"""Which part of the motion-capture solver's covariance under-states its error (issue 44):
each block's share of the error against the share the covariance gives it, offline, a
truth per run.

The solver's error is, to first order, a sum over its three blocks of residuals
(:mod:`swpc_hw.calibration.mocap.covariance`)::

    e = x - x_true ~ sum_b -H^-1 J_b^T f_b(x_true),   Cov = H^-1 (M_A + M_B + M_C) H^-1

(fixed point ``A``, settled caster ``B``, rolling ``C``).  Per run (a truth of its own:
:func:`benchmarks.calibration.bench_plan.seed_truths`, Table 4 perturbed; the offline
generator, mocap 0.5 mm / 0.05 deg, 2^17 counts) and per block, the share ``p_b`` is
taken at the truth's residuals, and along fixed directions ``a`` (the end ``x`` of the
CCW and of the CW square path through ``H^-1``: its ``x``, ``y`` and ``yaw`` rows are
nearly parallel; the four radii's mean) the benchmark prints
``sum (a' p_b)^2 / sum a' H^-1 M_b H^-1 a`` over the runs: 1 when the block's part of
the covariance is honest (the rolling block's ``M_C`` without its cross term with the
fixed points, which is not a covariance on its own).  For the rolling block also ``M_C``
from the truth's residuals (what the fit's absorption costs the estimate at the
solution).  Then the whole: NEES
``e' C^-1 e / 20`` and the square path's end error over its forecast (RMS z).

A single truth for every run would mislead: a settled caster's rounding to the encoder
count is fixed per truth and angle, one draw of the settled block's error that the runs
share (on one truth, 10.7 times the variance in the direction it picks).

``python -m benchmarks honesty_blocks``; ``SWPC_BENCH_BLOCKS_RUNS`` (default 100) runs
per spin length, ``SWPC_BENCH_BLOCKS_SPINS`` (default ``3,12``: s of steady spin, the
angles 45 and 225 deg).  About 0.7 s a run.
"""

from __future__ import annotations

import math
import os
import time

import numpy as np

from benchmarks.calibration.bench_plan import as_matrix, seed_truths
from simulators.offline.datagen import ExperimentOptions, generate_experiment
from swpc_hw.calibration.mocap.covariance import rolling_long_run, segment_terms
from swpc_hw.calibration.mocap.solver import solve_joint
from swpc_hw.calibration.parameters import BETA, N_PARAMS, R
from swpc_hw.calibration.plan.square_error import square_path_sensitivity
from swpc_hw.robot.model import wrap_angle
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED, PAPER_NOMINAL

BLOCKS = ("fixed point", "settled caster", "rolling", "rolling (M from the truth's residuals)")


def spin_length(duration: float, n: int) -> str:
    truths = seed_truths(PAPER_CALIBRATED, n, 4400)
    S = square_path_sensitivity(PAPER_NOMINAL)
    radii = np.zeros(N_PARAMS * len(PAPER_NOMINAL.modules))
    radii[R::N_PARAMS] = 1.0 / len(PAPER_NOMINAL.modules)
    names = ("square CCW", "square CW", "radii's mean")
    emp = np.zeros((len(BLOCKS), len(names)))
    model = np.zeros_like(emp)
    nees, zsq = [], []
    for k, truth in enumerate(truths):
        xt = as_matrix(truth).ravel()
        opts = ExperimentOptions(
            angles=(math.radians(45.0), math.radians(225.0)), spin_duration=duration,
            pose_sigma_xy=0.5e-3, pose_sigma_yaw=math.radians(0.05), seed=7000 + k,
        )  # fmt: skip
        sol = solve_joint(generate_experiment(truth, opts, PAPER_NOMINAL).dataset)
        prob, x = sol.problem, sol.x
        J, _, terms = segment_terms(prob, x, sol.fits)
        Hi = np.linalg.inv(J.T @ J)
        nA, nB, _ = prob.block_sizes()
        Jt, ft = prob.jacobian(xt), prob.residuals(xt)
        parts = [Jt[b].T @ ft[b] for b in (slice(0, nA), slice(nA, nA + nB), slice(nA + nB, None))]
        parts.append(parts[2])
        f = prob.residuals(x)
        M_sol = sum(rolling_long_run(prob, J[nA + nB :], f[nA + nB :]))
        M_truth = sum(rolling_long_run(prob, Jt[nA + nB :], ft[nA + nB :]))
        Ms = [sum(t.fixed_m for t in terms), sum(t.settled_h for t in terms), M_sol, M_truth]
        dirs = [Hi @ S[0], Hi @ S[3], Hi @ radii]
        for b, (g, M) in enumerate(zip(parts, Ms, strict=True)):
            for d, a in enumerate(dirs):
                emp[b, d] += float(a @ g) ** 2
                model[b, d] += float(a @ M @ a)
        e = x - xt
        e[BETA::N_PARAMS] = wrap_angle(e[BETA::N_PARAMS])
        C = sol.result.covariance
        assert C is not None
        nees.append(float(e @ np.linalg.solve(C, e)) / e.size)
        d, E = S @ e, S @ C @ S.T
        zsq.append([(d[i] ** 2 + d[i + 1] ** 2) / (E[i, i] + E[i + 1, i + 1]) for i in (0, 3)])
    lines = [f"{duration:g} s spins, {n} truths: NEES {np.mean(nees):.2f}; square path end "
             f"position error / forecast, RMS z (CCW, CW) "
             f"{', '.join(f'{v:.2f}' for v in np.sqrt(np.mean(zsq, axis=0)))}"]  # fmt: skip
    for b, block in enumerate(BLOCKS):
        ratios = ", ".join(f"{nm} {emp[b, d] / model[b, d]:.2f}" for d, nm in enumerate(names))
        lines.append(f"  {block}: error / covariance {ratios}")
    return "\n".join(lines)


def main() -> None:
    n = int(os.environ.get("SWPC_BENCH_BLOCKS_RUNS", "100"))
    spins = [float(s) for s in os.environ.get("SWPC_BENCH_BLOCKS_SPINS", "3,12").split(",")]
    for duration in spins:
        t0 = time.perf_counter()
        print(spin_length(duration, n))
        print(f"  ({time.perf_counter() - t0:.0f} s)", flush=True)


if __name__ == "__main__":
    main()
