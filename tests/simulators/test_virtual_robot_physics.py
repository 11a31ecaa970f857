"""Virtual robot physics (simulators.physics.robot) and mocap corruption
(simulators.sensors.mocap)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from firmware_protocol import codec
from firmware_protocol.codec import Axis, AxisState, ControlMode, ErrorFlag, HomingState
from simulators.drives.base import AxisModel, axis_drive, quantize
from simulators.drives.swpc import VirtualController
from simulators.physics.core import caster_rates, settled_trailing
from simulators.physics.robot import (
    FREE_MODULE,
    ModuleDrive,
    PhysicsOptions,
    RobotPhysics,
    SteerDrive,
    WheelDrive,
    module_rate,
    prioritized_twist,
)
from simulators.sensors.mocap import MocapOptions, MocapSim, corrupt_pose
from swpc_hw.robot.model import RobotParams, forward_kinematics, inverse_kinematics, wrap_angle
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED, PAPER_NOMINAL
from swpc_hw.sensors.mocap import decode_pose, encode_cdr

TRUTH = PAPER_CALIBRATED
A = TRUTH.arrays()
FREE = ModuleDrive()


def locked(rate: float = 0.0) -> ModuleDrive:
    return ModuleDrive(SteerDrive.RATE, rate, WheelDrive.BRAKE)


def torque(tau: float) -> ModuleDrive:
    return ModuleDrive(SteerDrive.PASSIVE, 0.0, WheelDrive.TORQUE, tau)


def spin(sim: RobotPhysics, k: int, seconds: float, tau: float = -0.6, dt: float = 0.005) -> None:
    """Module ``k`` locked, -0.6 N.m on every other wheel, for ``seconds`` in steps of
    ``dt`` (the simulator's default physics step): what the spins assert (a pinned contact
    point, settled casters, rolling by ``D dyaw / r``) is exact whatever the step, and
    holds to the same 1e-13..1e-15 with 2 ms steps."""
    drives = [locked() if i == k else torque(tau) for i in range(sim.n)]
    for _ in range(round(seconds / dt)):
        sim.step(dt, drives)


def test_module_rate_matches_the_physics_core() -> None:
    rng = np.random.default_rng(3)
    theta = rng.uniform(-math.pi, math.pi, 4)
    xi = (0.2, -0.1, 0.7)
    consts = [(float(p[0]), float(p[1]), float(b), float(r))
              for p, b, r in zip(A.P_s, A.b, A.r, strict=True)]  # fmt: skip
    ref_th, ref_psi = caster_rates(A, theta, xi[:2], xi[2])
    free = np.array([module_rate(c, xi, float(th)) for c, th in zip(consts, theta, strict=True)])
    assert free[:, 0] == pytest.approx(ref_th, abs=1e-12)
    assert free[:, 1] == pytest.approx(ref_psi, abs=1e-12)
    # a driven steering turns at its rate, a braked wheel not at all, a driven one at its
    assert module_rate(consts[0], xi, float(theta[0]), steer_rate=0.3, wheel_rate=0.0) == (
        0.3, 0.0)  # fmt: skip
    th_dot, psi_dot = module_rate(consts[1], xi, float(theta[1]), wheel_rate=2.0)
    assert psi_dot == 2.0 and th_dot == pytest.approx(ref_th[1], abs=1e-12)


@pytest.mark.parametrize("k", [0, 2])
def test_locked_module_pins_its_contact_point_and_torque_gives_a_steady_spin(k: int) -> None:
    sim = RobotPhysics(TRUTH, theta0=np.random.default_rng(k).uniform(-3, 3, 4))
    sim.theta[k] = math.radians(45) + A.beta[k]
    C_W = sim.contact_points_world()[k].copy()
    C_R = sim.contact_points()[k].copy()
    spin(sim, k, 4.0)
    w1 = sim.twist[2]
    spin(sim, k, 1.0)
    assert sim.twist[2] == pytest.approx(w1, rel=1e-7)  # steady
    assert 0.3 < abs(w1) < 1.0  # -0.6 N.m on three wheels: about 0.5 rad/s
    assert np.abs(sim.contact_points_world()[k] - C_W).max() < 1e-12
    assert np.abs(sim.contact_points()[k] - C_R).max() == 0.0
    # the twist is a pure rotation about the contact point: v = -omega x C
    w = sim.twist[2]
    assert sim.twist[:2] == pytest.approx([w * C_R[1], -w * C_R[0]], abs=1e-12)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_free_casters_trail_from_any_start_and_wheels_roll_d_dyaw_over_r(seed: int) -> None:
    rng = np.random.default_rng(seed)
    k = int(rng.integers(4))
    theta0 = rng.uniform(-math.pi, math.pi, 4)
    sim = RobotPhysics(TRUTH, theta0=theta0)
    spin(sim, k, 6.0)
    C = sim.contact_points()[k]
    target, D = settled_trailing(A.P_s, A.b, C, np.sign(sim.twist[2]))
    dyn = [i for i in range(4) if i != k]
    err = wrap_angle(sim.theta - target)[dyn]
    assert np.abs(err).max() < 1e-9
    # settled: the rolling direction is perpendicular to the radius from the pivot
    P_w = sim.contact_points()
    u = np.column_stack([np.cos(sim.theta), np.sin(sim.theta)])
    assert np.abs(np.einsum("ij,ij->i", P_w - C, u)[dyn]).max() < 1e-10
    yaw0, psi0 = sim.pose[2], sim.psi_encoder.copy()
    spin(sim, k, 2.0)
    dyaw = sim.pose[2] - yaw0
    dpsi = sim.psi_encoder - psi0
    assert abs(dyaw) > 0.5
    assert dpsi[dyn] == pytest.approx((-D * abs(dyaw) / A.r)[dyn], rel=1e-9)
    assert dpsi[k] == 0.0


def test_resteering_a_locked_module_moves_the_body_around_the_pinned_point() -> None:
    sim = RobotPhysics(TRUTH, theta0=[math.radians(45) + A.beta[0], 0.0, 1.0, 2.0])
    C_W = sim.contact_points_world()[0].copy()
    yaw0 = sim.pose[2]
    rate = math.radians(120) / 2.0
    for _ in range(1000):  # 2 s at 60 deg/s, every other module free
        sim.step(0.002, [locked(rate), FREE, FREE, FREE])
    assert sim.theta[0] - A.beta[0] == pytest.approx(math.radians(165), abs=1e-9)
    assert np.abs(sim.contact_points_world()[0] - C_W).max() < 1e-7
    assert abs(sim.pose[2] - yaw0) > math.radians(20)  # the body turned about the pin


def test_all_modules_driven_move_as_the_least_squares_twist_of_the_true_model() -> None:
    v, w = np.array([0.3, 0.1]), 0.2
    for model, slips in ((TRUTH, False), (PAPER_NOMINAL, True)):
        M = model.arrays()
        sim = RobotPhysics(TRUTH)
        for _ in range(300):
            th_dot, psi_dot = inverse_kinematics(M, sim.theta - M.beta, v, w)
            drives = [
                ModuleDrive(SteerDrive.RATE, th_dot[i], WheelDrive.RATE, psi_dot[i])
                for i in range(4)
            ]
            sim.step(0.002, drives)
        th_dot, psi_dot = inverse_kinematics(M, sim.theta - M.beta, v, w)
        drives = [
            ModuleDrive(SteerDrive.RATE, th_dot[i], WheelDrive.RATE, psi_dot[i]) for i in range(4)
        ]
        theta_mid = sim.theta + 0.001 * th_dot
        sim.step(0.002, drives)
        # the step's twist: least squares of the true model at the mid-step steering angles
        twist, res = forward_kinematics(A, theta_mid - A.beta, th_dot, psi_dot)
        assert sim.twist == pytest.approx(twist, abs=1e-12)
        if slips:
            assert np.abs(res).max() > 2e-3  # wrong parameters: slip, and the twist drifts
            assert np.abs(sim.twist - [*v, w]).max() > 1e-3
        else:
            # consistent commands (held for one 2 ms step): slip below 10 um/s
            assert np.abs(res).max() < 1e-5
            assert sim.twist == pytest.approx([*v, w], abs=1e-4)


def test_hard_rows_win_over_conflicting_soft_rows() -> None:
    A_h = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    A_s = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    xi = prioritized_twist(
        (A_h, np.array([0.1, 0.2])),
        (A_s, np.array([5.0, 0.3])),
        (np.eye(3), np.zeros(3)),
        np.eye(3),
        np.zeros(3),
        np.zeros(3),
        0.01,
    )
    assert xi == pytest.approx([0.1, 0.2, 0.3], abs=1e-12)


def test_a_push_turns_a_free_robot_steadily_and_braked_wheels_hold_it() -> None:
    """The external wrench enters the dynamics linearly: a free robot pushed with a torque
    settles to a steady yaw rate in the push's sense, twice the push gives twice the rate;
    braking every wheel (HOLD) stops it dead, push or not."""
    brake = [ModuleDrive(wheel=WheelDrive.BRAKE)] * 4
    rates = []
    for tau in (1.0, 2.0):
        r = RobotPhysics(PAPER_CALIBRATED, theta0=[0.3, -1.0, 2.0, 0.5])
        r.push = np.array([0.0, 0.0, tau])
        w = []
        for _ in range(2000):  # 10 s
            r.step(0.005, [FREE_MODULE] * 4)
            w.append(r.twist[2])
        assert w[-1] == pytest.approx(w[-200], rel=1e-3)  # steady over the last second
        rates.append(w[-1])
        for _ in range(2):
            r.step(0.005, brake)
        assert r.twist == pytest.approx(np.zeros(3), abs=1e-12)
    assert 0.05 < rates[0] < 0.2
    assert rates[1] == pytest.approx(2 * rates[0], rel=1e-3)


def test_slip_bursts_only_move_the_encoder() -> None:
    sim = RobotPhysics(TRUTH, PhysicsOptions(slip_burst_rate=2.0, seed=4), theta0=[0.8, 0, 0, 0])
    spin(sim, 0, 4.0)
    assert sim.slip_bursts
    extra = sim.psi_encoder - sim.psi
    slipped = {j for j, *_ in sim.slip_bursts}
    for j in range(4):
        if j in slipped:
            assert abs(extra[j]) > 1e-3
        else:
            assert extra[j] == 0.0
    assert 0 not in slipped  # the braked wheel does not roll, so it cannot slip


def drive_straight(wheel: ModuleDrive, length: float = 2.0) -> tuple[np.ndarray, float]:
    """Every steering held at the reported angle pi (nominal beta 0: true pi + beta, the
    wheel trailing its axis for a drive along x), every wheel driven by ``wheel`` until
    the first wheel turned ``length`` by its nominal radius.  Returns what every wheel's
    encoder says it rolled minus what its contact point moved along its rolling direction
    (m: slip), and the drive's yaw (rad)."""
    r = RobotPhysics(TRUTH, PhysicsOptions(), (0.0, 0.0, 0.0), [math.pi + b for b in A.beta])
    held = ModuleDrive(SteerDrive.RATE, 0.0, wheel.wheel, wheel.wheel_value)
    c0 = r.contact_points_world()
    while abs(float(r.psi_encoder[0])) * PAPER_NOMINAL.modules[0].r < length:
        r.step(0.005, [held] * 4)
    yaw = float(r.pose[2])
    u = np.column_stack([np.cos(r.theta + yaw), np.sin(r.theta + yaw)])  # in W
    moved = np.sum((r.contact_points_world() - c0) * u, axis=1)
    return A.r * r.psi_encoder - moved, yaw


