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
   gives the same digest, bit for bit, at any load (on one CPU: docs/time.md);
4. stops the service (by its PID).

``--drives cia402|odrive`` runs the same on those drives (the virtual robot's drives and the
service's robot config name them, :data:`DEMO_DRIVES`), then the swpc-drive run of the same seed,
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
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import httpx

from services.cli import add_metrology_argument
from swpc_hw.blas_threads import single_blas_thread
from swpc_hw.robot.model import PARAM_NAMES, RobotParams
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED
from swpc_hw.sensors.zenoh_session import free_tcp_endpoint


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
        float(m[k]).hex() for m in result["modules"] for k in PARAM_NAMES
    ]
    return hashlib.sha256(" ".join(values).encode()).hexdigest()[:16]


def tape_references(http: httpx.Client, seed: int) -> list[dict[str, Any]]:
    """What the operator measures with a tape before a run without motion capture: the
    distances between the steering axes of every pair of modules, each read twice, as the
    simulator's tape reads them (``GET /simulator/axis-distances``, the console's "Read
    the simulator's tape")."""
    r = http.get("/simulator/axis-distances", params={"seed": seed})
    r.raise_for_status()
    return list(r.json()["references"])


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
    from swpc_hw.robot.frames import design_fit_transform, transform_robot
    from swpc_hw.robot.paper_robot import PAPER_NOMINAL

    phi, t = design_fit_transform(PAPER_CALIBRATED.arrays().P_s, PAPER_NOMINAL.arrays().P_s)
    return transform_robot(PAPER_CALIBRATED, phi, t, result.get("frame", "design-fit"))


DEMO_DRIVES: dict[str, dict[str, Any]] = {
    "cia402": {"kind": "cia402"},
    "odrive": {
        "kind": "odrive",
        "homing": "index",
        "firmware": "0.6",
        "modules": {
            m: {
                "steer": {"node": 2 * i, "gear_ratio": 8.0},
                "wheel": {"node": 2 * i + 1, "gear_ratio": 4.0},
            }
            for i, m in enumerate(PAPER_CALIBRATED.ids)
        },
    },
}
"""The demo's drives of each kind but swpc's own (which is the robot config's default):
CiA 402 drives with their default nodes and factors (docs/drives.md); an ODrive per module
(steering axis0, wheel axis1), geared 8:1 and 4:1."""


def demo_robot_config(data_dir: Path, drives: str, firmware: str) -> Path | None:
    """The demo's robot config with ``drives`` (None: the default robot config, swpc's own
    drives), written into ``data_dir``."""
    if drives == "swpc":
        return None
    import yaml

    from services.config.robot import RobotConfig

    doc = RobotConfig().to_document()
    kind = dict(DEMO_DRIVES[drives])
    if "firmware" in kind:  # a kind with firmware lines: the one asked for
        kind["firmware"] = firmware
    doc["drives"] = kind
    path = data_dir / "robot.yaml"
    path.write_text(yaml.safe_dump(RobotConfig.model_validate(doc).to_document()))
    return path


def combined_sd_differences(a: dict[str, Any], b: dict[str, Any]) -> tuple[float, str]:
    """The largest ``|a - b| / sqrt(sd_a^2 + sd_b^2)`` over every calibrated parameter of
    two results, and which parameter it is."""
    worst, where = 0.0, ""
    sb = {m["id"]: m for m in b["modules"]}
    for m in a["modules"]:
        o = sb[m["id"]]
        for k in PARAM_NAMES:
            z = abs(m[k] - o[k]) / math.hypot(m["stddev"][k], o["stddev"][k])
            if z >= worst:
                worst, where = z, f"module {m['id']} {k}"
    return worst, where


