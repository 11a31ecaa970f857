"""``swpc commission``: what the robot's drives really move, and its robot config corrected
(docs/commissioning.md).

``swpc commission [--url URL] [--accept]`` starts a commissioning on a running service
(``POST /commissions`` with the bearer token, found as ``swpc check`` finds it), follows it
and prints what each module's drives move, the findings (each naming the axis and its fix),
what the config cannot hold, and the robot config corrected as a difference against the
one in force.  Nothing is written unless ``--accept`` (``POST /commissions/{id}/accept``:
the service's robot config file, the one in force kept beside it).

Exit status: 0 the robot matches its config, 1 it does not (the findings; with
``--accept`` the corrected config is written), 2 an error (one line on stderr), 3 the
commissioning did not finish (FAILED or ABORTED: its reason).
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

MISWIRED = 1
NOT_DONE = 3


def register(sub: Any) -> None:
    from services.cli.check import service_arguments

    p = sub.add_parser(
        "commission",
        help="find what the robot's drives really move (crossed nodes, swapped or inverted "
        "axes, ratios, steering zeros) and correct the robot config",
        description=(
            "Start a commissioning on a running service (POST /commissions): a few degrees of "
            "motion per module, observed by motion capture. Prints the findings and the "
            "corrected robot config as a difference; --accept writes it (the one in force "
            "is kept). Exit status 0 right, 1 miswired, 2 error, 3 not finished. See "
            "docs/commissioning.md."
        ),
    )
    service_arguments(p)
    p.add_argument(
        "--accept", action="store_true",
        help="write the corrected robot config over the service's (SWPC_ROBOT_CONFIG)",
    )  # fmt: skip
    p.add_argument("--timeout", type=float, default=600.0, help="wall s to wait (default 600)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import httpx

    from services.cli.check import follow_run, response_detail, token
    from swpc_hw.errors import SwpcError

    auth = {"Authorization": f"Bearer {token(args)}"}
    with httpx.Client(base_url=args.url, timeout=10.0) as http:
        st = follow_run(http, args.url, "/commissions", None, auth, "commissioning", args.timeout)
        cid = st["id"]
        print(f"robot time {st['elapsed_s']} s")
        if st["state"] != "DONE":
            print(f"commissioning {st['state']}: {st['reason']}", file=sys.stderr)
            return NOT_DONE
        res = st["result"]
        print(report_text(res))
        if res["right"]:
            return 0
        if args.accept:
            a = http.post(f"/commissions/{cid}/accept", headers=auth)
            if a.status_code != 200:
                why = response_detail(a)
                raise SwpcError(f"POST /commissions/{cid}/accept: {a.status_code}: {why}")
            got = a.json()
            print(f"written: {got['written']} (the one in force kept as {got['backup']})")
            if got["restart"]:
                print("the drives' part changed: restart the service to use it")
        else:
            print("nothing written: swpc commission --accept writes the corrected config")
    return MISWIRED


def report_text(res: dict[str, Any]) -> str:
    """What a commissioning found, for people: per module what its drives move, the
    findings, what the config cannot hold, the corrected config's difference."""
    lines = []
    for m in res["modules"]:
        moves = "?" if m["physical"] is None else f"module {m['physical']}"
        steer = (
            "?" if m["steer_sign"] is None
            else f"sign {m['steer_sign']:+d} ratio {m['steer_ratio']:.2f} "
            f"zero {m['zero_deg']:.1f} deg"
        )  # fmt: skip
        wheel = (
            "?" if m["wheel_sign"] is None
            else f"sign {m['wheel_sign']:+d} ratio {m['wheel_ratio']:.2f}"
        )  # fmt: skip
        swapped = "  STEER AND WHEEL SWAPPED" if m["swapped"] else ""
        lines.append(
            f"module {m['module']}: moves {moves}; steering {steer}; wheel {wheel}{swapped}"
        )
    lines.append(
        f"largest motion: {res['largest_turn_deg']:.1f} deg, {res['largest_move_mm']:.0f} mm"
    )
    if res["right"]:
        lines.append("the robot matches its config")
        return "\n".join(lines)
    lines.append("")
    lines += [f"- {f['text']}" for f in res["findings"]]
    if res["not_in_config"]:
        lines += ["", "not in the robot config (fix them where they are):"]
        lines += [f"- {t}" for t in res["not_in_config"]]
    if res["diff"]:
        lines += ["", res["diff"].rstrip()]
    if res.get("config_error"):
        lines += ["", f"the corrected config does not load: {res['config_error']}"]
    return "\n".join(lines)