def test_a_straight_drive_under_torque_rolls_every_wheel_without_slip() -> None:
    """Why the run without motion capture drives with a torque: under one torque every
    wheel rolls what its contact point moves (to a micrometre over 2 m: what the encoders
    say is the rolling) and the robot does not turn; one velocity commanded to wheels of
    unequal true radii (3 % apart) makes them fight and slip by centimetres, and it turns
    ten times more."""
    slip, yaw = drive_straight(ModuleDrive(wheel=WheelDrive.TORQUE, wheel_value=-0.6))
    assert np.max(np.abs(slip)) < 1e-6 and abs(yaw) < math.radians(0.05)
    nominal = PAPER_NOMINAL.modules[0].r
    fight, turn = drive_straight(ModuleDrive(wheel=WheelDrive.RATE, wheel_value=-0.3 / nominal))
    assert np.max(np.abs(fight)) > 0.02 and abs(turn) > 10 * abs(yaw)


def test_axis_drive_follows_the_controller_modes() -> None:
    ax = AxisModel(state=AxisState.ENABLED, mode=ControlMode.POSITION, setpoint=1.0)
    ax.max_velocity = 3.0
    assert axis_drive(ax, Axis.STEER, 0.99, 0.002, 0.02) == ("rate", pytest.approx(0.5))
    assert axis_drive(ax, Axis.STEER, -5.0, 0.002, 0.02) == ("rate", 3.0)
    ax.mode = ControlMode.HOLD
    assert axis_drive(ax, Axis.WHEEL, 0.0, 0.002, 0.02) == ("brake", 0.0)
    assert axis_drive(ax, Axis.STEER, 0.0, 0.002, 0.02) == ("rate", 0.0)
    ax.mode, ax.setpoint = ControlMode.TORQUE, -0.6
    assert axis_drive(ax, Axis.WHEEL, 0.0, 0.002, 0.02) == ("torque", -0.6)
    ax.state = AxisState.FAULT
    assert axis_drive(ax, Axis.WHEEL, 0.0, 0.002, 0.02) == ("passive", 0.0)
    ax.state = AxisState.HOMING
    assert axis_drive(ax, Axis.STEER, 0.0, 0.002, 0.02) == ("rate", 0.5)
    assert quantize(1.0, 2**14) == pytest.approx(1.0, abs=math.pi / 2**14)
    assert quantize(1.0, 2**14) / (2 * math.pi / 2**14) == pytest.approx(
        round(quantize(1.0, 2**14) / (2 * math.pi / 2**14)), abs=1e-9
    )


