"""The probes' motions on the robot (services/runs/commission.py, and the fast part of
every calibration and check): what :mod:`swpc_hw.calibration.commission.probes` plans,
done through a run's robot, its checks and its poses.

* every steering move is made with the robot pinned (every other module braked and its
  steering held) and watched: a steering axis that moves
  :data:`~swpc_hw.calibration.commission.probes.MOVE_MARGIN` stops every axis at once;
* a pivot probe locks module ``m`` at an angle, steers its driver across the circle about
  ``m``'s contact point, frees the others and rolls the driver at the rate that turns a
  right robot :data:`~swpc_hw.calibration.commission.probes.PROBE_RATE` counter-clockwise,
  until the robot has turned what it asks.  It stops at once (every axis held) when the
  robot turns :data:`~swpc_hw.calibration.commission.probes.WRONG_WAY` the other way (a
  wheel turning the other way round must not spin the robot), or when the wheel rolled
  :data:`~swpc_hw.calibration.commission.probes.ROLL_MARGIN` times what the turn asks
  without it.
"""

from __future__ import annotations

import logging
import math
from typing import Any

import numpy as np

from services.runs.machine import RunMachine
from services.runs.metrology.mocap import MocapMetrology
from services.runs.state import RunFailedError, State
from swpc_hw.calibration.commission.probes import (
    MOVE_MARGIN,
    PROBE_TURN,
    ROLL_MARGIN,
    WRONG_WAY,
    PivotProbe,
    SteerMove,
    pivot_plan,
)
from swpc_hw.calibration.fixed_point import fit_fixed_point
from swpc_hw.robot.model import wrap_angle

SETTLE = 0.3
"""s of robot time every probe waits after its motion (the robot comes to rest)."""
STEER_TOL = math.radians(1.0)
"""rad: a steering within this of its set-point is there."""


