"""``swpc datagen OUT_DIR``: write a simulated calibration run as a dataset directory.

The directory gets the dataset files of docs/dataset-format.md plus ``truth.yaml`` (the
hidden truth); with ``--metrology imu``, ``imu.csv`` and ``references.yaml`` instead of
``poses.csv``.  Human-facing options are in degrees and millimetres; everything written is
SI.  (``swpc simulate`` is its old name; ``swpc sim`` runs the virtual robot instead.)
"""

from __future__ import annotations

import argparse
import itertools
import math
from typing import Any

from services.cli import (
    add_gyro_arguments,
    add_metrology_argument,
    add_noise_arguments,
    gyro_options,
    noise,
)

TAPE_READINGS = 2
"""Tape readings of every distance between steering axes ``--metrology imu`` writes."""


def register(sub: Any) -> None:
    from swpc_hw.protocol import DEFAULT_PROTOCOL

    angles = DEFAULT_PROTOCOL.angles_deg
    p = sub.add_parser(
        "datagen",
        aliases=["simulate"],
        help="simulate the calibration experiment and write a dataset directory",
        description=(
            "Simulate the seed calibration experiment on a hidden truth robot (default: the "
            "paper's calibrated robot) and write robot.yaml (nominal), poses.csv, "
            "encoders.csv, segments.csv and truth.yaml."
        ),
    )
    p.add_argument("output", help="dataset directory to write")
    p.add_argument("--truth", help="kinematic file of the truth (default: paper Table 4)")
    p.add_argument("--nominal", help="kinematic file written as robot.yaml (default: design)")
    p.add_argument(
        "--angles", type=float, nargs="+", default=list(angles), metavar="DEG",
        help="steering angles of the locked module (deg, >= 2; default "
        + " ".join(f"{a:g}" for a in angles) + ")",
    )
    p.add_argument("--yaw-rate", type=float, default=0.5, help="rad/s, <0 clockwise (0.5)")
    p.add_argument("--spin-duration", type=float, default=12.0, help="s per segment (12)")
    add_noise_arguments(p)
    p.add_argument("--clock-offset", type=float, default=0.0, help="encoder - pose clock (s)")
    p.add_argument(
        "--counts-per-rev", type=int, default=2**17, help="encoder resolution, 0 = exact"
    )
    p.add_argument("--seed", type=int, default=0)
    g = p.add_argument_group(
        "metrology imu (without motion capture)",
        "--metrology imu writes imu.csv and references.yaml instead of poses.csv, from a "
        "run with rests and a straight drive (docs/imu.md)",
    )
    from simulators.offline.datagen_imu import IMU_PROTOCOL, ReferenceOptions

    rest, drive = IMU_PROTOCOL.rest_time, IMU_PROTOCOL.drive_length
    tape_mm = ReferenceOptions.stddev * 1e3
    add_metrology_argument(g)
    g.add_argument(
        "--rest-time", type=float, default=rest, help=f"s of stillness per rest ({rest:g})"
    )
    g.add_argument(
        "--drive-length", type=float, default=drive, help=f"straight drive, m ({drive:g})"
    )
    add_gyro_arguments(g)
    g.add_argument(
        "--reference-stddev",
        type=float,
        default=tape_mm,
        help=f"tape-measure std dev, mm ({tape_mm:g})",
    )
    g.add_argument(
        "--tape-readings",
        type=int,
        default=TAPE_READINGS,
        help=f"readings of every distance between steering axes ({TAPE_READINGS}: the "
        "recommended set, docs/imu-operation.md)",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from simulators.offline.datagen import ExperimentOptions, generate_experiment
    from swpc_hw.files.kinematic_file import load_robot
    from swpc_hw.robot.paper_robot import PAPER_CALIBRATED

    truth = load_robot(args.truth) if args.truth else PAPER_CALIBRATED
    nominal = load_robot(args.nominal) if args.nominal else None
    if len(args.angles) < 2:
        raise SystemExit("swpc datagen: error: --angles needs at least two values")
    n = noise(args)
    opt = ExperimentOptions(
        angles=tuple(math.radians(a) for a in args.angles),
        yaw_rate=args.yaw_rate,
        spin_duration=args.spin_duration,
        pose_sigma_xy=n.sigma_xy,
        pose_sigma_yaw=n.sigma_yaw,
        dropout_fraction=n.dropout,
        outlier_fraction=n.outliers,
        outlier_magnitude=n.outlier_magnitude,
        slip_burst_rate=n.slip_rate,
        clock_offset=args.clock_offset,
        counts_per_rev=args.counts_per_rev or None,
        seed=args.seed,
    )
    if args.metrology == "imu":
        return run_imu(args, truth, nominal, opt)
    exp = generate_experiment(truth, opt, nominal)
    exp.save(args.output)
    ds = exp.dataset
    n_enc = sum(len(e) for e in ds.encoders.values())
    print(
        f"wrote {args.output}: {exp.duration:.1f} s, {len(ds.poses)} poses, {n_enc} encoder "
        f"rows, {len(ds.segments)} segments ({exp.generation_seconds * 1e3:.0f} ms)"
    )
    return 0


def run_imu(args: argparse.Namespace, truth: Any, nominal: Any, opt: Any) -> int:
    """``--metrology imu``: the run with rests and a drive, written without poses.csv."""
    import dataclasses

    from simulators.offline.datagen_imu import ReferenceOptions, generate_imu_experiment

    opt = dataclasses.replace(opt, rest_time=args.rest_time, drive_length=args.drive_length)
    gyro = gyro_options(args)
    if args.tape_readings < 1:
        raise SystemExit("swpc datagen: error: --tape-readings needs at least 1")
    refs = ReferenceOptions(
        stddev=args.reference_stddev * 1e-3,
        axis_pairs=tuple(itertools.combinations(truth.ids, 2)) * args.tape_readings,
        straight_drive=args.drive_length > 0,
    )
    exp = generate_imu_experiment(truth, opt, gyro, refs, nominal)
    exp.save(args.output)
    ds = exp.dataset
    n_enc = sum(len(e) for e in ds.encoders.values())
    n_imu = 0 if ds.imu is None else len(ds.imu)
    print(
        f"wrote {args.output} (no poses.csv): {exp.experiment.duration:.1f} s, {n_imu} gyro "
        f"samples, {n_enc} encoder rows, {len(ds.segments)} segments, "
        f"{len(ds.references)} references"
    )
    return 0