class _Service:
    """``swpc serve`` as a child process on the in-process simulator (step 1 of the module
    docstring): its address, token and PID; stopped by its PID on exit."""

    def __init__(
        self, data_dir: Path, sim_speed: float, seed: int, robot_config: Path | None = None,
        port: int | None = None,
    ) -> None:
        self.data_dir = data_dir
        self.token = secrets.token_urlsafe(16)
        self.port = port if port is not None else _free_port()
        self.base = f"http://127.0.0.1:{self.port}"
        env = dict(
            os.environ,
            SWPC_TOKEN=self.token,
            SWPC_DATA_DIR=str(data_dir),
            SWPC_SIM_SPEED=str(sim_speed),
            SWPC_SIM_SEED=str(seed),
            SWPC_PORT=str(self.port),
        )
        for key in ("SWPC_CAN_INTERFACE", "SWPC_TIME_SCALE", "SWPC_ROBOT_CONFIG"):
            env.pop(key, None)
        if robot_config is not None:
            env["SWPC_ROBOT_CONFIG"] = str(robot_config)
        self.log = open(data_dir / "service.log", "w")  # noqa: SIM115 - closed in __exit__
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "services.cli", "serve", "--log-level", "warning"],
            env=env,
            stdout=self.log,
            stderr=subprocess.STDOUT,
        )
        speed = "as fast as the host allows" if sim_speed <= 0 else f"at most {sim_speed:g}x"
        drives = "the robot config's" if robot_config is not None else "swpc"
        print(f"swpc serve started (pid {self.proc.pid}) on {self.base}, in-process "
              f"simulator ({speed}), {drives} drives")  # fmt: skip

    def wait_healthy(self, http: httpx.Client, timeout: float = 60.0) -> bool:
        """Until ``/health`` answers with live motion capture; False (the service's log
        printed) when the process ends or ``timeout`` s of wall time pass first."""
        deadline = time.monotonic() + timeout
        while True:
            try:
                if not http.get("/health").json()["mocap_stale"]:
                    return True
            except httpx.TransportError:
                pass
            if self.proc.poll() is not None or time.monotonic() > deadline:
                print((self.data_dir / "service.log").read_text()[-2000:], file=sys.stderr)
                print("demo: the service did not come up", file=sys.stderr)
                return False
            time.sleep(0.2)

    def __enter__(self) -> _Service:
        return self

    def __exit__(self, *exc: object) -> None:
        self.proc.send_signal(signal.SIGINT)
        try:
            self.proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self.log.close()
        print(f"service (pid {self.proc.pid}) stopped")


def run_service_demo(
    data_dir: Path, sim_speed: float, seed: int, keep_serving: bool = False,
    metrology: str = "mocap", robot_config: Path | None = None,
    results: list[dict[str, Any]] | None = None,
) -> int:
    """One calibration through ``swpc serve`` (module docstring); ``robot_config``: the
    service's robot config (default: its own default); ``results`` gets the result."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    t0 = time.monotonic()
    with _Service(data_dir, sim_speed, seed, robot_config) as svc, httpx.Client(
        base_url=svc.base, timeout=10.0
    ) as http:
        print(f"operator console while the demo runs: {svc.base}/ (token {svc.token})")
        if not svc.wait_healthy(http):
            return 1
        auth = {"Authorization": f"Bearer {svc.token}"}
        body: dict[str, Any] = {}
        if metrology == "imu":
            body = {"metrology": "imu", "references": tape_references(http, seed)}
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
        if results is not None:
            results.append(res)
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
            print(f"the console stays at {svc.base}/ (token {svc.token}); Ctrl-C stops the "
                  "service")  # fmt: skip
            with contextlib.suppress(KeyboardInterrupt):
                svc.proc.wait()
        else:
            print(f"the demo's service stops now, and {svc.base}/ with it: `make console` "
                  "keeps one up on the simulated robot for calibrations from the page")  # fmt: skip
        return 0


CONSOLE_PORT = 8080
"""``make console``'s port when it is free (else any free one, printed)."""


