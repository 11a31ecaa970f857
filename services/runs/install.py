"""What happens to a run's data after the motion: solve it, judge it, install it, report it.

Kept apart from the state machine (:mod:`services.runs.protocol`), which calls these in
its SOLVE and WRITE states.  Everything here is a plain function of the run's data and
files: ``swpc solve <run>/dataset`` reproduces :func:`solve_run` exactly, because both
solve what was written (the run streams its dataset to disk as it records it,
:mod:`services.runs.recording`).
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import filecmp
import re
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from services.config.robot import RobotConfig, Tolerances
from swpc_hw.calibration.mocap.solver import CalibrationResult, SolverOptions, solve
from swpc_hw.calibration.report import result_rows
from swpc_hw.errors import CalibrationError, KinematicFileError
from swpc_hw.files.dataset import load_dataset
from swpc_hw.files.kinematic_file import load_kinematics, save_kinematics
from swpc_hw.robot.model import PARAM_NAMES


def solve_run(run_dir: Path) -> CalibrationResult:
    """Solve the dataset the run wrote under ``run_dir`` with the solver its files call
    for, as ``swpc solve`` does (no ``poses.csv`` but ``imu.csv``: the IMU solver).
    A solver failure names the kept dataset and the command that reproduces it."""
    from swpc_hw.calibration.gyro.solver import solve_imu

    directory = run_dir / "dataset"
    try:
        ds = load_dataset(directory)
        if ds.is_imu:
            return solve_imu(ds, SolverOptions(time_offset=0.0), source=str(directory))
        return solve(ds, SolverOptions(time_offset=0.0), source=str(directory))
    except CalibrationError as exc:
        raise CalibrationError(
            f"{exc} (the run's data is kept: `swpc solve {directory}` reproduces this)"
        ) from exc


def within_tolerance(result: CalibrationResult, tol: Tolerances) -> bool:
    """Every std dev known and within its tolerance (x_s, y_s, b: position; beta; r)."""
    sd = result.stddev_array()
    if not np.all(np.isfinite(sd)):
        return False  # an unknown uncertainty is never within tolerance
    return bool(
        np.all(sd[:, [0, 1, 3]] <= tol.position)
        and np.all(sd[:, 2] <= tol.beta)
        and np.all(sd[:, 4] <= tol.radius)
    )


BACKUP_STAMP = "%Y%m%dT%H%M%S%fZ"
"""UTC time in a backup's name: ``<stem>.<stamp><suffix>`` beside the file in force."""


def _backup_pattern(path: Path) -> re.Pattern[str]:
    return re.compile(rf"^{re.escape(path.stem)}\.(\d{{8}}T\d{{12}}Z){re.escape(path.suffix)}$")


def backups(path: Path) -> list[Path]:
    """The backups kept beside the kinematic file ``path``, newest first."""
    pat = _backup_pattern(path)
    if not path.parent.is_dir():
        return []
    found = [p for p in path.parent.iterdir() if pat.match(p.name) and p.is_file()]
    return sorted(found, key=lambda p: p.name, reverse=True)


def backup_kinematics(path: Path, keep: int) -> Path | None:
    """Keep a copy of the kinematic file in force at ``path`` beside it, as
    ``<stem>.<UTC time><suffix>``; its path (None when there is no file in force).  A file
    identical to the newest backup is not copied again (that backup is returned); beyond
    ``keep`` backups the oldest are removed.  :class:`KinematicFileError` if it cannot (the
    file in force untouched)."""
    if not path.exists():
        return None
    kept = backups(path)
    try:
        if kept and filecmp.cmp(path, kept[0], shallow=False):
            return kept[0]
    except OSError:
        pass  # unreadable: copy it (the error, if any, is the copy's)
    stamp = _dt.datetime.now(_dt.UTC).strftime(BACKUP_STAMP)
    backup = path.with_name(f"{path.stem}.{stamp}{path.suffix}")
    try:
        shutil.copy2(path, backup)
    except OSError as exc:  # a full disk: no half backup left behind, nothing replaced
        with contextlib.suppress(OSError):
            backup.unlink()
        raise KinematicFileError(
            f"{backup}: cannot keep the kinematic file in force as a backup: "
            f"{exc.strerror or exc} (the file in force is untouched)"
        ) from exc
    for old in backups(path)[keep:]:
        with contextlib.suppress(OSError):
            old.unlink()
    return backup


def file_run(path: Path) -> str | None:
    """The run the kinematic file at ``path`` came from (its ``provenance.run``); None when
    it names none or does not load."""
    try:
        prov = load_kinematics(path).extra.get("provenance")
    except (KinematicFileError, OSError):
        return None
    return str(prov["run"]) if isinstance(prov, dict) and prov.get("run") else None


