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

from services.config.commission import corrected_config
from services.config.robot import RobotConfig
from services.runs.metrology.base import Metrology
from services.runs.probing import Prober
from services.runs.protocol import CalibrationRun
from services.runs.state import RunFailedError, State
from swpc_hw.calibration.commission.analysis import Commissioning, analyse, ratio_off
from swpc_hw.calibration.commission.probes import (
    PIVOT_ANGLES,
    REFINE_ANGLES,
    driver_of,
)
from swpc_hw.drives.robot_io import RobotIO


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
        kwargs.pop("install", None)  # it installs nothing
        super().__init__(robot, metrology, config, install="never", **kwargs)
        self.status.kind = "commission"
        self.config_text = config_text
        self.prober = Prober(self)
        self.commissioning: Commissioning | None = None
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
    def _lock_angles(self, m: int, j: int) -> bool:
        """Module ``m``'s pivot probes at :data:`~.probes.PIVOT_ANGLES`, then at
        :data:`~.probes.REFINE_ANGLES` when those put its steering's ratio off
        (:func:`~swpc_hw.calibration.commission.analysis.ratio_off`); False when a
        steering moved the pinned robot (the probes stop there)."""
        angles = list(PIVOT_ANGLES)
        k = 0
        while k < len(angles):
            probes = self.prober.pivot_probe(m, angles[k], j)
            if probes is None:
                return False
            self.prober.pivot_probes.extend(probes)
            k += 1
            seen = self.prober.pivot_probes
            if k == len(PIVOT_ANGLES) and ratio_off(self.config.nominal, m, seen):
                angles += REFINE_ANGLES  # its ratio off: measured over a whole turn of commands
        return True

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
            if not self._lock_angles(m, j):  # a steering that moved the robot: nothing more
                break
            self.robot.free_steer(m)
            self.robot.wheel_hold(m)
        self.robot.stop_all()
        self.robot.release()
        self.enter(State.SOLVE, "analysing the probes")
        pr = self.prober
        self.commissioning = analyse(self.config.nominal, pr.steer_moves, pr.pivot_probes)
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

    # ------------------------------------------------------------------ the report
    def _write(self) -> None:
        c, pr = self.commissioning, self.prober
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
            "steer_moves": [p.document() for p in pr.steer_moves],
            "pivot_probes": [p.document() for p in pr.pivot_probes],
            "config": new_doc,
            "diff": diff,
            "config_error": config_error,
            "in_force_sha256": hashlib.sha256(text.encode()).hexdigest(),
            "not_in_config": not_in_config,
            "robot_time_s": round(self.clock.now() - self._t0, 2),
            "largest_turn_deg": round(math.degrees(pr.largest_turn), 2),
            "largest_move_mm": round(1000 * pr.largest_move, 1),
            "stops": pr.stops,
        }
        self.status.verdict = "right" if c.right else "miswired"
        self.event(
            logging.INFO if c.right else logging.WARNING,
            "commission.report",
            right=c.right,
            findings=len(c.findings),
            summary="; ".join(f.text for f in c.findings)[:2000],
        )
