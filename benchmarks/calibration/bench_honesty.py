"""The result's covariance against the truth, whole calibrations on the in-process
simulator, a truth per run (issue 44: honest where the robot uses it).

For each protocol the service runs, ``SWPC_BENCH_HONESTY_RUNS`` calibrations (default 20)
through the service on the in-process simulator, each with its own hidden truth (the
paper's Table 4 robot perturbed as :func:`benchmarks.calibration.bench_plan.seed_truths` does:
``P_s`` +-5 %, ``beta`` +-3 deg, ``b`` and ``r`` +-2 %) and its own simulator seed; the
nominal is the paper's design.  Per run, the error ``e`` of the 5N parameters against the
truth and the run's own covariance ``C`` (its kinematic file):

* the whole covariance's NEES, ``e' C^-1 e / 5N`` (about 1 when ``C`` is honest: its
  mean, spread and the share of runs above the 95 % point of ``chi2(5N) / 5N``);
* per kind (position ``x_s, y_s, b``; ``beta``; radius ``r``) the RMS of
  ``z = e / sqrt(diag C)``;
* the square path's end position error ``|S e|`` (the larger of the CCW and CW squares,
  :mod:`swpc_hw.calibration.plan.square_error`) against its forecast from the same
  covariance (:func:`~swpc_hw.calibration.plan.square_error.square_path_sd`): the RMS of
  each, their ratio, and the RMS of the per-run ratio (a z);
* how many runs end the square path within its budget (end position and heading within
  :data:`~swpc_hw.calibration.plan.square_error.SQUARE_BUDGET` at once), against the
  share the requirement promises (:data:`~swpc_hw.calibration.plan.square_error.SQUARE_SHARE`)
  and the mean of the run's own 90 % bound over the budget (at most 1: the covariance
  says the run meets the requirement); with motion capture only (without it the square
  path has no budget: the layout's scale is the tape's, docs/plan.md);
* the robot time.

Protocols (``SWPC_BENCH_HONESTY_PROTOCOLS``, comma-separated, default all four):
``default`` (the robot config's, motion capture), ``planned`` (``plan: auto`` with motion
capture: the plan's protocol with sequential stopping), ``gyro`` (the default without
motion capture) and ``gyro-planned`` (``plan: auto`` without motion capture: no
sequential stopping there).

``python -m benchmarks honesty``; ``SWPC_BENCH_HONESTY_SAVE=DIR`` keeps each run's error,
covariance and truth there (``<protocol>-<run>.npz``); ``SWPC_BENCH_HONESTY_SLICE=A:B`` runs
only the truths ``A..B-1`` of the set (one process per core: ``0:10`` and ``10:20``).  Each
run is a whole calibration in simulated time (about a minute of one core): the default
4 x 20 runs take over an hour.
"""

from __future__ import annotations

import contextlib
import math
import os
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy import stats

from benchmarks.calibration.bench_check import TOKEN
from benchmarks.calibration.bench_plan import as_matrix, seed_truths
from swpc_hw.calibration.plan.square_error import (
    SQUARE_SHARE,
    AgainstTruth,
    against_truth,
    square_path_error,
    square_path_quantile,
    square_path_sd,
    square_path_sensitivity,
    square_path_within,
)
from swpc_hw.files.kinematic_file import load_kinematics, save_kinematics
from swpc_hw.robot.frames import DESIGN_FIT, params_in_design_fit
from swpc_hw.robot.model import PARAM_KINDS, RobotParams
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED, PAPER_NOMINAL

PROTOCOLS: dict[str, dict[str, Any]] = {
    "default": {},
    "planned": {"plan": "auto"},
    "gyro": {"metrology": "imu"},
    "gyro-planned": {"metrology": "imu", "plan": "auto"},
}
"""Protocol name -> the body of its ``POST /calibrations`` (``install: never`` added)."""


@dataclass
class RunFigures:
    """One run against its truth: :class:`AgainstTruth` and the square path per column."""

    robot_time: float
    against: AgainstTruth
    by_param: np.ndarray  # (5, 2): per parameter column, the square path mm reached, forecast
    within: bool | None  # the square path's end position and heading within SQUARE_BUDGET
    bound: float | None  # the run's own SQUARE_SHARE bound over SQUARE_BUDGET (<= 1: met)


