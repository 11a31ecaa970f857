"""``swpc odometry --kinematics FILE``: the robot's odometry as ROS 2 over zenoh.

Publishes ``nav_msgs/msg/Odometry`` on ``/odom`` and ``tf2_msgs/msg/TFMessage`` on ``/tf``
(``odom -> base_link``) at the odometry's update rate, on rmw_zenoh's keys
(:mod:`swpc_hw.onboard.ros2`; docs/ros2.md), and reloads the kinematic file when a new one is
installed.  Readings come from the drives' CAN feedback (``--can-interface``, through the
robot config's driver, as ``swpc validate`` drives them) or from a recorded dataset's
``encoders.csv`` (``--encoders DIR``: a replay, stamps on the dataset's clock).

The drift monitor watches the calibration while the robot works (``--no-drift`` turns it
off; docs/odometry.md): a calibration suspect raised or cleared is a log line
``event=calibration_suspect`` / ``event=calibration_suspect_cleared`` with its evidence,
and a status on ``/diagnostics``.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import threading
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from swpc_hw.onboard.drift import SuspectChange

log = logging.getLogger("swpc.odometry")


def register(sub: Any) -> None:
    p = sub.add_parser(
        "odometry",
        help="the odometry as ROS 2 /odom and /tf over zenoh (rmw_zenoh's keys)",
        description=__doc__.split("\n\n", 1)[1] if __doc__ else None,
    )
    p.add_argument("--kinematics", required=True, metavar="FILE",
                   help="the installed kinematic file (reloaded when it changes)")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--can-interface", help="python-can interface of the drives, e.g. socketcan")
    src.add_argument("--encoders", metavar="DIR",
                     help="replay a dataset directory's encoders.csv instead")
    p.add_argument("--can-channel", default="can0")
    p.add_argument("--can-bitrate", type=int, default=1_000_000)
    p.add_argument("--robot-config", help="robot config YAML (default: the paper's robot)")
    p.add_argument("--wait-subscriber", type=float, default=5.0, metavar="SECONDS",
                   help="replay: wait up to this long for a subscriber of /odom first (5)")
    p.add_argument("--domain-id", type=int, default=0, help="ROS_DOMAIN_ID (0)")
    p.add_argument("--namespace", default="", help="ROS 2 namespace of the topics ('')")
    p.add_argument("--zenoh-mode", default="peer")
    p.add_argument("--zenoh-listen", nargs="*", default=[], metavar="ENDPOINT")
    p.add_argument("--zenoh-connect", nargs="*", default=[], metavar="ENDPOINT")
    p.add_argument("--zenoh-config", help="zenoh JSON5 config file")
    p.add_argument("--drift", action=argparse.BooleanOptionalAction, default=True,
                   help="watch the calibration for drift while driving (default: on)")
    p.set_defaults(func=run)


def log_suspect(change: SuspectChange) -> str:
    """The log line of a calibration suspect raised (WARNING) or cleared (INFO)."""
    from services.store.logs import event

    if change.raised:
        return event(log, logging.WARNING, "calibration_suspect", **change.suspect.fields())
    return event(log, logging.INFO, "calibration_suspect_cleared", **change.suspect.fields())


def _drift(args: argparse.Namespace) -> dict[str, Any]:
    """The stream's drift arguments for ``--drift`` / ``--no-drift``."""
    from swpc_hw.onboard.drift import DriftOptions

    return {"drift": DriftOptions(), "on_suspect": log_suspect} if args.drift else {}


