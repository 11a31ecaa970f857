"""``swpc validate --kinematics FILE [FILE ...] [--compare NOMINAL_FILE]``: the square-path
odometry test.

Drives the seed's validation (:mod:`swpc_hw.validation`): a 2.5 m square with a 90 deg turn
at each corner, CW and CCW, 4 runs each, ~0.2 m/s, once with the reference file (default:
the robot config's nominal, i.e. the paper's design) and once with each ``--kinematics``
file (e.g. a mocap-calibrated and a IMU-calibrated one), each used for both control
and odometry; prints the Table-5-like comparison, each file's error reduction against the
reference, and writes ``validation.txt``, ``validation.json`` and ``validation.png``
(Figure-13-like paths).

A file in another frame than the motion capture's body frame (``design-fit``, from a
calibration without motion capture) needs no conversion: the squares close in the frame
of the file that drives them, and the end-pose errors of a closed path do not depend on
the body frame to first order (docs/imu.md).

With no CAN interface it runs on the in-process simulator (like ``swpc serve``: a
python-can ``virtual`` bus, zenoh on loopback, simulated time in lockstep; truth = paper
Table 4, default noise), truth from ``sim/<robot>/truth/pose``.  With ``--can-interface`` it
drives the robot on that bus and takes the truth from the motion-capture pose key
``mocap/<robot>/pose`` over zenoh.  The CAN driver's settings come from
:func:`services.config.timing.robot_drives`, as the service's (``SWPC_*`` settings apply).
"""

from __future__ import annotations

import argparse
import contextlib
import uuid
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from services.config.robot import RobotConfig
    from services.config.settings import ServiceSettings
    from swpc_hw.drives.interface import Drives
    from swpc_hw.drives.types import AxisSigns
    from swpc_hw.robot.model import RobotParams
    from swpc_hw.validation import SquareOptions, ValidationReport


DESCRIPTION = (
    "Drive the paper's validation: a 2.5 m square with a 90 deg turn at each corner, CW and "
    "CCW, 4 runs each, ~0.2 m/s, once with the reference file (default: the robot config's "
    "nominal, i.e. the paper's design) and once with each --kinematics file, each used for "
    "both control and odometry. Prints the comparison of the end-pose errors and writes "
    "validation.txt, validation.json and validation.png (the paths). With no "
    "--can-interface it runs on the in-process simulator."
)


def register(sub: Any) -> None:
    p = sub.add_parser(
        "validate",
        help="square-path odometry validation: nominal vs calibrated kinematics",
        description=DESCRIPTION,
    )
    p.add_argument(
        "--kinematics", required=True, nargs="+", metavar="FILE",
        help="kinematic file(s) under test, e.g. a mocap-calibrated and an IMU one",
    )
    p.add_argument(
        "--compare", default="nominal",
        help="reference kinematic file ('nominal': the robot config's nominal, default; "
        "'none': only --kinematics)",
    )
    p.add_argument(
        "--label", nargs="+", metavar="NAME",
        help="name of each --kinematics file in the report (default: 'calibrated' for one "
        "file, else each file's name without its extension)",
    )
    p.add_argument("--compare-label", default="nominal", help="name of the reference")
    p.add_argument("--runs", type=int, default=4, help="squares per direction and file (4)")
    p.add_argument("--side", type=float, default=2.5, help="square side, m (2.5)")
    p.add_argument("--speed", type=float, default=0.2, help="leg speed, m/s (0.2)")
    p.add_argument("--yaw-rate", type=float, default=0.3, help="turn rate, rad/s (0.3)")
    p.add_argument("--directions", nargs="+", choices=["cw", "ccw"], default=["cw", "ccw"])
    p.add_argument("--out", default="swpc-validation", help="output directory")
    p.add_argument("--robot-config", help="robot config YAML (default: the paper's robot)")
    p.add_argument("--seed", type=int, default=1, help="in-process simulator seed")
    p.add_argument(
        "--truth",
        help="in-process simulator: kinematic file of the hidden true robot (default: the "
        "paper's Table 4 for the paper's robot, else the robot config's nominal)",
    )
    p.add_argument("--can-interface", help="python-can interface (unset: in-process simulator)")
    p.add_argument("--can-channel", default="vcan0")
    p.add_argument("--can-bitrate", type=int, default=1_000_000)
    p.add_argument("--zenoh-mode", default="peer")
    p.add_argument("--zenoh-listen", nargs="*", default=[], metavar="ENDPOINT")
    p.add_argument("--zenoh-connect", nargs="*", default=[], metavar="ENDPOINT")
    p.add_argument("--zenoh-config", help="zenoh JSON5 config file")
    p.add_argument(
        "--truth-key",
        help="zenoh key of the true pose (default: sim/<robot>/truth/pose in-process, "
        "mocap/<robot>/pose on a robot)",
    )
    p.set_defaults(func=run)


