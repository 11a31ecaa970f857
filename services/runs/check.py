"""A check: does the robot still match its kinematic file? (docs/check.md)

A :class:`CheckRun` is a calibration run (:class:`~services.runs.protocol.CalibrationRun`):
the same states, safety (watchdog, limits, step timeout, abort, faults), metrology and
recordings, with the robot config's check protocol (:meth:`RobotConfig.check_config
<services.config.robot.RobotConfig.check_config>`: every module locked once per check
angle, short sweeps).  Only its end differs:

* SOLVE: the recorded dataset is solved by the joint solver started from the file in
  force (a snapshot taken at the check's start, kept as ``file-in-force.yaml`` in the
  run's directory) and judged against it
  (:func:`swpc_hw.calibration.check.dataset_check.check_dataset`): per module and parameter
  the change, its std dev and z, per module a chi-square against a Sidak threshold, the
  verdict.  With the gyro (metrology ``imu``: no references, no drive) the IMU solver
  fitted to the file and the robot's shape judged
  (:mod:`swpc_hw.calibration.check.shape`).
  ``swpc check --offline <run>/dataset --file <run>/file-in-force.yaml`` reproduces it.
* WRITE: nothing is installed (the file in force stays as it is): the verdict is the
  result (``GET /checks/{id}``), kept in the run store for the history.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from services.config.robot import RobotConfig
from services.runs.metrology.base import Metrology
from services.runs.protocol import CalibrationRun
from services.runs.state import RunFailedError
from swpc_hw.calibration.check.dataset_check import check_dataset
from swpc_hw.calibration.check.verdict import CheckVerdict
from swpc_hw.calibration.report import DISPLAY
from swpc_hw.calibration.result import CalibrationResult
from swpc_hw.drives.robot_io import RobotIO
from swpc_hw.errors import CalibrationError, DatasetError
from swpc_hw.files.kinematic_file import KinematicFile
from swpc_hw.robot.model import PARAM_NAMES

FILE_IN_FORCE = "file-in-force.yaml"
"""In a check's run directory: the kinematic file in force when it started."""


def check_document(
    run_id: str,
    result: CalibrationResult,
    verdict: CheckVerdict,
    config: RobotConfig,
    *,
    file: dict[str, Any],
    run_dir: Path,
) -> dict[str, Any]:
    """``GET /checks/{id}``'s ``result``: the verdict (:meth:`CheckVerdict.document`), the
    file it judged, the check's estimate with its std devs (SI, the history's), the
    repeatability used and the solver's quality figures."""
    sd = result.stddev_array()
    return {
        "check": run_id,
        **verdict.document(),
        "metrology": result.mode,
        "frame": result.params.frame,
        "file": file,
        "estimate": [
            {
                "id": m.id,
                **{k: float(getattr(m, k)) for k in PARAM_NAMES},
                "stddev": {k: float(sd[i, c]) for c, k in enumerate(PARAM_NAMES)},
            }
            for i, m in enumerate(result.params.modules)
        ],
        "units": {k: u for k, (u, _) in DISPLAY.items()},
        "repeatability": config.check.repeatability.model_dump(),
        "quality": result.quality_document(),
        "dataset_dir": str(run_dir / "dataset"),
        "file_path": str(run_dir / FILE_IN_FORCE),
    }


class CheckRun(CalibrationRun):
    """A check of ``file`` (the kinematic file in force at its start, loaded), ``file_info``
    what the API says of it (name, sha256, the run it came from); module docstring."""

    write_step = "writing the check's verdict (no kinematic file is installed)"

    def __init__(
        self,
        robot: RobotIO,
        metrology: Metrology,
        config: RobotConfig,
        *,
        file: KinematicFile,
        file_info: dict[str, Any],
        **kwargs: Any,
    ) -> None:
        super().__init__(robot, metrology, config, install="never", **kwargs)
        self.status.kind = "check"
        self.file = file
        self.file_info = file_info
        self.verdict: CheckVerdict | None = None

    def run_problems(self) -> list[str]:
        return self.config.run_problems(self.metrology.name, "check")

    def _start_fields(self) -> dict[str, Any]:
        fields = super()._start_fields()
        fields.pop("install", None)
        return {"kind": "check", **fields, "file": self.file_info.get("name")}

    def _solve(self) -> None:
        from swpc_hw.files.dataset import load_dataset

        run_dir = self.journal.close_dataset(self.metrology.sensor, self.robot)
        c = self.config.check
        try:
            ds = load_dataset(run_dir / "dataset")
            self.result, self.verdict = check_dataset(
                ds, self.file.params, self.file.covariance,
                false_alarm=c.false_alarm, whole_robot=c.whole_robot,
                repeatability=c.repeatability.per_parameter(), source=str(run_dir / "dataset"),
            )  # fmt: skip
        except (CalibrationError, DatasetError) as exc:
            raise RunFailedError(f"check refused: {exc}") from exc

    def _write(self) -> None:
        assert self.result is not None and self.verdict is not None
        v = self.verdict
        self.result_doc = check_document(
            self.id, self.result, v, self.config, file=self.file_info, run_dir=self.run_dir
        )
        self.status.installed = None
        self.status.verdict = "consistent" if v.verdict == "consistent" else "drifted"
        self.event(
            logging.INFO if v.verdict == "consistent" else logging.WARNING,
            "check.verdict",
            verdict=v.verdict,
            action=v.action,
            drifted=",".join(map(str, v.drifted)),
            summary=v.summary,
        )