def figures(
    result: RobotParams, C: np.ndarray, truth: RobotParams, S: np.ndarray, robot_time: float
) -> RunFigures:
    """``result`` (its covariance ``C``) against ``truth``; ``S`` the square path's
    sensitivity.  ``by_param``: the square path's error and forecast from one parameter
    column's errors alone (``x_s, y_s, beta, b, r``), to see which column's forecast falls
    short."""
    a = against_truth(result, C, truth, PAPER_NOMINAL, S)
    v = (as_matrix(result) - as_matrix(truth)).ravel()
    by = np.zeros((5, 2))
    for c in range(5):
        cols = np.arange(c, v.size, 5)
        by[c] = (
            square_path_error(S[:, cols], v[cols])[0] * 1e3,
            square_path_sd(S[:, cols], C[np.ix_(cols, cols)])[0] * 1e3,
        )
    if result.frame == DESIGN_FIT:  # no budget without motion capture
        return RunFigures(robot_time, a, by, None, None)
    return RunFigures(
        robot_time, a, by, square_path_within(a.square), square_path_quantile(S, C)[2]
    )


@contextlib.contextmanager
def service(data: Path, truth: Path, seed: int) -> Iterator[Any]:
    """The service on the in-process simulator (hidden truth ``truth``, simulator seed
    ``seed``, the robot config ``data/robot.yaml``): a client."""
    from fastapi.testclient import TestClient
    from pydantic import SecretStr

    from services.config.settings import ServiceSettings
    from services.http.app import create_app

    s = ServiceSettings(
        data_dir=data, token=SecretStr(TOKEN), sim_truth=truth, sim_seed=seed,
        robot_config=data / "robot.yaml", allowed_hosts=["testserver"],
    )  # fmt: skip
    with TestClient(create_app(s)) as client:
        yield client


def one_run(data: Path, truth_path: Path, seed: int, body: dict[str, Any]) -> dict[str, Any]:
    """One calibration with ``body``; without motion capture the operator played as
    ``swpc`` asks one to (the simulator's tape between the steering axes, each pair twice,
    then MARK and the straight drive's tape): its final status."""
    auth = {"Authorization": f"Bearer {TOKEN}"}
    with service(data, truth_path, seed) as client:
        req = {**body, "install": "never"}
        if body.get("metrology") == "imu":
            refs = client.get("/simulator/axis-distances", params={"seed": seed}).json()
            req["references"] = refs["references"]
        deadline = time.monotonic() + 600
        while True:  # 409 while the plan is being made (seconds to a minute)
            r = client.post("/calibrations", json=req, headers=auth)
            if r.status_code != 409 or time.monotonic() > deadline:
                break
            time.sleep(0.2)
        assert r.status_code == 202, r.text
        rid, deadline = r.json()["id"], time.monotonic() + 900
        while True:
            st: dict[str, Any] = client.get(f"/calibrations/{rid}").json()
            if st["state"] in ("DONE", "FAILED", "ABORTED"):
                return st
            assert time.monotonic() < deadline, st
            if st["state"] == "MARK":
                client.post(f"/calibrations/{rid}/continue", headers=auth)
            elif st["state"] == "MEASURE":
                tape = client.get("/simulator/tape-measure", params={"run": rid, "seed": seed})
                ref = {k: tape.json()[k] for k in ("kind", "value", "stddev")}
                client.post(f"/calibrations/{rid}/references", json={"references": [ref]},
                            headers=auth)  # fmt: skip
            time.sleep(0.02)


def runs_slice(n: int) -> tuple[int, int]:
    """``SWPC_BENCH_HONESTY_SLICE=A:B``: the runs ``A..B-1`` of the ``n`` (default all):
    the same truths and seeds as in the whole set, e.g. one half per core."""
    a, _, b = os.environ.get("SWPC_BENCH_HONESTY_SLICE", f"0:{n}").partition(":")
    return int(a or 0), min(int(b or n), n)


def protocol_runs(name: str, n: int) -> list[RunFigures]:
    body = PROTOCOLS[name]
    save = os.environ.get("SWPC_BENCH_HONESTY_SAVE")  # a folder: each run's e, C, truth
    S = square_path_sensitivity(PAPER_NOMINAL)
    out: list[RunFigures] = []
    with tempfile.TemporaryDirectory() as tmp:
        data = Path(tmp)
        save_kinematics(data / "nominal.yaml", PAPER_NOMINAL)
        (data / "robot.yaml").write_text("nominal: nominal.yaml\n", encoding="utf-8")
        first, last = runs_slice(n)
        truths = seed_truths(PAPER_CALIBRATED, n, 4400)[first:last]
        for k, truth in enumerate(truths, start=first):
            save_kinematics(data / "truth.yaml", truth)
            st = one_run(data, data / "truth.yaml", 1 + k, body)
            if st["state"] != "DONE":
                print(f"  {name} run {k}: {st['state']} ({st['reason']})", flush=True)
                continue
            kf = load_kinematics(data / "runs" / st["id"] / "kinematics.yaml")
            if kf.covariance is None:
                print(f"  {name} run {k}: no covariance in its file", flush=True)
                continue
            result, C = kf.params, np.asarray(kf.covariance, dtype=float)
            if result.frame == DESIGN_FIT:  # without motion capture
                truth = params_in_design_fit(truth, PAPER_NOMINAL)[0]
            f = figures(result, C, truth, S, float(st["elapsed_s"]))
            out.append(f)
            if save:
                e = as_matrix(result) - as_matrix(truth)
                np.savez(Path(save) / f"{name}-{k}.npz", e=e, C=C, truth=as_matrix(truth))
            a = f.against
            print(f"  {name} run {k}: NEES {a.nees:.2f} ({a.dof}), square path "
                  f"{a.square[0] * 1e3:.3f} mm (forecast {a.square_forecast[0] * 1e3:.3f}"
                  + ("" if f.bound is None else f", 90 % bound / budget {f.bound:.2f}, "
                     f"{'within' if f.within else 'beyond'}") + "), "
                  f"{f.robot_time:.0f} s of robot time", flush=True)  # fmt: skip
    return out


