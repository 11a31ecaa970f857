"""``swpc plan``: the calibration protocol that reaches the targets in the least robot time.

Prints the plan (steering angles, sweep, pauses, spin torque and its predicted yaw
rate), its predicted robot time, the requirement (per-kind targets, the square path's
budget) and each module's predicted std devs, then every candidate predicted on the way
(docs/plan.md).  ``--json`` prints
the same as a document.  ``POST /calibrations {"plan": "auto"}`` runs it.  Exit status 2
(one line on stderr) when no candidate reaches the requirement, naming the closest.
"""

from __future__ import annotations

import argparse
import json
import math
from typing import Any


def register(sub: Any) -> None:
    p = sub.add_parser(
        "plan",
        help="plan a calibration: the protocol reaching the targets in the least robot time",
        description=(
            "Choose the steering angles, sweep and spin torque of a calibration (without "
            "motion capture the rests and the straight drive too) from "
            "the Fisher information each candidate yields (its simulated data solved by the "
            "joint solver, on the nominal robot), the fastest whose predicted std devs meet "
            "the targets and keep the square path within its budget. See docs/plan.md."
        ),
    )
    p.add_argument("--robot-config", help="robot config YAML (default: the paper's robot)")
    p.add_argument(
        "--metrology", choices=("mocap", "imu"), default="mocap",
        help="mocap (motion capture) or imu (the gyro and a tape: rests and a straight drive "
        "planned too; the gyro as the in-process simulator's, SWPC_SIM_GYRO_*)",
    )  # fmt: skip
    p.add_argument("--target-position-mm", type=float, help="x_s, y_s, b (default: tolerances)")
    p.add_argument("--target-beta-deg", type=float, help="beta (default: tolerances)")
    p.add_argument("--target-radius-mm", type=float, help="r (default: tolerances)")
    p.add_argument(
        "--square-mm", type=float,
        help="square path: end position std dev budget, mm (default 0.5; imu: none)",
    )  # fmt: skip
    p.add_argument(
        "--square-deg", type=float,
        help="square path: end heading std dev budget, deg (default 0.016; imu: none)",
    )  # fmt: skip
    p.add_argument("--no-square", action="store_true", help="the per-kind targets only")
    p.add_argument("--sigma-xy-mm", type=float, default=0.5, help="mocap noise, mm (0.5)")
    p.add_argument("--sigma-yaw-deg", type=float, default=0.05, help="mocap noise, deg (0.05)")
    p.add_argument("--rate", type=float, default=100.0, help="mocap rate, Hz (100)")
    p.add_argument("--rho", type=float, default=0.0, help="mocap noise AR(1) coefficient (0)")
    p.add_argument(
        "--yaw-rate", type=float,
        help="the robot's yaw rate while spinning at the config's limits.spin_torque, rad/s "
        "(default: the simulator's); other spin torques' in proportion",
    )  # fmt: skip
    p.add_argument("--json", action="store_true", help="print the plan as JSON")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from services.config.robot import RobotConfig, load_robot_config
    from services.config.settings import ServiceSettings
    from services.plan.planner import PlanRequest, default_budget, plan_for, plan_text
    from swpc_hw.calibration.plan.plan import MocapNoise, PlanError, Targets
    from swpc_hw.calibration.plan.square_error import SQUARE_BUDGET

    cfg = load_robot_config(args.robot_config) if args.robot_config else RobotConfig()
    tol = cfg.tolerances
    targets = Targets(
        tol.position if args.target_position_mm is None else args.target_position_mm * 1e-3,
        tol.beta if args.target_beta_deg is None else math.radians(args.target_beta_deg),
        tol.radius if args.target_radius_mm is None else args.target_radius_mm * 1e-3,
    )
    if not (args.sigma_xy_mm > 0 and args.sigma_yaw_deg > 0 and args.rate > 0
            and 0 <= args.rho < 1):  # fmt: skip
        raise PlanError("mocap noise: sigmas and rate > 0, 0 <= rho < 1")
    budget = default_budget(args.metrology)
    if args.square_mm is not None or args.square_deg is not None:
        pos, head = budget or SQUARE_BUDGET
        budget = (
            pos if args.square_mm is None else args.square_mm * 1e-3,
            head if args.square_deg is None else math.radians(args.square_deg),
        )
    request = PlanRequest(
        targets=targets,
        budget=None if args.no_square else budget,
        metrology=args.metrology,
        gyro=ServiceSettings().sim_gyro,
        noise=MocapNoise(
            args.sigma_xy_mm * 1e-3, math.radians(args.sigma_yaw_deg), args.rate, args.rho
        ),
        yaw_rate=args.yaw_rate,
    )
    p = plan_for(cfg, request)
    print(json.dumps(p.document(), indent=2) if args.json else plan_text(p), flush=True)
    return 0
