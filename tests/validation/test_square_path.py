"""Square-path validation drive.

Pure parts (path, follower, statistics, odometry feed from the real driver's feedback type)
run instantly; the end-to-end tests share one drive of the in-process simulator through CAN
(python-can ``virtual``) with truth over zenoh on loopback: one small square with the
nominal and one with the calibrated file; one asserts the calibrated errors are >= 95 %
smaller, the other that ``swpc odometry``'s ROS 2 stream, fed by the same drives' CAN
feedback, published the square the truth drove.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pytest

from simulators.offline.datagen import ExperimentOptions, generate_experiment
from swpc_hw.calibration.mocap.solver import solve
from swpc_hw.drives.bus import CanConfig
from swpc_hw.drives.swpc.driver import SwpcDriver
from swpc_hw.drives.types import FeedbackSample
from swpc_hw.files.kinematic_file import save_kinematics
from swpc_hw.onboard.ros2.messages import ODOMETRY
from swpc_hw.onboard.ros2.stream import Ros2OdometryStream
from swpc_hw.robot.model import wrap_angle
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED, PAPER_NOMINAL
from swpc_hw.validation import (
    DriverOdometry,
    Leg,
    RunResult,
    SquareOptions,
    ValidationReport,
    follow_step,
    square_plan,
    to_start_frame,
)

# --------------------------------------------------------------------------- path


@pytest.mark.parametrize("direction,sign", [("ccw", 1.0), ("cw", -1.0)])
def test_square_plan_is_a_closed_square_with_four_quarter_turns(
    direction: str, sign: float
) -> None:
    start = (1.0, -2.0, 0.3)
    legs = square_plan(start, 2.5, direction)  # type: ignore[arg-type]
    assert [leg.kind for leg in legs] == ["line", "turn"] * 4
    corners = [leg.start for leg in legs if leg.kind == "line"]
    for k, leg in enumerate(legs[0::2]):
        assert math.dist(leg.start, leg.end) == pytest.approx(2.5)
        assert leg.yaw == pytest.approx(0.3 + sign * k * math.pi / 2)
        d = np.subtract(leg.end, leg.start)
        assert math.atan2(d[1], d[0]) == pytest.approx(float(wrap_angle(leg.yaw)))
    assert legs[-1].end == pytest.approx(start[:2])
    assert legs[-1].yaw == pytest.approx(0.3 + sign * 2 * math.pi)
    # the second corner lies to the left (ccw) or right (cw) of the first leg
    c = np.array(corners)
    a, b = c[1] - c[0], c[2] - c[1]
    assert math.copysign(1.0, float(a[0] * b[1] - a[1] * b[0])) == sign


def _simulate_follower(leg: Leg, pose: np.ndarray, opt: SquareOptions) -> tuple[np.ndarray, int]:
    """Integrate the follower's body twist exactly (perfect robot) until it reports done."""
    dt = 1.0 / opt.control_rate
    mem = 0.0
    for k in range(20_000):
        (vx, vy, om), mem, done = follow_step(leg, pose, mem, dt, opt)
        if done:
            return pose, k
        c, s = math.cos(pose[2]), math.sin(pose[2])
        pose = pose + dt * np.array([c * vx - s * vy, s * vx + c * vy, om])
    raise AssertionError("follower never finished")


def test_follower_reaches_the_end_of_a_line_and_of_a_turn_within_tolerance() -> None:
    opt = SquareOptions()
    legs = square_plan((0.0, 0.0, 0.0), 2.5, "ccw")
    pose = np.array([0.0, 0.02, 0.05])  # off the line and heading: the follower corrects
    pose, steps = _simulate_follower(legs[0], pose, opt)
    assert abs(pose[0] - 2.5) < opt.position_tol
    assert abs(pose[1]) < 2e-3 and abs(pose[2]) < 2e-3
    t = steps / opt.control_rate
    assert 2.5 / opt.speed < t < 2.5 / opt.speed + 6.0  # cruise at 0.2 m/s, short ramps
    pose, steps = _simulate_follower(legs[1], pose, opt)
    assert abs(pose[2] - math.pi / 2) < opt.yaw_tol
    assert math.dist(pose[:2], (2.5, 0.0)) < 3e-3
    assert steps / opt.control_rate < (math.pi / 2) / opt.yaw_rate + 4.0


