"""``make demo``: a whole calibration on the in-process simulator, as an operator runs it.

1. starts ``swpc serve`` (a separate process) on its default: the virtual robot (hidden
   truth = the paper's Table 4 calibrated values; the robot config claims the nominal
   design) in the service's process on a virtual CAN bus, mocap over zenoh on loopback,
   in simulated time (as fast as the host allows; ``--sim-speed`` caps it);
2. starts a calibration through the HTTP API with the bearer token (what ``curl -X POST
   -H 'Authorization: Bearer ...' http://127.0.0.1:PORT/calibrations`` does);
3. shows the progress (the operator console at ``/`` shows it too: its address and the
   token are printed first), then prints the nominal / calibrated / true table, where the
   kinematic file was written, and a digest of the calibrated parameters: the same seed
   gives the same digest, bit for bit, on any host and at any load;
4. stops the service (by its PID).

``--drives cia402`` runs the same on CiA 402 drives (the virtual robot's drives and the
service's robot config say ``drives: cia402``), then the swpc-drive run of the same seed,
and prints the largest difference between the two calibrations in combined std devs.

``--offline`` instead generates a dataset and solves it with ``swpc solve`` (no service).
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import math
import os
import secrets
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import httpx

from services.cli._sim_options import add_metrology_argument
from swpc_hw.blas_threads import single_blas_thread
from swpc_hw.model import RobotParams
from swpc_hw.paper_robot import PAPER_CALIBRATED
from swpc_hw.zenoh_session import free_tcp_endpoint


def _free_port() -> int:
    return int(free_tcp_endpoint().rsplit(":", 1)[1])


def _table(result: dict[str, Any], truth_robot: RobotParams = PAPER_CALIBRATED) -> str:
    truth = {m.id: m for m in truth_robot.modules}
    rows = [["module", "param", "unit", "nominal", "calibrated", "std dev", "true", "error"]]
    units = {
        "x_s": ("mm", 1e3),
        "y_s": ("mm", 1e3),
        "beta": ("deg", 180 / math.pi),
        "b": ("mm", 1e3),
        "r": ("mm", 1e3),
    }
    for m in result["modules"]:
        for k, (unit, f) in units.items():
            est, nom, tru = m[k] * f, m["nominal"][k] * f, getattr(truth[m["id"]], k) * f
            sd = (m["stddev"] or {}).get(k, math.nan) * f
            fmt = "{:.4f}" if unit == "deg" else "{:.3f}"
            rows.append(
                [
                    str(m["id"]),
                    k,
                    unit,
                    fmt.format(nom),
                    fmt.format(est),
                    fmt.format(sd),
                    fmt.format(tru),
                    f"{est - tru:+.4f}",
                ]
            )
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    lines = ["  ".join(c.rjust(w) for c, w in zip(r, widths, strict=True)) for r in rows]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


def parameters_digest(result: dict[str, Any]) -> str:
    """sha256 (first 16 hex digits) of every calibrated parameter's exact float value."""
    values = [
        float(m[k]).hex() for m in result["modules"] for k in ("x_s", "y_s", "beta", "b", "r")
    ]
    return hashlib.sha256(" ".join(values).encode()).hexdigest()[:16]


def tape_references(seed: int, stddev: float = 0.5e-3) -> list[dict[str, Any]]:
    """What the operator measures with a tape before a run without motion capture: the
    distances between the steering axes of every pair of modules (the simulator's truth,
    with the tape's error)."""
    import itertools

    import numpy as np

    rng = np.random.default_rng([seed, 20])
    a = PAPER_CALIBRATED.arrays()
    ids = PAPER_CALIBRATED.ids
    return [
        {
            "kind": "axis_distance",
            "modules": [ids[i], ids[j]],
            "value": float(np.linalg.norm(a.P_s[i] - a.P_s[j])) + float(rng.normal(0, stddev)),
            "stddev": stddev,
        }
        for i, j in itertools.combinations(range(len(ids)), 2)
    ]


def operator_step(
    http: httpx.Client, run_id: str, st: dict[str, Any], auth: dict[str, str]
) -> None:
    """Play the operator of a run without motion capture: mark the floor (MARK), measure
    the drive with the simulator's tape (MEASURE)."""
    if st["state"] == "MARK":
        http.post(f"/calibrations/{run_id}/continue", headers=auth)
        print(f"\nMARK: {st['step']}\n  -> POST /calibrations/{run_id}/continue")
    elif st["state"] == "MEASURE":
        tape = http.get("/simulator/tape-measure", params={"run": run_id}).json()
        ref = {k: tape[k] for k in ("kind", "value", "stddev")}
        r = http.post(f"/calibrations/{run_id}/references", json={"references": [ref]},
                      headers=auth)  # fmt: skip
        if r.status_code == 200:
            sd = ref["stddev"] * 1e3
            print(f"\nMEASURE: the simulator's tape reads {ref['value']:.4f} m (std {sd:g} mm)"
                  f" -> POST /calibrations/{run_id}/references")  # fmt: skip


