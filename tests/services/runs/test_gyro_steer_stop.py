"""The fast part's steering move with the gyro alone stops every axis once the pinned
robot has turned :data:`~swpc_hw.calibration.commission.probes.MOVE_TURN` (issue 43,
item 5): the real :class:`~services.runs.probing.Prober`, gyro ingest and metrology, a
stand-in run whose robot turns while one steering moves.  The in-process simulator
cannot show it: its braked wheels hold a pinned robot exactly, whatever the steering
does."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from services.config.robot import RobotConfig
from services.runs.metrology.imu import ImuMetrology
from services.runs.probing import Prober
from services.sensors.gyro import GyroIngest
from swpc_hw.calibration.commission.probes import MOVE_TURN
from swpc_hw.clock import VirtualClock
from swpc_hw.sensors.gyro import GyroSample, encode_imu

RATE = 0.5  # rad/s: the pinned robot turning while the miswired steering moves
GYRO_DT = 0.005  # s: 200 Hz


@dataclass
class TurningRobot:
    """Module 3's steering drive turns the robot at :data:`RATE` while it moves (its
    setpoint away from its reading); every command is logged."""

    clock: VirtualClock
    gyro: GyroIngest
    steer: dict[int, float] = field(default_factory=lambda: {m: 0.0 for m in (1, 2, 3, 4)})
    target: dict[int, float] = field(default_factory=dict)
    log: list[tuple[float, str, int]] = field(default_factory=list)

    def steering(self, m: int) -> float:
        return self.steer[m]

    def steer_to(self, m: int, angle: float) -> None:
        self.target[m] = angle
        self.log.append((self.clock.now(), "steer_to", m))

    def wheel_hold(self, m: int) -> None:
        self.log.append((self.clock.now(), "wheel_hold", m))

    def wheel_free(self, m: int) -> None:
        self.log.append((self.clock.now(), "wheel_free", m))

    def advance(self, dt: float) -> None:
        """Time and the gyro: module 3 steers 1 rad/s towards its target, the robot turning
        while it does."""
        t_end = self.clock.now() + dt
        while self.clock.now() < t_end - 1e-12:
            self.clock.advance(GYRO_DT)
            moving = abs(self.target.get(3, self.steer[3]) - self.steer[3]) > 1e-6
            if moving:
                step = math.copysign(min(GYRO_DT, abs(self.target[3] - self.steer[3])),
                                     self.target[3] - self.steer[3])  # fmt: skip
                self.steer[3] += step
            wz = RATE if moving else 0.0
            self.gyro.feed(encode_imu(GyroSample(self.clock.wall(), wz)))


@dataclass
class Run:
    """What the prober asks of a run (services.runs.machine.RunMachine), on a virtual
    clock whose sleeps move the stand-in robot."""

    robot: TurningRobot
    metrology: ImuMetrology
    config: RobotConfig
    clock: Any
    poll: float = 0.02
    events: list[tuple[str, dict[str, Any]]] = field(default_factory=list)

    def check(self, motion: bool, deadline: float | None) -> None:
        assert deadline is None or self.clock.now() < deadline, "step timeout"

    def deadline(self) -> float:
        return self.clock.now() + self.config.limits.step_timeout

    def wait(self, seconds: float, motion: bool = True) -> None:
        self.clock.sleep(seconds)

    def event(self, level: int, name: str, **fields: Any) -> None:
        self.events.append((name, fields))

    def enter(self, state: Any, step: str) -> None:
        self.events.append(("enter", {"step": step}))


class Clock(VirtualClock):
    """A virtual clock whose sleeps advance the robot (set after construction)."""

    robot: TurningRobot | None = None

    def sleep(self, dt: float) -> None:
        assert self.robot is not None
        self.robot.advance(dt)


def test_a_steering_move_that_turns_the_pinned_robot_stops_every_axis() -> None:
    clock = Clock(start=10.0)
    gyro = GyroIngest(clock=clock, stale_after=0.5)
    config = RobotConfig()
    robot = TurningRobot(clock, gyro)
    clock.robot = robot
    robot.advance(0.1)  # the gyro's first samples
    run = Run(robot, ImuMetrology(gyro, config), config, clock)
    prober = Prober(run)  # type: ignore[arg-type]
    t0 = clock.now()
    # the fast part's probe about module 3 at 90 deg: its lock's steering move comes first
    assert prober.pivot_probe(3, math.radians(90.0), 1, retry=False) is None
    move = prober.steer_moves[-1]
    assert move.stopped and move.module == 3
    # stopped once the turn passed 2 deg: at 0.5 rad/s that is 70 ms, seen within a poll
    stop = next(t for t, what, m in robot.log if what == "wheel_hold" and t > t0)
    assert MOVE_TURN / RATE <= stop - t0 <= MOVE_TURN / RATE + 2 * run.poll
    # every axis held at once: every wheel braked, every steering held where it was
    held = [(what, m) for t, what, m in robot.log if t == stop]
    assert {m for what, m in held if what == "wheel_hold"} == {1, 2, 3, 4}
    assert {m for what, m in held if what == "steer_to"} == {1, 2, 3, 4}
    assert robot.target[3] == robot.steer[3]  # module 3 held where the stop found it
    assert math.radians(2.0) < move.turned < math.radians(3.0)
    stops = [f for n, f in run.events if n == "commission.stop"]
    assert len(stops) == 1 and stops[0]["module"] == 3 and stops[0]["turned_deg"] > 2.0
    print(f"\nstopped {1000 * (stop - t0):.0f} ms after the move began, the robot "
          f"turned {math.degrees(move.turned):.2f} deg")  # fmt: skip
