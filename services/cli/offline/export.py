"""``swpc export FILE --to urdf|ros2-params|kinematics [-o OUT] [--robot-config CONFIG]``:
a kinematic file where a ROS 2 robot looks, in its base_link (docs/ros2.md)."""

from __future__ import annotations

import argparse
import sys
from typing import Any

TARGET_NAMES = ("urdf", "ros2-params", "kinematics")


def register(sub: Any) -> None:
    p = sub.add_parser(
        "export",
        help="write a kinematic file as a URDF, a ROS 2 parameter file or a kinematic file, "
        "in base_link",
        description=(
            "Re-express a kinematic file (frame R, design-fit or base_link) in the robot's "
            "base_link (the robot config's base_link; none: base_link = R) and write it as a "
            "URDF of the caster modules, a ROS 2 parameter file (the layout of ros2_controllers' "
            "swerve_drive_controller, and the whole calibration), or a kinematic file with "
            "frame: base_link. See docs/ros2.md. A bad file: one-line error, exit status 2, "
            "no output."
        ),
    )
    p.add_argument("file", help="kinematic file (swpc-kinematics/1)")
    p.add_argument("--to", required=True, choices=TARGET_NAMES, help="what to write")
    p.add_argument("-o", "--output", help="file to write (default: standard output)")
    p.add_argument(
        "--robot-config",
        help="robot config YAML whose base_link places base_link and whose polarity is "
        "written beside the joints (default: none, base_link = R, polarity unknown)",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from services.config.robot import load_robot_config
    from swpc_hw.errors import SwpcError
    from swpc_hw.files.kinematic_file import atomic_write_text, load_kinematics
    from swpc_hw.onboard.export import make_export, render

    kf = load_kinematics(args.file)
    config = load_robot_config(args.robot_config) if args.robot_config else None
    base_link = config.base_link if config is not None else None
    polarity = config.axis_signs() if config is not None else None
    try:
        text = render(make_export(kf, base_link, str(args.file), polarity), args.to)
    except ValueError as exc:
        raise SwpcError(f"{args.file}: {exc}") from exc
    if args.output is None:
        sys.stdout.write(text)
    else:
        atomic_write_text(args.output, text)
        print(f"wrote {args.output} ({args.to}, frame base_link)", file=sys.stderr)
    return 0