# --------------------------------------------------------------------------- shared set-up


def validation_settings(**overrides: Any) -> ServiceSettings:
    """The service settings (``SWPC_*`` environment) with the command's flags on top."""
    from services.config.settings import ServiceSettings

    return ServiceSettings(**{k: v for k, v in overrides.items() if v is not None})


def drive_files(
    driver: Drives,
    session: Any,
    truth_key: str,
    files: Sequence[tuple[str, RobotParams]],
    options: SquareOptions,
    *,
    mocap_truth: bool = False,
    log: Callable[[str], None] | None = None,
    polarity: AxisSigns | None = None,
) -> ValidationReport:
    """Home, then run :func:`swpc_hw.validation.validate` on a configured driver (on the
    driver's clock; in lockstep the calling thread is a participant), what is commanded
    and read turned by ``polarity`` (the robot config's)."""
    from swpc_hw.validation import (
        SquareDrive,
        ZenohTruth,
        mocap_decoder,
        prepare_driver,
        sim_truth_decoder,
        validate,
    )

    truth = ZenohTruth(
        session,
        truth_key,
        mocap_decoder if mocap_truth else sim_truth_decoder,
        clock=driver.clock,
    )
    try:
        truth.wait_first(10.0)
        try:
            prepare_driver(driver, timeout=10.0)
            drive = SquareDrive(driver, truth, files[0][1], options, log=log, polarity=polarity)
            return validate(drive, files)
        finally:
            with contextlib.suppress(Exception):
                driver.stop_all()
    finally:
        truth.close()


def run_in_process(
    files: Sequence[tuple[str, RobotParams]],
    options: SquareOptions,
    *,
    seed: int = 1,
    truth: RobotParams | None = None,
    config: RobotConfig | None = None,
    settings: ServiceSettings | None = None,
    log: Callable[[str], None] | None = None,
    observe: Callable[[Drives], object] | None = None,
) -> ValidationReport:
    """The drive against the in-process simulator in lockstep (``truth`` hidden in it:
    default paper Table 4; default noise); a busy host slows it down, never changes it.
    ``observe(driver)``: called once the driver is configured, to attach more listeners
    to its feedback (e.g. ``swpc odometry``'s stream)."""
    from services.config.robot import RobotConfig
    from services.config.timing import robot_drives
    from services.runtime.simulator import in_process_simulator, simulated_robot
    from simulators.sensors.mocap import truth_pose_key
    from swpc_hw.clock import SimClock
    from swpc_hw.sensors.zenoh_session import free_tcp_endpoint, open_session

    cfg = config or RobotConfig()
    st = settings or validation_settings()
    channel = f"swpc-validate-{uuid.uuid4().hex[:8]}"
    ep = free_tcp_endpoint()
    clock = SimClock(max_speed=st.sim_speed)
    session = open_session(listen=[ep])
    sim = None
    driver = None
    try:
        driver = robot_drives(st, cfg, interface="virtual", channel=channel, clock=clock)
        driver.configure()
        if observe is not None:
            observe(driver)
        built, wiring = simulated_robot(st, cfg)
        sim = in_process_simulator(
            config=built,
            wiring=wiring,
            channel=channel,
            zenoh_endpoints=[ep],
            clock=clock,
            seed=seed,
            truth=truth,
            physics_dt=st.sim_physics_dt,
            feedback_rate_hz=st.feedback_rate_hz,
        )
        sim.start()
        with clock.participant():
            report = drive_files(
                driver, session, truth_pose_key(cfg.robot), files, options, log=log,
                polarity=cfg.axis_signs(),
            )
        if sim.error is not None:
            raise RuntimeError(f"simulator failed: {sim.error!r}")
        return report
    finally:
        if driver is not None:
            driver.shutdown()
        if sim is not None:
            sim.stop()
        clock.close()
        with contextlib.suppress(Exception):
            session.close()


