"""Check benchmarks (issue 33: is the calibration still valid?  docs/check.md).

1. **The check's design.**  Candidate protocols (modules locked, angles, sweep): the
   robot time of one check of each through the service (the in-process simulator), and
   from ``SWPC_BENCH_CHECK_DESIGN`` offline runs each (default 10) the solver's covariance
   used as the Fisher information: for every drift of the issue applied to every module in
   turn, the non-centrality ``lambda = d^T Cov(d)^-1 d`` of the module's chi-square and
   the power ``P(chi2_5(lambda) > q)``; its smallest over modules and runs, and the RMS z
   of the check's estimate against the truth (1 when its std devs are right).
2. **Detection and false alarms, offline**: ``SWPC_BENCH_CHECK_SEEDS`` seeds per case
   (default 50).  Per seed a robot (Table 4 perturbed: ``P_s`` +-5 %, ``beta`` +-3 deg, ``b``
   and ``r`` +-2 %, as the solver's honesty benchmark), its file in force = a real
   calibration (the default protocol: 4 modules x 2 angles x 12 s spins) solved by the
   joint solver with its own covariance, then the robot config's check protocol
   (``check``) run on: the same robot (false alarms), ``r`` -0.3 mm on one wheel, ``beta``
   +0.3 deg on one module, one module swapped (``P_s`` moved 2 mm in a random direction,
   ``b`` +1 mm); the changed module is seed mod 4 + 1.  Detected: the verdict is drifted
   and names the changed module.  Mocap 0.5 mm / 0.05 deg at 100 Hz, 2^17-count encoders.
   The bare statistic (repeatability 0) is reported beside the robot config's.
3. **Through the service**: ``SWPC_BENCH_CHECK_SERVICE`` seeds (default 3; 0 skips): per
   seed the same robot family on the in-process simulator (``SWPC_SIM_TRUTH``), one full
   calibration installed (``POST /calibrations``), then the service restarted on each
   changed truth and ``POST /checks``: verdicts, robot time, wall time.

2 and 3 for each metrology of ``SWPC_BENCH_CHECK_METROLOGY`` (default ``mocap,imu``):
``imu`` is the check with the gyro (:data:`MEMS`, the encoders, no poses, no references;
the verdict on the robot's shape, :mod:`swpc_hw.calibration.check.shape`), the file in
force the same calibration with motion capture; its offline table adds the RMS z of the
check's shape against the truth.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import os
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from services.config.robot import RobotConfig
from simulators.offline.datagen import ExperimentOptions, generate_experiment
from simulators.offline.random_robots import random_robots
from swpc_hw.calibration.check.verdict import check_estimates, stated_covariance
from swpc_hw.calibration.mocap.solver import CalibrationResult, solve
from swpc_hw.calibration.parameters import N_PARAMS
from swpc_hw.robot.model import PARAM_NAMES, RobotParams
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED, PAPER_NOMINAL
from swpc_hw.sensors.gyro import GyroOptions

MOCAP = ExperimentOptions(pose_sigma_xy=0.5e-3, pose_sigma_yaw=math.radians(0.05))
MEMS = GyroOptions(noise_density=math.radians(0.014), bias=math.radians(0.5))
"""A check with the gyro: a MEMS gyro (white noise 0.014 deg/s/sqrt(Hz), bias 0.5 deg/s,
the default walk and 0.3 % scale error)."""
YAW_RATE = MOCAP.yaw_rate
CASES = ("unchanged", "r -0.3 mm", "beta +0.3 deg", "swapped")
TOKEN = "bench-token-0123456789"
HONEST = 1.1
"""A design's check std devs are taken as right when the RMS z of its estimates is at most
this (without the repeatability, the chi-square's tail grows fast with it)."""


def truths(n: int) -> list[RobotParams]:
    """The seeds' robots: Table 4 perturbed (module docstring)."""
    robots = random_robots(
        n, np.random.default_rng(22), PAPER_CALIBRATED,
        pos_frac=0.05, beta_max=math.radians(3.0), br_frac=0.02,
    )  # fmt: skip
    return [robots.robot(i, PAPER_CALIBRATED.ids) for i in range(n)]


def drift(case: str, module: int, seed: int) -> dict[str, float]:
    """The change of ``case`` (SI), on ``module``; the swapped module's axis moves 2 mm in a
    direction drawn from ``seed``."""
    if case == "r -0.3 mm":
        return {"r": -0.3e-3}
    if case == "beta +0.3 deg":
        return {"beta": math.radians(0.3)}
    if case == "swapped":
        a = float(np.random.default_rng([seed, 33]).uniform(-math.pi, math.pi))
        return {"x_s": 2e-3 * math.cos(a), "y_s": 2e-3 * math.sin(a), "b": 1e-3}
    return {}


def changed(truth: RobotParams, module: int, d: dict[str, float]) -> RobotParams:
    mods = [
        m.model_copy(update={k: getattr(m, k) + v for k, v in d.items()}) if m.id == module else m
        for m in truth.modules
    ]
    return truth.model_copy(update={"modules": mods})


def check_options(protocol: dict[str, Any], seed: int) -> ExperimentOptions:
    """A check protocol's offline experiment: its angles, every module locked (or
    ``modules``), a window of ``sweep_deg`` at the generator's yaw rate."""
    return dataclasses.replace(
        MOCAP,
        angles=tuple(math.radians(a) for a in protocol["angles_deg"]),
        spin_duration=math.radians(protocol["sweep_deg"]) / YAW_RATE,
        modules=None if protocol.get("modules") is None else tuple(protocol["modules"]),
        seed=seed,
    )


def calibrate(truth: RobotParams, seed: int) -> CalibrationResult:
    """The seed's file in force: a real calibration (default protocol) of ``truth``."""
    opts = dataclasses.replace(MOCAP, seed=10_000 + seed)
    return solve(generate_experiment(truth, opts, PAPER_NOMINAL).dataset)


def check_run(
    truth: RobotParams, protocol: dict[str, Any], seed: int, file: CalibrationResult
) -> CalibrationResult:
    """A check's estimate on ``truth``, solved from the file's parameters."""
    from swpc_hw.calibration.check.dataset_check import check_dataset

    ds = generate_experiment(truth, check_options(protocol, seed), PAPER_NOMINAL).dataset
    result, _ = check_dataset(ds, file.params, file.covariance)
    return result


def as_matrix(p: RobotParams) -> np.ndarray:
    return np.array([[getattr(m, k) for k in PARAM_NAMES] for m in p.modules])


# ---------------------------------------------------------------------------- design


CANDIDATES: list[tuple[str, dict[str, Any]]] = [
    ("every module at 45 deg, 60 deg sweeps", {"angles_deg": [45.0], "sweep_deg": 60.0}),
    ("every module at 45 deg, 90 deg sweeps", {"angles_deg": [45.0], "sweep_deg": 90.0}),
    ("every module at 45 deg, 120 deg sweeps", {"angles_deg": [45.0], "sweep_deg": 120.0}),
    ("modules 1, 3 at 45 and 165 deg, 90 deg", {"angles_deg": [45.0, 165.0],
                                                 "sweep_deg": 90.0, "modules": [1, 3]}),
    ("every module at 45 and 165 deg, 45 deg", {"angles_deg": [45.0, 165.0], "sweep_deg": 45.0}),
]  # fmt: skip


def rep_text(cfg: RobotConfig) -> str:
    r = cfg.check.repeatability
    return f"{r.position * 1e3:g} mm / {math.degrees(r.beta):g} deg / {r.radius * 1e3:g} mm"


def power(lam: float, q: float) -> float:
    from scipy.stats import ncx2

    return float(ncx2.sf(q, N_PARAMS, lam))


def design(runs: int, cfg: RobotConfig, service_times: dict[str, float]) -> None:
    from swpc_hw.calibration.check.verdict import thresholds

    rep = np.array(cfg.check.repeatability.per_parameter())
    ids = PAPER_CALIBRATED.ids
    _, q, _ = thresholds(cfg.check.false_alarm, len(ids))
    robots = truths(runs)
    print(
        f"[design] check protocols: the solver's covariance as the Fisher information, {runs} "
        f"offline runs each (file: a calibration; repeatability {rep_text(cfg)}); "
        f"power = P(chi2_5(lambda) > {q:.2f}) and sqrt(lambda), smallest over the runs and "
        "the module changed"
    )
    head = f"{'protocol':<42} {'robot s':>7} " + " ".join(f"{c:>16}" for c in CASES[1:])
    print(head + f" {'RMS z':>6}")
    files = [calibrate(robots[i], i) for i in range(runs)]
    chosen: list[tuple[float, str]] = []
    for name, proto in CANDIDATES:
        worst = {c: 1.0 for c in CASES[1:]}
        root = {c: math.inf for c in CASES[1:]}
        zs = []
        for i, truth in enumerate(robots):
            try:
                res = check_run(truth, proto, 500 + i, files[i])
            except Exception as exc:  # a design the solver cannot determine
                worst = {c: math.nan for c in CASES[1:]}
                print(f"  {name}: {type(exc).__name__}: {exc}")
                break
            C = res.covariance + stated_covariance(files[i].params, files[i].covariance, ids)
            C = C + np.diag(np.tile(rep**2, len(ids)))
            zs.append((as_matrix(res.params) - as_matrix(truth)) / res.stddev_array())
            for k in range(len(ids)):
                sl = slice(N_PARAMS * k, N_PARAMS * (k + 1))
                inv = np.linalg.inv(C[sl, sl])
                for c in CASES[1:]:
                    dv = np.zeros(N_PARAMS)
                    for p, v in drift(c, ids[k], i).items():
                        dv[PARAM_NAMES.index(p)] = v
                    lam = float(dv @ inv @ dv)
                    worst[c] = min(worst[c], power(lam, q))
                    root[c] = min(root[c], math.sqrt(lam))
        rms = float(np.sqrt(np.mean(np.array(zs) ** 2))) if zs else math.nan
        t = service_times.get(name, math.nan)
        print(f"{name:<42} {t:7.1f} "
              + " ".join(f"{worst[c]:8.4f} ({root[c]:4.1f})" for c in CASES[1:])
              + f" {rms:6.2f}")  # fmt: skip
        if min(worst.values()) >= 0.95 and rms <= HONEST and (t <= 30 or math.isnan(t)):
            chosen.append((t, name))
    best = min(chosen)[1] if chosen else "none"
    print(
        f"  the rule: the shortest with power >= 0.95 in every case, RMS z <= {HONEST:g} (its "
        f"std devs right to 10 %) and <= 30 s of robot time: {best}"
    )


# ---------------------------------------------------------------------------- offline


def check_data(robot: RobotParams, proto: dict[str, Any], seed: int, metrology: str) -> Any:
    """A check's dataset on ``robot``: with motion capture, or (``imu``) as the robot
    records it without: a MEMS gyro (:data:`MEMS`), the encoders, no poses, no
    references."""
    if metrology == "mocap":
        return generate_experiment(robot, check_options(proto, seed), PAPER_NOMINAL).dataset
    from simulators.offline.datagen_imu import ReferenceOptions, generate_imu_experiment

    opts = dataclasses.replace(
        check_options(proto, seed), pose_sigma_xy=0.0, pose_sigma_yaw=0.0,
        rest_time=proto["rest_time"], drive_length=0.0,
    )  # fmt: skip
    exp = generate_imu_experiment(
        robot, opts, MEMS, ReferenceOptions(axis_pairs=(), straight_drive=False), PAPER_NOMINAL
    )
    return dataclasses.replace(exp.experiment.dataset, poses=np.zeros((0, 4)))


def offline(seeds: int, cfg: RobotConfig, metrology: str = "mocap") -> None:
    from swpc_hw.calibration.check.dataset_check import check_dataset

    c = cfg.check
    proto = cfg.check_config().protocol.model_dump()
    rep = c.repeatability.per_parameter()
    robots = truths(seeds)
    ids = PAPER_CALIBRATED.ids
    hits = {k: 0 for k in CASES}
    named = {k: 0 for k in CASES}
    others = {k: 0 for k in CASES}
    bare = {k: 0 for k in CASES}
    params_named = {k: 0 for k in CASES}
    honesty: list[np.ndarray] = []
    t0 = time.perf_counter()
    t_cal = t_chk = 0.0
    for i, truth in enumerate(robots):
        t = time.perf_counter()
        file = calibrate(truth, i)
        t_cal += time.perf_counter() - t
        module = ids[i % len(ids)]
        for case in CASES:
            d = drift(case, module, i)
            robot = changed(truth, module, d) if d else truth
            t = time.perf_counter()
            ds = check_data(robot, proto, i, metrology)
            res, v = check_dataset(
                ds, file.params, file.covariance, false_alarm=c.false_alarm,
                whole_robot=c.whole_robot, repeatability=rep,
            )  # fmt: skip
            t_chk += time.perf_counter() - t
            if metrology == "mocap":
                b = check_estimates(
                    res.params, res.covariance, file.params, file.covariance,
                    false_alarm=c.false_alarm, whole_robot=c.whole_robot,
                )  # fmt: skip
            else:
                from swpc_hw.calibration.check.shape import compare_shape

                assert res.covariance is not None
                b = compare_shape(
                    as_matrix(res.params), res.covariance, as_matrix(file.params),
                    stated_covariance(file.params, file.covariance, ids), ids,
                    false_alarm=c.false_alarm, whole_robot=c.whole_robot,
                )  # fmt: skip
                honesty.append(shape_z(res, truth if case == "unchanged" else robot))
            if case == "unchanged":
                hits[case] += v.verdict != "consistent"
                bare[case] += b.verdict != "consistent"
                continue
            ok = v.verdict == "drifted" and module in v.drifted
            hits[case] += ok
            bare[case] += b.verdict == "drifted" and module in b.drifted
            named[case] += ok and v.drifted == [module]
            others[case] += any(m != module for m in v.drifted)
            mine = next(m for m in v.modules if m.id == module)
            big = max(abs(x) for x in d.values())
            main_params = {p for p, x in d.items() if abs(x) >= 0.5 * big}
            params_named[case] += ok and set(mine.parameters) >= main_params
    wall = time.perf_counter() - t0
    print(
        f"\n[offline {metrology}] {seeds} seeds per case ({wall:.0f} s: calibrations "
        f"{t_cal / seeds:.2f} s, "
        f"checks {t_chk / (4 * seeds):.2f} s each); check protocol {proto['angles_deg']} deg, "
        f"{proto['sweep_deg']:g} deg sweeps, every module; false alarm {c.false_alarm:g} "
        f"(Sidak), repeatability {rep_text(cfg)}"
    )
    print(f"{'case':<16} {'rate':>6} {'only it':>8} {'its params':>10} {'other':>6} "
          f"{'bare stat':>9}")  # fmt: skip
    for case in CASES:
        what = "false alarms" if case == "unchanged" else "detected"
        if case == "unchanged":
            print(f"{case:<16} {hits[case] / seeds:6.3f} {'':>8} {'':>10} {'':>6} "
                  f"{bare[case] / seeds:9.3f}   ({what})")  # fmt: skip
        else:
            print(
                f"{case:<16} {hits[case] / seeds:6.3f} {named[case] / seeds:8.3f} "
                f"{params_named[case] / seeds:10.3f} {others[case] / seeds:6.3f} "
                f"{bare[case] / seeds:9.3f}   ({what})"
            )
    print(
        "  rate: detected (the verdict names the changed module) or false alarm; only it: "
        "no other module named; its params: its parameters changed by half the largest "
        "change or more all named; other: another module named too; bare stat: the same "
        "without the repeatability"
    )
    if honesty:
        z = np.array(honesty)
        print(
            "  the check's std devs against the truth (each module's change relative to the "
            f"others, {z.shape[0]} checks): RMS z {float(np.sqrt(np.mean(z**2))):.2f}; per "
            "parameter " + ", ".join(
                f"{k} {float(np.sqrt(np.mean(z[..., c] ** 2))):.2f}"
                for c, k in enumerate(PARAM_NAMES)
            )
        )


def shape_z(res: CalibrationResult, truth: RobotParams) -> np.ndarray:
    """(N, 5) z of a check's shape against the truth: each module's error relative to the
    others (:func:`swpc_hw.calibration.check.shape.relative_map`) over its std dev from
    the check's covariance alone."""
    from swpc_hw.calibration.check.shape import gauge_directions, module_statistic, relative_map

    T = as_matrix(truth)
    d = as_matrix(res.params) - T
    d[:, 2] = (d[:, 2] + math.pi) % (2 * math.pi) - math.pi
    assert res.covariance is not None
    C = res.covariance
    G = gauge_directions(T)
    w = 1.0 / np.maximum(np.diag(C), 1e-30)
    n = T.shape[0]
    out = []
    for k in range(n):
        L = relative_map(G, w, k, [a for a in range(n) if a != k])
        _, e, sd = module_statistic(L, d.ravel(), C)
        out.append(e / sd)
    return np.array(out)


# ---------------------------------------------------------------------------- service


@contextlib.contextmanager
def service(data: Path, truth: Path, seed: int) -> Iterator[Any]:
    """The service on the in-process simulator whose hidden truth is ``truth``: a client."""
    from fastapi.testclient import TestClient
    from pydantic import SecretStr

    from services.config.settings import ServiceSettings
    from services.http.app import create_app

    s = ServiceSettings(
        data_dir=data, token=SecretStr(TOKEN), sim_truth=truth, sim_seed=seed,
        allowed_hosts=["testserver"],
    )  # fmt: skip
    with TestClient(create_app(s)) as client:
        yield client


def start_and_wait(client: Any, what: str, body: dict[str, Any]) -> dict[str, Any]:
    """POST ``/<what>`` and poll it until it ends: its final status."""
    r = client.post(f"/{what}", json=body, headers={"Authorization": f"Bearer {TOKEN}"})
    assert r.status_code == 202, r.text
    path = f"/{what}/{r.json()['id']}"
    deadline = time.monotonic() + 900
    while True:
        st: dict[str, Any] = client.get(path).json()
        if st["state"] in ("DONE", "FAILED", "ABORTED"):
            return st
        assert time.monotonic() < deadline, f"{path} stuck in {st['state']}"
        time.sleep(0.05)


def service_check(
    data: Path,
    truth: Path,
    seed: int,
    overrides: dict[str, Any] | None = None,
    metrology: str = "mocap",
) -> dict[str, Any]:
    """One check on a service on ``truth`` (data dir ``data``, its file in force)."""
    with service(data, truth, seed) as client:
        body = {"overrides": overrides or {}, "metrology": metrology}
        return start_and_wait(client, "checks", body)


def service_calibration(data: Path, truth: Path, seed: int) -> dict[str, Any]:
    """One calibration (the default protocol), installed, on a service on ``truth``."""
    with service(data, truth, seed) as client:
        return start_and_wait(client, "calibrations", {})


def service_times() -> dict[str, float]:
    """Robot time of one check of each design candidate, the file in force the truth."""
    from swpc_hw.files.kinematic_file import save_kinematics

    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        truth = Path(tmp) / "truth.yaml"
        save_kinematics(truth, PAPER_CALIBRATED)
        save_kinematics(Path(tmp) / "kinematics.yaml", PAPER_CALIBRATED)
        for name, proto in CANDIDATES:
            st = service_check(Path(tmp), truth, 1, {"protocol": proto})
            out[name] = float(st["elapsed_s"]) if st["state"] == "DONE" else math.nan
    return out


def through_service(seeds: int, metrology: str = "mocap") -> None:
    from swpc_hw.files.kinematic_file import save_kinematics

    robots = truths(seeds)
    ids = PAPER_CALIBRATED.ids
    counts = {k: 0 for k in CASES}
    robot_s: list[float] = []
    wall: list[float] = []
    t0 = time.perf_counter()
    for i, truth in enumerate(robots):
        module = ids[i % len(ids)]
        with tempfile.TemporaryDirectory() as tmp:
            data = Path(tmp)
            path = data / "truth.yaml"
            save_kinematics(path, truth)
            cal = service_calibration(data, path, 100 + i)
            assert cal["state"] == "DONE", cal["reason"]
            line = []
            for case in CASES:
                d = drift(case, module, i)
                save_kinematics(path, changed(truth, module, d) if d else truth)
                t = time.perf_counter()
                st = service_check(data, path, 200 + i, metrology=metrology)
                wall.append(time.perf_counter() - t)
                assert st["state"] == "DONE", st["reason"]
                robot_s.append(float(st["elapsed_s"]))
                res = st["result"]
                ok = (res["verdict"] == "consistent") if case == "unchanged" else (
                    module in res["drifted_modules"]
                )
                counts[case] += ok if case != "unchanged" else not ok
                line.append(f"{case}: {res['verdict']} {res['drifted_modules']}")
            print(f"  seed {i} (module {module} changed): " + "; ".join(line), flush=True)
    print(
        f"[service {metrology}] {seeds} seeds per case through the service "
        f"({time.perf_counter() - t0:.0f} "
        f"s): false alarms {counts['unchanged'] / seeds:.3f}, detected "
        + ", ".join(f"{c} {counts[c] / seeds:.3f}" for c in CASES[1:])
        + f"; check robot time {min(robot_s):.1f}-{max(robot_s):.1f} s "
        f"(median {float(np.median(robot_s)):.1f}), wall {float(np.median(wall)):.1f} s median"
    )


def main() -> None:
    import logging

    logging.getLogger("swpc").setLevel(logging.ERROR)  # the verdicts' log lines
    cfg = RobotConfig()
    runs = int(os.environ.get("SWPC_BENCH_CHECK_DESIGN", "10"))
    seeds = int(os.environ.get("SWPC_BENCH_CHECK_SEEDS", "50"))
    service = int(os.environ.get("SWPC_BENCH_CHECK_SERVICE", "3"))
    if runs > 0:
        times = service_times() if service > 0 else {}
        design(runs, cfg, times)
    metrologies = os.environ.get("SWPC_BENCH_CHECK_METROLOGY", "mocap,imu").split(",")
    for metrology in metrologies:
        if seeds > 0:
            offline(seeds, cfg, metrology)
        if service > 0:
            through_service(service, metrology)


if __name__ == "__main__":
    main()
