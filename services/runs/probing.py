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

What sees the robot turn is the run's metrology: motion capture's poses, or the gyro's
integrated rate alone (metrology ``imu``: no position, so a steering move is watched by
its turn, :data:`~swpc_hw.calibration.commission.probes.MOVE_TURN`, and a pivot probe's
fixed point comes from the free casters' wheel encoders,
:mod:`swpc_hw.calibration.commission.trailing`).
"""

from __future__ import annotations

import logging
import math
from dataclasses import replace
from typing import Any

import numpy as np

from services.runs.machine import RunMachine
from services.runs.metrology.gyro_motion import GyroYaw
from services.runs.metrology.imu import ImuMetrology
from services.runs.metrology.mocap import MocapMetrology
from services.runs.state import RunFailedError, State
from swpc_hw.calibration.commission.analysis import MOCAP_TURNS
from swpc_hw.calibration.commission.probes import (
    MOVE_MARGIN,
    MOVE_TURN,
    PIVOT_TRIES,
    PROBE_TURN,
    ROLL_MARGIN,
    WRONG_WAY,
    PivotPlan,
    PivotProbe,
    SteerMove,
    is_pinned,
    next_pivot,
    pivot_plan,
    plan_about,
)
from swpc_hw.calibration.commission.trailing import STD as TRAILING_STD
from swpc_hw.calibration.commission.trailing import trailing_fixed_point
from swpc_hw.calibration.fixed_point import fit_fixed_point
from swpc_hw.robot.model import wrap_angle

SETTLE = 0.3
"""s of robot time every probe waits after its motion (the robot comes to rest)."""
STALL = 3.0
"""s of robot time: a roll by torque that has not turned the robot half its turn by then
stops as one that does not turn it (its wheel pushes across the turn; a right robot's
turns it in under 2 s)."""
STEER_TOL = math.radians(1.0)
"""rad: a steering within this of its set-point is there."""


class GyroTurn:
    """The robot's yaw as the gyro integrates it, less the bias of the last rest: rows
    ``(t, nan, nan, yaw)`` as motion capture's poses are ``(t, x, y, yaw)`` (module
    docstring)."""

    def __init__(self, metrology: ImuMetrology) -> None:
        self.metrology = metrology
        self._cursor = 0
        self._yaw = GyroYaw(metrology.bias)
        self._rows: list[tuple[float, float, float, float]] = []

    def latest(self) -> tuple[float, float, float, float]:
        rows, self._cursor = self.metrology.gyro.samples_since(self._cursor)
        for t, wz in rows[:, [2, 3]].tolist():
            self._rows.append((t, math.nan, math.nan, self._yaw.add(t, wz)))
        if not self._rows:
            raise RunFailedError("no gyro sample: the probes need the robot's turn")
        return self._rows[-1]

    def since(self, t0: float) -> Any:
        self.latest()
        a = np.array(self._rows)
        return a[a[:, 0] >= t0]


class Prober:
    """The probes of one run (module docstring), and what they saw."""

    def __init__(self, run: RunMachine) -> None:
        self.run = run
        self._gyro = (
            GyroTurn(run.metrology) if isinstance(run.metrology, ImuMetrology) else None
        )
        self.steer_moves: list[SteerMove] = []
        self.pivot_probes: list[PivotProbe] = []
        self.largest_turn = 0.0
        self.largest_move = 0.0
        self.stops: list[dict[str, Any]] = []
        """Every roll stopped early: its modules, why, when after the roll began and after
        the pose that showed it (robot ms), how far the robot turned its way in all."""

    def _poses(self, since: float) -> Any:
        """The poses ``t, x, y, yaw`` since ``since`` (run clock; x, y nan: the gyro)."""
        if self._gyro is not None:
            return self._gyro.since(since)
        assert isinstance(self.run.metrology, MocapMetrology)
        return self.run.metrology.poses(since)

    def _pose(self) -> tuple[float, float, float, float]:
        """The latest pose ``(t, x, y, yaw)`` (run clock; x, y nan: the gyro)."""
        if self._gyro is not None:
            return self._gyro.latest()
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
            if self._gyro is None:
                moved = max(moved, self._axis_moved(m, p0, p))
            turned = max(turned, abs(math.remainder(p[3] - p0[3], 2 * math.pi)))
            if moved > budget if self._gyro is None else turned > MOVE_TURN:
                self._hold_all()
                self.run.event(
                    logging.WARNING, "commission.stop", module=m, moved_mm=moved * 1e3,
                    turned_deg=math.degrees(turned),
                )  # fmt: skip
                self.run.wait(SETTLE)
                p = self._pose()
                if self._gyro is None:
                    moved = max(moved, self._axis_moved(m, p0, p))
                turned = max(turned, abs(math.remainder(p[3] - p0[3], 2 * math.pi)))
                stopped = True
                break
            now = self.run.clock.now()
            if there is None and abs(wrap_angle(self.run.robot.steering(m) - target)) < STEER_TOL:
                there = now
            if there is not None and now - there >= SETTLE:
                break
            self.run.clock.poll(self.run.poll)
        self.largest_move = max(self.largest_move, moved)
        self.largest_turn = max(self.largest_turn, turned)
        move = SteerMove(m, step, moved, turned, budget, stopped)
        self.steer_moves.append(move)
        return move

    def pivot_probe(
        self, m: int, angle: float, j: int, turn: float = PROBE_TURN, retry: bool = True
    ) -> list[PivotProbe] | None:
        """Pivot probes about module ``m`` locked at ``angle``, rolled by ``j`` until the
        robot has turned ``turn`` (module docstring); None when a steering moved the robot
        (it stopped).  Without ``retry`` (the fast part), one roll.  With it (a
        commissioning), a roll that turned the robot the wrong way is stopped and rolled
        the other way (the turn then asked is counter-clockwise again); one that did not
        turn it (its driver's heading across the circle, or its drive not a wheel's) is
        tried with the next driver; one whose fixed point is not where its driver was
        steered to turn about is rolled again about the next estimate of the lock's
        contact point, then by the next driver (a fought lock,
        :mod:`~swpc_hw.calibration.commission.probes`).  Returns every roll's probe, the
        last one the one that tells (pinned, unless none was); the earlier ones unpinned."""
        ids = self.run.config.nominal.ids
        nominal = self.run.config.nominal
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
        if not retry:
            got = self._drive(m, j, pivot_plan(nominal, m, angle, j), turn, 1.0, False)
            return None if got is None else [self._observed(m, j, got[0], got[1], got[3])]
        drivers = [j] + [d for d in ids if d not in (m, j)]
        unpinned: list[PivotProbe] = []
        first_stop: str | None = None
        last = (math.nan, 0.0)  # the last roll's start and the wheel's reading then
        pivot = pivot_plan(nominal, m, angle, j).pivot
        for driver in drivers:
            # from where the rolls so far put the lock (the next driver too: a lock that
            # is elsewhere is elsewhere for every driver)
            history: list[tuple[tuple[float, float], tuple[float, float]]] = []
            sign = 1.0
            push = self.run.robot.spins_by_torque(driver)
            for _ in range(PIVOT_TRIES):
                plan = plan_about(nominal, pivot, driver)
                got = self._drive(m, driver, plan, turn, sign, push)
                if got is None:
                    return None
                if got[2] == "wrong way":  # its wheel turns the other way: rolled the other way
                    first_stop = first_stop or got[3]
                    sign = -sign
                    self._free_others(m, driver)
                    expected = abs(plan.roll_per_turn * turn)
                    got = self._roll(m, driver, sign * plan.roll_rate, expected, turn, push)
                last = (got[0], got[1])
                probe = self._observed(m, driver, got[0], got[1], first_stop or got[3], push)
                pinned = is_pinned(probe, pivot, MOCAP_TURNS)
                if got[2] == "no turn":
                    # a roll that turned the robot a little about a point elsewhere (a
                    # push across the turn about where the lock is not) steers again
                    first_stop = first_stop or got[3]
                    if probe.fixed_point is None or pinned:
                        break  # its wheel cannot turn the robot about this lock
                elif probe.fixed_point is None or len(drivers) == 1 or pinned:
                    return [*unpinned, probe]
                else:
                    elsewhere = self._not_pinned(m, driver, probe, pivot)
                    first_stop = first_stop or elsewhere
                assert probe.fixed_point is not None
                unpinned.append(replace(probe, pinned=False))
                history.append((pivot, probe.fixed_point))
                pivot = next_pivot(history)
        if unpinned:
            return unpinned
        return [self._observed(m, drivers[-1], last[0], last[1], first_stop)]

    def _drive(
        self, m: int, driver: int, plan: PivotPlan, turn: float, sign: float, push: bool
    ) -> tuple[float, float, str | None, str | None] | None:
        """The driver steered as ``plan`` says (the others held, the robot pinned), then the
        others freed and the driver rolled at ``sign`` times the plan's rate, pushed or not
        (:meth:`_roll`'s answer); None when its steering moved the robot."""
        for mod in self.run.config.nominal.ids:
            if mod != m:
                self.run.robot.wheel_hold(mod)
                self.run.robot.steer_to(mod, self.run.robot.steering(mod))
        self.run.robot.wheel_free(driver)
        if self._steer(driver, plan.driver_steering).stopped:
            return None
        self._free_others(m, driver)
        expected = abs(plan.roll_per_turn * turn)
        return self._roll(m, driver, sign * plan.roll_rate, expected, turn, push)

    def _not_pinned(
        self, m: int, driver: int, probe: PivotProbe, pivot: tuple[float, float]
    ) -> str:
        """A roll whose fixed point was not where its driver was steered to turn about:
        recorded as a stop; the probe goes on (:meth:`pivot_probe`)."""
        assert probe.fixed_point is not None
        off = 1000 * math.hypot(probe.fixed_point[0] - pivot[0], probe.fixed_point[1] - pivot[1])
        text = (
            f"module {driver}'s roll turned the robot about a point {off:.0f} mm from where it "
            f"was steered to turn about module {m}'s lock: the lock is elsewhere, or the "
            "roll fought it (a steering not where the config says); steered again about "
            "the point seen"
        )
        self.stops.append({
            "module": m, "driver": driver, "why": "not pinned", "after_ms": None,
            "seen_ms": None, "turned_deg": round(math.degrees(probe.turn), 2),
            "off_mm": round(off, 1),
        })  # fmt: skip
        self.run.event(logging.WARNING, "commission.stop", module=m, driver=driver, why=text)
        return text

    def _free_others(self, m: int, driver: int) -> None:
        """The modules but the locked one and the driver free (their casters trail)."""
        for mod in self.run.config.nominal.ids:
            if mod not in (m, driver):
                self.run.robot.free_steer(mod)
                self.run.robot.wheel_free(mod)
        self.run.wait(SETTLE)

    def _roll(
        self, m: int, j: int, rate: float, expected: float, target: float, push: bool = False
    ) -> tuple[float, float, str | None, str | None]:
        """Module ``j``'s wheel at ``rate`` (``push``: by ``limits.spin_torque`` the way
        ``rate`` turns, see :mod:`~swpc_hw.calibration.commission.probes`) until the robot
        has turned ``target`` counter-clockwise (the plan's rate turns it so; the
        other way round, a wheel that turns the other way): ``(t0, psi0, stop, text)``, its
        start, the wheel's reading then, and why it stopped early (``wrong way``, ``no
        turn``; None)."""
        t0, _, _, yaw0 = self._pose()
        rows0 = self.run.robot.encoders(j, t0 - 0.2)
        psi0 = float(rows0[-1, 2]) if len(rows0) else 0.0
        if push:
            self.run.robot.wheel_torque(j, math.copysign(self.run.config.limits.spin_torque, rate))
        else:
            self.run.robot.wheel_velocity(j, rate)
        deadline = self.run.deadline()
        last, stop, text = yaw0, None, None
        unseen = (
            "the sensor does not see the robot turn (a Y-up motion capture)"
            if self._gyro is None else "the gyro does not see the robot turn"
        )  # fmt: skip
        while True:
            self.run.check(True, deadline)
            t, _, _, yaw = self._pose()
            last += math.remainder(yaw - last, 2 * math.pi)
            turn = last - yaw0
            rows = self.run.robot.encoders(j, t0)
            roll = float(rows[-1, 2]) - psi0 if len(rows) else 0.0
            stalled = push and self.run.clock.now() - t0 > STALL and turn < 0.5 * target
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
            elif abs(roll) >= ROLL_MARGIN * expected or stalled:
                stop = "no turn"
                how = f"pushed {STALL:.0f} s" if stalled else "rolled"
                text = (
                    f"module {j}'s wheel {how} ({math.degrees(abs(roll)):.0f} deg) and the "
                    f"robot turned {math.degrees(turn):.1f} deg of the "
                    f"{math.degrees(target):.0f} deg asked: {unseen}, its drive does not roll "
                    "a wheel, or the wheel points across the turn"
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
            self.run.clock.poll(self.run.poll)
        self.run.robot.wheel_hold(j)
        self.run.wait(SETTLE)
        if stop is not None:  # the whole turn the wrong way, once the robot has stopped
            _, _, _, yaw = self._pose()
            self.stops[-1]["turned_deg"] = round(
                math.degrees(math.remainder(yaw - yaw0, 2 * math.pi)), 2
            )
        return t0, psi0, stop, text

    def _observed(
        self, m: int, j: int, t0: float, psi0: float, stopped: str | None, pushed: bool = False
    ) -> PivotProbe:
        """What the poses and the encoders since ``t0`` say of a pivot probe."""
        rows = self._poses(t0)
        poses = np.column_stack([rows[:, :3], np.unwrap(rows[:, 3])])
        turn = float(poses[-1, 3] - poses[0, 3]) if len(poses) else 0.0
        enc_m, enc_j = self.run.robot.encoders(m, t0), self.run.robot.encoders(j, t0)
        roll = float(enc_j[-1, 2]) - psi0 if len(enc_j) else 0.0
        F: tuple[float, float] | None = None
        std = math.inf
        if self._gyro is not None:
            F, std, stopped = self._trailing(m, j, t0, poses, stopped)
        elif abs(turn) >= math.radians(1.0) and len(poses) >= 10:
            fit = fit_fixed_point(poses)
            F = (float(fit.C_R[0]), float(fit.C_R[1]))
            std = fit.std
        self.largest_turn = max(self.largest_turn, abs(turn))
        if self._gyro is None:
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
            pushed=pushed,
        )

    def _trailing(
        self, m: int, j: int, t0: float, poses: Any, stopped: str | None
    ) -> tuple[tuple[float, float] | None, float, str | None]:
        """A gyro probe's fixed point from its free modules' encoders
        (:func:`~swpc_hw.calibration.commission.trailing.trailing_fixed_point`): ``(point,
        its std dev, stopped)``; a point the free modules disagree on is None, ``stopped``
        then saying so."""
        ids = self.run.config.nominal.ids
        trailing = {k: self.run.robot.encoders(k, t0) for k in ids if k not in (m, j)}
        fix = trailing_fixed_point(self.run.config.nominal, trailing, poses[:, [0, 3]])
        if fix is None:
            return None, math.inf, stopped
        if fix.agrees:
            return fix.point, TRAILING_STD, stopped
        worst = "" if fix.worst is None else f", module {fix.worst}'s the most"
        text = (
            f"the free modules' wheels ({', '.join(map(str, fix.modules))}) rolled "
            f"{1000 * fix.residual:.1f} mm (RMS) off what the gyro's turn about one point "
            f"asks{worst}: a wheel or steering of theirs turns the other way round or by "
            "another ratio, or their nodes are crossed"
        )
        self.run.event(logging.WARNING, "commission.stop", module=m, driver=j, why=text)
        return None, math.inf, stopped or text
