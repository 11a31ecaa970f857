"""``swpc drives scan``: which drives are on the robot's CAN bus, and are they the config's.

For a technician on a robot whose wiring nobody has checked: it finds the nodes on the
bus, says what each is and what state it is in, and sets that against the robot config's
``drives:`` (``--config``): each configured module and axis found or missing, the nodes
the config does not name, node ids two devices share.  It never moves a motor: it reads
(CANopen SDO uploads, ODrive's ``Get_Version`` on 0.6.x) and listens, and sends no NMT
command unless ``--wake`` asks for one reset of communication.  The kinds' scans are
``swpc_hw.drives.<kind>.scan``; the comparison ``swpc_hw.drives.scan``.

Exit status 0 when every node the config expects was found and none is in FAULT; 1
otherwise (one line on stderr naming what is wrong); 2 for bad arguments or a bus that
cannot be opened.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from typing import Any

KINDS = ("cia402", "odrive", "swpc")
TABLES: dict[str, list[list[str]]] = {
    "cia402": [
        ["NMT", "402 state", "error code", "error register", "heartbeat", "consumers"],
        ["device type", "vendor", "product", "revision", "serial", "name", "software", "modes"],
    ],
}
"""The kinds whose columns are split over several tables (else one table of them all)."""


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser("drives", help="the drives on the CAN bus (scan)")
    sub = parser.add_subparsers(dest="drives_command", metavar="DRIVES_COMMAND", required=True)
    p = sub.add_parser(
        "scan",
        help="find the drives on the bus and compare them with the robot config (reads only)",
        description="Find the drives on the CAN bus, say what each is and its state, and "
        "compare them with the robot config's drives (--config). It never moves a motor: it "
        "only reads and listens, and sends no NMT command unless --wake. CiA 402: "
        "heartbeats, then SDO uploads (0x1000 of every candidate node, then "
        "identity, modes, heartbeat settings, statusword, error code of each that answers); "
        "ODrive: heartbeats, and Get_Version (0.6.x); swpc: heartbeats. Exit status 1 when "
        "a node the config expects is missing, a drive is in FAULT or two devices share a "
        "node id.",
    )
    p.add_argument("--interface", default="virtual", help="python-can interface (virtual)")
    p.add_argument("--channel", default="swpc", help="channel, e.g. can0 or vcan0 (swpc)")
    p.add_argument("--bitrate", type=int, default=1_000_000)
    p.add_argument(
        "--config", help="robot config YAML: the drive kind and the nodes it expects"
    )
    p.add_argument("--kind", choices=KINDS, help="the drive kind, without --config")
    p.add_argument(
        "--firmware",
        choices=("0.5", "0.6"),
        help="ODrive firmware line without --config (0.6: S1, Pro; 0.5: v3.6)",
    )
    p.add_argument(
        "--nodes",
        help="cia402: probe only these nodes and the config's, e.g. 1,2,5-9 (default: "
        "1-127); odrive 0.6: also ask these for their version",
    )
    p.add_argument("--listen", type=float, default=1.0, help="s to listen first (1.0)")
    p.add_argument(
        "--probe-timeout", type=float, default=0.05, help="cia402: s for the 0x1000 probe (0.05)"
    )
    p.add_argument(
        "--sdo-timeout", type=float, default=0.3, help="cia402: s for each later SDO read (0.3)"
    )
    p.add_argument(
        "--wake",
        action="store_true",
        help="cia402: first send NMT reset communication to every node and wait for their "
        "boot-ups. This RESETS THE DRIVES' COMMUNICATION (PDOs stop, each node restarts its "
        "CANopen stack in PRE-OPERATIONAL): never while the robot runs",
    )
    p.add_argument("--json", action="store_true", help="print JSON instead of tables")
    p.set_defaults(func=run_scan)


def _table(headers: list[str], rows: list[list[str]]) -> str:
    widths = [max(len(h), *(len(r[i]) for r in rows)) for i, h in enumerate(headers)]
    lines = ["  ".join(h.ljust(w) for h, w in zip(headers, widths, strict=True)).rstrip()]
    lines += ["  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)).rstrip() for r in rows]
    return "\n".join(lines)


def render(report: Any) -> str:
    """The report as plain tables, the nodes' notes, and a summary line."""
    labels: list[str] = []
    for r in report.rows:
        for k in r.found.fields if r.found is not None else ():
            if k not in labels:
                labels.append(k)
    groups = [list(g) for g in TABLES.get(report.kind, [labels])]
    grouped = {k for g in groups for k in g}
    groups[0] += [k for k in labels if k not in grouped]  # e.g. "SDO": a heartbeat only
    out = []
    for group in groups:
        cols = [k for k in group if k in labels] or ["state"]
        rows = [
            [str(r.node), r.label(), r.status]
            + [(r.found.fields.get(k, "-") if r.found is not None else "-") for k in cols]
            for r in report.rows
        ]
        out.append(_table(["node", "expected", "status", *cols], rows) if rows else "")
    by_note: dict[str, list[int]] = {}
    for r in report.rows:
        for n in r.found.notes if r.found is not None else ():
            by_note.setdefault(n, []).append(r.node)
        if r.found is not None and r.found.duplicate:
            by_note.setdefault(f"duplicate node id ({r.found.duplicate})", []).append(r.node)
    notes = [
        f"node{'s' if len(ns) > 1 else ''} {', '.join(map(str, ns))}: {n}"
        for n, ns in by_note.items()
    ]
    counts = {s: sum(r.status == s for r in report.rows) for s in ("found", "MISSING",
                                                                 "unexpected", "DUPLICATE")}
    found = sum(r.found is not None for r in report.rows)
    summary = (
        f"{report.kind} on {report.bus}: {found} node(s) found"
        + (f" of {report.candidates} probed" if report.candidates else "")
        + f" in {report.elapsed_s:.2f} s"
    )
    if report.configured:
        summary += (
            f"; config: {counts['MISSING']} missing, {counts['unexpected']} unexpected, "
            f"{counts['DUPLICATE']} duplicate"
        )
    text = "\n\n".join(t for t in out if t) or "no node found"
    return "\n".join([text, "", *notes, *report.notes, summary]).replace("\n\n\n", "\n\n")


