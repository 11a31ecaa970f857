"""``swpc sim``: run the virtual robot as a process (CAN controllers + physics + mocap).

Example (a separate process on a virtual CAN interface, mocap on loopback)::

    swpc sim --interface socketcan --channel vcan0 --zenoh-listen tcp/127.0.0.1:7447

The service then opens the same CAN channel and connects its zenoh session to the
listen endpoint.  Human-facing options are in mm, degrees and ms; everything published
is SI.  ``--time-scale S`` runs the simulated clock S times faster than wall time (see
:mod:`simulators.virtual_robot` for how a client matches it).
"""

from __future__ import annotations

import argparse
import errno
import math
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any

from services.cli import add_gyro_arguments, add_noise_arguments, gyro_options, noise

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"


def register(sub: Any) -> None:
    p = sub.add_parser(
        "sim",
        help="run the virtual robot: controllers on CAN, physics, mocap poses over zenoh",
        description=(
            "Simulate the robot's four (N) motor controllers on a CAN bus with the DBC's "
            "frames, the robot's motion (hidden true parameters), the motion-capture "
            "system (poses over zenoh on mocap/<robot>/pose), its gyro (imu/<robot>/data) "
            "and the ground truth (sim/<robot>/truth/{pose,params})."
        ),
    )
    p.add_argument("--interface", default="socketcan", help="python-can interface (socketcan)")
    p.add_argument("--channel", default="vcan0", help="CAN channel (vcan0)")
    p.add_argument("--bitrate", type=int, default=None, help="bit/s, if the interface needs it")
    p.add_argument(
        "--zenoh-listen",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help=f"zenoh endpoint to listen on (repeatable; default {DEFAULT_ENDPOINT})",
    )
    p.add_argument(
        "--zenoh-connect",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="zenoh endpoint to connect to (repeatable)",
    )
    p.add_argument("--zenoh-config", help="zenoh JSON5 config file (endpoints still explicit)")
    p.add_argument("--robot", default="swpc", help="robot id in the zenoh keys (swpc)")
    p.add_argument("--truth", help="kinematic file of the hidden truth (default: paper Table 4)")
    p.add_argument(
        "--wiring",
        help="YAML file of how the drives are really wired: crossed, swapped, inverted, "
        "another ratio, a turned motion-capture body (docs/commissioning.md; default: as "
        "configured)",
    )
    p.add_argument(
        "--drives",
        default=None,
        help="the drive kind the virtual robot's drives speak: swpc (default), cia402 (CiA 402 "
        "drives over CANopen) or odrive (virtual ODrives, firmware 0.6.x), each with its "
        "default CAN nodes",
    )
    p.add_argument(
        "--robot-config",
        help="robot config YAML whose drives: (kind, CAN nodes) the virtual drives take, as "
        "the service does",
    )
    p.add_argument(
        "--nodes",
        help="swpc drives: module:node pairs, e.g. 1:1,2:2,3:3,4:4 (default 1..N in order)",
    )
    p.add_argument("--time-scale", type=float, default=1.0, help="simulated s per wall s (1)")
    p.add_argument(
        "--physics-dt",
        type=float,
        default=5.0,
        help="longest physics step, ms (5; shorter when the feedback rate asks for it)",
    )
    from simulators.options import SimOptions

    rate, watchdog = SimOptions.feedback_rate_hz, SimOptions.watchdog_ms
    p.add_argument(
        "--feedback-rate", type=int, default=rate, help=f"initial feedback Hz ({rate})"
    )
    p.add_argument(
        "--watchdog-ms", type=int, default=watchdog, help=f"initial watchdog, ms ({watchdog})"
    )
    p.add_argument("--steer-counts", type=int, default=2**17, help="steering counts/turn")
    p.add_argument("--wheel-counts", type=int, default=2**17, help="wheel counts/turn")
    p.add_argument("--pose-rate", type=float, default=100.0, help="mocap Hz, <= 2000 (100)")
    p.add_argument(
        "--pose-encoding",
        choices=["native", "ros2-cdr"],
        default="native",
        help="mocap payload (native)",
    )
    add_noise_arguments(p)
    p.add_argument(
        "--mocap-qtm",
        type=int,
        metavar="PORT",
        help="serve the poses as a QTM real-time server on this loopback port instead of "
        "zenoh, for `swpc mocap --source qtm://127.0.0.1:PORT` (docs/mocap-bridge.md)",
    )
    p.add_argument("--latency", type=float, default=0.0, help="mocap latency, ms")
    p.add_argument(
        "--mocap-clock",
        choices=["host", "sim"],
        default="host",
        help="pose time stamps: the host's wall clock at sampling, as a real mocap's clock "
        "(host; a service on this machine maps them exactly with SWPC_MOCAP_CLOCK=wall), or "
        "the simulated time (sim; the service then needs SWPC_MOCAP_CLOCK=receive if the "
        "time scale is not 1)",
    )
    p.add_argument(
        "--clock-offset", type=float, default=0.0, help="mocap clock - its base clock, s"
    )
    p.add_argument("--bus-error-rate", type=float, default=0.0, help="injected bus errors /s")
    p.add_argument(
        "--mute",
        type=int,
        action="append",
        default=[],
        metavar="MODULE",
        help="start with this module's controller silent (heartbeat loss; repeatable)",
    )
    g = p.add_argument_group("gyro (imu/<robot>/data, sensor_msgs/msg/Imu in CDR)")
    add_gyro_arguments(g)
    p.add_argument("--truth-rate", type=float, default=50.0, help="truth pose Hz (50)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--duration", type=float, default=0.0, help="wall s to run (0: until ^C)")
    p.add_argument("--stats-every", type=float, default=0.0, help="print stats every s (0: off)")
    p.set_defaults(func=run)