def test_follower_speed_respects_the_acceleration_and_speed_limits() -> None:
    opt = SquareOptions()
    leg = square_plan((0.0, 0.0, 0.0), 2.5, "cw")[0]
    dt = 1.0 / opt.control_rate
    mem, pose = 0.0, np.zeros(3)
    speeds = []
    for _ in range(400):
        (vx, _vy, _om), mem, done = follow_step(leg, pose, mem, dt, opt)
        speeds.append(vx)
        pose = pose + dt * np.array([vx, 0.0, 0.0])
        if done:
            break
    assert done
    v = np.array(speeds)
    assert v.max() <= opt.speed + 1e-12
    assert v.min() >= 0.0  # no overshoot and reversal at the end of the leg
    assert np.all(np.abs(np.diff(v[:-1])) <= opt.accel * dt + 1e-12)
    assert abs(v[-2]) <= 2 * opt.accel * dt  # the final stop is a small step


# --------------------------------------------------------------------------- statistics


def _result(label: str, direction: str, run: int, dp: float, dyaw: float) -> RunResult:
    start = (0.0, 0.0, 0.0)
    path = np.zeros((2, 2))
    return RunResult(label, direction, run, start, (1.0, 2.0, 0.5),  # type: ignore[arg-type]
                     (1.0 + dp, 2.0, 0.5 - dyaw), 10.0, path, path)


def test_report_means_reduction_and_table() -> None:
    opt = SquareOptions(runs=2)
    res = [
        _result("nominal", "cw", 0, 0.4, math.radians(10.0)),
        _result("nominal", "cw", 1, 0.2, math.radians(-6.0)),
        _result("nominal", "ccw", 0, 0.3, math.radians(4.0)),
        _result("nominal", "ccw", 1, 0.1, math.radians(-4.0)),
        _result("calibrated", "cw", 0, 0.01, math.radians(0.2)),
        _result("calibrated", "cw", 1, 0.01, math.radians(-0.2)),
        _result("calibrated", "ccw", 0, 0.02, math.radians(0.1)),
        _result("calibrated", "ccw", 1, 0.0, math.radians(0.1)),
    ]
    rep = ValidationReport(["nominal", "calibrated"], res, opt)
    s = rep.summary()
    assert s["nominal"]["cw"]["position"] == pytest.approx(0.3)
    assert s["nominal"]["all"]["position"] == pytest.approx(0.25)
    assert s["nominal"]["all"]["heading"] == pytest.approx(math.radians(6.0))  # absolute
    assert s["calibrated"]["all"]["position"] == pytest.approx(0.01)
    red = rep.reduction()
    assert red is not None
    assert red["position"] == pytest.approx(0.96)
    assert red["heading"] == pytest.approx(1.0 - 0.15 / 6.0)
    table = rep.table()
    assert "250.00 mm" in table and "6.000 deg" in table and "96.0 %" in table
    doc = rep.to_document()
    assert len(doc["runs"]) == 8 and doc["runs"][0]["heading_error"] == pytest.approx(
        math.radians(10.0)
    )


