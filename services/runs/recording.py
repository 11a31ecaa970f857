"""A run's recordings, streamed to disk as they are taken.

The poses and encoder samples of a run go to its dataset directory (the offline dataset
format of ``docs/dataset-format.md``: ``robot.yaml``, ``poses.csv``, ``encoders.csv``,
``segments.csv``; without motion capture ``imu.csv`` instead of ``poses.csv``, and
``references.yaml`` once the references are known) and to its MCAP file
(:mod:`services.runs.mcap`) while the run goes on, in batches
(:meth:`RunRecording.flush`, every half second of robot time), each handed to the OS in
one write: a service killed mid-run keeps everything up to its last flush, and
``swpc solve <run>/dataset`` reads it.  The rows are formatted exactly as
:func:`swpc_hw.files.dataset.save_dataset` formats them, so what the run solves (it loads the
directory) is what a later ``swpc solve`` solves.

Disk: every flush checks the run's bytes against what the disk budget leaves it and the
file system's free space against ``min_free`` (:class:`SpaceGuard`); a write that fails
(``ENOSPC``, ``EDQUOT``, any ``OSError``) is cut back to the last whole batch, so the files
stay loadable.  Either raises :class:`RecordingError`, which fails the run.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import numpy as np

from services.runs.mcap import McapRecorder, spin_circles
from swpc_hw.errors import SwpcError
from swpc_hw.files.dataset import (
    ENCODERS_COLUMNS,
    IMU_COLUMNS,
    POSES_COLUMNS,
    SEGMENTS_COLUMNS,
    Segment,
    load_dataset,
)
from swpc_hw.files.kinematic_file import save_kinematics
from swpc_hw.files.references import Reference, save_references
from swpc_hw.robot.frames import BaseLink
from swpc_hw.robot.model import FloatArray, RobotParams

POSE_FORMAT = "%.6f,%.9f,%.9f,%.9f\n"
GYRO_FORMAT = "%.6f,%.10f\n"
ENCODER_FORMAT = "%.6f,%d,%.10f,%.10f\n"
SEGMENT_FORMAT = "%d,%.6f,%.6f\n"
MIB = 1 << 20


class RecordingError(SwpcError):
    """The run's recordings cannot be written (disk full, disk budget, an I/O error)."""


@dataclass
class SpaceGuard:
    """What a run may write: ``allowed`` bytes (what the disk budget leaves), and no
    further once the file system of ``path`` has less than ``min_free`` bytes free."""

    path: Path
    allowed: int
    min_free: int

    def check(self, written: int) -> None:
        if written > self.allowed:
            raise RecordingError(
                f"disk budget: the run wrote {written / MIB:.1f} MiB, more than the "
                f"{self.allowed / MIB:.1f} MiB the data dir's budget (SWPC_DISK_BUDGET) leaves"
            )
        free = shutil.disk_usage(self.path).free
        if free < self.min_free:
            raise RecordingError(
                f"disk nearly full: {free / MIB:.1f} MiB free on the data dir's file system, "
                f"below SWPC_MIN_FREE ({self.min_free / MIB:.1f} MiB)"
            )


class _Appender:
    """One CSV file, appended a batch at a time in one unbuffered write; a failed write
    is cut back to the previous end of file."""

    def __init__(self, path: Path, header: tuple[str, ...]) -> None:
        self.path = path
        self.fh: IO[bytes] = path.open("wb", buffering=0)
        self.size = 0
        self.write((",".join(header) + "\n").encode())

    def write(self, data: bytes) -> int:
        if not data:
            return 0
        try:
            view = memoryview(data)
            while view:  # an unbuffered write may be partial
                n = self.fh.write(view)
                view = view[n or 0 :]
        except OSError as exc:
            try:
                self.fh.truncate(self.size)
                self.fh.seek(self.size)
            except OSError:
                pass
            raise RecordingError(_io_reason(self.path, exc)) from exc
        self.size += len(data)
        return len(data)

    def close(self, sync: bool) -> None:
        if self.fh.closed:
            return
        try:
            if sync:
                os.fsync(self.fh.fileno())
        finally:
            self.fh.close()


