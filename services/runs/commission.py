"""Commissioning: what the robot's drives really move, before its first calibration
(docs/commissioning.md).

A :class:`CommissionRun` is a run (:class:`~services.runs.protocol.CalibrationRun`'s
CONNECT, PRECHECK and REST, its watchdog, limits, step timeout, abort, faults and
recordings) whose motion is the probes of :mod:`swpc_hw.calibration.commission.probes`,
each a state PROBE:

* every steering move is made with the robot pinned (every other module braked and its
  steering held) and watched: a steering axis that moves
  (:func:`~swpc_hw.calibration.commission.probes.steer_budget`) stops every axis at once,
  and the probes there.
* two **pivot probes** per module ``m``: ``m`` locked at each angle of
  :data:`~.probes.PIVOT_ANGLES`, the driver (:func:`~.probes.driver_of`) steered across the
  circle about ``m``'s contact point, its wheel rolled at the rate that turns a right
  robot :data:`~.probes.PROBE_RATE` counter-clockwise, until the robot has turned
  :data:`~.probes.PROBE_TURN`.  It stops at once when the robot turns
  :data:`~.probes.WRONG_WAY` the other way (a wheel turning the other way round must not
  spin the robot) or when the wheel rolled :data:`~.probes.ROLL_MARGIN` times what the turn
  asks without it.

SOLVE analyses them (:func:`swpc_hw.calibration.commission.analysis.analyse`) and WRITE
makes the report: the findings, each naming the axis and its fix, and the robot config
corrected (:mod:`services.config.commission`), shown as a difference; nothing is written
before the operator accepts it (``POST /commissions/{id}/accept``).
"""

from __future__ import annotations

import hashlib
import logging
import math
from typing import Any

import numpy as np

from services.config.commission import corrected_config
from services.config.robot import RobotConfig
from services.runs.metrology.base import Metrology
from services.runs.metrology.mocap import MocapMetrology
from services.runs.protocol import CalibrationRun
from services.runs.state import RunFailedError, State
from swpc_hw.calibration.commission.analysis import Commissioning, analyse
from swpc_hw.calibration.commission.probes import (
    MOVE_MARGIN,
    PIVOT_ANGLES,
    PROBE_TURN,
    ROLL_MARGIN,
    WRONG_WAY,
    PivotProbe,
    SteerMove,
    driver_of,
    pivot_plan,
)
from swpc_hw.calibration.fixed_point import fit_fixed_point
from swpc_hw.drives.robot_io import RobotIO
from swpc_hw.robot.model import wrap_angle

SETTLE = 0.3
"""s of robot time every probe waits after its motion (the robot comes to rest)."""
STEER_TOL = math.radians(1.0)
"""rad: a steering within this of its set-point is there."""


