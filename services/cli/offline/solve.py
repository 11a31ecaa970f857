"""``swpc solve DATASET_DIR -o kinematics.yaml``: calibrate a recorded run offline."""

from __future__ import annotations

import argparse
import math
import os
import sys
from typing import Any


def _offset(value: str) -> float | str:
    if value == "auto":
        return value
    try:
        x = float(value)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"expected seconds or 'auto', got {value!r}") from exc
    if not math.isfinite(x):
        raise argparse.ArgumentTypeError("time offset must be finite")
    return x


def register(sub: Any) -> None:
    p = sub.add_parser(
        "solve",
        help="calibrate from an offline dataset directory and write the kinematic file",
        description=(
            "Solve a dataset directory (robot.yaml, poses.csv, encoders.csv, segments.csv; "
            "see docs/dataset-format.md) and write the kinematic file. Without poses.csv "
            "(imu.csv and references.yaml instead) the IMU solver runs and writes the "
            "design-fit frame. Bad data: one-line error, exit status 2, no output file."
        ),
    )
    p.add_argument("dataset", help="dataset directory")
    p.add_argument("-o", "--output", required=True, help="kinematic file to write (YAML)")
    p.add_argument(
        "--time-offset",
        type=_offset,
        default=0.0,
        metavar="SECONDS|auto",
        help="encoder clock minus pose clock (s), or 'auto' to estimate it (default 0)",
    )
    p.add_argument(
        "--method",
        choices=("joint", "paper"),
        default="joint",
        help="joint robust solver (default) or the paper's literal two-angle procedure",
    )
    p.add_argument(
        "--truth",
        help="kinematic file of the true parameters (adds an error column; re-expressed in "
        "the design-fit frame for an IMU result)",
    )
    p.add_argument("--robot", help="robot id written to the file (default: robot.yaml's)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from swpc_hw.calibration.gyro.solver import solve_imu
    from swpc_hw.calibration.mocap.baseline import solve_paper
    from swpc_hw.calibration.mocap.solver import SolverOptions, solve
    from swpc_hw.calibration.report import format_table
    from swpc_hw.errors import CalibrationError
    from swpc_hw.files.dataset import load_dataset
    from swpc_hw.files.kinematic_file import load_robot, save_kinematics

    if args.method == "paper" and args.time_offset == "auto":
        raise CalibrationError(
            "--time-offset auto is not available with --method paper (the paper's procedure "
            "cannot estimate a clock offset): give it in seconds, or use --method joint"
        )
    truth = load_robot(args.truth) if args.truth else None
    ds = load_dataset(args.dataset)
    if not ds.has_poses:  # no poses.csv: the loader wants imu.csv then
        if args.method == "paper":
            raise CalibrationError(
                f"{args.dataset}: no poses.csv: the paper's procedure needs motion capture "
                "(this dataset is for the IMU solver: leave out --method paper)"
            )
        opts = SolverOptions(time_offset=args.time_offset)
        result = solve_imu(ds, opts, source=args.dataset)
    elif args.method == "paper":
        result = solve_paper(ds, float(args.time_offset), source=args.dataset)
    else:
        result = solve(ds, SolverOptions(time_offset=args.time_offset), source=args.dataset)
    if truth is not None and result.params.frame != truth.frame:
        from swpc_hw.robot.frames import design_fit_transform, transform_robot

        phi, t = design_fit_transform(truth.arrays().P_s, ds.robot.arrays().P_s)
        truth = transform_robot(truth, phi, t, result.params.frame)
    params = result.params
    if args.robot:
        params = params.model_copy(update={"robot": args.robot})
    from services.store.provenance import UNITS, dataset_sha256, provenance
    from swpc_hw.robot.model import PARAM_NAMES

    extra = {
        "provenance": provenance(
            "swpc solve",
            method=result.method,
            dataset=args.dataset,
            dataset_sha256=dataset_sha256(args.dataset),
            units=dict(UNITS),
        ),
        "quality": result.quality_document(),
        "nominal": [
            {k: float(getattr(m, k)) for k in PARAM_NAMES} | {"id": m.id}
            for m in ds.robot.modules
        ],
    }
    save_kinematics(args.output, params, extra=extra, covariance=result.covariance)
    return _print(format_table(result, truth) + f"\n\nwrote {args.output}")


def _print(text: str) -> int:
    """Print to stdout; a reader that stops early (``| head``) is no error: the file is written."""
    try:
        print(text, flush=True)
    except BrokenPipeError:
        # stdout's buffer would fail again at exit: point it at /dev/null
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    return 0