def parse_nodes(text: str | None) -> dict[int, int] | None:
    """``"1:1,2:2"`` -> ``{1: 1, 2: 2}``."""
    if not text:
        return None
    out: dict[int, int] = {}
    for part in text.split(","):
        m, _, n = part.partition(":")
        out[int(m)] = int(n)
    return out


def sim_drives(args: argparse.Namespace) -> Any:
    """The virtual drives' config: ``--robot-config``'s ``drives:``, else ``--drives`` (its
    kind's default nodes), ``--nodes`` the old spelling of swpc drives' node map."""
    from pydantic import TypeAdapter

    from services.config.robot import load_robot_config
    from swpc_hw.drives.registry import DrivesConfig, parse_drives
    from swpc_hw.errors import SwpcError

    given = [n for n in ("robot_config", "drives", "nodes") if getattr(args, n)]
    if len(given) > 1:
        raise SwpcError(
            "give the drives once: " + " or ".join("--" + n.replace("_", "-") for n in given)
        )
    if args.robot_config:
        return load_robot_config(args.robot_config).drives
    doc: Any = parse_drives(args.drives or "swpc")
    if args.nodes:
        doc = {"kind": "swpc", "modules": parse_nodes(args.nodes)}
    try:
        return TypeAdapter(DrivesConfig).validate_python(doc)
    except ValueError as exc:
        raise SwpcError(f"--drives: {' '.join(str(exc).split())}") from None