def read_replaced(path: Path | None) -> str | None:
    """The text of the file an install replaced, from ``path`` (its backup, or the file
    in force before the install); None when there was none or it cannot be read."""
    if path is None:
        return None
    try:
        return path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError):
        return None


def install_kinematics(
    path: Path, result: CalibrationResult, extra: dict[str, Any], keep: int
) -> Path | None:
    """Install the result (with its parameters' covariance) as the kinematic file in force
    at ``path`` (atomic replace); the file it replaces is kept beside it
    (:func:`backup_kinematics`), whose path is returned (None when there was none)."""
    backup = backup_kinematics(path, keep)
    path.parent.mkdir(parents=True, exist_ok=True)
    save_kinematics(path, result.params, extra=extra, covariance=result.covariance)
    return backup


def result_document(
    run_id: str,
    result: CalibrationResult,
    config: RobotConfig,
    *,
    run_dir: Path,
    kinematics_path: Path,
    within: bool,
    installed: bool,
) -> dict[str, Any]:
    """``GET /calibrations/{id}/result``: per module nominal, estimate and std dev, the
    quality figures, a human table, and where the files are."""
    modules = []
    for m in result.params.modules:
        nom = config.nominal.module(m.id)
        std = m.stddev
        modules.append(
            {
                "id": m.id,
                **{k: getattr(m, k) for k in PARAM_NAMES},
                "stddev": None if std is None else std.model_dump(),
                "nominal": {k: getattr(nom, k) for k in PARAM_NAMES},
            }
        )
    header = ["module", "param", "unit", "nominal", "estimate", "std dev"]
    return {
        "run": run_id,
        "modules": modules,
        "quality": result.quality_document(),
        "table": [dict(zip(header, row, strict=True)) for row in result_rows(result)],
        "within_tolerance": within,
        "tolerances": config.tolerances.model_dump(),
        "installed": installed,
        "kinematics_path": str(kinematics_path) if installed else None,
        "run_kinematics_path": str(run_dir / "kinematics.yaml"),
        "dataset_dir": str(run_dir / "dataset"),
    }


@dataclass(frozen=True)
class Written:
    """What :func:`write_result` did: within tolerance, installed, the backup of the file
    it replaced, the result document, and why a result within tolerance was not installed
    by ``if-within-tolerance`` (``held``)."""

    within: bool
    installed: bool
    backup: Path | None
    document: dict[str, Any]
    held: str | None = None


def frame_in_force(path: Path) -> str | None:
    """The frame of the kinematic file at ``path``; None when there is none or it does not
    load (a broken file holds nothing back)."""
    try:
        return load_kinematics(path).params.frame if path.is_file() else None
    except (KinematicFileError, OSError):
        return None


def held_back(result: CalibrationResult, in_force: str | None) -> str | None:
    """Why ``if-within-tolerance`` does not install ``result`` over a file in force in
    another frame (None: nothing holds it back).  Parameters of two frames (R of the motion
    capture, design-fit of a calibration without it) differ by the frames' rotation and
    offset, not by the robot: what odometry then reads would move by that much without the
    operator having chosen it."""
    frame = result.params.frame
    if in_force is None or in_force == frame:
        return None
    return (
        f"the file in force is in frame {in_force}, this result in frame {frame}: a file of "
        "another frame is installed only when asked (install: always, or Install on the "
        "result page)"
    )


def write_result(
    run_id: str,
    result: CalibrationResult,
    config: RobotConfig,
    *,
    run_dir: Path,
    kinematics_path: Path,
    install: str,
    provenance: dict[str, Any],
    keep_backups: int,
) -> Written:
    """The run's WRITE: its kinematic file (with ``provenance`` and the quality figures)
    in ``run_dir``, installed at ``kinematics_path`` when ``install`` is ``always``, or
    ``if-within-tolerance``, every std dev is within the config's tolerances and the file
    in force, if any, is in the result's frame (:func:`held_back`)."""
    ok = within_tolerance(result, config.tolerances)
    held = None
    if install == "if-within-tolerance" and ok:
        held = held_back(result, frame_in_force(kinematics_path))
    installed = install == "always" or (install == "if-within-tolerance" and ok and held is None)
    extra = {"provenance": provenance, "quality": result.quality_document()}
    save_kinematics(
        run_dir / "kinematics.yaml", result.params, extra=extra, covariance=result.covariance
    )
    backup = (
        install_kinematics(kinematics_path, result, extra, keep_backups) if installed else None
    )
    document = result_document(
        run_id,
        result,
        config,
        run_dir=run_dir,
        kinematics_path=kinematics_path,
        within=ok,
        installed=installed,
    )
    document["install_held"] = held
    return Written(ok, installed, backup, document, held)