def test_over_speed_is_judged_under_the_mode_in_force_not_on_a_command_frame() -> None:
    """Under a simulator the physics owns the axes (it sets ``_t``): a free caster swinging
    at 7 rad/s, then put in POSITION mode, must not fault on the next command frame (its
    velocity is still the free one); it faults if it really runs that fast under a command."""
    c = VirtualController(node=3, watchdog_ms=0)
    c.homed = True
    t = 1.0
    c.handle(codec.make_set_axis_state(3, Axis.STEER, True), t)
    c.handle(codec.make_set_limits(3, Axis.STEER, 5.0, 3.0), t)
    steer = c.axes[Axis.STEER]
    assert steer.state == AxisState.ENABLED and steer.mode == ControlMode.FREE
    t += 0.005
    steer.velocity = -7.0  # the physics: the free caster trails a moving body
    c._t = t
    c.step(t)
    assert steer.errors == 0  # FREE: moved by the world, no check
    c.handle(codec.make_set_control(3, Axis.STEER, ControlMode.POSITION, 0.5), t)
    c.handle(codec.make_set_control(3, Axis.WHEEL, ControlMode.HOLD), t)  # same instant
    c.handle(codec.make_set_control(3, Axis.STEER, ControlMode.POSITION, 0.5), t)  # refresh
    assert steer.state == AxisState.ENABLED and steer.errors == 0
    t += 0.005
    steer.velocity = 3.0  # the physics under POSITION: clamped to max_velocity
    c._t = t
    c.step(t)
    assert steer.state == AxisState.ENABLED and steer.errors == 0
    t += 0.005
    steer.velocity = 3.7  # > 1.2 x 3 rad/s under a command: the firmware stops it
    c._t = t
    c.step(t)
    assert steer.state == AxisState.FAULT and steer.errors == ErrorFlag.OVER_SPEED
    # without a physics (ControllerEmulator), a frame after time passed still checks
    w = c.axes[Axis.WHEEL]
    c.handle(codec.make_set_axis_state(3, Axis.WHEEL, True), t)
    c.handle(codec.make_set_limits(3, Axis.WHEEL, 5.0, 2.0), t)
    c.handle(codec.make_set_control(3, Axis.WHEEL, ControlMode.TORQUE, 5.0), t)
    c.handle(codec.make_set_control(3, Axis.WHEEL, ControlMode.TORQUE, 5.0), t + 0.5)
    assert w.velocity > 2.4 and w.errors == ErrorFlag.OVER_SPEED


