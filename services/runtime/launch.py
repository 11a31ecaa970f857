"""Starting a run: the checks before it (one at a time, the disk budget, the kinematic file
in force a check judges), its metrology on the service's sensors, its directory and CAN
recording, its first state saved.  Part of :class:`services.runtime.runtime.Runtime`.
"""

from __future__ import annotations

import hashlib
import logging
import os
import shutil
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from services.config.robot import RobotConfig, RunKind
from services.config.settings import ServiceSettings
from services.runs.check import FILE_IN_FORCE, CheckRun
from services.runs.commission import CommissionRun
from services.runs.metrology.base import Metrology
from services.runs.metrology.imu import ImuMetrology
from services.runs.metrology.mocap import MocapMetrology
from services.runs.protocol import CalibrationRun
from services.runs.recording import SpaceGuard
from services.runtime.errors import (
    DiskSpaceError,
    NoFileError,
    RunConflictError,
    StoreError,
    room_error,
)
from services.runtime.records import RunRecords
from services.sensors.gyro import GyroIngest
from services.sensors.mocap import MocapIngest
from services.store.disk import make_room, run_reserve
from services.store.logs import event
from swpc_hw.calibration.plan.forecast import Stopping
from swpc_hw.clock import Clock
from swpc_hw.drives.robot_io import DrivesRobotIO
from swpc_hw.errors import KinematicFileError
from swpc_hw.files.kinematic_file import (
    KinematicFile,
    atomic_write_text,
    load_yaml,
    module_mismatch,
    parse_kinematics,
    read_kinematics_text,
)
from swpc_hw.files.references import Reference

log = logging.getLogger("swpc.service")
MIB = 1 << 20