# --------------------------------------------------------------------------- command


def _labels(args: argparse.Namespace) -> list[str]:
    """A name for each ``--kinematics`` file (one-line error if they do not match)."""
    from swpc_hw.validation.errors import ValidationError

    paths: list[str] = args.kinematics
    if args.label is not None:
        labels = list(args.label)
        if len(labels) != len(paths):
            raise ValidationError(
                f"--label: {len(labels)} name(s) for {len(paths)} --kinematics file(s)"
            )
    else:
        labels = ["calibrated"] if len(paths) == 1 else [Path(p).stem for p in paths]
    names = [args.compare_label, *labels] if args.compare != "none" else labels
    if len(set(names)) != len(names):
        raise ValidationError(f"the files need distinct names in the report, got {names}")
    return labels


def _files(
    args: argparse.Namespace, config: RobotConfig
) -> tuple[list[tuple[str, RobotParams]], dict[str, str]]:
    """The files in report order (the reference first) and where each came from."""
    from swpc_hw.files.kinematic_file import load_robot

    files: list[tuple[str, RobotParams]] = []
    where: dict[str, str] = {}
    if args.compare == "nominal":
        files.append((args.compare_label, config.nominal))
        where[args.compare_label] = "robot config nominal"
    elif args.compare != "none":
        files.append((args.compare_label, load_robot(args.compare)))
        where[args.compare_label] = str(args.compare)
    for label, path in zip(_labels(args), args.kinematics, strict=True):
        files.append((label, load_robot(path)))
        where[label] = str(path)
    return files, where


def run(args: argparse.Namespace) -> int:
    import json

    from services.config.robot import load_robot_config
    from swpc_hw.validation import SquareOptions

    config = load_robot_config(args.robot_config)
    files, where = _files(args, config)
    lim = config.limits
    options = SquareOptions(
        side=args.side, speed=args.speed, yaw_rate=args.yaw_rate, runs=args.runs,
        directions=tuple(args.directions),
        max_wheel_rate=min(16.0, 0.8 * lim.max_wheel_velocity),
        max_steer_rate=min(0.8, 0.8 * lim.max_steer_velocity),
    )

    def log(msg: str) -> None:
        print(msg, flush=True)

    if args.can_interface is None:
        log(f"swpc validate: in-process simulator (seed {args.seed}); "
            f"files: {', '.join(lab for lab, _ in files)}")
        truth = None
        if args.truth is not None:
            from swpc_hw.files.kinematic_file import load_robot

            truth = load_robot(args.truth)
        report = run_in_process(
            files, options, seed=args.seed, truth=truth, config=config, log=log
        )
    else:
        if args.truth is not None:
            from swpc_hw.validation.errors import ValidationError

            raise ValidationError("--truth is for the in-process simulator: a robot's truth "
                                  "is its motion capture")
        from services.config.timing import robot_drives
        from swpc_hw.clock import SystemClock
        from swpc_hw.sensors.zenoh_session import open_session

        st = validation_settings(
            can_interface=args.can_interface, can_channel=args.can_channel,
            can_bitrate=args.can_bitrate,
        )
        session = open_session(
            mode=args.zenoh_mode, listen=args.zenoh_listen, connect=args.zenoh_connect,
            config_file=args.zenoh_config,
        )
        driver = robot_drives(
            st,
            config,
            interface=args.can_interface,
            channel=args.can_channel,
            clock=SystemClock(rate=st.external_time_scale),
        )
        try:
            driver.configure()
            report = drive_files(
                driver, session, args.truth_key or config.pose_key, files, options,
                mocap_truth=args.truth_key is None or args.truth_key.startswith("mocap/"),
                log=log, polarity=config.axis_signs(),
            )
        finally:
            driver.shutdown()
            with contextlib.suppress(Exception):
                session.close()
    report.files = where
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    table = report.table()
    (out / "validation.txt").write_text(table + "\n", encoding="utf-8")
    (out / "validation.json").write_text(
        json.dumps(report.to_document(), indent=2) + "\n", encoding="utf-8"
    )
    report.plot(str(out / "validation.png"))
    print()
    print(table)
    print(f"\nwrote {out / 'validation.txt'}, {out / 'validation.json'}, "
          f"{out / 'validation.png'}")
    return 0