def design_fit_truth(result: dict[str, Any]) -> RobotParams:
    """The simulator's truth in the design-fit frame of a result without motion capture
    (as ``swpc solve --truth`` re-expresses it)."""
    from swpc_hw.frames import design_fit_transform, transform_robot
    from swpc_hw.paper_robot import PAPER_NOMINAL

    phi, t = design_fit_transform(PAPER_CALIBRATED.arrays().P_s, PAPER_NOMINAL.arrays().P_s)
    return transform_robot(PAPER_CALIBRATED, phi, t, result.get("frame", "design-fit"))


DRIVES = ("swpc", "cia402")
"""The drive kinds the demo's virtual robot and service can run on (swpc_hw.drives)."""


def run_service_demo(
    data_dir: Path, sim_speed: float, seed: int, keep_serving: bool = False,
    metrology: str = "mocap", drives: str = "swpc", result: dict[str, Any] | None = None,
) -> int:
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    token = secrets.token_urlsafe(16)
    port = _free_port()
    env = dict(
        os.environ,
        SWPC_TOKEN=token,
        SWPC_DATA_DIR=str(data_dir),
        SWPC_SIM_SPEED=str(sim_speed),
        SWPC_SIM_SEED=str(seed),
        SWPC_PORT=str(port),
    )
    for key in ("SWPC_CAN_INTERFACE", "SWPC_TIME_SCALE", "SWPC_ROBOT_CONFIG"):
        env.pop(key, None)
    if drives != "swpc":
        robot = data_dir / "robot.yaml"
        robot.write_text(f"# written by services.demo --drives {drives}\ndrives: {drives}\n")
        env["SWPC_ROBOT_CONFIG"] = str(robot)
    t0 = time.monotonic()
    log = open(data_dir / "service.log", "w")  # noqa: SIM115 - lives as long as the process
    proc = subprocess.Popen(
        [sys.executable, "-m", "services.cli", "serve", "--log-level", "warning"],
        env=env,
        stdout=log,
        stderr=subprocess.STDOUT,
    )
    base = f"http://127.0.0.1:{port}"
    speed = "as fast as the host allows" if sim_speed <= 0 else f"at most {sim_speed:g}x"
    print(f"swpc serve started (pid {proc.pid}) on {base}, in-process simulator ({speed}), "
          f"{drives} drives")  # fmt: skip
    print(f"operator console: {base}/ (token {token})")
    try:
        with httpx.Client(base_url=base, timeout=10.0) as http:
            deadline = time.monotonic() + 60
            while True:
                try:
                    health = http.get("/health").json()
                    if not health["mocap_stale"]:
                        break
                except httpx.TransportError:
                    pass
                if proc.poll() is not None or time.monotonic() > deadline:
                    print((data_dir / "service.log").read_text()[-2000:], file=sys.stderr)
                    print("demo: the service did not come up", file=sys.stderr)
                    return 1
                time.sleep(0.2)
            auth = {"Authorization": f"Bearer {token}"}
            body: dict[str, Any] = {}
            if metrology == "imu":
                body = {"metrology": "imu", "references": tape_references(seed)}
                print("without motion capture: the tape-measured distances between the steering "
                      "axes go with the request")  # fmt: skip
            r = http.post("/calibrations", json=body, headers=auth)
            r.raise_for_status()
            run_id = r.json()["id"]
            print(f"POST /calibrations -> {r.status_code}, Location: {r.headers['location']}")
            with Progress(
                TextColumn("{task.description}"),
                BarColumn(),
                TextColumn("{task.percentage:>5.1f}%"),
                TimeElapsedColumn(),
            ) as bar:
                task = bar.add_task("starting", total=1.0)
                while True:
                    st = http.get(f"/calibrations/{run_id}").json()
                    desc = f"{st['state']:<8} module {st['module'] or '-'}/{st['modules_total']}"
                    bar.update(task, completed=st["progress"], description=desc)
                    if st["state"] in ("DONE", "FAILED", "ABORTED"):
                        break
                    operator_step(http, run_id, st, auth)
                    time.sleep(0.25)
            if st["state"] != "DONE":
                print(f"calibration {st['state']}: {st['reason']}", file=sys.stderr)
                return 1
            res = http.get(f"/calibrations/{run_id}/result").json()
            if result is not None:
                result.update(res)
            print()
            if metrology == "imu":
                print("frame design-fit: the truth re-expressed in it")
                print(_table(res, design_fit_truth(res)))
            else:
                print(_table(res))
            q = res["quality"]
            print(f"\nposes used {q.get('poses_used', 0)}, wheel increments used "
                  f"{q['increments_used']}")  # fmt: skip
            print(f"kinematic file written: {res['kinematics_path']}")
            print(f"run dataset (solve offline with `swpc solve`): {res['dataset_dir']}")
            print(f"calibrated parameters digest (seed {seed}): {parameters_digest(res)}")
            print(f"demo wall time: {time.monotonic() - t0:.1f} s")
            if keep_serving:
                print(f"the console stays at {base}/ (token {token}); Ctrl-C stops the service")
                with contextlib.suppress(KeyboardInterrupt):
                    proc.wait()
            return 0
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        log.close()
        print(f"service (pid {proc.pid}) stopped")