def run_console(data_dir: Path, seed: int, port: int | None = None) -> int:
    """``make console``: ``swpc serve`` on the in-process simulator at the robot's own pace
    (1 simulated s per wall s, so that a run in the console moves as on a robot), no
    calibration started; prints where to click and the token, and keeps the service up
    until Ctrl-C (then stops it by its PID).  ``port``: the one asked for (``make console
    PORT=N``; taken: an error), else :data:`CONSOLE_PORT` when free, else any free one."""
    asked = port is not None
    try:
        with contextlib.closing(socket.socket()) as probe:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as uvicorn binds
            probe.bind(("127.0.0.1", CONSOLE_PORT if port is None else port))
        port = CONSOLE_PORT if port is None else port
    except OSError as exc:
        if asked:
            print(f"port {port} on 127.0.0.1 is not free ({exc.strerror}): pick another "
                  "(make console PORT=N)", file=sys.stderr)  # fmt: skip
            return 2
        port = _free_port()
    with _Service(data_dir, 1.0, seed, port=port) as svc, httpx.Client(
        base_url=svc.base, timeout=10.0
    ) as http:
        if not svc.wait_healthy(http):
            return 1
        print(
            f"\nopen {svc.base}/ in a browser: the operator console, on the simulated robot"
            f"\n  press Start; the console asks once for the bearer token: {svc.token}"
            "\n  the console shows the run as it goes; Abort stops the robot at once"
            f"\n  the API's own pages: {svc.base}/docs; the service's data and log: {data_dir}"
            "\nCtrl-C stops the service"
        )
        try:
            code = svc.proc.wait()
        except KeyboardInterrupt:
            return 0  # the way to stop it; __exit__ stops the service
        if code in (0, -signal.SIGINT, -signal.SIGTERM):
            return 0  # a terminal's Ctrl-C reached the service before this process
        print(f"the service ended on its own (exit status {code}): its log is "
              f"{data_dir / 'service.log'}", file=sys.stderr)  # fmt: skip
        return 1


AGREEMENT = 3.0
"""Two calibrations of the same robot agree when every parameter differs by at most this
many combined std devs (their noise is independent: the largest of 20 such differences is
about 2 by chance alone)."""


def run_offline_demo(out: Path, seed: int) -> int:
    from services.cli import main as swpc_main
    from simulators.offline.datagen import ExperimentOptions, generate_experiment

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
        "--console", action="store_true",
        help="start no calibration: keep the service and its console up, on the simulator at "
        "the robot's own pace, until Ctrl-C (make console)",
    )
    parser.add_argument(
        "--port", type=int, default=None,
        help=f"--console's port on 127.0.0.1 (default {CONSOLE_PORT} when free, else any free "
        "one; make console PORT=N)",
    )
    parser.add_argument(
        "--keep-serving", action="store_true",
        help="after the run, keep the service (and its console at /) up until Ctrl-C",
    )
    add_metrology_argument(parser)
    parser.add_argument(
        "--drives", choices=["swpc", *DEMO_DRIVES], default="swpc",
        help="the drive kind of the virtual robot and the service (default swpc); with "
        "another kind the same seed then runs on swpc drives, and the largest difference "
        "of the two results in combined std devs is printed",
    )
    parser.add_argument(
        "--odrive-firmware", choices=["0.5", "0.6"], default="0.6",
        help="the firmware line of drives that have them (--drives odrive; default 0.6)",
    )
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.offline:
        return run_offline_demo(out, args.seed)
    if args.console:
        return run_console(out.resolve(), args.seed, args.port)
    results: list[dict[str, Any]] = []
    code = run_service_demo(
        out.resolve(), args.sim_speed, args.seed, args.keep_serving, args.metrology,
        demo_robot_config(out.resolve(), args.drives, args.odrive_firmware), results,
    )
    if code != 0 or args.drives == "swpc":
        return code
    ref = out.resolve() / "swpc"
    ref.mkdir(exist_ok=True)
    print(f"\nthe same seed on swpc drives ({ref}):")
    code = run_service_demo(
        ref, args.sim_speed, args.seed, False, args.metrology, None, results
    )
    if code != 0:
        return code
    worst, where = combined_sd_differences(results[0], results[1])
    print(f"{args.drives} against swpc drives, seed {args.seed}: largest difference "
          f"{worst:.2f} combined std devs ({where}); digests "
          f"{parameters_digest(results[0])} / {parameters_digest(results[1])}")  # fmt: skip
    return 0 if worst <= AGREEMENT else 1


if __name__ == "__main__":
    sys.exit(main())