def test_frames_that_fall_due_as_a_command_arrives_go_out_with_its_answer() -> None:
    """A homing run that ends, or a watchdog that expires, just as a host frame arrives:
    its HomingStatus / FaultReport goes out before the command's answer.  They used to be
    dropped: the driver suite in the VM waited 21 s for a homing DONE that never came."""

    def parsed(frames: list[codec.Frame]) -> list[codec.Decoded]:
        return [codec.parse(f.arbitration_id, f.data) for f in frames]

    c = VirtualController(node=2, watchdog_ms=0, homing_duration=0.2)
    c.handle(codec.make_set_axis_state(2, Axis.STEER, True), 0.0)
    c.handle(codec.make_set_axis_state(2, Axis.WHEEL, True), 0.0)
    started = parsed(c.handle(codec.make_start_homing(2), 0.0))
    assert [(m.status, m.axis) for m in started] == [(HomingState.IN_PROGRESS, Axis.STEER)]
    out = parsed(c.handle(codec.make_set_control(2, Axis.WHEEL, ControlMode.HOLD), 0.25))
    done = [m for m in out if isinstance(m, codec.HomingStatus)]
    assert c.homed and [(m.status, m.axis) for m in done] == [(HomingState.DONE, Axis.STEER)]
    assert done[0].sensor_position == pytest.approx(c.sensor_position, abs=1e-4)

    c = VirtualController(node=2, watchdog_ms=100)
    c.handle(codec.make_set_axis_state(2, Axis.WHEEL, True), 0.0)
    out = parsed(c.handle(codec.make_set_control(2, Axis.WHEEL, ControlMode.HOLD), 0.3))
    faults = [m for m in out if isinstance(m, codec.FaultReport)]
    assert [(m.axis, m.new_errors) for m in faults] == [(Axis.WHEEL, ErrorFlag.WATCHDOG_TIMEOUT)]
    assert c.axes[Axis.WHEEL].state == AxisState.FAULT

    c = VirtualController(node=2, watchdog_ms=0, homing_duration=0.2, sync_mode=True)
    c.handle(codec.make_set_axis_state(2, Axis.STEER, True), 0.0)
    c.handle(codec.make_start_homing(2), 0.0)
    kinds = [type(m).__name__ for m in parsed(c.handle(codec.make_sync(7), 0.25))]
    assert kinds == ["HomingStatus", "FeedbackPosition", "FeedbackVelocityTorque"]


