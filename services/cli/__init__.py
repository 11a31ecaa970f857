"""The ``swpc`` command: one subcommand per module of this package (and of its
:data:`GROUPS`).

Every module here whose name does not start with ``_`` is a subcommand (discovered at
start-up, as cantools discovers its subparsers): it defines ``register(subparsers) ->
None``, which adds its parser and sets ``func(args) -> int`` as default.  Heavy imports
stay inside ``func`` so that ``swpc --help`` is fast.  Add a subcommand by adding a
module.  The options several commands share are here (:func:`add_noise_arguments`,
:func:`add_gyro_arguments`, :func:`add_metrology_argument`).

Errors the user can act on (bad input, a file, a CAN interface that cannot be opened)
are one line on stderr, ``swpc <command>: error: ...``, and exit status 2; a bug keeps
its traceback.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import math
import pkgutil
import sys
from collections.abc import Sequence
from typing import Any, NamedTuple

from firmware_protocol.errors import FirmwareProtocolError
from swpc_hw.errors import SwpcError

SERVICE_EXTRA_PROBES = ("scipy", "can", "fastapi", "zenoh", "threadpoolctl")
"""One import name per part of pyproject's ``service`` extra that every command needs."""


def missing_service_extra() -> str | None:
    """The first of :data:`SERVICE_EXTRA_PROBES` not installed (a robot that installed
    ``swpc`` for its odometry only), or None."""
    return next((m for m in SERVICE_EXTRA_PROBES if importlib.util.find_spec(m) is None), None)


GROUPS = ("offline",)
"""Subpackages whose modules are subcommands too (:mod:`services.cli.offline`: the ones
that work on files and models, not on a robot)."""


def subcommand_modules() -> list[str]:
    """Dotted names of the subcommand modules (here and in :data:`GROUPS`), sorted by
    their subcommand's name."""
    names = [
        f"{__name__}.{info.name}"
        for info in pkgutil.iter_modules(__path__)
        if not info.name.startswith("_") and info.name not in GROUPS
    ]
    for group in GROUPS:
        pkg = importlib.import_module(f"{__name__}.{group}")
        names += [
            f"{pkg.__name__}.{info.name}"
            for info in pkgutil.iter_modules(pkg.__path__)
            if not info.name.startswith("_")
        ]
    return sorted(names, key=lambda n: n.rsplit(".", 1)[1])


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The ``swpc`` parser with every subcommand, or only ``command``'s when a module of
    that name exists: a subcommand's ``register`` may import what its defaults come
    from (``datagen``: the gyro simulator, 1 s of imports), which ``swpc sim`` or
    ``swpc serve`` should not pay at start-up."""
    from services.store.provenance import version_line

    parser = argparse.ArgumentParser(
        prog="swpc", description="Calibration system for single-wheel powered caster robots."
    )
    parser.add_argument("--version", action="version", version=version_line())
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    names = subcommand_modules()
    only = [n for n in names if n.rsplit(".", 1)[1] == command]
    for name in only or names:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    missing = missing_service_extra()
    if missing is not None:
        print(
            f"swpc: error: no module {missing!r}: the swpc command needs the extra 'service' "
            "(pip install 'swpc[service]'); a robot that runs only the odometry does not",
            file=sys.stderr,
        )
        return 2
    from swpc_hw.blas_threads import single_blas_thread

    single_blas_thread()
    args_in = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser(args_in[0] if args_in and not args_in[0].startswith("-") else None)
    args = parser.parse_args(args_in)
    try:
        return int(args.func(args))
    except (SwpcError, FirmwareProtocolError, OSError) as exc:
        print(f"swpc {args.command}: error: {one_line(exc)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    except Exception as exc:
        if type(exc).__module__.split(".")[0] != "can":  # a bug: keep its traceback
            raise
        print(f"swpc {args.command}: error: CAN: {one_line(exc)}", file=sys.stderr)
        return 2


def one_line(exc: BaseException) -> str:
    """The error's message on one line (an OSError with its errno name and file)."""
    if isinstance(exc, OSError) and exc.strerror:
        where = f"{exc.filename}: " if exc.filename else ""
        return f"{where}{exc.strerror}"
    text = " ".join(str(exc).split())
    return text or type(exc).__name__


# ---------------------------------------------------------- options several commands share
# the commands that simulate (``swpc datagen``, ``swpc sim``) and the demo, in human units


def add_noise_arguments(p: Any) -> None:
    """Mocap noise, dropouts, outliers and wheel slip (mm and degrees on the command line)."""
    p.add_argument("--pose-sigma-xy", type=float, default=0.0, help="pose noise, mm (0)")
    p.add_argument("--pose-sigma-yaw", type=float, default=0.0, help="yaw noise, deg (0)")
    p.add_argument("--dropout", type=float, default=0.0, help="fraction of poses dropped")
    p.add_argument("--outliers", type=float, default=0.0, help="fraction of outlier poses")
    p.add_argument("--outlier-magnitude", type=float, default=50.0, help="outlier jump, mm")
    p.add_argument("--slip-rate", type=float, default=0.0, help="slip bursts /s per wheel")


class Noise(NamedTuple):
    """:func:`add_noise_arguments`' values in SI units (m, rad)."""

    sigma_xy: float
    sigma_yaw: float
    dropout: float
    outliers: float
    outlier_magnitude: float
    slip_rate: float


def noise(args: argparse.Namespace) -> Noise:
    """The values of :func:`add_noise_arguments` in SI units (mm -> m, deg -> rad)."""
    return Noise(
        sigma_xy=args.pose_sigma_xy * 1e-3,
        sigma_yaw=math.radians(args.pose_sigma_yaw),
        dropout=args.dropout,
        outliers=args.outliers,
        outlier_magnitude=args.outlier_magnitude * 1e-3,
        slip_rate=args.slip_rate,
    )


def add_gyro_arguments(g: Any) -> None:
    """The simulated z gyro (:class:`swpc_hw.sensors.gyro.GyroOptions`, its defaults)."""
    from swpc_hw.sensors.gyro import GyroOptions

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
    """The :class:`~swpc_hw.sensors.gyro.GyroOptions` of :func:`add_gyro_arguments`."""
    from swpc_hw.sensors.gyro import GyroOptions

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


if __name__ == "__main__":
    sys.exit(main())