class Prober:
    """The probes of one run (module docstring), and what they saw."""

    def __init__(self, run: RunMachine) -> None:
        self.run = run
        self.steer_moves: list[SteerMove] = []
        self.pivot_probes: list[PivotProbe] = []
        self.largest_turn = 0.0
        self.largest_move = 0.0
        self.stops: list[dict[str, Any]] = []
        """Every roll stopped early: its modules, why, when after the roll began and after
        the pose that showed it (robot ms), how far the robot turned its way in all."""

    def _poses(self, since: float) -> Any:
        """The poses ``t, x, y, yaw`` since ``since`` (run clock)."""
        assert isinstance(self.run.metrology, MocapMetrology)
        return self.run.metrology.poses(since)

    def _pose(self) -> tuple[float, float, float, float]:
        """The latest pose ``(t, x, y, yaw)`` (run clock)."""
        assert isinstance(self.run.metrology, MocapMetrology)
        p = self.run.metrology.mocap.latest()
        if p is None:
            raise RunFailedError("no pose: the probes need the poses")
        return p.t_host, p.x, p.y, p.yaw

    def _hold_all(self) -> None:
        """Every axis held where it is (a probe's stop)."""
        for mod in self.run.config.nominal.ids:
            self.run.robot.wheel_hold(mod)
            self.run.robot.steer_to(mod, self.run.robot.steering(mod))

    def _axis_moved(self, m: int, p0: tuple[float, ...], p1: tuple[float, ...]) -> float:
        """How far module ``m``'s steering axis (nominal) moved between two poses (m)."""
        A = self.run.config.nominal.arrays()
        x, y = A.P_s[self.run.config.nominal.ids.index(m)]

        def at(p: tuple[float, ...]) -> tuple[float, float]:
            c, s = math.cos(p[3]), math.sin(p[3])
            return p[1] + c * x - s * y, p[2] + s * x + c * y

        (x0, y0), (x1, y1) = at(p0), at(p1)
        return math.hypot(x1 - x0, y1 - y0)

    def _steer(self, m: int, target: float) -> SteerMove:
        """Module ``m``'s steering to ``target`` (host rad) while the poses are watched: its
        steering axis moving :data:`~.probes.MOVE_MARGIN` stops every axis at once (module
        docstring)."""
        p0 = self._pose()
        step = math.remainder(target - self.run.robot.steering(m), 2 * math.pi)
        budget = MOVE_MARGIN
        self.run.robot.steer_to(m, target)
        deadline, there = self.run.deadline(), None
        moved = turned = 0.0
        stopped = False
        while True:
            self.run.check(True, deadline)
            p = self._pose()
            moved = max(moved, self._axis_moved(m, p0, p))
            turned = max(turned, abs(math.remainder(p[3] - p0[3], 2 * math.pi)))
            if moved > budget:
                self._hold_all()
                self.run.event(logging.WARNING, "commission.stop", module=m, moved_mm=moved * 1e3)
                self.run.wait(SETTLE)
                p = self._pose()
                moved = max(moved, self._axis_moved(m, p0, p))
                stopped = True
                break
            now = self.run.clock.now()
            if there is None and abs(wrap_angle(self.run.robot.steering(m) - target)) < STEER_TOL:
                there = now
            if there is not None and now - there >= SETTLE:
                break
            self.run.clock.sleep(self.run.poll)
        self.largest_move = max(self.largest_move, moved)
        self.largest_turn = max(self.largest_turn, turned)
        move = SteerMove(m, step, moved, turned, budget, stopped)
        self.steer_moves.append(move)
        return move

    def pivot_probe(
        self, m: int, angle: float, j: int, turn: float = PROBE_TURN, retry: bool = True
    ) -> PivotProbe | None:
        """A pivot probe about module ``m`` locked at ``angle`` rolled by ``j`` until the
        robot has turned ``turn`` (module docstring); None when a steering moved the robot
        (it stopped).  With ``retry``, a roll that turned the robot the wrong way is
        stopped and rolled the other way (the turn then asked is counter-clockwise again),
        and one that did not turn it (its driver's heading across the circle, or its drive
        not a wheel's) is tried with the next driver; without, the probe ends there."""
        ids = self.run.config.nominal.ids
        deg = math.degrees(angle)
        self.run.enter(State.PROBE, f"pivot probe: module {m} locked at {deg:.0f} deg, {j} rolls")
        # every steering move with the robot pinned by the others (braked and held), its
        # own wheel free (its tyre turns on the spot), then braked
        for mod in ids:
            self.run.robot.wheel_hold(mod)
            if mod != m:
                self.run.robot.steer_to(mod, self.run.robot.steering(mod))
        self.run.robot.wheel_free(m)
        if self._steer(m, angle).stopped:
            return None
        self.run.robot.wheel_hold(m)
        drivers = [j] + [d for d in ids if d not in (m, j)]
        first_stop: str | None = None
        for driver in drivers:
            plan = pivot_plan(self.run.config.nominal, m, angle, driver)
            for mod in ids:
                if mod != m:
                    self.run.robot.wheel_hold(mod)
                    self.run.robot.steer_to(mod, self.run.robot.steering(mod))
            self.run.robot.wheel_free(driver)
            if self._steer(driver, plan.driver_steering).stopped:
                return None
            self._free_others(m, driver)
            got = self._roll(m, driver, plan.roll_rate, abs(plan.roll_per_turn * turn), turn)
            if not retry:
                return self._observed(m, driver, got[0], got[1], got[3])
            if got[2] == "wrong way":  # its wheel turns the other way: rolled the other way
                first_stop = first_stop or got[3]
                self._free_others(m, driver)
                got = self._roll(
                    m, driver, -plan.roll_rate, abs(plan.roll_per_turn * turn), turn
                )
            if got[2] != "no turn":
                return self._observed(m, driver, got[0], got[1], first_stop or got[3])
            first_stop = first_stop or got[3]
        return self._observed(m, drivers[-1], got[0], got[1], first_stop)

    def _free_others(self, m: int, driver: int) -> None:
        """The modules but the locked one and the driver free (their casters trail)."""
        for mod in self.run.config.nominal.ids:
            if mod not in (m, driver):
                self.run.robot.free_steer(mod)
                self.run.robot.wheel_free(mod)
        self.run.wait(SETTLE)

    def _roll(
        self, m: int, j: int, rate: float, expected: float, target: float
    ) -> tuple[float, float, str | None, str | None]:
        """Module ``j``'s wheel at ``rate`` until the robot has turned ``target``
        counter-clockwise (the plan's rate turns it so; the
        other way round, a wheel that turns the other way): ``(t0, psi0, stop, text)``, its
        start, the wheel's reading then, and why it stopped early (``wrong way``, ``no
        turn``; None)."""
        t0, _, _, yaw0 = self._pose()
        rows0 = self.run.robot.encoders(j, t0 - 0.2)
        psi0 = float(rows0[-1, 2]) if len(rows0) else 0.0
        self.run.robot.wheel_velocity(j, rate)
        deadline = self.run.deadline()
        last, stop, text = yaw0, None, None
        while True:
            self.run.check(True, deadline)
            t, _, _, yaw = self._pose()
            last += math.remainder(yaw - last, 2 * math.pi)
            turn = last - yaw0
            rows = self.run.robot.encoders(j, t0)
            roll = float(rows[-1, 2]) - psi0 if len(rows) else 0.0
            if turn <= -WRONG_WAY:
                stop = "wrong way"
                text = (
                    f"module {j}'s wheel turned the robot {math.degrees(-turn):.1f} deg the "
                    "other way than its roll turns it (stopped "
                    f"{1000 * (self.run.clock.now() - t0):.0f} ms after the roll began): its "
                    "wheel turns the other way round, or it points another way than its "
                    "steering says"
                )
            elif turn >= target:
                break
            elif abs(roll) >= ROLL_MARGIN * expected:
                stop = "no turn"
                text = (
                    f"module {j}'s wheel rolled {math.degrees(abs(roll)):.0f} deg and the "
                    f"robot turned {math.degrees(turn):.1f} deg of the "
                    f"{math.degrees(target):.0f} deg asked: the sensor does not see the robot "
                    "turn (a Y-up motion capture), its drive does not roll a wheel, or the "
                    "wheel points across the turn"
                )
            if stop is not None:
                self._hold_all()
                self.stops.append({
                    "module": m, "driver": j, "why": stop,
                    "after_ms": round(1000 * (self.run.clock.now() - t0), 1),
                    "seen_ms": round(1000 * (self.run.clock.now() - t), 1),
                })  # fmt: skip
                self.run.event(logging.WARNING, "commission.stop", module=m, driver=j, why=text)
                break
            self.run.clock.sleep(self.run.poll)
        self.run.robot.wheel_hold(j)
        self.run.wait(SETTLE)
        if stop is not None:  # the whole turn the wrong way, once the robot has stopped
            _, _, _, yaw = self._pose()
            self.stops[-1]["turned_deg"] = round(
                math.degrees(math.remainder(yaw - yaw0, 2 * math.pi)), 2
            )
        return t0, psi0, stop, text

    def _observed(self, m: int, j: int, t0: float, psi0: float, stopped: str | None) -> PivotProbe:
        """What the poses and the encoders since ``t0`` say of a pivot probe."""
        rows = self._poses(t0)
        poses = np.column_stack([rows[:, :3], np.unwrap(rows[:, 3])])
        turn = float(poses[-1, 3] - poses[0, 3]) if len(poses) else 0.0
        enc_m, enc_j = self.run.robot.encoders(m, t0), self.run.robot.encoders(j, t0)
        roll = float(enc_j[-1, 2]) - psi0 if len(enc_j) else 0.0
        F: tuple[float, float] | None = None
        std = math.inf
        if abs(turn) >= math.radians(1.0) and len(poses) >= 10:
            fit = fit_fixed_point(poses)
            F = (float(fit.C_R[0]), float(fit.C_R[1]))
            std = fit.std
        self.largest_turn = max(self.largest_turn, abs(turn))
        self.largest_move = max(
            self.largest_move, float(np.max(np.hypot(*(poses[:, 1:3] - poses[0, 1:3]).T)))
        )
        return PivotProbe(
            module=m,
            steering=float(np.mean(enc_m[:, 1])) if len(enc_m) else self.run.robot.steering(m),
            driver=j,
            driver_steering=float(np.mean(enc_j[:, 1])) if len(enc_j) else math.nan,
            roll=roll,
            turn=turn,
            fixed_point=F,
            fixed_point_std=std,
            stopped=stopped,
        )

