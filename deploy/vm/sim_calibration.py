"""Calibrate through a running ``swpc serve`` over HTTP, and compare two results.

Standard library only (it runs inside the QEMU VM, where every import is slow)::

    sim_calibration.py run --url http://127.0.0.1:8080 --token T --overrides '{...}' \\
        --out result.json [--health-timeout 300] [--timeout 1800] [--service-log LOG]
    sim_calibration.py compare A.json B.json [--k 3]

``run`` waits for ``GET /health`` to answer with every node alive and a live mocap stream,
starts ``POST /calibrations`` with the overrides (``install: never``), follows the run
(state changes are printed) and writes the result document, plus the run's wall time and
final status, to ``--out``.  Exit status 0 only if the run ended DONE.

``run --abort-in STATE`` aborts the run (``POST /calibrations/{id}/abort``) once it
reaches STATE (e.g. SPIN: the robot turning under the service's control) and exits 0 only
if it then ends ABORTED (``--out`` gets its final status).  ``health`` only waits for
``GET /health`` as ``run`` does.

``compare`` checks that two results of the same configuration agree: for every module
and parameter (x_s, y_s, beta, b, r) the difference d and the combined std dev
s = sqrt(s_A**2 + s_B**2) of the two results satisfy |d| <= k s (k = 3).  A parameter
whose std dev is unknown in either result fails.  Prints the table of d / s.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path
from typing import Any

PARAMS = ("x_s", "y_s", "beta", "b", "r")


def _request(url: str, token: str | None, body: Any = None, timeout: float = 30.0) -> Any:
    data = None if body is None else json.dumps(body).encode()
    req = urllib.request.Request(url, data=data, method="GET" if body is None else "POST")
    req.add_header("Content-Type", "application/json")
    if token:
        req.add_header("Authorization", f"Bearer {token}")
    with urllib.request.urlopen(req, timeout=timeout) as resp:
        return json.loads(resp.read().decode())


def _tail(path: str | None, n: int = 15) -> str:
    if not path or not Path(path).exists():
        return ""
    lines = Path(path).read_text(errors="replace").splitlines()[-n:]
    return "\n".join(f"    | {line}" for line in lines)


def wait_healthy(url: str, timeout: float, service_log: str | None) -> dict[str, Any]:
    """Poll /health until every node is alive and mocap is live (on the in-process
    simulator, whose time stands still between runs: until it is ``ok``); the last answer."""
    t0 = time.monotonic()
    last: Any = None
    while time.monotonic() - t0 < timeout:
        try:
            last = _request(f"{url}/health", None, timeout=10.0)
        except urllib.error.HTTPError as exc:  # 503 "failing": not ready yet; keep its body
            last = f"HTTP {exc.code}: {exc.read().decode(errors='replace')[:500]}"
        except (urllib.error.URLError, ConnectionError, TimeoutError, OSError) as exc:
            last = f"{type(exc).__name__}: {exc}"
        else:
            nodes = last.get("nodes", {})
            live = nodes and all(n["alive"] for n in nodes.values()) and not last["mocap_stale"]
            if live or (last.get("simulated_time_still") and last.get("status") == "ok"):
                print(f"health: ok after {time.monotonic() - t0:.1f} s: {json.dumps(last)}")
                return dict(last)
        time.sleep(1.0)
    raise SystemExit(
        f"health: not ready within {timeout:g} s; last answer: {last}\n"
        f"  service log (tail):\n{_tail(service_log)}"
    )


def run(args: argparse.Namespace) -> int:
    url = args.url.rstrip("/")
    wait_healthy(url, args.health_timeout, args.service_log)
    overrides = json.loads(args.overrides)
    t0 = time.monotonic()
    started = _request(
        f"{url}/calibrations", args.token, {"overrides": overrides, "install": "never"}
    )
    run_id = started["id"]
    print(f"run {run_id} started with overrides {json.dumps(overrides)}", flush=True)
    seen = ""
    aborted = False
    st: dict[str, Any] = {}
    while time.monotonic() - t0 < args.timeout:
        st = _request(f"{url}/calibrations/{run_id}", None)
        key = f"{st['state']} {st['step']}"
        if key != seen:
            seen = key
            print(
                f"  {time.monotonic() - t0:7.1f} s  {st['state']:8s} {st['step']}  "
                f"progress {st['progress']:.2f}  poses {st['poses']}  "
                f"encoder samples {st['encoder_samples']}",
                flush=True,
            )
        if st["state"] in ("DONE", "FAILED", "ABORTED"):
            break
        if args.abort_in and st["state"] == args.abort_in and not aborted:
            _request(f"{url}/calibrations/{run_id}/abort", args.token, {})
            aborted = True
            print(f"  {time.monotonic() - t0:7.1f} s  abort requested in {st['state']}")
        time.sleep(0.5 if args.abort_in else 1.0)
    wall = time.monotonic() - t0
    doc: dict[str, Any] = {"status": st, "wall_s": wall, "overrides": overrides}
    if st.get("state") == "DONE":
        doc["result"] = _request(f"{url}/calibrations/{run_id}/result", None)
    Path(args.out).write_text(json.dumps(doc, indent=1))
    print(f"run {run_id}: {st.get('state')} after {wall:.1f} s wall; {st.get('reason') or ''}")
    if args.abort_in:
        return 0 if aborted and st.get("state") == "ABORTED" else 1
    if st.get("state") != "DONE":
        print(f"  errors: {st.get('errors')}\n  service log (tail):\n{_tail(args.service_log)}")
        return 1
    return 0


def compare(args: argparse.Namespace) -> int:
    docs = [json.loads(Path(p).read_text()) for p in (args.a, args.b)]
    for p, d in zip((args.a, args.b), docs, strict=True):
        if "result" not in d:
            print(f"{p}: no result (run {d.get('status', {}).get('state')})")
            return 1
    if docs[0].get("overrides") != docs[1].get("overrides"):
        print(f"not the same protocol: overrides {docs[0].get('overrides')} in {args.a}, "
              f"{docs[1].get('overrides')} in {args.b}")
        return 1
    mods = [{m["id"]: m for m in d["result"]["modules"]} for d in docs]
    print(
        f"{'module':>6} {'param':>5} {'A':>14} {'B':>14} {'A-B':>11} {'std dev':>10} {'|d|/s':>6}"
    )
    worst, bad = 0.0, []
    for mid in sorted(mods[0]):
        a, b = mods[0][mid], mods[1].get(mid)
        if b is None:
            bad.append(f"module {mid} missing in {args.b}")
            continue
        for p in PARAMS:
            sa = (a.get("stddev") or {}).get(p)
            sb = (b.get("stddev") or {}).get(p)
            d = a[p] - b[p]
            if sa is None or sb is None:
                bad.append(f"module {mid} {p}: std dev unknown")
                print(f"{mid:>6} {p:>5} {a[p]:14.7g} {b[p]:14.7g} {d:11.3g} {'unknown':>10}")
                continue
            s = math.hypot(sa, sb)
            ratio = abs(d) / s if s > 0 else math.inf
            worst = max(worst, ratio)
            if not ratio <= args.k:
                bad.append(f"module {mid} {p}: |A-B| = {abs(d):.3g} > {args.k:g} x {s:.3g}")
            print(f"{mid:>6} {p:>5} {a[p]:14.7g} {b[p]:14.7g} {d:11.3g} {s:10.3g} {ratio:6.2f}")
    print(f"largest |A-B| / combined std dev: {worst:.2f} (limit {args.k:g})")
    for d, p in zip(docs, (args.a, args.b), strict=True):
        print(
            f"{p}: {d['status']['state']} in {d['wall_s']:.1f} s wall, "
            f"{d['status']['poses']} poses, {d['status']['encoder_samples']} encoder samples"
        )
    for line in bad:
        print(f"MISMATCH {line}")
    return 1 if bad else 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("--url", default="http://127.0.0.1:8080")
    r.add_argument("--token", required=True)
    r.add_argument("--overrides", default="{}")
    r.add_argument("--out", required=True)
    r.add_argument("--health-timeout", type=float, default=300.0)
    r.add_argument("--timeout", type=float, default=1800.0)
    r.add_argument("--service-log")
    r.add_argument("--abort-in", metavar="STATE", help="abort the run once it reaches STATE")
    h = sub.add_parser("health")
    h.add_argument("--url", default="http://127.0.0.1:8080")
    h.add_argument("--timeout", type=float, default=300.0)
    h.add_argument("--service-log")
    c = sub.add_parser("compare")
    c.add_argument("a")
    c.add_argument("b")
    c.add_argument("--k", type=float, default=3.0)
    args = ap.parse_args(argv)
    if args.cmd == "health":
        wait_healthy(args.url.rstrip("/"), args.timeout, args.service_log)
        return 0
    return run(args) if args.cmd == "run" else compare(args)


if __name__ == "__main__":
    sys.exit(main())
