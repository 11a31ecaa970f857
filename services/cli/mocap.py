"""``swpc mocap``: a lab's motion capture onto swpc's pose key (docs/mocap-bridge.md).

Reads one rigid body from QTM (Qualisys' real-time protocol), Vicon, OptiTrack, VRPN or
the motioncapture library's mock, converts it to swpc's world frame (z up, metres) and
publishes it on ``mocap/<robot>/pose`` over zenoh, with the robot's service's user and
password when it asks for them.  Prints frames, rate, frames dropped and frames without
the body every ``--report-every`` seconds.  Runs on the motion-capture PC, until ^C.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

LINK_TIMEOUT_S = 5.0
"""Wall seconds the bridge waits by default (``--link-timeout``) for its zenoh link to the
endpoints it connects to."""


def linked(session: Any, timeout: float) -> bool:
    """The session has a link with another within ``timeout`` wall seconds."""
    import time

    from swpc_hw.sensors.zenoh_session import linked_sessions

    deadline = time.monotonic() + timeout
    while linked_sessions(session) == 0:
        if time.monotonic() > deadline:
            return False
        time.sleep(0.05)
    return True


def register(sub: Any) -> None:
    p = sub.add_parser(
        "mocap",
        help="bridge a lab's motion capture (QTM, Vicon, OptiTrack, VRPN) to a robot",
        description=__doc__.split("\n\n", 1)[1] if __doc__ else None,
    )
    p.add_argument("--source", required=True,
                   help="qtm://HOST[:PORT], vicon://HOST, optitrack://HOST, vrpn://HOST, "
                        "qualisys://HOST or mock://")  # fmt: skip
    p.add_argument("--body", required=True, help="the rigid body's name in the system")
    p.add_argument("--robot", default="swpc", help="robot id in the zenoh key (swpc)")
    p.add_argument("--up", choices=("z", "y"), default="z",
                   help="the system's up axis (z; y for Motive's default)")  # fmt: skip
    p.add_argument(
        "--units",
        choices=("mm", "m"),
        default=None,
        help="the system's position unit (default: mm for qtm, m otherwise)",
    )
    p.add_argument("--zenoh-mode", default="peer", choices=("peer", "client"))
    p.add_argument("--zenoh-listen", action="append", default=[], metavar="ENDPOINT")
    p.add_argument("--zenoh-connect", action="append", default=[], metavar="ENDPOINT")
    p.add_argument("--zenoh-config", help="zenoh JSON5 config file")
    p.add_argument("--zenoh-user", help="zenoh user (the service's SWPC_ZENOH_PUBLISHERS)")
    p.add_argument(
        "--zenoh-password-file",
        type=Path,
        help="file holding the zenoh password (never on the command line)",
    )
    p.add_argument(
        "--link-timeout",
        type=float,
        default=LINK_TIMEOUT_S,
        help=f"s to wait for a zenoh link to --zenoh-connect before giving up "
        f"({LINK_TIMEOUT_S:g})",
    )
    p.add_argument("--report-every", type=float, default=5.0, help="s between reports (5)")
    p.add_argument("--duration", type=float, default=0.0, help="s to run (0: until ^C)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from services.sensors.bridge import Bridge, BridgeError, Source, zenoh_publisher
    from swpc_hw.sensors.mocap import pose_key, source_key
    from swpc_hw.sensors.zenoh_session import ZenohAuth, open_session

    source = Source.parse(args.source)
    auth = None
    if args.zenoh_user is not None or args.zenoh_password_file is not None:
        if args.zenoh_user is None or args.zenoh_password_file is None:
            raise BridgeError("--zenoh-user and --zenoh-password-file go together")
        try:
            password = args.zenoh_password_file.read_text().strip()
        except OSError as exc:
            raise BridgeError(f"--zenoh-password-file: {exc}") from None
        auth = ZenohAuth(user=args.zenoh_user, password=password)
    units = args.units or ("mm" if source.kind == "qtm" else "m")
    if args.link_timeout <= 0:
        raise BridgeError(f"--link-timeout {args.link_timeout:g}: must be above 0 s")
    session = open_session(
        mode=args.zenoh_mode, listen=args.zenoh_listen, connect=args.zenoh_connect,
        config_file=args.zenoh_config, auth=auth,
    )  # fmt: skip
    if args.zenoh_connect and not linked(session, args.link_timeout):
        session.close()
        raise BridgeError(
            f"no zenoh link to {', '.join(args.zenoh_connect)} within {args.link_timeout:g} s: "
            "a refused user or password, a wrong address, or nothing listening there"
        )
    key = pose_key(args.robot)
    status = zenoh_publisher(session, source_key(args.robot), "application/json")
    bridge = Bridge(source, args.body, zenoh_publisher(session, key), up=args.up, units=units,
                    report_every=args.report_every, status=status)  # fmt: skip
    print(f"swpc mocap: {args.source} body {args.body!r} ({args.up} up, {units}) -> {key}",
          flush=True)  # fmt: skip
    try:
        bridge.run(args.duration)
    except KeyboardInterrupt:
        pass
    finally:
        bridge.stop()
        session.close()
    print(f"swpc mocap: {bridge.count.line()}", flush=True)
    return 0