AGREEMENT = 3.0
"""Two calibrations of the same robot agree when every parameter differs by at most this
many combined std devs (their noise is independent: the largest of 20 such differences is
about 2 by chance alone)."""


def largest_difference(a: dict[str, Any], b: dict[str, Any]) -> tuple[float, str]:
    """The largest ``|a - b| / sqrt(sd_a^2 + sd_b^2)`` over every calibrated parameter of
    two results of the same robot, and which parameter it is."""
    worst, which = 0.0, ""
    other = {m["id"]: m for m in b["modules"]}
    for m in a["modules"]:
        o = other[m["id"]]
        for k in ("x_s", "y_s", "beta", "b", "r"):
            sd = math.hypot(m["stddev"][k], o["stddev"][k])
            z = abs(m[k] - o[k]) / sd
            if z >= worst:
                worst, which = z, f"module {m['id']} {k}"
    return worst, which


def compare_drives(out: Path, sim_speed: float, seed: int, metrology: str) -> int:
    """The demo on CiA 402 drives, then on swpc drives (same seed): both DONE, and how far
    apart their parameters are in combined std devs."""
    results: dict[str, dict[str, Any]] = {}
    for kind in ("cia402", "swpc"):
        d = out / kind
        d.mkdir(parents=True, exist_ok=True)
        print(f"\n=== {kind} drives ===")
        res: dict[str, Any] = {}
        code = run_service_demo(d, sim_speed, seed, metrology=metrology, drives=kind, result=res)
        if code:
            return code
        results[kind] = res
    z, which = largest_difference(results["cia402"], results["swpc"])
    print(f"\ncia402 vs swpc drives (seed {seed}): largest difference {z:.2f} combined std "
          f"devs ({which}); digests {parameters_digest(results['cia402'])} / "
          f"{parameters_digest(results['swpc'])}")  # fmt: skip
    return 0 if z <= AGREEMENT else 1


def run_offline_demo(out: Path, seed: int) -> int:
    from services.cli import main as swpc_main
    from simulators.datagen import ExperimentOptions, generate_experiment

    opts = ExperimentOptions(
        pose_sigma_xy=0.5e-3,
        pose_sigma_yaw=math.radians(0.05),
        dropout_fraction=0.05,
        outlier_fraction=0.005,
        slip_burst_rate=0.1,
        seed=seed,
    )
    exp = generate_experiment(PAPER_CALIBRATED, opts)
    dataset = out / "dataset"
    exp.save(dataset)
    return swpc_main(
        [
            "solve",
            str(dataset),
            "-o",
            str(out / "kinematics.yaml"),
            "--truth",
            str(dataset / "truth.yaml"),
        ]
    )


def main(argv: list[str] | None = None) -> int:
    single_blas_thread()
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--out", default="out/demo", help="data directory (default out/demo)")
    parser.add_argument(
        "--sim-speed", type=float, default=0.0,
        help="most simulated s per wall s (default 0: as fast as the host allows)",
    )
    parser.add_argument("--offline", action="store_true", help="dataset + swpc solve only")
    parser.add_argument(
        "--keep-serving", action="store_true",
        help="after the run, keep the service (and its console at /) up until Ctrl-C",
    )
    add_metrology_argument(parser)
    parser.add_argument(
        "--drives", choices=DRIVES, default="swpc",
        help="the robot's drive kind (swpc); cia402 also runs swpc and compares the results",
    )
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.offline:
        return run_offline_demo(out, args.seed)
    if args.drives != "swpc":
        return compare_drives(out.resolve(), args.sim_speed, args.seed, args.metrology)
    return run_service_demo(
        out.resolve(), args.sim_speed, args.seed, args.keep_serving, args.metrology
    )


if __name__ == "__main__":
    sys.exit(main())