def test_the_watchdog_judges_a_command_by_its_arrival() -> None:
    """An emulator thread that was not scheduled handles a command late: a command that
    arrived within the watchdog period still feeds it (the test rig faulted both axes of a
    module under a loaded host with its commands sitting in the queue); one that arrived
    late does not."""
    c = VirtualController(node=2, watchdog_ms=100)
    c.handle(codec.make_set_axis_state(2, Axis.WHEEL, True), 0.0)
    c.handle(codec.make_set_control(2, Axis.WHEEL, ControlMode.HOLD), 0.3, arrived=0.05)
    assert c.axes[Axis.WHEEL].state == AxisState.ENABLED and c.axes[Axis.WHEEL].errors == 0
    c.handle(codec.make_set_control(2, Axis.WHEEL, ControlMode.HOLD), 0.6, arrived=0.45)
    assert c.axes[Axis.WHEEL].errors == ErrorFlag.WATCHDOG_TIMEOUT


def test_a_step_judges_the_watchdog_when_the_queue_was_last_found_empty() -> None:
    """The emulator thread found its queue empty at 0.08 s and only stepped at 0.2 s (it
    waited for the GIL); a command may sit in the queue since 0.08 s, so the watchdog
    (100 ms after the last command, at 0.0 s) is judged at 0.08 s: no fault.  The rig
    faulted module 1's wheel this way under a loaded host.  Judged at 0.15 s, it fires."""
    c = VirtualController(node=1, watchdog_ms=100)
    c.handle(codec.make_set_axis_state(1, Axis.WHEEL, True), 0.0)
    c.step(0.2, watchdog_at=0.08)
    assert c.axes[Axis.WHEEL].state == AxisState.ENABLED and c.axes[Axis.WHEEL].errors == 0
    c.step(0.25, watchdog_at=0.15)
    assert c.axes[Axis.WHEEL].errors == ErrorFlag.WATCHDOG_TIMEOUT