def run(args: argparse.Namespace) -> int:
    from simulators.drives.wiring import WIRED_AS_CONFIGURED, load_wiring
    from simulators.options import SimOptions
    from simulators.physics.robot import PhysicsOptions
    from simulators.sensors.mocap import MocapOptions
    from simulators.virtual_robot import VirtualRobot
    from swpc_hw.files.kinematic_file import load_robot
    from swpc_hw.heap_freeze import freeze_startup_heap
    from swpc_hw.robot.paper_robot import PAPER_CALIBRATED

    truth = load_robot(args.truth) if args.truth else PAPER_CALIBRATED
    try:
        wiring = (
            load_wiring(Path(args.wiring), truth.ids) if args.wiring else WIRED_AS_CONFIGURED
        )
    except ValueError as exc:
        print(f"swpc sim: --wiring {exc}", file=sys.stderr)
        return 2
    n = noise(args)
    opt = SimOptions(
        robot=args.robot,
        drives=sim_drives(args),
        time_scale=args.time_scale,
        physics_dt=args.physics_dt * 1e-3,
        feedback_rate_hz=args.feedback_rate,
        watchdog_ms=args.watchdog_ms,
        steer_counts=args.steer_counts,
        wheel_counts=args.wheel_counts,
        physics=PhysicsOptions(slip_burst_rate=n.slip_rate, seed=args.seed),
        mocap=MocapOptions(
            rate=args.pose_rate,
            encoding=args.pose_encoding,
            sigma_xy=n.sigma_xy,
            sigma_yaw=n.sigma_yaw,
            dropout=n.dropout,
            outliers=n.outliers,
            outlier_magnitude=n.outlier_magnitude,
            latency=args.latency * 1e-3,
            clock_offset=args.clock_offset,
            seed=args.seed,
            qtm_port=args.mocap_qtm,
        ),
        gyro=gyro_options(args),
        truth_rate=args.truth_rate,
        bus_error_rate=args.bus_error_rate,
        mocap_clock=args.mocap_clock,
        seed=args.seed,
        wiring=wiring,
    )
    listen = args.zenoh_listen or ([] if args.zenoh_connect else [DEFAULT_ENDPOINT])
    import can

    from swpc_hw.errors import SwpcError

    try:
        sim = _open(VirtualRobot, truth, args, listen, opt)
    except (OSError, can.CanError, ValueError) as exc:
        code = exc.errno if isinstance(exc, OSError) else None
        hint = {
            errno.EAFNOSUPPORT: " (this kernel has no SocketCAN: see deploy/README.md, or run "
            "`swpc serve` with no SWPC_CAN_INTERFACE, which embeds the simulator)",
            errno.ENODEV: f" (no interface {args.channel}: deploy/vcan-up.sh {args.channel})",
        }.get(code or 0, "")
        detail = exc.strerror if isinstance(exc, OSError) and exc.strerror else exc
        raise SwpcError(
            f"cannot open CAN interface {args.interface!r} channel {args.channel!r}: "
            f"{detail}{hint}"
        ) from None
    done = threading.Event()

    def _stop(signum: int, frame: Any) -> None:
        done.set()

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _stop)
        signal.signal(signal.SIGINT, _stop)
    for m in args.mute:
        sim.mute(m)
    sim.start()
    freeze_startup_heap()  # no full-collection pause over the start-up heap (heartbeats)
    print(
        f"swpc sim: robot {args.robot!r}, {len(truth.modules)} modules on "
        f"{args.interface}:{args.channel} (drives {opt.drives.kind}, nodes "
        f"{opt.drives.for_modules(truth.ids).nodes()}), mocap {args.pose_rate:g} Hz "
        f"{args.pose_encoding} on mocap/{args.robot}/pose, gyro {args.gyro_rate:g} Hz on "
        f"imu/{args.robot}/data via {listen or args.zenoh_connect}, time scale {args.time_scale:g}",
        flush=True,
    )
    t_end = time.monotonic() + args.duration if args.duration > 0 else math.inf
    next_stats = time.monotonic() + args.stats_every if args.stats_every > 0 else math.inf
    try:
        while not done.is_set() and sim.running:
            now = time.monotonic()
            if now >= t_end:
                break
            if now >= next_stats:
                next_stats += args.stats_every
                print(format_stats(sim), flush=True)
            done.wait(min(t_end, next_stats, now + 0.5) - now)
    finally:
        sim.stop()
    print(format_stats(sim), flush=True)
    if sim.error is not None:
        print(f"swpc sim: simulation thread failed: {sim.error!r}")
        return 1
    return 0


def _open(
    simulator: Any, truth: Any, args: argparse.Namespace, listen: list[str], opt: Any
) -> Any:
    return simulator.open(
        truth,
        interface=args.interface,
        channel=args.channel,
        bitrate=args.bitrate,
        zenoh_listen=listen,
        zenoh_connect=args.zenoh_connect,
        zenoh_config=args.zenoh_config,
        options=opt,
    )


def format_stats(sim: Any) -> str:
    st = sim.stats()
    r = st.rates()
    fb = [v for k, v in r.items() if k.endswith("_feedback_hz")]
    return (
        f"sim {st.sim_time:8.2f} s  wall {st.wall_time:8.2f} s  scale {st.achieved_time_scale:5.2f}"
        f"  cpu {100 * st.cpu_share:5.1f} %  feedback {min(fb, default=0):6.1f} Hz/node  "
        f"poses {r['poses_hz']:7.1f} Hz  rx {st.frames_rx}  tx {st.frames_tx}  "
        f"overruns {st.overruns}"
    )
