"""``swpc check``: does the robot still match its kinematic file? (docs/check.md)

* ``swpc check [--url URL]``: starts a check on a running service (``POST /checks`` with
  the bearer token: ``SWPC_TOKEN``, else ``--token-file``, else the token the service
  keeps in its data dir, ``<SWPC_DATA_DIR>/api-token``), follows it and prints the
  verdict and the per-parameter table.
* ``swpc check --offline RUN_DIR`` (a check's directory: its ``dataset/`` and
  ``file-in-force.yaml``) or ``--offline DATASET --file KINEMATICS``: the same check
  solved here, from recorded data, no robot (what the service's SOLVE does).

Exit status: 0 consistent, 1 drifted, 2 an error (one line on stderr), 3 the check did
not finish (FAILED or ABORTED: its reason).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path
from typing import Any

DRIFTED = 1
NOT_DONE = 3


def register(sub: Any) -> None:
    p = sub.add_parser(
        "check",
        help="check that the robot still matches its kinematic file (a short run, or a "
        "recorded one with --offline)",
        description=(
            "Start a check of the kinematic file in force on a running service (POST /checks) "
            "and print its verdict: per module and parameter the change since the file, its "
            "std dev and z, per module a chi-square against its threshold, and consistent or "
            "drifted (recalibrate module k, or the whole robot). --offline solves a recorded "
            "check instead. Exit status 0 consistent, 1 drifted, 2 error, 3 not finished. "
            "See docs/check.md."
        ),
    )
    service_arguments(p)
    p.add_argument(
        "--metrology", choices=("mocap", "imu"),
        help="mocap (motion capture) or imu (the gyro and the encoders: the robot's shape); "
        "default the service's",
    )  # fmt: skip
    p.add_argument("--overrides", help="JSON overrides of the check's protocol and limits")
    p.add_argument("--timeout", type=float, default=600.0, help="wall s to wait (default 600)")
    p.add_argument(
        "--offline",
        metavar="DIR",
        help="solve a recorded check: a check's directory (dataset/, file-in-force.yaml) "
        "or a dataset directory with --file",
    )
    p.add_argument("--file", help="with --offline: the kinematic file to judge")
    p.add_argument(
        "--robot-config", help="with --offline: robot config YAML (its check settings)"
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.offline:
        return offline(args)
    return over_http(args)


def service_arguments(p: argparse.ArgumentParser) -> None:
    """``--url`` and ``--token-file``: the running service a subcommand talks to (read by
    :func:`token` and :func:`follow_run`)."""
    p.add_argument(
        "--url",
        default=os.environ.get("SWPC_URL", "http://127.0.0.1:8080"),
        help="the service (default $SWPC_URL, else http://127.0.0.1:8080)",
    )
    p.add_argument(
        "--token-file", help="file holding the bearer token (default: $SWPC_TOKEN, else the "
        "service's data dir's api-token)"
    )  # fmt: skip


def token(args: argparse.Namespace) -> str:
    from services.config.settings import ServiceSettings, SettingsError

    if args.token_file:
        try:
            return Path(args.token_file).read_text(encoding="utf-8").strip()
        except OSError as exc:
            raise SettingsError(f"--token-file: {args.token_file}: {exc.strerror}") from exc
    env = os.environ.get("SWPC_TOKEN")
    if env:
        return env
    path = ServiceSettings().token_file
    try:
        return path.read_text(encoding="utf-8").strip()
    except OSError as exc:
        raise SettingsError(
            f"no token: set SWPC_TOKEN or --token-file (the data dir's {path}: {exc.strerror})"
        ) from exc


def over_http(args: argparse.Namespace) -> int:
    import json

    import httpx

    from swpc_hw.errors import SwpcError

    body: dict[str, Any] = {}
    if args.overrides:
        try:
            body["overrides"] = json.loads(args.overrides)
        except ValueError as exc:
            raise SwpcError(f"--overrides: not JSON: {exc}") from exc
    if args.metrology:
        body["metrology"] = args.metrology
    auth = {"Authorization": f"Bearer {token(args)}"}
    with httpx.Client(base_url=args.url, timeout=10.0) as http:
        st = follow_run(http, args.url, "/checks", body, auth, "check", args.timeout)
    print(f"robot time {st['elapsed_s']} s")
    if st["state"] != "DONE":
        print(f"check {st['state']}: {st['reason']}", file=sys.stderr)
        return NOT_DONE
    res = st["result"]
    print(verdict_text(res))
    return 0 if res["verdict"] == "consistent" else DRIFTED


def follow_run(
    http: Any, url: str, path: str, body: dict[str, Any] | None, auth: dict[str, str],
    noun: str, timeout: float,
) -> dict[str, Any]:
    """POST ``path`` (a run: a check or a commissioning), then its status until it ends,
    each new state and step printed: the ended run's status.  :class:`SwpcError` when no
    service answers, the start is refused, or the run outlasts ``timeout`` s."""
    import httpx

    from swpc_hw.errors import SwpcError

    try:
        r = http.post(path, json=body, headers=auth)
    except httpx.TransportError as exc:
        raise SwpcError(f"{url}: no service answers: {exc}") from exc
    if r.status_code != 202:
        raise SwpcError(f"POST {path}: {r.status_code}: {response_detail(r)}")
    rid = r.json()["id"]
    print(f"{noun} {rid} started ({url}{r.headers.get('location', '')})", flush=True)
    deadline = time.monotonic() + timeout
    last = None
    while True:
        st: dict[str, Any] = http.get(f"{path}/{rid}").json()
        line = f"{st['state']} {st['step']}"
        if line != last:
            print(f"  {line}", flush=True)
            last = line
        if st["state"] in ("DONE", "FAILED", "ABORTED"):
            return st
        if time.monotonic() > deadline:
            raise SwpcError(f"{noun} {rid} still {st['state']} after {timeout:g} s")
        time.sleep(0.25)


def response_detail(r: Any) -> str:
    try:
        d = r.json().get("detail")
    except ValueError:
        return str(r.text)[:200]
    if isinstance(d, list):
        return "; ".join(str(e.get("msg")) for e in d)
    return str(d)


def offline(args: argparse.Namespace) -> int:
    from services.config.robot import RobotConfig, load_robot_config
    from services.runs.check import FILE_IN_FORCE
    from swpc_hw.calibration.check.dataset_check import check_dataset
    from swpc_hw.errors import SwpcError
    from swpc_hw.files.dataset import load_dataset
    from swpc_hw.files.kinematic_file import load_kinematics

    d = Path(args.offline)
    dataset, file = d, args.file
    if (d / "dataset").is_dir():
        dataset = d / "dataset"
        file = file or str(d / FILE_IN_FORCE)
    if file is None:
        raise SwpcError("--offline DATASET needs --file KINEMATICS (the file to judge)")
    cfg = load_robot_config(args.robot_config) if args.robot_config else RobotConfig()
    c = cfg.check
    kf = load_kinematics(file)
    _, verdict = check_dataset(
        load_dataset(dataset), kf.params, kf.covariance,
        false_alarm=c.false_alarm, whole_robot=c.whole_robot,
        repeatability=c.repeatability.per_parameter(), source=str(dataset),
    )  # fmt: skip
    print(verdict_text(verdict.document()))
    return 0 if verdict.verdict == "consistent" else DRIFTED


def verdict_text(res: dict[str, Any]) -> str:
    """The verdict, the modules' chi-squares and the per-parameter table, for people."""
    lines = [res["summary"], ""]
    q = res["chi2_threshold"]
    for m in res["modules"]:
        mark = "DRIFTED " + ", ".join(m["parameters"]) if m["drifted"] else "ok"
        lines.append(f"module {m['id']}: chi2 {m['chi2']:7.2f} (threshold {q:.2f})  {mark}")
    lines.append("")
    head = ["module", "param", "unit", "file", "check", "change", "std dev", "z", ""]
    rows = [head]
    for r in res["table"]:
        d = 4 if r["unit"] == "deg" else 3
        rows.append(
            [
                str(r["module"]), r["param"], r["unit"], f"{r['file']:.{d}f}",
                f"{r['check']:.{d}f}", f"{r['change']:+.{d}f}", f"{r['stddev']:.{d + 1}f}",
                f"{r['z']:+.1f}", "drifted" if r["drifted"] else "",
            ]
        )  # fmt: skip
    widths = [max(len(r[i]) for r in rows) for i in range(len(head))]
    for k, r in enumerate(rows):
        lines.append("  ".join(c.rjust(w) for c, w in zip(r, widths, strict=True)).rstrip())
        if k == 0:
            lines.append("  ".join("-" * w for w in widths))
    lines += [f"note: {n}" for n in res.get("notes", [])]
    return "\n".join(lines)