def test_steering_position_setpoints_are_taken_modulo_the_feedback_wrap() -> None:
    """The host knows the multi-turn steering only modulo the SteerPosition wrap (8 turns):
    a setpoint goes to its equivalent nearest the current position."""
    c = VirtualController(node=1, watchdog_ms=0)
    c.homed = True
    c.handle(codec.make_set_axis_state(1, Axis.STEER, True), 0.0)
    steer = c.axes[Axis.STEER]
    steer.position = 60.0  # 9.5 turns, e.g. the host unwrapped from a sample 8 turns off
    c._t = 0.0
    c.handle(codec.make_set_control(1, Axis.STEER, ControlMode.POSITION, 0.5), 0.0)
    assert steer.setpoint == pytest.approx(0.5 + codec.STEER_SPAN, abs=1e-4)
    c.handle(codec.make_set_control(1, Axis.STEER, ControlMode.POSITION, 59.0), 0.0)
    assert steer.setpoint == pytest.approx(59.0, abs=1e-4)  # within half a span: as sent


def test_mocap_noise_dropout_outliers_and_timestamps() -> None:
    rng = np.random.default_rng(0)
    opt = MocapOptions(sigma_xy=1e-3, sigma_yaw=1e-3, dropout=0.1, outliers=0.05)
    out = [corrupt_pose(rng, np.zeros(3), opt) for _ in range(20000)]
    kept = np.array([p for p, o in out if p is not None and not o])
    n_out = sum(o for _, o in out)
    assert len(kept) + n_out == pytest.approx(18000, rel=0.02)
    assert n_out == pytest.approx(0.05 * 18000, rel=0.15)
    assert kept[:, :2].std() == pytest.approx(1e-3, rel=0.03)
    assert kept[:, 2].std() == pytest.approx(1e-3, rel=0.03)
    jumps = np.array([np.hypot(p[0], p[1]) for p, o in out if o and p is not None])
    assert np.median(jumps) == pytest.approx(0.05, abs=0.005)

    m = MocapSim(
        "r1",
        MocapOptions(rate=200, latency=0.012, clock_offset=3.0, encoding="ros2-cdr"),
        keep_sent=100,
    )
    assert m.due_times(0.0, 0.0101) == pytest.approx([0.0, 0.005, 0.01])
    assert m.due_times(0.0101, 0.02) == pytest.approx([0.015, 0.02])
    m.sample(0.0, np.array([1.0, 2.0, 0.5]))
    m.sample(0.005, np.array([1.0, 2.0, 0.5]))
    assert m.flush(0.011) == 0 and m.flush(0.012) == 1 and m.flush(0.02) == 1
    assert [p.t for p in m.sent] == pytest.approx([3.0, 3.005])
    assert m.sent[0].yaw == pytest.approx(0.5)
    assert decode_pose(encode_cdr(m.sent[0])).x == pytest.approx(1.0)
    with pytest.raises(ValueError):
        MocapOptions(rate=2500)


@pytest.mark.parametrize("n", [2, 3, 6])
def test_any_number_of_modules_spins_about_the_locked_contact_point(n: int) -> None:
    ang = np.linspace(0.0, 2 * math.pi, n, endpoint=False) + 0.3
    truth = RobotParams.from_arrays(
        np.arange(1, n + 1),
        np.column_stack([0.3 * np.cos(ang), 0.2 * np.sin(ang)]),
        np.full(n, 0.01),
        np.full(n, 0.02),
        np.full(n, 0.05),
    )
    sim = RobotPhysics(truth, theta0=np.random.default_rng(n).uniform(-3, 3, n))
    C_W = sim.contact_points_world()[0].copy()
    spin(sim, 0, 5.0)
    assert abs(sim.twist[2]) > 0.1
    assert np.abs(sim.contact_points_world()[0] - C_W).max() < 1e-12
    Ta = truth.arrays()
    target, _ = settled_trailing(Ta.P_s, Ta.b, sim.contact_points()[0], np.sign(sim.twist[2]))
    assert np.abs(wrap_angle(sim.theta - target)[1:]).max() < 1e-6