def test_report_of_three_files_gives_each_its_reduction_against_the_first() -> None:
    """nominal, mocap-calibrated, IMU-calibrated: one reduction each."""
    opt = SquareOptions(runs=1, directions=("ccw",))
    res = [
        _result("nominal", "ccw", 0, 0.20, math.radians(4.0)),
        _result("mocap", "ccw", 0, 0.01, math.radians(0.1)),
        _result("imu", "ccw", 0, 0.02, math.radians(0.2)),
    ]
    rep = ValidationReport(["nominal", "mocap", "imu"], res, opt)
    reds = rep.reductions()
    assert list(reds) == ["mocap", "imu"]
    assert reds["mocap"]["position"] == pytest.approx(0.95)
    assert reds["imu"]["position"] == pytest.approx(0.90)
    assert reds["imu"]["heading"] == pytest.approx(0.95)
    assert rep.reduction() == reds["imu"]  # the last file, as before
    table = rep.table()
    assert "mocap vs nominal" in table and "imu vs nominal" in table
    assert rep.to_document()["reductions"] == reds


def test_validate_names_the_files_and_refuses_what_it_cannot_do(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Several --kinematics files: named after their files unless --label says; a label
    count that does not match, two files of one name, or --truth on a robot: one line,
    exit 2, before anything moves."""
    import argparse

    from services.cli import main
    from services.cli.offline.validate import _labels
    from swpc_hw.files.kinematic_file import save_kinematics

    def args(**kw: object) -> argparse.Namespace:
        base: dict[str, object] = {"label": None, "compare": "nominal", "compare_label": "nominal"}
        return argparse.Namespace(**{**base, **kw})

    assert _labels(args(kinematics=["a/k.yaml"])) == ["calibrated"]
    assert _labels(args(kinematics=["a/mocap.yaml", "b/imu.yaml"])) == ["mocap", "imu"]
    assert _labels(args(kinematics=["x.yaml", "y.yaml"], label=["m", "i"])) == ["m", "i"]
    f = tmp_path / "k.yaml"
    save_kinematics(f, PAPER_CALIBRATED)
    for argv, message in (
        ([str(f), str(f), "--label", "one"], "--label: 1 name(s) for 2 --kinematics file(s)"),
        ([str(f), str(tmp_path / "k.yaml")], "the files need distinct names"),
        ([str(f), "--truth", str(f), "--can-interface", "socketcan"], "--truth is for the"),
    ):
        assert main(["validate", "--kinematics", *argv, "--out", str(tmp_path / "o")]) == 2
        err = capsys.readouterr().err.strip()
        assert "\n" not in err and message in err, err
    assert not (tmp_path / "o").exists()


def test_start_frame_moves_the_start_pose_to_the_origin_heading_x() -> None:
    start = (2.0, 1.0, math.pi / 2)
    pts = np.array([[2.0, 1.0], [2.0, 3.0], [1.0, 1.0]])
    np.testing.assert_allclose(to_start_frame(start, pts), [[0, 0], [2, 0], [0, 1]], atol=1e-12)


# --------------------------------------------------------------------------- odometry feed


def test_driver_odometry_aligns_unsynchronised_modules_on_the_counter_clock() -> None:
    """Straight motion at 0.2 m/s with module 1 sampling 2 ms after the others and bursty
    delivery: the counter clock and interpolation give the exact pose, the slip indicator
    stays ~0."""
    params = PAPER_CALIBRATED
    drv = SwpcDriver(CanConfig(feedback_rate_hz=100))  # never configured: only its callbacks
    feed = DriverOdometry(drv, params)
    A = params.arrays()
    rate, v = 100.0, 0.2
    t0 = 5000.0  # the driver clock's time of the first frame
    skew = {1: 0.002, 2: 0.0, 3: 0.0, 4: 0.0}  # module 1 samples 2 ms after the others
    for k in range(300):
        # after the first 10 (on time), frames arrive 10 at a time at the end of their
        # burst (their bus stamps on the driver's clock)
        burst = (k if k < 10 else math.ceil((k + 1) / 10) * 10) / rate
        for i, m in enumerate(params.ids):
            t = k / rate + skew[m]
            arrival = t0 + burst + skew[m]
            s = FeedbackSample(
                t=arrival, t_bus=arrival + 1.7e9, counter=k & 0xFF, seq=k,
                theta_hat=math.pi - A.beta[i],  # trailing for +x: u = (-1, 0)
                psi=-v * t / A.r[i],
            )
            feed._on_sample(m, s)
    tr = np.array(feed.track)
    assert tr.shape[0] > 250
    # steps of the counter's 10 ms whatever the bursts; distance per robot second = v
    np.testing.assert_allclose(np.diff(tr[:, 0]), 1.0 / rate, atol=1e-6)
    dist = np.hypot(*(tr[-1, 1:3] - tr[0, 1:3]))
    assert dist / (tr[-1, 0] - tr[0, 0]) == pytest.approx(v, rel=1e-6)
    # readings 0..298 of module 1 (299 has no bracket yet), the others interpolated
    assert tr[-1, 1] == pytest.approx(v * 298 / rate, abs=1e-6)  # float clocks: ~0.1 us
    assert abs(tr[-1, 2]) < 1e-7 and abs(tr[-1, 3]) < 1e-7
    # ~0 (float clocks); a slipping wheel reads > 0.02 m/s (test_odometry)
    assert max(feed.slip) < 1e-4


# --------------------------------------------------------------------------- end to end


class SquareDriveRun(NamedTuple):
    """What the one drive of the in-process simulator left for the end-to-end tests."""

    report: ValidationReport
    lines: list[str]  # the drive's log
    stream: Ros2OdometryStream
    odom: list[tuple[float, bytes]]  # (stamp, CDR) of every /odom the stream published
    tf: list[float]  # the stamp of every /tf


@pytest.fixture(scope="module")
def square_drive(tmp_path_factory: pytest.TempPathFactory) -> SquareDriveRun:
    """The short variant of ``swpc validate`` on the in-process simulator in lockstep,
    through CAN and zenoh: a 0.3 m square counter-clockwise with the nominal file, then
    with the calibrated one (the command drives both ways), 1 run per file; all along,
    ``swpc odometry``'s robot path (the drives' CAN feedback -> DriverOdometry -> the
    ROS 2 stream, on the simulator's truth: the right file) follows the drives.  The
    casters swivel at up to 2 rad/s (the robot config's limit is 3; ``swpc validate``'s
    0.8 made each corner 1.5 s longer): 32 s a square instead of 45, the same errors.

    The robot has module 2's wheel and module 3's steering motor mounted the other way
    round, and its config says so (``polarity``, as a commissioning writes it): the drive
    and the odometry turn what they command and read by it, as a run does (a drive that
    did not would steer module 3 away and roll module 2 against the others).

    One drive for the two tests below: they assert on different outputs of it (the
    report; the stream's messages), and a drive is most of their cost."""
    from services.cli.offline.odometry import follow_drives
    from services.cli.offline.validate import run_in_process, validation_settings
    from services.config.robot import Polarity, RobotConfig

    where = tmp_path_factory.mktemp("square")
    kin = where / "kinematics.yaml"
    wiring = where / "wiring.yaml"
    wiring.write_text("inverted: [{module: 2, axis: wheel}, {module: 3, axis: steer}]\n")
    config = RobotConfig(polarity={2: Polarity(wheel=-1), 3: Polarity(steer=-1)})
    save_kinematics(kin, PAPER_CALIBRATED)  # the simulator's truth: the right file
    odom: list[tuple[float, bytes]] = []
    tf: list[float] = []

    def sink(topic: str, _ty: str, stamp: float, cdr: bytes) -> None:
        if topic == "/odom":
            odom.append((stamp, cdr))
        else:
            tf.append(stamp)

    stream = Ros2OdometryStream(kin, sink)
    # a calibration of the truth as the solver makes one (motion capture, frame R), not
    # whatever `make demo` left in out/demo (a gyro demo's file is in design-fit)
    data = generate_experiment(PAPER_CALIBRATED, ExperimentOptions(seed=1)).dataset
    calibrated = solve(data).params
    opt = SquareOptions(
        side=0.3, runs=1, yaw_rate=0.6, yaw_accel=0.8, settle=0.4, directions=("ccw",),
        max_steer_rate=2.0,
    )
    lines: list[str] = []
    rep = run_in_process(
        [("nominal", PAPER_NOMINAL), ("calibrated", calibrated)], opt, log=lines.append,
        config=config, settings=validation_settings(sim_wiring=wiring),
        observe=lambda drv: follow_drives(drv, stream, polarity=config.axis_signs()),
    )  # fmt: skip
    return SquareDriveRun(rep, lines, stream, odom, tf)


def test_square_drive_on_the_in_process_simulator_calibrated_beats_nominal_by_95_percent(
    square_drive: SquareDriveRun,
) -> None:
    """The short variant of ``swpc validate``: a 0.3 m square counter-clockwise (the
    command drives both ways), 1 run per file, on the in-process simulator in lockstep,
    through CAN and zenoh: errors of the calibrated file are >= 95 % smaller."""
    rep = square_drive.report
    print("\n".join(square_drive.lines))
    print(rep.table())
    assert len(rep.results) == 2
    s = rep.summary()
    for r in rep.results:
        assert r.true_path.shape[0] > 50 and r.odometry_path.shape[0] > 50
        # the robot really drove the square (truth), not just the odometry
        span = np.ptp(r.true_path, axis=0)
        assert np.all(span > 0.27)
    assert s["nominal"]["all"]["position"] > 2e-3  # the nominal file is measurably wrong
    assert s["nominal"]["all"]["heading"] > math.radians(0.3)
    red = rep.reduction()
    assert red is not None
    assert red["position"] >= 0.95 and red["heading"] >= 0.95


def test_swpc_odometry_follows_the_drives_on_can_while_the_robot_drives(
    square_drive: SquareDriveRun,
) -> None:
    """``swpc odometry``'s robot path (the drives' CAN feedback -> DriverOdometry -> the
    stream) on the in-process simulator in lockstep, while ``swpc validate`` drives its
    0.3 m squares: one /odom and one /tf per reading at the drives' feedback rate, and the
    pose it publishes follows the last square the simulator's truth drove.

    (With the tests of the ROS 2 stream in tests/onboard/test_ros2_odometry.py by its
    subject; here to share the drive.)"""
    from services.cli.offline.validate import validation_settings
    from swpc_hw.sensors.mocap import ros2_typestore

    odom, tf, stream = square_drive.odom, square_drive.tf, square_drive.stream
    last = square_drive.report.results[-1]
    rate = validation_settings().feedback_rate_hz
    assert len(odom) == len(tf) == stream.published > 10 * rate
    stamps = np.array([s for s, _ in odom])
    assert np.all(np.diff(stamps) > 0)
    assert len(stamps) / (stamps[-1] - stamps[0]) == pytest.approx(rate, rel=0.02)
    ts = ros2_typestore()
    xy = np.array([[m.pose.pose.position.x, m.pose.pose.position.y]
                   for m in (ts.deserialize_cdr(b, ODOMETRY) for _, b in odom)])  # fmt: skip
    true = last.true_path
    square = xy[-len(last.odometry_path):]  # the last square's readings: the last

    def diameter(p: np.ndarray) -> float:  # the square's diagonal, in any frame
        return float(np.max(np.linalg.norm(p[:, None, :] - p[None, :, :], axis=-1)))

    print(f"\n{len(stamps)} messages at {len(stamps) / (stamps[-1] - stamps[0]):.2f} Hz; "
          f"the square's diagonal {diameter(square):.5f} m published, "
          f"{diameter(true):.5f} m true")  # fmt: skip
    assert diameter(true) == pytest.approx(0.3 * math.sqrt(2), abs=0.005)
    assert diameter(square) == pytest.approx(diameter(true), abs=1e-3)
