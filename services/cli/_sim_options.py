"""Command-line options shared by the commands that simulate (``swpc datagen``, ``swpc
sim``, the demo), in human units."""

from __future__ import annotations

import argparse
from typing import Any


def add_noise_arguments(p: Any) -> None:
    """Mocap noise, dropouts, outliers and wheel slip (mm and degrees on the command line)."""
    p.add_argument("--pose-sigma-xy", type=float, default=0.0, help="pose noise, mm (0)")
    p.add_argument("--pose-sigma-yaw", type=float, default=0.0, help="yaw noise, deg (0)")
    p.add_argument("--dropout", type=float, default=0.0, help="fraction of poses dropped")
    p.add_argument("--outliers", type=float, default=0.0, help="fraction of outlier poses")
    p.add_argument("--outlier-magnitude", type=float, default=50.0, help="outlier jump, mm")
    p.add_argument("--slip-rate", type=float, default=0.0, help="slip bursts /s per wheel")


def add_gyro_arguments(g: Any) -> None:
    """The simulated z gyro (:class:`swpc_hw.imu.GyroOptions`, its defaults)."""
    from swpc_hw.imu import GyroOptions

    rate, noise, bias, walk, scale = GyroOptions().human()
    g.add_argument("--gyro-rate", type=float, default=rate, help=f"gyro samples /s ({rate:g})")
    g.add_argument(
        "--gyro-noise", type=float, default=noise, help=f"white noise, deg/s/sqrt(Hz) ({noise:g})"
    )
    g.add_argument("--gyro-bias", type=float, default=bias, help=f"bias, deg/s ({bias:g})")
    g.add_argument(
        "--gyro-bias-walk", type=float, default=walk, help=f"bias walk, deg/s/sqrt(s) ({walk:g})"
    )
    g.add_argument(
        "--gyro-scale-error", type=float, default=scale, help=f"scale error, %% ({scale:g})"
    )


def gyro_options(args: argparse.Namespace) -> Any:
    """The :class:`~swpc_hw.imu.GyroOptions` of :func:`add_gyro_arguments`."""
    from swpc_hw.imu import GyroOptions

    return GyroOptions.from_human(
        args.gyro_rate, args.gyro_noise, args.gyro_bias, args.gyro_bias_walk, args.gyro_scale_error
    )


METROLOGIES = ("mocap", "imu")
"""What measures the robot's motion: motion capture, or the IMU's gyro with the encoders
and a tape measure (the API's ``metrology``)."""


def add_metrology_argument(p: Any) -> None:
    """``--metrology mocap|imu`` (``--mocap-free``: the old spelling of ``imu``)."""
    p.add_argument(
        "--metrology",
        choices=METROLOGIES,
        default="mocap",
        help="what measures the robot's motion: motion capture (mocap) or the gyro, the "
        "encoders and a tape (imu)",
    )
    p.add_argument(
        "--mocap-free", dest="metrology", action="store_const", const="imu", help=argparse.SUPPRESS
    )