def _kind_and_drives(args: argparse.Namespace) -> tuple[str, Any]:
    from swpc_hw.drives.errors import CanConfigError

    if args.config is None:
        if args.kind is None:
            raise CanConfigError("give --config (a robot config) or --kind cia402|odrive|swpc")
        return args.kind, None
    from services.config.robot import load_robot_config

    drives = load_robot_config(args.config).drives
    if args.kind is not None and args.kind != drives.kind:
        raise CanConfigError(
            f"--kind {args.kind} but {args.config} has drives.kind {drives.kind}"
        )
    return drives.kind, drives


def run_scan(args: argparse.Namespace) -> int:
    from swpc_hw.drives.errors import CanConfigError
    from swpc_hw.drives.scan import ScanReport, compare, parse_nodes

    kind, drives = _kind_and_drives(args)
    if args.wake and kind != "cia402":
        raise CanConfigError(f"--wake is for cia402 drives (NMT), not {kind}")
    if args.listen < 0 or args.probe_timeout <= 0 or args.sdo_timeout <= 0:
        raise CanConfigError("--listen must be >= 0, --probe-timeout and --sdo-timeout > 0")
    low, high = (1, 127) if kind == "cia402" else (0, 63) if kind == "odrive" else (1, 8)
    try:
        extra = parse_nodes(args.nodes, low, high) if args.nodes else []
    except ValueError as exc:
        raise CanConfigError(f"--nodes: {exc}") from None
    bus_name = f"{args.interface}:{args.channel}"
    notes: list[str] = []
    if kind == "cia402":
        expected, found, candidates, elapsed = _scan_cia402(args, drives, extra, notes)
    elif kind == "odrive":
        expected, found, candidates, elapsed = _scan_odrive(args, drives, extra, notes)
    else:
        expected, found, candidates, elapsed = _scan_swpc(args, drives, notes)
    report = ScanReport(
        kind, bus_name, compare(expected, found, configured=drives is not None),
        configured=drives is not None, candidates=candidates, elapsed_s=elapsed, notes=notes,
    )  # fmt: skip
    if args.json:
        print(json.dumps(report.to_json(), indent=2))
    else:
        print(render(report))
    problems = report.problems()
    if problems:
        print(f"swpc drives scan: error: {'; '.join(problems)}", file=sys.stderr)
        return 1
    return 0


