"""What a calibration run leaves behind as it goes: log lines, recordings, provenance.

:class:`RunJournal` is a run's one writer:

* every run event (state, segment, fault, result) is a structured log line on the
  ``swpc.run`` logger (:mod:`services.store.logs`: ``event=<name> run=<id> ...``) and, once the
  recordings are open, a ``foxglove.Log`` message in the run's MCAP;
* the poses (or, without motion capture, the gyro's samples) and encoder samples are
  streamed to the run's dataset directory and MCAP file (:mod:`services.runs.recording`)
  every :data:`RECORD_PERIOD` of robot time, read from the sensor's ingest and the robot
  by cursor (each sample once); a service killed mid-run keeps everything up to the last
  batch;
* the provenance of what the run writes (tool version and commit, the robot config's and
  the dataset's hashes, units: :mod:`services.store.provenance`).

The run's protocol (:mod:`services.runs.protocol`) calls it; it never moves anything.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from services.config.robot import RobotConfig
from services.runs.recording import RunRecording, SpaceGuard, json_bytes
from services.store.logs import event
from services.store.provenance import UNITS, config_sha256, provenance
from swpc_hw.clock import Clock
from swpc_hw.files.dataset import Segment
from swpc_hw.files.references import Reference
from swpc_hw.robot.model import FloatArray

log = logging.getLogger("swpc.run")

RECORD_PERIOD = 0.5
"""s of robot time between two writes of the run's recordings (what a kill may lose)."""


class SampleSource(Protocol):
    """The motion sensor's ingest (:class:`~services.sensors.mocap.MocapIngest` rows
    ``t_source, t_recv, t_host, x, y, yaw``, :class:`~services.sensors.gyro.GyroIngest` rows
    ``t_source, t_recv, t_host, wz``)."""

    def samples_since(self, cursor: int, since: float) -> tuple[FloatArray, int]: ...



def log_wall_offset(host_wall: float, clock_now: float, after: float | None = None) -> float:
    """A run's MCAP ``wall_offset`` (epoch s minus clock s) at its start, log time =
    clock time + offset.

    The run's log times start at the host's time ``host_wall`` (the API's ``started``),
    so a viewer lines the file up with the API on a robot and in a simulator alike (a
    simulated clock's own epoch drifts from the host's time: it stands still while
    nothing runs, and races ahead of it flat out).  ``after``: where the previous run's
    log times ended; a simulator faster than the robot can leave them past
    ``host_wall``, and then this run starts there instead, so that two runs never
    overlap::

        offset = max(host_wall, after) - clock_now
    """
    return max(host_wall, -math.inf if after is None else after) - clock_now


class EncoderSource(Protocol):
    def encoder_rows(self, module: int, cursor: int, since: float) -> tuple[FloatArray, int]: ...