class CommissionRun(CalibrationRun):
    """One commissioning (module docstring); ``config_text``: the robot config file as
    written (None: the embedded default), which the correction edits."""

    write_step = "writing the commissioning report (nothing is written to the config)"

    def __init__(
        self,
        robot: RobotIO,
        metrology: Metrology,
        config: RobotConfig,
        *,
        config_text: str | None = None,
        **kwargs: Any,
    ) -> None:
        super().__init__(robot, metrology, config, install="never", **kwargs)
        self.status.kind = "commission"
        self.config_text = config_text
        self.steer_moves: list[SteerMove] = []
        self.pivot_probes: list[PivotProbe] = []
        self.commissioning: Commissioning | None = None
        self.largest_turn = 0.0
        self.largest_move = 0.0
        self.stops: list[dict[str, Any]] = []
        """Every roll stopped early: its modules, why, when after the roll began and after
        the pose that showed it (robot ms), how far the robot turned its way in all."""
        ids = config.nominal.ids
        self.plan = [State.PROBE] * (len(ids) * len(PIVOT_ANGLES))

    def run_problems(self) -> list[str]:
        return self.config.run_problems(self.metrology.name, "commission")

    def _start_fields(self) -> dict[str, Any]:
        fields = super()._start_fields()
        fields.pop("install", None)
        fields.pop("angles_deg", None)
        return {"kind": "commission", **fields}

    def planned(self, state: State) -> float | None:
        return 2.0 if state is State.PROBE else 0.0

    # ------------------------------------------------------------------ protocol
    def _protocol(self) -> None:
        problems = self.run_problems()
        if problems:
            raise RunFailedError("refused before any motion: " + "; ".join(problems))
        self.journal.open(t0=self._t0, install=self.install, created=self.status.created)
        self.record(force=True)
        self._connect()
        ids = self.config.nominal.ids
        self.status.modules_total = len(ids)
        for i, m in enumerate(ids):
            self.status.module, self.status.module_index = m, i + 1
            j = driver_of(ids, m)
            for a in PIVOT_ANGLES:
                probe = self._pivot_probe(m, a, j)
                if probe is None:  # a steering that moved the robot: nothing more moves
                    break
                self.pivot_probes.append(probe)
            else:
                self.robot.free_steer(m)
                self.robot.wheel_hold(m)
                continue
            break
        self.robot.stop_all()
        self.robot.release()
        self.enter(State.SOLVE, "analysing the probes")
        self.commissioning = analyse(self.config.nominal, self.steer_moves, self.pivot_probes)
        if self._abort.is_set():
            if self._stop_reason is not None:
                raise RunFailedError(self._stop_reason)
            raise RunFailedError("aborted during the analysis")
        self.enter(State.WRITE, self.write_step)
        self._write()
        with self._lock:
            self.status.progress = 1.0
            self.status.elapsed_s = round(self.clock.now() - self._t0, 2)
        self.journal.finish({"state": "DONE", "installed": None, "reason": ""}, self.result_doc)
        self.enter(State.DONE, "done")

    # ------------------------------------------------------------------ the probes
    def _poses(self, since: float) -> Any:
        """The poses ``t, x, y, yaw`` since ``since`` (run clock)."""
        assert isinstance(self.metrology, MocapMetrology)
        return self.metrology.poses(since)

    def _pose(self) -> tuple[float, float, float, float]:
        """The latest pose ``(t, x, y, yaw)`` (run clock)."""
        assert isinstance(self.metrology, MocapMetrology)
        p = self.metrology.mocap.latest()
        if p is None:
            raise RunFailedError("no pose: the probes need the poses")
        return p.t_host, p.x, p.y, p.yaw

    def _hold_all(self) -> None:
        """Every axis held where it is (a probe's stop)."""
        for mod in self.config.nominal.ids:
            self.robot.wheel_hold(mod)
            self.robot.steer_to(mod, self.robot.steering(mod))

    def _axis_moved(self, m: int, p0: tuple[float, ...], p1: tuple[float, ...]) -> float:
        """How far module ``m``'s steering axis (nominal) moved between two poses (m)."""
        A = self.config.nominal.arrays()
        x, y = A.P_s[self.config.nominal.ids.index(m)]

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
        step = math.remainder(target - self.robot.steering(m), 2 * math.pi)
        budget = MOVE_MARGIN
        self.robot.steer_to(m, target)
        deadline, there = self.deadline(), None
        moved = turned = 0.0
        stopped = False
        while True:
            self.check(True, deadline)
            p = self._pose()
            moved = max(moved, self._axis_moved(m, p0, p))
            turned = max(turned, abs(math.remainder(p[3] - p0[3], 2 * math.pi)))
            if moved > budget:
                self._hold_all()
                self.event(logging.WARNING, "commission.stop", module=m, moved_mm=moved * 1e3)
                self.wait(SETTLE)
                p = self._pose()
                moved = max(moved, self._axis_moved(m, p0, p))
                stopped = True
                break
            now = self.clock.now()
            if there is None and abs(wrap_angle(self.robot.steering(m) - target)) < STEER_TOL:
                there = now
            if there is not None and now - there >= SETTLE:
                break
            self.clock.sleep(self.poll)
        self.largest_move = max(self.largest_move, moved)
        self.largest_turn = max(self.largest_turn, turned)
        move = SteerMove(m, step, moved, turned, budget, stopped)
        self.steer_moves.append(move)
        return move

    def _pivot_probe(self, m: int, angle: float, j: int) -> PivotProbe | None:
        """A pivot probe about module ``m`` locked at ``angle`` rolled by ``j`` (module
        docstring); None when a steering moved the robot (it stopped).  A roll that turned
        the robot the wrong way is stopped and rolled the other way (the turn then asked
        is counter-clockwise again); a roll that did not turn it (its driver's heading
        across the circle, or its drive not a wheel's) is tried with the next driver."""
        ids = self.config.nominal.ids
        deg = math.degrees(angle)
        self.enter(State.PROBE, f"pivot probe: module {m} locked at {deg:.0f} deg, {j} rolls")
        # every steering move with the robot pinned by the others (braked and held), its
        # own wheel free (its tyre turns on the spot), then braked
        for mod in ids:
            self.robot.wheel_hold(mod)
            if mod != m:
                self.robot.steer_to(mod, self.robot.steering(mod))
        self.robot.wheel_free(m)
        if self._steer(m, angle).stopped:
            return None
        self.robot.wheel_hold(m)
        drivers = [j] + [d for d in ids if d not in (m, j)]
        first_stop: str | None = None
        for driver in drivers:
            plan = pivot_plan(self.config.nominal, m, angle, driver)
            for mod in ids:
                if mod != m:
                    self.robot.wheel_hold(mod)
                    self.robot.steer_to(mod, self.robot.steering(mod))
            self.robot.wheel_free(driver)
            if self._steer(driver, plan.driver_steering).stopped:
                return None
            self._free_others(m, driver)
            got = self._roll(m, driver, plan.roll_rate, abs(plan.roll_per_turn * PROBE_TURN))
            if got[2] == "wrong way":  # its wheel turns the other way: rolled the other way
                first_stop = first_stop or got[3]
                self._free_others(m, driver)
                got = self._roll(m, driver, -plan.roll_rate, abs(plan.roll_per_turn * PROBE_TURN))
            if got[2] != "no turn":
                return self._observed(m, driver, got[0], got[1], first_stop or got[3])
            first_stop = first_stop or got[3]
        return self._observed(m, drivers[-1], got[0], got[1], first_stop)

    def _free_others(self, m: int, driver: int) -> None:
        """The modules but the locked one and the driver free (their casters trail)."""
        for mod in self.config.nominal.ids:
            if mod not in (m, driver):
                self.robot.free_steer(mod)
                self.robot.wheel_free(mod)
        self.wait(SETTLE)

    def _roll(
        self, m: int, j: int, rate: float, expected: float
    ) -> tuple[float, float, str | None, str | None]:
        """Module ``j``'s wheel at ``rate`` until the robot has turned
        :data:`~.probes.PROBE_TURN` counter-clockwise (the plan's rate turns it so; the
        other way round, a wheel that turns the other way): ``(t0, psi0, stop, text)``, its
        start, the wheel's reading then, and why it stopped early (``wrong way``, ``no
        turn``; None)."""
        t0, _, _, yaw0 = self._pose()
        rows0 = self.robot.encoders(j, t0 - 0.2)
        psi0 = float(rows0[-1, 2]) if len(rows0) else 0.0
        self.robot.wheel_velocity(j, rate)
        deadline = self.deadline()
        last, stop, text = yaw0, None, None
        while True:
            self.check(True, deadline)
            t, _, _, yaw = self._pose()
            last += math.remainder(yaw - last, 2 * math.pi)
            turn = last - yaw0
            rows = self.robot.encoders(j, t0)
            roll = float(rows[-1, 2]) - psi0 if len(rows) else 0.0
            if turn <= -WRONG_WAY:
                stop = "wrong way"
                text = (
                    f"module {j}'s roll turned the robot {math.degrees(-turn):.1f} deg the "
                    f"other way (stopped {1000 * (self.clock.now() - t0):.0f} ms after the "
                    "roll began, then rolled the other way)"
                )
            elif turn >= PROBE_TURN:
                break
            elif abs(roll) >= ROLL_MARGIN * expected:
                stop = "no turn"
                text = (
                    f"module {j}'s wheel rolled {math.degrees(abs(roll)):.0f} deg and the "
                    f"robot turned {math.degrees(turn):.1f} deg of the "
                    f"{math.degrees(PROBE_TURN):.0f} deg asked"
                )
            if stop is not None:
                self._hold_all()
                self.stops.append({
                    "module": m, "driver": j, "why": stop,
                    "after_ms": round(1000 * (self.clock.now() - t0), 1),
                    "seen_ms": round(1000 * (self.clock.now() - t), 1),
                })  # fmt: skip
                self.event(logging.WARNING, "commission.stop", module=m, driver=j, why=text)
                break
            self.clock.sleep(self.poll)
        self.robot.wheel_hold(j)
        self.wait(SETTLE)
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
        enc_m, enc_j = self.robot.encoders(m, t0), self.robot.encoders(j, t0)
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
            steering=float(np.mean(enc_m[:, 1])) if len(enc_m) else self.robot.steering(m),
            driver=j,
            driver_steering=float(np.mean(enc_j[:, 1])) if len(enc_j) else math.nan,
            roll=roll,
            turn=turn,
            fixed_point=F,
            fixed_point_std=std,
            stopped=stopped,
        )

    # ------------------------------------------------------------------ the report
    def _write(self) -> None:
        c = self.commissioning
        assert c is not None
        new_doc, diff, not_in_config = corrected_config(self.config, self.config_text, c)
        try:
            RobotConfig.model_validate(new_doc)
            config_error = None
        except ValueError as exc:  # a fix the config refuses (say why; accept refuses it)
            config_error = str(exc)
        text = self.config_text or ""
        self.result_doc = {
            "commission": self.id,
            **c.document(),
            "steer_moves": [p.document() for p in self.steer_moves],
            "pivot_probes": [p.document() for p in self.pivot_probes],
            "config": new_doc,
            "diff": diff,
            "config_error": config_error,
            "in_force_sha256": hashlib.sha256(text.encode()).hexdigest(),
            "not_in_config": not_in_config,
            "robot_time_s": round(self.clock.now() - self._t0, 2),
            "largest_turn_deg": round(math.degrees(self.largest_turn), 2),
            "largest_move_mm": round(1000 * self.largest_move, 1),
            "stops": self.stops,
        }
        self.status.verdict = "right" if c.right else "miswired"
        self.event(
            logging.INFO if c.right else logging.WARNING,
            "commission.report",
            right=c.right,
            findings=len(c.findings),
            summary="; ".join(f.text for f in c.findings)[:2000],
        )