def _io_reason(path: Path, exc: OSError) -> str:
    if exc.errno in (errno.ENOSPC, errno.EDQUOT):
        return f"disk full: cannot write {path}: {exc.strerror}"
    return f"cannot write {path}: {exc.strerror or exc}"


class RunRecording:
    """The dataset directory and MCAP file of one run, written as the run records."""

    def __init__(
        self,
        run_dir: Path,
        robot: RobotParams,
        *,
        wall_offset: float,
        guard: SpaceGuard | None = None,
        mcap: bool = True,
        mcap_profile: str = "foxglove",
        metrology: str = "mocap",
    ) -> None:
        self.run_dir = Path(run_dir)
        self.metrology = metrology
        self.with_mcap = mcap
        self.mcap_profile = mcap_profile
        self.dataset_dir = self.run_dir / "dataset"
        self.robot = robot
        self.wall_offset = wall_offset
        self.guard = guard
        self.written = 0
        self.samples = 0
        """The motion sensor's samples: poses, or gyro samples without motion capture."""
        self.encoder_samples = 0
        self.segments: list[Segment] = []
        self.mcap: McapRecorder | None = None
        self._files: dict[str, _Appender] = {}
        self._dataset_open = False

    @property
    def dataset_open(self) -> bool:
        return self._dataset_open

    @property
    def mcap_path(self) -> Path:
        return self.run_dir / "run.mcap"

    def open(
        self,
        metadata: dict[str, dict[str, Any]],
        *,
        at: float = 0.0,
        base_link: BaseLink | None = None,
    ) -> None:
        """Create the dataset (``robot.yaml``, the CSV headers) and the MCAP file, with
        ``metadata`` records (name -> values) and the robot's description at clock time
        ``at`` (:meth:`McapRecorder.robot_description`, the robot config's ``base_link``)."""
        try:
            self.dataset_dir.mkdir(parents=True, exist_ok=True)
            save_kinematics(self.dataset_dir / "robot.yaml", self.robot)
            sensor = (
                _Appender(self.dataset_dir / "imu.csv", IMU_COLUMNS)
                if self.metrology == "imu"
                else _Appender(self.dataset_dir / "poses.csv", POSES_COLUMNS)
            )
            self._files = {
                "sensor": sensor,
                "encoders": _Appender(self.dataset_dir / "encoders.csv", ENCODERS_COLUMNS),
                "segments": _Appender(self.dataset_dir / "segments.csv", SEGMENTS_COLUMNS),
            }
            self._dataset_open = True
            if self.with_mcap:
                self.mcap = McapRecorder(
                    self.mcap_path, list(self.robot.ids), wall_offset=self.wall_offset,
                    profile=self.mcap_profile,
                )
                for name, values in metadata.items():
                    self.mcap.metadata(name, values)
                self.mcap.robot_description(self.robot, base_link, at)
                self.mcap.flush()
        except RecordingError:
            raise
        except (OSError, SwpcError) as exc:
            raise RecordingError(f"cannot start the run's recordings: {exc}") from exc

    # ---------------------------------------------------------------- data
    def add(self, sensor: FloatArray, encoders: dict[int, FloatArray]) -> None:
        """New pose rows ``t, x, y, yaw`` (gyro rows ``t, wz`` without motion capture) and
        per-module encoder rows ``t, theta_hat, psi``: written to the dataset (the OS has
        them on return) and the MCAP buffer."""
        imu = self.metrology == "imu"
        if sensor.shape[0]:
            fmt = GYRO_FORMAT if imu else POSE_FORMAT
            text = "".join(fmt % tuple(r) for r in sensor.tolist())
            self.written += self._files["sensor"].write(text.encode())
            self.samples += sensor.shape[0]
        parts = []
        for m, rows in encoders.items():
            if rows.shape[0]:
                lines = (ENCODER_FORMAT % (t, m, th, psi) for t, th, psi in rows.tolist())
                parts.append("".join(lines))
                self.encoder_samples += rows.shape[0]
        if parts:
            self.written += self._files["encoders"].write("".join(parts).encode())
        if self.mcap is not None:
            if imu:
                self._mcap(lambda rec: rec.gyro(sensor))
            else:
                self._mcap(lambda rec: rec.poses(sensor))
            for m, rows in encoders.items():
                self._mcap(lambda rec, m=m, rows=rows: rec.encoders(m, rows))

    def add_segment(self, seg: Segment) -> None:
        self.segments.append(seg)
        line = SEGMENT_FORMAT % (seg.static_module, seg.start, seg.end)
        self.written += self._files["segments"].write(line.encode())
        self._mcap(lambda rec: rec.segment(seg.static_module, seg.start, seg.end))

    def save_references(self, refs: list[Reference]) -> None:
        """``references.yaml`` in the dataset (atomic), counted against the disk."""
        path = self.dataset_dir / "references.yaml"
        try:
            save_references(path, refs)
            self.written += path.stat().st_size
        except OSError as exc:
            raise RecordingError(_io_reason(path, exc)) from exc

    def event(self, t: float, level: str, message: str) -> None:
        """A run event in the MCAP's ``/calibration/events`` (never fails the run: the
        structured log has it too)."""
        if self.mcap is not None:
            try:
                self.mcap.event(t, level, message)
            except (OSError, ValueError):
                self._drop_mcap()

    def _mcap(self, fn: Any) -> None:
        if self.mcap is None:
            return
        try:
            fn(self.mcap)
        except OSError as exc:
            self._drop_mcap()
            raise RecordingError(_io_reason(self.mcap_path, exc)) from exc

    def _drop_mcap(self) -> None:
        if self.mcap is not None:
            self.mcap.abandon()
            self.mcap = None

    def flush(self) -> None:
        """Hand the MCAP's open chunk to the OS and check the disk (:class:`SpaceGuard`:
        the dataset, the MCAP and the run's raw CAN recording ``dataset/can.log``)."""
        if self.mcap is not None:
            self._mcap(lambda rec: rec.flush())
        if self.guard is not None:
            total = 0
            for p in (self.mcap_path, self.dataset_dir / "can.log"):
                with contextlib.suppress(OSError):
                    total += p.stat().st_size
            self.guard.check(self.written + total)

    # ---------------------------------------------------------------- end
    def close_dataset(self) -> None:
        """Flush, fsync and close the dataset's files (before it is solved)."""
        self.flush()
        try:
            for f in self._files.values():
                f.close(sync=True)
        except OSError as exc:
            raise RecordingError(f"cannot close the run's dataset: {exc}") from exc
        self._dataset_open = False

    def finish(
        self,
        t: float,
        outcome: dict[str, Any],
        attachments: dict[str, tuple[bytes, str]] | None = None,
    ) -> None:
        """Close everything: the dataset files, and the MCAP with the ``outcome``
        metadata and ``attachments`` (name -> (bytes, media type)) and its summary.
        Best effort after a failure (the run's end is already decided)."""
        for f in self._files.values():
            with contextlib.suppress(OSError):
                f.close(sync=True)
        if self.mcap is None:
            return
        try:
            if self.metrology == "mocap":  # each spin's fitted circle, from what was written
                with contextlib.suppress(SwpcError, OSError, ValueError):
                    self.mcap.circles(t, spin_circles(load_dataset(self.dataset_dir)))
            self.mcap.metadata("outcome", outcome)
            for name, (data, media_type) in (attachments or {}).items():
                self.mcap.attach(name, data, media_type, t)
            self.mcap.finish()
        except OSError:
            self._drop_mcap()
        self.mcap = None


def json_bytes(doc: Any) -> bytes:
    """``doc`` as JSON (non-finite numbers as null) for an attachment."""

    def clean(v: Any) -> Any:
        if isinstance(v, float) and not np.isfinite(v):
            return None
        if isinstance(v, dict):
            return {k: clean(x) for k, x in v.items()}
        if isinstance(v, list | tuple):
            return [clean(x) for x in v]
        return v

    return json.dumps(clean(doc), indent=1).encode()