def run(args: argparse.Namespace) -> int:
    from services.store.logs import configure
    from swpc_hw.onboard.ros2.publisher import ZenohRos2Publisher
    from swpc_hw.onboard.ros2.stream import Ros2OdometryStream
    from swpc_hw.sensors.zenoh_session import open_session

    configure()  # swpc's lines to stderr, as swpc serve writes them
    session = open_session(
        mode=args.zenoh_mode, listen=args.zenoh_listen, connect=args.zenoh_connect,
        config_file=args.zenoh_config,
    )
    # a replay has no real time to keep: it delivers every message (the drives' odometry
    # drops what the network cannot take, as rmw_zenoh's keep-last publishers do)
    publisher = ZenohRos2Publisher(session, domain_id=args.domain_id, namespace=args.namespace,
                                   block=bool(args.encoders))
    try:
        if args.encoders:
            base_link = None
            if args.robot_config is not None:
                from services.config.robot import load_robot_config

                base_link = load_robot_config(args.robot_config).base_link
            stream = Ros2OdometryStream(args.kinematics, publisher, base_link=base_link,
                                        **_drift(args))
            _wait_subscriber(publisher, args.wait_subscriber)
            _replay(stream, args.encoders)
        else:
            stream = _on_the_drives(args, publisher)
        print(f"swpc odometry: {stream.published} messages on /odom and /tf, "
              f"{stream.reloads} reloads")
    finally:
        publisher.close()
        with contextlib.suppress(Exception):
            session.close()
    return 0


def _wait_subscriber(publisher: Any, limit: float) -> None:
    """Until a subscriber of ``/odom`` matches (a replay has no message to lose), at most
    ``limit`` seconds."""
    from swpc_hw.clock import SystemClock
    from swpc_hw.onboard.ros2.messages import ODOMETRY

    clock = SystemClock()
    end = clock.now() + limit
    while not publisher.matched("/odom", ODOMETRY) and clock.now() < end:
        clock.sleep(0.01)


def _replay(stream: Any, directory: str) -> None:
    from swpc_hw.files.dataset import load_dataset
    from swpc_hw.onboard.odometry_log import synchronize_encoders

    ds = load_dataset(directory)
    t, th, ps = synchronize_encoders(ds.encoders, stream.ids)
    for k in range(t.shape[0]):
        stream.update(float(t[k]), th[k], ps[k])


def _on_the_drives(args: argparse.Namespace, publisher: Any) -> Any:
    """Until Ctrl-C: the drives' feedback, aligned by :class:`DriverOdometry`, into the
    stream (stamps: the host's epoch time of each reading)."""
    from services.cli.offline.validate import validation_settings
    from services.config.robot import load_robot_config
    from services.config.timing import robot_drives
    from swpc_hw.clock import SystemClock
    from swpc_hw.onboard.ros2.stream import Ros2OdometryStream

    config = load_robot_config(args.robot_config)
    st = validation_settings(can_interface=args.can_interface, can_channel=args.can_channel,
                             can_bitrate=args.can_bitrate)
    clock = SystemClock(rate=st.external_time_scale)
    stream = Ros2OdometryStream(args.kinematics, publisher,
                                stamp_offset=clock.wall() - clock.now(),
                                base_link=config.base_link, **_drift(args))
    driver = robot_drives(st, config, interface=args.can_interface, channel=args.can_channel,
                          clock=clock)
    stream.watch(clock)  # the kinematic file looked at and parsed off the update loop
    try:
        driver.configure()
        follow_drives(driver, stream, polarity=config.axis_signs())
        print("swpc odometry: publishing /odom and /tf; Ctrl-C stops")
        with contextlib.suppress(KeyboardInterrupt):
            threading.Event().wait()
    finally:
        driver.shutdown()
        stream.close()
    return stream


def follow_drives(driver: Any, stream: Any, polarity: Any = None) -> Any:
    """The drives' feedback into ``stream`` (a :class:`~swpc_hw.onboard.ros2.stream.
    Ros2OdometryStream`), one reading of all modules at a time, aligned on the modules'
    counter clock by :class:`~swpc_hw.validation.odometry_feed.DriverOdometry`, each axis
    turned by the robot config's ``polarity``: what ``swpc odometry`` does on a robot."""
    from swpc_hw.validation.odometry_feed import DriverOdometry

    return DriverOdometry(
        driver, stream.odometry.params, on_update=stream.update, polarity=polarity
    )
