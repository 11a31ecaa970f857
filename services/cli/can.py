"""``swpc can monitor``: live table of the module controllers on the CAN bus.

The driver stays INACTIVE (it only listens): state, mode and errors per axis, measured
heartbeat and feedback rates, positions, and the driver's error counters.  Exit status 1
(one line on stderr naming them) when a node has no heartbeat at the end.
``--emulate`` runs emulated controllers on the same (virtual) bus, for a demo.
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import Any


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser("can", help="CAN bus tools (monitor)")
    sub = parser.add_subparsers(dest="can_command", metavar="CAN_COMMAND", required=True)
    mon = sub.add_parser("monitor", help="live table of nodes: state, errors, rates, positions")
    mon.add_argument("--interface", default="virtual", help="python-can interface (virtual)")
    mon.add_argument("--channel", default="swpc", help="channel, e.g. vcan0 (swpc)")
    mon.add_argument("--bitrate", type=int, default=1_000_000)
    mon.add_argument("--nodes", default="1,2,3,4", help="node ids of modules 1..N (1,2,3,4)")
    mon.add_argument("--interval", type=float, default=0.5, help="refresh period, s (0.5)")
    mon.add_argument("--duration", type=float, default=0.0, help="stop after s (0 = Ctrl-C)")
    mon.add_argument("--plain", action="store_true", help="print plain tables, no live view")
    mon.add_argument("--emulate", action="store_true", help="also run emulated controllers")
    mon.add_argument(
        "--heartbeat-loss-periods",
        type=int,
        default=3,
        help="heartbeat periods (0.1 s) without one before a node counts as lost (3)",
    )
    mon.set_defaults(func=run_monitor)


def _table(drv: Any, prev: dict[int, tuple[float, int, int]], now: float) -> tuple[Any, str]:
    import math

    from rich.table import Table

    from firmware_protocol.codec import error_names

    table = Table(title=f"swpc can monitor — {drv.config.interface}:{drv.config.channel}")
    for col in (
        "module",
        "node",
        "alive",
        "steer",
        "wheel",
        "errors steer/wheel",
        "homed",
        "hb Hz",
        "fb Hz",
        "theta_hat deg",
        "psi rad",
        "counter",
    ):
        table.add_column(col, justify="right")
    lines = []
    for st in drv.iter_modules():
        first = st.module not in prev
        t0, hb0, fb0 = prev.get(st.module, (now, st.heartbeats, st.feedback_frames))
        dt = max(now - t0, 1e-9)
        hb_hz = "-" if first else f"{(st.heartbeats - hb0) / dt:.1f}"
        fb_hz = "-" if first else f"{(st.feedback_frames - fb0) / dt / 2:.1f}"  # 2 frames/sample
        prev[st.module] = (now, st.heartbeats, st.feedback_frames)
        theta = st.theta_hat
        row = [
            str(st.module),
            str(st.node),
            "yes" if st.alive else "NO",
            f"{st.states[0].name}/{st.modes[0].name}",
            f"{st.states[1].name}/{st.modes[1].name}",
            f"{error_names(st.errors[0])} / {error_names(st.errors[1])}",
            "yes" if st.homed else "no",
            hb_hz,
            fb_hz,
            "-" if math.isnan(theta) else f"{math.degrees(theta):.2f}",
            "-" if math.isnan(st.psi) else f"{st.psi:.4f}",
            "-" if st.feedback is None else str(st.feedback.counter),
        ]
        table.add_row(*row)
        lines.append("  ".join(row))
    s = drv.stats()
    caption = (
        f"rx {s.rx_frames}  tx {s.tx_frames}  error frames {s.error_frames}  bus-off {s.bus_off}"
        f"  unknown ids {s.unknown_ids}  bad DLC {s.bad_dlc}  decode errors {s.decode_errors}"
        f"  listener errors {s.listener_errors}  lost samples {s.feedback_gaps}"
        f"  heartbeat losses {s.heartbeat_losses}"
    )
    table.caption = caption
    return table, "\n".join(lines) + "\n" + caption


def run_monitor(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.live import Live

    from simulators.drives.swpc import ControllerEmulator, VirtualController
    from swpc_hw.drives.bus import CanConfig
    from swpc_hw.drives.errors import CanConfigError
    from swpc_hw.drives.swpc.driver import SwpcDriver

    try:
        nodes = [int(x) for x in args.nodes.split(",") if x.strip()]
    except ValueError:
        raise CanConfigError(
            f"--nodes: expected comma-separated node ids, got {args.nodes!r}"
        ) from None
    cfg = CanConfig(
        interface=args.interface,
        channel=args.channel,
        bitrate=args.bitrate,
        modules={i + 1: n for i, n in enumerate(nodes)},
        heartbeat_loss_periods=args.heartbeat_loss_periods,
    )
    emu = None
    if args.emulate:
        emu = ControllerEmulator(
            [VirtualController(n) for n in nodes], interface=args.interface, channel=args.channel
        )
        emu.start()
    console = Console()
    prev: dict[int, tuple[float, int, int]] = {}
    lost: list[str] = []
    end = time.monotonic() + args.duration if args.duration > 0 else float("inf")
    try:
        with SwpcDriver(cfg) as drv:
            time.sleep(min(args.interval, max(0.0, end - time.monotonic())))
            if args.plain or not sys.stdout.isatty():
                while True:
                    _, text = _table(drv, prev, time.monotonic())
                    print(text, flush=True)
                    if time.monotonic() + args.interval > end:
                        break
                    time.sleep(args.interval)
            else:
                with Live(console=console, refresh_per_second=4) as live:
                    while time.monotonic() < end:
                        table, _ = _table(drv, prev, time.monotonic())
                        live.update(table)
                        time.sleep(args.interval)
            lost = [
                f"module {st.module} (node {st.node})" for st in drv.iter_modules() if not st.alive
            ]
    finally:
        if emu is not None:
            emu.stop()
    if lost:
        print(
            f"swpc can monitor: error: no heartbeat from {', '.join(lost)} on "
            f"{args.interface}:{args.channel}",
            file=sys.stderr,
        )
        return 1
    return 0
