"""One calibration run on the fake robot (tests/fake_robot.py) and a virtual clock: the
rig of the state machine's tests and of every test that needs a run without a service.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from services.config.robot import RobotConfig
from services.runs.commission import CommissionRun
from services.runs.metrology.imu import ImuMetrology
from services.runs.metrology.mocap import MocapMetrology
from services.runs.protocol import CalibrationRun
from services.runs.state import State
from services.sensors.gyro import GyroIngest
from services.sensors.mocap import MocapIngest
from simulators.sensors.gyro import axis_travel
from swpc_hw.clock import VirtualClock
from swpc_hw.files.references import AxisDistance, Reference
from swpc_hw.robot.model import RobotParams
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED, PAPER_NOMINAL
from tests.fake_robot import FakeRobot

# three modules (N >= 2 is allowed) and three angles: every edge of TRANSITIONS, quickly
TRUTH = RobotParams(robot="swpc", modules=PAPER_CALIBRATED.modules[:3])

NOMINAL = RobotParams(robot="swpc", modules=PAPER_NOMINAL.modules[:3])

PROTOCOL = {
    "angles_deg": [30, 150, 270],
    "sweep_deg": 90,
    "settle_time": 0.5,
    "stop_time": 0.3,
    "align_time": 0.3,
    "resteer_time": 0.5,
}

IMU_PROTOCOL = {"rest_time": 1.0, "drive_length": 1.0, "operator_timeout": 30.0}
"""Without motion capture: 1 s rests, a 1 m drive (2.5 s on the fake robot)."""


def axis_distances(truth: RobotParams, stddev: float = 0.5e-3) -> list[Reference]:
    """Every distance between two steering axes of ``truth``, exact, with ``stddev``."""
    a = truth.arrays()
    return [
        AxisDistance((i, j), float(np.linalg.norm(a.P_s[truth.index(i)] - a.P_s[truth.index(j)])),
                     stddev)
        for i, j in itertools.combinations(truth.ids, 2)
    ]  # fmt: skip


class Rig:
    """One run on a fresh fake robot; ``hooks[state]`` run as the run enters ``state``.

    ``metrology="imu"``: the run without motion capture (the fake robot's gyro, the
    exact axis distances) whose operator (``operator``) marks the floor at MARK and
    measures the drive exactly at MEASURE."""

    def __init__(
        self,
        tmp: Path,
        overrides: dict[str, Any] | None = None,
        metrology: str = "mocap",
        **robot: Any,
    ) -> None:
        self.clock = VirtualClock(start=1000.0)
        self.mocap = MocapIngest(clock=self.clock, clock_mode="wall", stale_after=0.5)
        self.imu = GyroIngest(clock=self.clock, stale_after=0.5)
        self.robot = FakeRobot(
            TRUTH,
            self.clock,
            self.mocap,
            dt=0.01,
            pose_every=1,
            imu=self.imu if metrology == "imu" else None,
            **robot,
        )
        # the fast part (PROBE) is the path test's and the commissioning's; the other
        # tests aim at one step of the protocol, which it would reach first
        doc = {"nominal": NOMINAL.model_dump(),
               "protocol": {**PROTOCOL, **IMU_PROTOCOL, "precheck": False}}  # fmt: skip
        self.config = RobotConfig.model_validate(doc).with_overrides(overrides or {})
        self.metrology = metrology
        self.references = axis_distances(TRUTH)
        self.operator = True
        self.kinematics = tmp / "kinematics.yaml"
        self.states: list[State] = [State.PENDING]
        self.entered_at: dict[State, float] = {}
        self.entries: list[tuple[State, float]] = []
        self.hooks: dict[State, Callable[[CalibrationRun], None]] = {}
        self.install = "if-within-tolerance"
        self.tmp = tmp
        # the state machine's tests need the run's dataset, not its MCAP (tested with the
        # service and in tests/services/runs/test_run_outputs.py): half the CPU of a run on the
        # fake robot
        self.run_kwargs: dict[str, Any] = {"mcap": False}

    def _changed(self, run: CalibrationRun) -> None:
        st = run.status.state
        if st != self.states[-1]:
            self.states.append(st)
            self.entries.append((st, self.clock.now()))
            self.entered_at.setdefault(st, self.clock.now())
            hook = self.hooks.pop(st, None)
            if hook is not None:
                hook(run)
            if self.operator:
                self.play_operator(run)

    def play_operator(self, run: CalibrationRun) -> None:
        """Mark the floor (MARK) and measure the drive exactly (MEASURE), at once."""
        if run.waits_for == "continue":
            run.answer("continue")
        elif run.waits_for == "references":
            drive = run.metrology.drive
            assert drive is not None
            start, end = (self.robot.pose_at(t) for t in drive)
            travel = axis_travel(start, end, TRUTH.arrays().P_s[0])
            drive_ref = {"kind": "straight_drive", "value": travel, "stddev": 0.5e-3}
            run.answer("references", [drive_ref])

    def make_run(self, kind: str = "calibration") -> CalibrationRun:
        kwargs: dict[str, Any] = {
            "clock": self.clock,
            "data_dir": self.tmp,
            "kinematics_path": self.kinematics,
            "install": self.install,
            "on_change": self._changed,
            **self.run_kwargs,
        }
        metrology = (
            ImuMetrology(self.imu, self.config, self.references)
            if self.metrology == "imu"
            else MocapMetrology(self.mocap, self.config.pose_key)
        )
        if kind == "commission":
            return CommissionRun(self.robot, metrology, self.config, **kwargs)
        return CalibrationRun(self.robot, metrology, self.config, **kwargs)

    def run(self, kind: str = "calibration") -> CalibrationRun:
        run = self.make_run(kind)
        run._main()  # the run's thread body, here on the test's thread
        assert run.finished and self.robot.closed
        return run


def stopped_after(rig: Rig, t: float) -> bool:
    """stop_all() came at or after ``t`` and no motion command followed it."""
    return rig.robot.stopped_for_good_after(t)