class RunJournal:
    """The log lines, recordings and provenance of run ``run_id`` (module docstring)."""

    def __init__(
        self,
        run_id: str,
        run_dir: Path,
        config: RobotConfig,
        clock: Clock,
        *,
        space: SpaceGuard | None = None,
        mcap: bool = True,
        mcap_profile: str = "foxglove",
        robot_config_path: str | None = None,
        metrology: str = "mocap",
        log_after: float | None = None,
        host_wall: Callable[[], float] = time.time,
    ) -> None:
        """``log_after``, ``host_wall``: :func:`log_wall_offset`'s ``after`` and where its
        ``host_wall`` is read."""
        self.run_id = run_id
        self.log_after = log_after
        self.host_wall = host_wall
        self.wall_offset: float | None = None
        """:func:`log_wall_offset` from :meth:`open` on."""
        self.metrology = metrology
        self.mcap_profile = mcap_profile
        self.run_dir = run_dir
        self.config = config
        self.clock = clock
        self.space = space
        self.mcap = mcap
        self.robot_config_path = robot_config_path
        self.config_sha256 = config_sha256(config.to_document())
        self.recording: RunRecording | None = None
        self._since = -math.inf
        self._next_record = -math.inf
        self._pose_cursor = 0
        self._enc_cursors = dict.fromkeys(config.nominal.ids, 0)

    def log_end(self) -> float | None:
        """Epoch s no earlier than any log time this run has written (the clock's now on
        the run's log axis: a later run starts after it), None before :meth:`open`."""
        return None if self.wall_offset is None else self.clock.now() + self.wall_offset

    @property
    def recording_open(self) -> bool:
        """The dataset takes rows (from :meth:`open` until :meth:`close_dataset`)."""
        return self.recording is not None and self.recording.dataset_open

    # ---------------------------------------------------------------- events
    def event(self, level: int, name: str, **fields: Any) -> str:
        """``event=<name> run=<id> <fields>`` on ``swpc.run`` at ``level``, and in the MCAP
        once the recordings are open; returns the line."""
        line = event(log, level, name, run=self.run_id, **fields)
        if self.recording is not None:
            self.recording.event(self.clock.now(), logging.getLevelName(level).lower(), line)
        return line

    # ---------------------------------------------------------------- recordings
    def open(self, *, t0: float, install: str, created: str) -> None:
        """Create the run's dataset and MCAP (with the robot config, the provenance and
        the run's request as metadata); samples from ``t0 - 1 s`` on are recorded.
        Raises :class:`~services.runs.recording.RecordingError`."""
        self._since = t0 - 1.0
        self.wall_offset = log_wall_offset(self.host_wall(), self.clock.now(), self.log_after)
        rec = RunRecording(
            self.run_dir,
            self.config.nominal,
            wall_offset=self.wall_offset,
            guard=self.space,
            mcap=self.mcap,
            mcap_profile=self.mcap_profile,
            metrology=self.metrology,
        )
        rec.open(
            {
                "robot-config": self.config.to_document(),
                "provenance": self.provenance(),
                "run": {"id": self.run_id, "install": install, "created": created},
            },
            at=t0,
            base_link=self.config.base_link,
        )
        self.recording = rec

    def record(
        self, sensor: SampleSource, encoders: EncoderSource, force: bool = False
    ) -> tuple[int, int] | None:
        """Every :data:`RECORD_PERIOD` of robot time (or now, ``force``): the motion
        sensor's samples (the poses, or the gyro's without motion capture) and the encoder
        samples since the last call to the dataset and MCAP, then the disk checks.
        Returns ``(sensor samples, encoder samples)`` recorded so far, or ``None`` when
        nothing was written.  Raises :class:`~services.runs.recording.RecordingError`."""
        rec = self.recording
        if rec is None or not rec.dataset_open:
            return None
        now = self.clock.now()
        if not force and now < self._next_record:
            return None
        self._next_record = now + RECORD_PERIOD
        rows, self._pose_cursor = sensor.samples_since(self._pose_cursor, self._since)
        enc = {}
        for m in self.config.nominal.ids:
            enc[m], self._enc_cursors[m] = encoders.encoder_rows(
                m, self._enc_cursors[m], self._since
            )
        cols = [2, 3] if self.metrology == "imu" else [2, 3, 4, 5]  # t_host and the values
        rec.add(np.ascontiguousarray(rows[:, cols]), enc)
        rec.flush()
        return rec.samples, rec.encoder_samples

    def add_segment(self, seg: Segment) -> None:
        if self.recording is not None:
            self.recording.add_segment(seg)

    def close_dataset(self, sensor: SampleSource, encoders: EncoderSource) -> Path:
        """The last samples, then the dataset's files flushed, synced and closed (to be
        solved); returns the run's directory.  Idempotent."""
        assert self.recording is not None
        if self.recording.dataset_open:
            self.record(sensor, encoders, force=True)
            self.recording.close_dataset()
        return self.run_dir

    def save_references(self, refs: list[Reference]) -> None:
        """The run's references as the dataset's ``references.yaml`` (without motion
        capture)."""
        assert self.recording is not None
        self.recording.save_references(refs)

    def finish(self, outcome: dict[str, Any], result_doc: dict[str, Any] | None = None) -> None:
        """Close the recordings with the run's ``outcome``; the result and, when DONE, the
        run's kinematic file attached to the MCAP.  Best effort: the end is decided."""
        rec, self.recording = self.recording, None
        if rec is None:
            return
        attachments: dict[str, tuple[bytes, str]] = {}
        run_kin = self.run_dir / "kinematics.yaml"
        if outcome.get("state") == "DONE" and run_kin.is_file():
            attachments["kinematics.yaml"] = (run_kin.read_bytes(), "application/yaml")
        if result_doc is not None:
            attachments["result.json"] = (json_bytes(result_doc), "application/json")
        rec.finish(self.clock.now(), outcome, attachments)

    # ---------------------------------------------------------------- provenance
    def provenance(
        self, dataset_hash: str | None = None, method: str | None = None
    ) -> dict[str, Any]:
        """Where what the run writes comes from (:func:`services.store.provenance.provenance`);
        with the dataset's hash and the solver's method, as the kinematic file has it."""
        doc = provenance(
            "swpc service",
            run=self.run_id,
            robot_config=self.robot_config_path,
            config_sha256=self.config_sha256,
            dataset_sha256=dataset_hash,
        )
        if method is not None:
            doc["method"] = method
            doc["units"] = dict(UNITS)
        return doc