def whole_and_kinds(against: list[AgainstTruth]) -> tuple[np.ndarray, int, float, str]:
    """Over runs against their truths: every run's NEES, its degrees of freedom, the
    share above the chi2 95 % point, and the RMS z per kind as text."""
    nees = np.array([a.nees for a in against])
    dof = against[0].dof
    above = float(np.mean(nees > stats.chi2.ppf(0.95, dof) / dof))
    kinds = ", ".join(
        f"{k} {math.sqrt(float(np.mean([a.rms_z[k] ** 2 for a in against]))):.2f}"
        for k in PARAM_KINDS
    )
    return nees, dof, above, kinds


def summary(name: str, runs: list[RunFigures]) -> str:
    if not runs:
        return f"{name}: no run DONE"
    nees, _, above, kinds = whole_and_kinds([r.against for r in runs])
    mm = np.array([r.against.square[0] * 1e3 for r in runs])
    fc = np.array([r.against.square_forecast[0] * 1e3 for r in runs])
    rms_mm, rms_fc = (math.sqrt(float(np.mean(a**2))) for a in (mm, fc))
    t = np.array([r.robot_time for r in runs])
    bounds = [r.bound for r in runs if r.bound is not None]
    budget = (
        "no budget without motion capture"
        if not bounds
        else f"within the budget {sum(bool(r.within) for r in runs)} of {len(runs)} (the "
        f"requirement: {SQUARE_SHARE:.0%}; the runs' own 90 % bound / budget "
        f"{float(np.mean(bounds)):.2f} on average)"
    )
    by = np.sqrt(np.mean(np.stack([r.by_param for r in runs]) ** 2, axis=0))
    cols = ", ".join(
        f"{k} {by[c, 0]:.3f}/{by[c, 1]:.3f}" for c, k in enumerate(("x_s", "y_s", "beta", "b", "r"))
    )
    return (
        f"{name} ({len(runs)} runs): NEES mean {nees.mean():.2f} (median {np.median(nees):.2f}, "
        f"{nees.min():.2f}-{nees.max():.2f}, {above:.0%} above chi2 95 %); RMS z {kinds}; "
        f"square path forecast {rms_fc:.3f} mm, reached {rms_mm:.3f} mm RMS (largest "
        f"{mm.max():.3f}), ratio {rms_mm / rms_fc:.2f}, RMS z "
        f"{math.sqrt(float(np.mean((mm / fc) ** 2))):.2f} (per column alone, RMS mm reached/"
        f"forecast: {cols}); {budget}; "
        f"robot time "
        f"{t.mean():.0f} s ({t.min():.0f}-{t.max():.0f})"
    )


def main() -> None:
    import logging

    logging.getLogger("swpc").setLevel(logging.ERROR)
    n = int(os.environ.get("SWPC_BENCH_HONESTY_RUNS", "20"))
    names = os.environ.get("SWPC_BENCH_HONESTY_PROTOCOLS", ",".join(PROTOCOLS)).split(",")
    print(f"[honesty] {n} runs per protocol on the in-process simulator, a truth per run "
          "(Table 4 +-5 % / 3 deg / 2 %), mocap 0.5 mm / 0.05 deg")  # fmt: skip
    lines = []
    for name in names:
        t0 = time.perf_counter()
        runs = protocol_runs(name.strip(), n)
        lines.append(summary(name.strip(), runs) + f" [{time.perf_counter() - t0:.0f} s]")
        print(lines[-1], flush=True)
    print("\n".join(["", "[honesty] summary", *lines]))


if __name__ == "__main__":
    main()