class RunLauncher(RunRecords):
    """The run starts of :class:`~services.runtime.runtime.Runtime`, which sets these
    attributes."""

    settings: ServiceSettings
    config: RobotConfig
    clock: Clock
    data_dir: Path
    mocap: MocapIngest
    gyro: GyroIngest
    session: Any
    _contact: threading.Thread | None
    _contact_stop: threading.Event

    def file_in_force(self) -> tuple[KinematicFile, dict[str, Any], str]:
        """The kinematic file in force: loaded, what the API says of it (``name``,
        ``sha256``, ``run``, ``created``, ``frame``) and its text.  :class:`NoFileError`
        when there is none or it does not load."""
        path = self.settings.kinematics_file
        if not os.path.lexists(path):
            raise NoFileError(
                f"no kinematic file in force at {path}: nothing to check (calibrate first)"
            )
        try:
            text = read_kinematics_text(path)
            kf = parse_kinematics(load_yaml(text, str(path)), str(path))
        except KinematicFileError as exc:
            raise NoFileError(f"the kinematic file in force does not load: {exc}") from exc
        mismatch = module_mismatch(kf.params.ids, self.config.nominal.ids)
        if mismatch is not None:
            raise NoFileError(
                f"the kinematic file in force does not match the robot: {mismatch} "
                "(calibrate the robot, or install the file made for it)"
            )
        prov = kf.extra.get("provenance")
        info = {
            "name": path.name,
            "sha256": hashlib.sha256(text.encode()).hexdigest()[:16],
            "run": str(prov["run"]) if isinstance(prov, dict) and prov.get("run") else None,
            "created": kf.created or None,
            "frame": kf.params.frame,
        }
        return kf, info, text

    def start_run(
        self,
        config: RobotConfig,
        install: str,
        metrology: str = "mocap",
        references: Sequence[Reference] = (),
        kind: RunKind = "calibration",
        stopping: Stopping | None = None,
    ) -> CalibrationRun:
        """Start a run of ``kind`` and ``config`` (already checked:
        :meth:`RobotConfig.for_run`) with ``metrology`` (``imu``: without motion capture,
        with ``references``, checked: :func:`services.runs.metrology.imu.reference_problems`);
        ``stopping``: a planned run's sequential stopping (motion capture only).  A
        check (docs/check.md) judges the kinematic file in force as it is now (a copy in
        its directory) and installs nothing.

        Raises :class:`RunConflictError` while one runs, :class:`NoFileError` for a check
        without a file in force that loads, :class:`DiskSpaceError` when the disk budget
        (after pruning the oldest runs' recordings) or the file system's free space leaves
        no room for it, :class:`StoreError` when its first state cannot be saved (nothing
        has moved; the service takes the next start once the store does).
        """
        assert self.drives is not None
        s = self.settings
        if self._contact is not None:  # the drives' first contact: its attempt ends first
            self._contact_stop.set()
            self._contact.join()
        with self.lock:
            if self.current is not None and not self.current.finished:
                what = self.current.status.kind
                raise RunConflictError(f"{what} {self.current.id} is still running")
            checked = self.file_in_force() if kind == "check" else None
            if (
                checked is not None
                and metrology == "mocap"
                and checked[0].params.frame != config.nominal.frame
            ):
                raise NoFileError(
                    f"the kinematic file in force is in frame {checked[0].params.frame!r}: a "
                    f"check measures in {config.nominal.frame!r} with motion capture, where "
                    "it cannot be compared (calibrate with motion capture first, or check "
                    "with metrology imu)"
                )
            budget, reserve = int(s.disk_budget), run_reserve(int(s.disk_budget))
            room = make_room(self.data_dir, budget, reserve=reserve)
            for p in room.pruned:
                event(log, logging.INFO, "disk.pruned", path=str(p))
            if room.used > budget - reserve:
                raise DiskSpaceError(
                    f"disk budget: the data dir holds {room.used / MIB:.1f} MiB of "
                    f"SWPC_DISK_BUDGET {budget / MIB:.1f} MiB, and a run needs "
                    f"{reserve / MIB:.1f} MiB (nothing left to prune)"
                )
            if room.free < int(s.min_free) + reserve:
                raise DiskSpaceError(
                    f"disk nearly full: {room.free / MIB:.1f} MiB free on the data dir's file "
                    f"system; a run needs {reserve / MIB:.1f} MiB above SWPC_MIN_FREE "
                    f"{int(s.min_free) / MIB:.1f} MiB"
                )
            if metrology == "imu" and not self.gyro.subscribed:
                self._listen_to_the_gyro()
            lim = config.limits
            io = DrivesRobotIO(
                self.drives,
                limits=(lim.max_wheel_torque, (lim.max_steer_velocity, lim.max_wheel_velocity)),
                polarity=config.axis_signs(),
            )
            common: dict[str, Any] = dict(
                clock=self.clock,
                data_dir=self.data_dir,
                kinematics_path=s.kinematics_file,
                keep_backups=s.kinematics_backups,
                on_change=self._persist,
                space=SpaceGuard(self.data_dir, room.allowed, int(s.min_free)),
                robot_config_path=None if s.robot_config is None else str(s.robot_config),
                mcap_profile=s.mcap_profile,
                log_after=None if self.current is None else self.current.journal.log_end(),
            )
            measure = self.metrology(metrology, config, references, stopping)
            run: CalibrationRun
            if kind == "commission":
                run = CommissionRun(io, measure, config, config_text=self.config_text(), **common)
            elif checked is None:
                run = CalibrationRun(io, measure, config, install=install, **common)
            else:
                kf, info, _ = checked
                run = CheckRun(io, measure, config, file=kf, file_info=info, **common)
            if isinstance(measure, MocapMetrology):
                run.status.forecast = measure.forecast()
            # its directory, and its raw CAN traffic beside its dataset (candump format, our
            # DBC decodes it), before it exists for anyone: nothing is left half-made
            try:
                (run.run_dir / "dataset").mkdir(parents=True, exist_ok=True)
                if checked is not None:  # what it judges, for `swpc check --offline`
                    atomic_write_text(run.run_dir / FILE_IN_FORCE, checked[2])
                self.drives.start_recording(str(run.run_dir / "dataset" / "can.log"))
            except OSError as exc:
                self._forget_files(run)
                raise room_error(run.run_dir, exc) from exc
            previous, self.current = self.current, run
            self.runs[run.id] = run
        try:
            self._persist(run)
        except Exception as exc:  # a run that was never saved would block every next one
            with self.lock:
                self.runs.pop(run.id, None)
                self.current = previous
            self._forget_files(run)
            raise StoreError(f"run store not writable: {self.store_error}: no run started") from exc
        run.start()
        return run

    def config_text(self) -> str | None:
        """The robot config file as written (None: the service runs on the embedded
        default)."""
        path = self.settings.robot_config
        return None if path is None else Path(path).read_text(encoding="utf-8")

    def _forget_files(self, run: CalibrationRun) -> None:
        """A run that does not start leaves no recording and no directory."""
        assert self.drives is not None
        self.drives.stop_recording()
        shutil.rmtree(run.run_dir, ignore_errors=True)

    def metrology(
        self,
        name: str,
        config: RobotConfig,
        references: Sequence[Reference] = (),
        stopping: Stopping | None = None,
    ) -> Metrology:
        """A new run's metrology on this service's sensors: ``mocap`` (motion capture,
        with a planned run's ``stopping``) or ``imu`` (the gyro, the encoders and
        ``references``)."""
        if name == "imu":
            if stopping is not None:
                raise ValueError("sequential stopping needs motion capture")
            return ImuMetrology(self.gyro, config, references)
        return MocapMetrology(self.mocap, config.pose_key, stopping)

    def _listen_to_the_gyro(self) -> None:
        """Subscribe to the gyro (from now on: its first run without motion capture on a
        service set up for motion capture).  Until then nothing decodes 200 samples a
        second that no one reads, and the in-process simulator does not even send them."""
        assert self.session is not None
        self.gyro.subscribe(self.session, self.config.imu_key)
        event(log, logging.INFO, "imu.subscribed", key=self.config.imu_key)
