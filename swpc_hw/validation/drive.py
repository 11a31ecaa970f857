"""The validation drive: squares through the CAN driver, measured against the truth."""

from __future__ import annotations

import math
import threading
from collections.abc import Callable, Iterator, Sequence

import numpy as np

from firmware_protocol.codec import Axis
from swpc_hw.drives.interface import Drives
from swpc_hw.drives.types import AxisSigns, DriverEvent, Lifecycle, Severity, axis_sign
from swpc_hw.onboard.odometry import OdometryOptions
from swpc_hw.onboard.square_path import Direction, Leg, SquareOptions, follow_step, square_plan
from swpc_hw.onboard.twist_controller import TwistController
from swpc_hw.robot.model import RobotParams
from swpc_hw.validation.errors import ValidationError
from swpc_hw.validation.odometry_feed import DriverOdometry
from swpc_hw.validation.report import RunResult, ValidationReport, to_start_frame
from swpc_hw.validation.truth import ZenohTruth


class SquareDrive:
    """Drives squares through the robot's :class:`~swpc_hw.drives.interface.Drives`
    (activated, homed) and measures them.

    Time is the driver's clock (robot seconds; in lockstep with the in-process simulator
    the calling thread must be a participant of it).  ``polarity`` (the robot config's)
    turns what is commanded to each axis and read from it, as a run does.
    """

    def __init__(
        self,
        driver: Drives,
        truth: ZenohTruth,
        params: RobotParams,
        options: SquareOptions | None = None,
        *,
        odometry_options: OdometryOptions | None = None,
        log: Callable[[str], None] | None = None,
        polarity: AxisSigns | None = None,
    ) -> None:
        self.driver = driver
        self.polarity = dict(polarity or {})
        self.truth = truth
        self.options = opt = options or SquareOptions()
        self.clock = driver.clock
        self.controller = TwistController(
            params, max_wheel_rate=opt.max_wheel_rate, max_steer_rate=opt.max_steer_rate
        )
        self.odometry = DriverOdometry(
            driver, params, options=odometry_options, polarity=self.polarity
        )
        self._faults: list[str] = []
        self._flock = threading.Lock()
        driver.add_event_callback(self._on_event)
        self._log = log or (lambda _msg: None)

    def _on_event(self, ev: DriverEvent) -> None:
        if ev.severity is Severity.FAULT:
            with self._flock:
                self._faults.append(ev.message)

    def _check(self) -> None:
        with self._flock:
            faults = list(self._faults)
        if faults:
            raise ValidationError(f"driver fault: {faults[0]}")
        if self.driver.state is not Lifecycle.ACTIVE:
            raise ValidationError(f"driver is {self.driver.state.value}, not active")
        if self.driver.last_exception is not None:
            raise ValidationError(f"driver error: {self.driver.last_exception}")

    # ------------------------------------------------------------------ low level
    def set_params(self, params: RobotParams) -> None:
        """Use another kinematic file for control and odometry."""
        self.controller = TwistController(
            params, max_wheel_rate=self.options.max_wheel_rate,
            max_steer_rate=self.options.max_steer_rate,
        )
        self.odometry.set_params(params)

    def _command(self, twist: Sequence[float]) -> tuple[float, float, float]:
        """Send the rates realising ``twist``; returns the applied (rate-limited) twist.

        The inverse kinematics is evaluated at the steering predicted for the middle of the
        interval the command will act over, ``theta_hat + theta_hat_dot * lead`` (reported
        steering rate of the feedback, ``lead = lead_time``): commands stay consistent
        with the no-slip model while the casters re-orient (to second order in the step).
        """
        ids = self.controller.params.ids
        opt = self.options
        lead = opt.lead_time if opt.lead_time is not None else 0.5 / opt.control_rate + 0.005
        th = []
        for m in ids:
            fb = self.driver.module_state(m).feedback
            if fb is None:
                raise ValidationError(f"module {m}: no feedback")
            rate = fb.steer_velocity if math.isfinite(fb.steer_velocity) else 0.0
            th.append(axis_sign(self.polarity, m, Axis.STEER) * (fb.theta_hat + rate * lead))
        cmd = self.controller.command(th, twist)
        for i, m in enumerate(ids):
            s, w = (axis_sign(self.polarity, m, a) for a in (Axis.STEER, Axis.WHEEL))
            self.driver.set_velocity(m, Axis.STEER, s * float(cmd.theta_hat_dot[i]))
            self.driver.set_velocity(m, Axis.WHEEL, w * float(cmd.psi_dot[i]))
        return cmd.twist

    def stand_still(self, duration: float) -> None:
        """Zero twist for ``duration`` robot seconds."""
        self._command((0.0, 0.0, 0.0))
        clock = self.clock
        end = clock.now() + duration
        while clock.now() < end:
            self._check()
            clock.sleep(min(0.02, max(0.0, end - clock.now())))

    def _robot_now(self) -> float:
        """Robot time of the latest odometry reading (the clock's before any)."""
        t = self.odometry.t
        return t if t is not None else self.clock.now()

    def _pace(self) -> Iterator[None]:
        """Yield once per control period (``1 / control_rate`` robot s)."""
        clock = self.clock
        period = 1.0 / self.options.control_rate
        nxt = clock.now()
        while True:
            yield
            nxt += period
            if nxt > clock.now():
                clock.sleep_until(nxt)
            elif nxt < clock.now() - period:
                nxt = clock.now()

    def follow(self, legs: Sequence[Leg]) -> float:
        """Drive the legs (odometry frame); returns the robot time taken."""
        opt = self.options
        t_start = self._robot_now()
        for leg in legs:
            if leg.kind == "line":
                limit = 3.0 * math.dist(leg.start, leg.end) / opt.speed + 30.0
            else:
                turn = abs(leg.yaw - self.odometry.pose[2])
                limit = 3.0 * turn / opt.yaw_rate + 30.0
            t_leg = t_prev = self._robot_now()
            memory = 0.0
            for _ in self._pace():
                self._check()
                now = self._robot_now()
                dt, t_prev = min(max(now - t_prev, 0.0), 5.0 / opt.control_rate), now
                twist, memory, done = follow_step(leg, self.odometry.pose, memory, dt, opt)
                applied = self._command(twist)
                if done:
                    break
                if leg.kind == "line":
                    if abs(twist[0]) + abs(twist[1]) > 1e-12:
                        k = math.hypot(*applied[:2]) / math.hypot(*twist[:2])
                        memory *= min(1.0, k)
                elif abs(twist[2]) > 1e-12:
                    memory *= min(1.0, abs(applied[2] / twist[2]))
                if now - t_leg > limit:
                    raise ValidationError(
                        f"{leg.kind} leg not completed within {limit:.0f} s (robot time)"
                    )
        self._command((0.0, 0.0, 0.0))
        return self._robot_now() - t_start

    # ------------------------------------------------------------------ one square
    def run_square(self, label: str, direction: Direction, run: int) -> RunResult:
        opt = self.options
        self.stand_still(opt.settle / 2)
        w0 = self.clock.now()
        self.stand_still(opt.settle)
        start = self.truth.mean_pose(w0)
        self.odometry.reset(start)
        mark = self.odometry.mark()
        t_path = self.clock.now()
        legs = square_plan(start, opt.side, direction)
        duration = self.follow(legs)
        self.stand_still(opt.settle / 2)
        w1 = self.clock.now()
        self.stand_still(opt.settle)
        end_true = self.truth.mean_pose(w1)
        end_odo = self.odometry.pose
        tr = self.truth.since(t_path)
        od = self.odometry.track_since(mark)
        slip = self.odometry.slip_since(mark)
        res = RunResult(
            label=label, direction=direction, run=run, start=start, end_true=end_true,
            end_odometry=end_odo, duration=duration,
            true_path=to_start_frame(start, tr[:, 2:4]),
            odometry_path=to_start_frame(start, od[:, 1:3]),
            max_slip=float(np.max(slip)) if slip.size else 0.0,
        )
        self._log(
            f"{label:<11} {direction.upper():<4} run {run + 1}: end error "
            f"{res.position_error * 1e3:8.2f} mm {math.degrees(res.heading_error):7.3f} deg "
            f"({duration:.0f} s, max slip indicator {res.max_slip * 1e3:.1f} mm/s)"
        )
        return res


def validate(
    drive: SquareDrive, files: Sequence[tuple[str, RobotParams]]
) -> ValidationReport:
    """Every file x direction x run on ``drive`` (stop_all on any error)."""
    opt = drive.options
    results: list[RunResult] = []
    try:
        for label, params in files:
            drive.set_params(params)
            for direction in opt.directions:
                for k in range(opt.runs):
                    results.append(drive.run_square(label, direction, k))
    finally:
        drive.driver.stop_all()
    return ValidationReport(labels=[lab for lab, _ in files], results=results, options=opt)


def prepare_driver(driver: Drives, timeout: float = 10.0) -> None:
    """Activate (if needed), clear errors, enable both axes and home unhomed steering."""
    if driver.state is not Lifecycle.ACTIVE:
        driver.activate()
    for m in driver.modules():
        driver.clear_errors(m)
        driver.enable(m, Axis.STEER)
        driver.enable(m, Axis.WHEEL)
    for m in driver.modules():
        if not driver.module_state(m).homed:
            driver.start_homing(m)
    for m in driver.modules():
        driver.wait_for(m, lambda s: s.homed and s.feedback is not None, timeout, "homed")