def _open_error(args: argparse.Namespace, exc: BaseException) -> Exception:
    from swpc_hw.drives.errors import CanBusError

    return CanBusError(
        f"cannot open CAN bus interface={args.interface!r} channel={args.channel!r}: {exc}"
    )


def _scan_cia402(
    args: argparse.Namespace, drives: Any, extra: list[int], notes: list[str]
) -> tuple[list[Any], list[Any], int, float]:
    import can
    import canopen

    from swpc_hw.drives.cia402 import scan as cia
    from swpc_hw.drives.cia402.config import ABSOLUTE

    homing: dict[int, object] = {}
    expected = []
    host = None
    if drives is not None:
        expected = cia.expected(drives)
        host = drives.host_node
        for md in drives.axes().values():
            homing[md.steer.node] = md.steer.homing
            homing[md.wheel.node] = ABSOLUTE  # a wheel does not home
    # every node by default (127 in about 0.2 s): a drive the config does not name, and
    # whose heartbeat is off (CiA 301's default), is found too; --nodes narrows the probe
    # to the config's nodes and those
    wanted = set(extra) if extra else set(range(1, 128))
    candidates = sorted(wanted | {e.node for e in expected})
    net = canopen.Network()
    net.NOTIFIER_CYCLE = 0.05  # disconnect() joins the notifier's wait
    try:
        net.connect(interface=args.interface, channel=args.channel, bitrate=args.bitrate)
    except (can.CanError, OSError, ValueError, ImportError) as exc:
        raise _open_error(args, exc) from exc
    try:
        result = cia.scan(
            net, candidates, listen_s=args.listen, probe_timeout_s=args.probe_timeout,
            sdo_timeout_s=args.sdo_timeout, wake=args.wake, homing=homing,
        )  # fmt: skip
    finally:
        net.disconnect()
    found = result.found
    if host is not None:
        mine = [f for f in found if f.node == host and f.fields.get("SDO") == "no answer"]
        if mine:
            found = [f for f in found if f not in mine]
            notes.append(
                f"node {host} (drives.host_node) sends heartbeats: a host (swpc serve?) is "
                "running on this bus"
            )
    notes += result.notes
    notes.append(f"probe of {result.candidates} node(s) (SDO 0x1000): {result.probe_s:.2f} s")
    return expected, found, result.candidates, result.elapsed_s


def _open_bus(args: argparse.Namespace) -> Any:
    import can

    try:
        return can.Bus(interface=args.interface, channel=args.channel, bitrate=args.bitrate)
    except (can.CanError, OSError, ValueError, ImportError) as exc:
        raise _open_error(args, exc) from exc


def _scan_odrive(
    args: argparse.Namespace, drives: Any, extra: list[int], notes: list[str]
) -> tuple[list[Any], list[Any], int, float]:
    from swpc_hw.drives.errors import CanConfigError
    from swpc_hw.drives.odrive import scan as od

    firmware = args.firmware or "0.6"
    expected = []
    if drives is not None:
        if args.firmware is not None and args.firmware != drives.firmware:
            raise CanConfigError(
                f"--firmware {args.firmware} but {args.config} has drives.firmware "
                f"{drives.firmware}"
            )
        firmware = drives.firmware
        expected = od.expected(drives)
    bus = _open_bus(args)
    try:
        result = od.scan(
            bus, firmware, sorted({e.node for e in expected} | set(extra)), listen_s=args.listen
        )
    finally:
        bus.shutdown()
    notes += result.notes
    return expected, result.found, result.candidates, result.elapsed_s


def _scan_swpc(
    args: argparse.Namespace, drives: Any, notes: list[str]
) -> tuple[list[Any], list[Any], int, float]:
    from swpc_hw.drives.swpc import scan as sw

    expected = sw.expected(drives) if drives is not None else []
    bus = _open_bus(args)
    t0 = time.monotonic()
    try:
        result = sw.scan(bus, listen_s=args.listen)
    finally:
        bus.shutdown()
    notes += result.notes
    return expected, result.found, result.candidates, time.monotonic() - t0
