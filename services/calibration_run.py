"""The calibration protocol as an explicit state machine.

One place to read it — :data:`TRANSITIONS`::

    PENDING -> CONNECT -> PRECHECK -> REST -> LOCK -> ALIGN -> FREE -> SPIN -> STOP
    STOP    -> RESTEER (next angle of the same module) | RELEASE
    RESTEER -> SPIN
    RELEASE -> LOCK (next module) | SOLVE
    SOLVE   -> WRITE -> DONE
    any non-terminal state -> FAILED | ABORTED

* CONNECT: the robot's controllers are activated (commands flow, watchdog refreshed) and
  any steering not homed yet runs its homing sequence.
* PRECHECK: every node alive, no active errors, steering homed, mocap stream live.
* REST: every wheel braked until mocap shows the robot still (a robot coasting from an
  aborted run, or pushed, would drag the module being locked off its angle).
* LOCK k: steering of k position-held at the first angle, wheel braked.
* ALIGN: the other (dynamic) modules steer to their nominal trailing angle for a spin
  about k's contact point (so their transients are short), wheels free.
* FREE: the dynamic modules' steering is released (zero torque).
* SPIN: constant wheel torque on the dynamic wheels; after ``settle_time`` the segment
  window opens and stays open until mocap has measured ``sweep_deg`` of yaw.
* STOP: torque off, wheels held, the robot spins down.
* RESTEER: k steers to its next angle (dynamic steering and wheels free so the body can
  follow), then SPIN again.
* RELEASE: k released; next module.
* SOLVE: the recorded poses, encoder feedback and segment windows are written as an
  offline dataset (CONVENTIONS.md) and solved by :func:`swpc_hw.calibration.solve` —
  exactly what ``swpc solve`` does offline.
* WRITE: the kinematic file is installed atomically (previous one kept as a timestamped
  backup) unless the std devs exceed the configured tolerances (then reported only,
  unless the request said ``install: always``).

Any fault (driver fault event, stale mocap stream during motion, yaw rate above the
limit, a step longer than ``step_timeout``, a recording that cannot be written, a state
that cannot be saved) or an abort: ``stop_all()`` first, then FAILED or ABORTED with the
reason.  A service that stops (SIGTERM) ends its run FAILED, not "aborted by the
operator" (:meth:`CalibrationRun.shutdown`).  Before PENDING -> CONNECT, the config's
:meth:`~services.robot_config.RobotConfig.run_problems` (the service refuses such a run
with 422 before it gets here).

Recording: from the start, the run streams its poses and encoder samples to its dataset
directory and MCAP file (:mod:`services.run_recording`) every :data:`RECORD_PERIOD` of
robot time; SOLVE solves what is on disk.  Every event (state, segment, fault, result)
is a structured log line on the ``swpc.run`` logger (:mod:`services.logs`) and a
``foxglove.Log`` message in the MCAP.

Time is an input: every duration is robot seconds on the injected clock
(:mod:`swpc_hw.clock`): the host's on a robot, the simulated one in lockstep against the
in-process simulator (the run's thread is then a participant: the simulation waits for it
at every step), a scaled one against an external time-scaled simulator.  Solving and
installing live in :mod:`services.calibration_result`.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import logging
import math
import threading
import time
import traceback
import uuid
from collections.abc import Callable, Iterator
from enum import StrEnum
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, Field

from services.calibration_result import (
    install_kinematics,
    result_document,
    solve_run,
    within_tolerance,
)
from services.logs import event
from services.mocap_ingest import MocapIngest
from services.provenance import UNITS, config_sha256, dataset_sha256, provenance
from services.robot_config import RobotConfig
from services.robot_io import RobotIO
from services.run_recording import RecordingError, RunRecording, SpaceGuard, json_bytes
from swpc_hw.calibration.solver import CalibrationResult
from swpc_hw.clock import SYSTEM_CLOCK, Clock, SimClock
from swpc_hw.dataset import Dataset, Segment, load_dataset
from swpc_hw.kinematic_file import save_kinematics
from swpc_hw.model import FloatArray, contact_point, trailing_steering_angle, wrap_angle

log = logging.getLogger("swpc.run")


class State(StrEnum):
    PENDING = "PENDING"
    CONNECT = "CONNECT"
    PRECHECK = "PRECHECK"
    REST = "REST"
    LOCK = "LOCK"
    ALIGN = "ALIGN"
    FREE = "FREE"
    SPIN = "SPIN"
    STOP = "STOP"
    RESTEER = "RESTEER"
    RELEASE = "RELEASE"
    SOLVE = "SOLVE"
    WRITE = "WRITE"
    DONE = "DONE"
    FAILED = "FAILED"
    ABORTED = "ABORTED"


TERMINAL = frozenset({State.DONE, State.FAILED, State.ABORTED})
MOTION = frozenset({State.REST, State.ALIGN, State.FREE, State.SPIN, State.STOP, State.RESTEER})

TRANSITIONS: dict[State, frozenset[State]] = {
    State.PENDING: frozenset({State.CONNECT}),
    State.CONNECT: frozenset({State.PRECHECK}),
    State.PRECHECK: frozenset({State.REST}),
    State.REST: frozenset({State.LOCK}),
    State.LOCK: frozenset({State.ALIGN}),
    State.ALIGN: frozenset({State.FREE}),
    State.FREE: frozenset({State.SPIN}),
    State.SPIN: frozenset({State.STOP}),
    State.STOP: frozenset({State.RESTEER, State.RELEASE}),
    State.RESTEER: frozenset({State.SPIN}),
    State.RELEASE: frozenset({State.LOCK, State.SOLVE}),
    State.SOLVE: frozenset({State.WRITE}),
    State.WRITE: frozenset({State.DONE}),
}


REST_WINDOW = 0.5
"""s of robot time over which the robot must be still before a module is locked."""
YAW_RATE_WINDOW = 0.2
"""s of robot time over which the spin's yaw rate is checked against its limit."""
RECORD_PERIOD = 0.5
"""s of robot time between two writes of the run's recordings (what a kill may lose)."""


def motion_rates(
    t: FloatArray, x: FloatArray, y: FloatArray, yaw: FloatArray
) -> tuple[float, float]:
    """Speed (m/s) and yaw rate (rad/s) of poses ``(t_k, x_k, y_k, yaw_k)``: the slopes of
    least-squares lines through them (noise-averaging, unlike end-point differences)::

        s_q = sum_k (t_k - t_mean)(q_k - q_mean) / sum_k (t_k - t_mean)^2,  q in {x, y, yaw}
        speed = hypot(s_x, s_y),   yaw rate = s_yaw   (yaw unwrapped first)

    Needs at least two distinct times.
    """
    tc = t - np.mean(t) if t.shape[0] else t
    den = float(tc @ tc)
    if den <= 0.0:
        raise ValueError("motion_rates needs poses at two distinct times at least")
    q = np.column_stack([x, y, np.unwrap(yaw)])
    s = tc @ (q - q.mean(axis=0)) / den
    return float(math.hypot(s[0], s[1])), float(s[2])


class RunFailedError(Exception):
    """A fault: the run ends FAILED with this reason."""


class RunAbortedError(Exception):
    """The operator aborted: the run ends ABORTED."""


class PersistError(RunFailedError):
    """The run's state could not be saved (the run store): the run ends FAILED."""


class RunStatus(BaseModel):
    """What an operator sees of a run (``GET /calibrations/{id}``)."""

    id: str
    created: str
    state: State = State.PENDING
    step: str = "waiting to start"
    module: int | None = None
    module_index: int = 0
    modules_total: int = 0
    progress: float = 0.0
    sweep_deg: float = 0.0
    poses: int = 0
    encoder_samples: int = 0
    segments: int = 0
    errors: list[str] = Field(default_factory=list)
    reason: str | None = None
    started: str | None = None
    finished: str | None = None
    installed: bool | None = None

    def to_dict(self) -> dict[str, Any]:
        return self.model_dump(mode="json")


def _now_iso() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")


class CalibrationRun:
    """One calibration: runs the protocol on its own thread (see the module docstring)."""

    def __init__(
        self,
        robot: RobotIO,
        mocap: MocapIngest,
        config: RobotConfig,
        *,
        clock: Clock = SYSTEM_CLOCK,
        data_dir: Path,
        kinematics_path: Path,
        install: str = "if-within-tolerance",
        on_change: Callable[[CalibrationRun], None] | None = None,
        poll: float = 0.02,
        space: SpaceGuard | None = None,
        robot_config_path: str | None = None,
        mcap: bool = True,
    ) -> None:
        self.robot = robot
        self.mocap = mocap
        self.config = config
        self.clock = clock
        self.install = install
        self.status = RunStatus(id=uuid.uuid4().hex[:12], created=_now_iso())
        self.run_dir = Path(data_dir) / "runs" / self.status.id
        self.kinematics_path = Path(kinematics_path)
        self.result: CalibrationResult | None = None
        self.result_doc: dict[str, Any] | None = None
        self.segments: list[Segment] = []
        self._on_change = on_change
        self._poll = poll
        self._abort = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()
        self._t0 = 0.0
        self.abort_latency: float | None = None
        modules = config.protocol.modules or config.nominal.ids
        self.modules = [m for m in config.nominal.ids if m in modules]
        self.status.modules_total = len(self.modules)
        self.space = space
        self.mcap = mcap
        self.robot_config_path = robot_config_path
        self.config_sha256 = config_sha256(config.to_document())
        self.recording: RunRecording | None = None
        self._recording_live = False
        self._next_record = -math.inf
        self._pose_cursor = 0
        self._enc_cursors = dict.fromkeys(config.nominal.ids, 0)
        self._stop_reason: str | None = None
        self.persist_error: str | None = None
        self.backup: Path | None = None

    # ------------------------------------------------------------------ control
    @property
    def id(self) -> str:
        return self.status.id

    @property
    def finished(self) -> bool:
        return self.status.state in TERMINAL

    def start(self) -> None:
        self._thread = threading.Thread(target=self._main, name=f"calib-{self.id}", daemon=True)
        self._thread.start()

    def abort(self) -> None:
        """Stop motion at once (``stop_all()`` from the caller's thread) and end ABORTED."""
        if self.finished:
            return
        self._abort.set()
        self.robot.stop_all()

    def shutdown(self, reason: str = "the service was stopped during the run") -> None:
        """Stop motion at once and end FAILED with ``reason`` (the service is stopping:
        SIGTERM is no operator's abort)."""
        if self.finished:
            return
        self._stop_reason = reason
        self._abort.set()
        self.robot.stop_all()

    def join(self, timeout: float | None = None) -> None:
        if self._thread is not None:
            self._thread.join(timeout)

    # ---------------------------------------------------------------- internals
    def _enter(self, state: State, step: str) -> None:
        cur = self.status.state
        if state not in TERMINAL and state not in TRANSITIONS.get(cur, frozenset()):
            raise RuntimeError(f"illegal transition {cur} -> {state}")
        with self._lock:
            self.status.state = state
            self.status.step = step
        self._event(
            logging.INFO, "run.state", state=str(state), step=step, module=self.status.module
        )
        self._changed()
        if state not in TERMINAL:
            # an abort or a fault since the last check ends the run before this state's
            # first command
            self._check(False, None)

    def _changed(self) -> None:
        """Tell the owner (the service saves the state); a failure to save fails a run
        still going (robot stopped first), and is kept in :attr:`persist_error`."""
        if self._on_change is None:
            return
        try:
            self._on_change(self)
        except Exception as exc:
            self.persist_error = f"{type(exc).__name__}: {exc}"
            self._event(logging.ERROR, "run.persist_failed", error=self.persist_error)
            if self.status.state not in TERMINAL:
                raise PersistError(f"cannot save the run's state: {self.persist_error}") from exc

    def _event(self, level: int, name: str, **fields: Any) -> None:
        """A structured log line (``event=<name> run=<id> ...``) and, once recording, a
        ``foxglove.Log`` message in the run's MCAP."""
        line = event(log, level, name, run=self.id, **fields)
        if self.recording is not None and self._recording_live:
            self.recording.event(
                self.clock.now(), logging.getLevelName(level).lower(), line
            )

    def _record(self, force: bool = False) -> None:
        """Every :data:`RECORD_PERIOD` (or now): the poses and encoder samples since the
        last time to the run's dataset and MCAP, then the disk checks."""
        rec = self.recording
        if rec is None or not self._recording_live or not rec.dataset_open:
            return
        now = self.clock.now()
        if not force and now < self._next_record:
            return
        self._next_record = now + RECORD_PERIOD
        since = self._t0 - 1.0
        rows, self._pose_cursor = self.mocap.samples_since(self._pose_cursor, since)
        enc = {}
        for m in self.config.nominal.ids:
            enc[m], self._enc_cursors[m] = self.robot.encoder_rows(
                m, self._enc_cursors[m], since
            )
        rec.add(np.ascontiguousarray(rows[:, [2, 3, 4, 5]]), enc)
        rec.flush()
        with self._lock:
            self.status.poses = rec.poses
            self.status.encoder_samples = rec.encoder_samples

    def _check(self, motion: bool, deadline: float | None) -> None:
        if self._abort.is_set():
            if self._stop_reason is not None:
                raise RunFailedError(self._stop_reason)
            raise RunAbortedError("aborted by the operator")
        self._record()
        faults = self.robot.take_faults()
        if faults:
            raise RunFailedError(f"robot fault: {faults[0]}")
        if motion and self.mocap.is_stale():
            raise RunFailedError(
                f"motion capture stale: no pose for {self.mocap.age():.3f} s "
                f"(limit {self.mocap.stale_after:.3f} s)"
            )
        if deadline is not None and self.clock.now() > deadline:
            raise RunFailedError(
                f"step timeout: {self.status.step} took longer than "
                f"{self.config.limits.step_timeout:g} s"
            )

    def _deadline(self) -> float:
        return self.clock.now() + self.config.limits.step_timeout

    def _wait(self, seconds: float, motion: bool = True) -> None:
        """Wait ``seconds`` of robot time, checking for faults and abort."""
        end = self.clock.now() + seconds
        deadline = self._deadline()
        while True:
            self._check(motion, deadline)
            left = end - self.clock.now()
            if left <= 0:
                return
            self.clock.sleep(min(self._poll, left))

    def _wait_until(self, cond: Callable[[], bool], motion: bool) -> None:
        deadline = self._deadline()
        while not cond():
            self._check(motion, deadline)
            self.clock.sleep(self._poll)

    @contextlib.contextmanager
    def _in_step(self) -> Iterator[None]:
        """Lockstep: the run's thread is a participant of the simulated clock."""
        if isinstance(self.clock, SimClock):
            with self.clock.participant():
                yield
        else:
            yield

    def _main(self) -> None:
        with self._in_step():
            self._run()

    def _run(self) -> None:
        self.status.started = _now_iso()
        self._t0 = self.clock.now()
        self._event(
            logging.INFO,
            "run.start",
            install=self.install,
            modules=",".join(map(str, self.modules)),
            angles_deg=",".join(f"{a:g}" for a in self.config.protocol.angles_deg),
            config_sha256=self.config_sha256[:16],
            dir=str(self.run_dir),
        )
        try:
            problems = self.config.run_problems()
            if problems:  # the service refuses these with 422: never reached through it
                raise RunFailedError("refused before any motion: " + "; ".join(problems))
            self._start_recording()
            self._protocol()
        except RunAbortedError as exc:
            self._end(State.ABORTED, str(exc))
        except (RunFailedError, RecordingError) as exc:
            self._end(State.FAILED, str(exc))
        except Exception as exc:  # a bug or an I/O error: still stop the robot first
            error = f"{type(exc).__name__}: {exc}"
            # a command refused because the driver had just stopped on a fault: the fault is
            # the reason, the refusal only its consequence
            faults: list[str] = []
            with contextlib.suppress(Exception):
                faults = self.robot.take_faults()
            if faults:
                self._end(State.FAILED, f"robot fault: {faults[0]}", f"then {error}")
            else:
                self._end(State.FAILED, error, traceback.format_exc())
        finally:
            with contextlib.suppress(Exception):
                self.robot.close()

    def _start_recording(self) -> None:
        wall_offset = self.clock.wall() - self.clock.now()
        self.recording = RunRecording(
            self.run_dir,
            self.config.nominal,
            wall_offset=wall_offset,
            guard=self.space,
            mcap=self.mcap,
        )
        self.recording.open(
            {
                "robot-config": self.config.to_document(),
                "provenance": self._provenance(),
                "run": {"id": self.id, "install": self.install, "created": self.status.created},
            }
        )
        self._recording_live = True
        self._record(force=True)

    def _provenance(self, dataset_hash: str | None = None) -> dict[str, Any]:
        return provenance(
            "swpc service",
            run=self.id,
            robot_config=self.robot_config_path,
            config_sha256=self.config_sha256,
            dataset_sha256=dataset_hash,
        )

    def _finish_recording(self, outcome: dict[str, Any]) -> None:
        rec, self.recording = self.recording, None
        self._recording_live = False
        if rec is None:
            return
        attachments: dict[str, tuple[bytes, str]] = {}
        run_kin = self.run_dir / "kinematics.yaml"
        if outcome.get("state") == "DONE" and run_kin.is_file():
            attachments["kinematics.yaml"] = (run_kin.read_bytes(), "application/yaml")
        if self.result_doc is not None:
            attachments["result.json"] = (json_bytes(self.result_doc), "application/json")
        rec.finish(self.clock.now(), outcome, attachments)

    def _end(self, state: State, reason: str, detail: str | None = None) -> None:
        t = time.perf_counter()  # a measurement of the host, not a judgement of time
        try:
            self.robot.stop_all()
        except Exception as exc:
            self.status.errors.append(f"stop_all failed: {exc}")
        if state is State.ABORTED and self.abort_latency is None:
            self.abort_latency = time.perf_counter() - t
        try:
            self.robot.release()
        except Exception as exc:
            self.status.errors.append(f"release failed: {exc}")
        if self.status.state not in TERMINAL and self.status.state is not State.PENDING:
            reason = f"{reason} (during {self.status.state}: {self.status.step})"
        with self._lock:
            self.status.reason = reason
            self.status.errors.append(reason)
            if detail:
                self.status.errors.append(detail.strip().splitlines()[-1])
            self.status.finished = _now_iso()
            self.status.state = state
            self.status.step = "stopped"
        level = logging.WARNING if state is State.ABORTED else logging.ERROR
        self._event(level, "run.end", state=str(state), reason=reason)
        with contextlib.suppress(Exception):  # best effort: the end is decided
            if self._recording_live:
                self._record(force=True)
        with contextlib.suppress(Exception):
            self._finish_recording({"state": str(state), "reason": reason})
        self._changed()

    # ------------------------------------------------------------------ protocol
    def _protocol(self) -> None:
        cfg = self.config
        angles = [math.radians(a) for a in cfg.protocol.angles_deg]
        self._enter(State.CONNECT, "activating the controllers")
        self.robot.activate()
        unhomed = self.robot.unhomed()
        if unhomed:
            self.status.step = f"homing the steering of modules {unhomed}"
            self._changed()
            for m in unhomed:
                self.robot.start_homing(m)
            self._wait_until(lambda: not self.robot.unhomed(), motion=False)
        self._enter(State.PRECHECK, "checking nodes, errors, homing and mocap")
        self._precheck()
        self._come_to_rest()
        nominal = cfg.nominal.arrays()
        ids = cfg.nominal.ids
        spins_total = len(self.modules) * len(angles)
        spins_done = 0
        torque = cfg.limits.spin_torque
        for mi, k in enumerate(self.modules):
            ki = ids.index(k)
            dyn = [m for m in ids if m != k]
            self.status.module, self.status.module_index = k, mi + 1
            self._enter(State.LOCK, f"locking module {k} at {cfg.protocol.angles_deg[0]:g} deg")
            for m in dyn:
                self.robot.wheel_hold(m)
            self.robot.lock(k, angles[0])
            self._settle_steering(k, angles[0])
            for ai, a in enumerate(angles):
                if ai > 0:
                    self._enter(
                        State.RESTEER,
                        f"re-steering module {k} to {cfg.protocol.angles_deg[ai]:g} deg",
                    )
                    for m in dyn:
                        self.robot.free_steer(m)
                        self.robot.wheel_free(m)
                    self.robot.steer_to(k, a)
                    self._settle_steering(k, a)
                    self._wait(cfg.protocol.resteer_time * 0.2)
                else:
                    # dynamic modules to their nominal trailing angle for a CCW spin about C
                    self._enter(State.ALIGN, "aligning the dynamic modules")
                    C = contact_point(
                        nominal.P_s[ki], np.array(nominal.b[ki]), a + nominal.beta[ki]
                    )
                    v = -np.array([-C[1], C[0]])  # v = -omega x C with omega = 1
                    targets = trailing_steering_angle(nominal, v, 1.0)
                    for m in dyn:
                        self.robot.wheel_free(m)
                        self.robot.steer_to(m, float(targets[ids.index(m)]))
                    self._wait(cfg.protocol.align_time)
                    self._enter(State.FREE, "releasing the dynamic steering")
                    for m in dyn:
                        self.robot.free_steer(m)
                self._enter(State.SPIN, f"spinning about module {k} ({ai + 1}/{len(angles)})")
                for m in dyn:
                    # trailing wheels roll backwards for a CCW spin (r dpsi = -D dyaw)
                    self.robot.wheel_torque(m, -torque)
                self._spin(k, spins_done, spins_total)
                spins_done += 1
                self._enter(State.STOP, "spinning down")
                for m in dyn:
                    self.robot.wheel_hold(m)
                self._wait(cfg.protocol.stop_time)
            self._enter(State.RELEASE, f"releasing module {k}")
            self.robot.free_steer(k)
            self.robot.wheel_hold(k)
        self.robot.stop_all()
        self.robot.release()
        self._enter(State.SOLVE, "solving")
        self._solve()
        if self._abort.is_set():  # nothing moves any more, but nothing is installed either
            if self._stop_reason is not None:
                raise RunFailedError(f"{self._stop_reason} (the result is not installed)")
            raise RunAbortedError("aborted by the operator (the result is not installed)")
        self._enter(State.WRITE, "writing the kinematic file")
        self._write()
        with self._lock:
            self.status.progress = 1.0
            self.status.finished = _now_iso()
        self._finish_recording(
            {"state": "DONE", "installed": self.status.installed, "reason": ""}
        )
        self._enter(State.DONE, "done")

    def _precheck(self) -> None:
        deadline = self.clock.now() + min(5.0, self.config.limits.step_timeout)
        while True:
            problems = self.robot.problems()
            if self.mocap.is_stale():
                problems.append(f"motion capture not live (last pose {self.mocap.age():.2f} s ago)")
            clock = self.mocap.clock_problem()
            if clock is not None:
                problems.append(clock)
            if not problems:
                return
            if self.clock.now() > deadline:
                raise RunFailedError("precheck failed: " + "; ".join(problems))
            self._check(False, None)
            self.clock.sleep(0.01)

    def _come_to_rest(self) -> None:
        """Brake every wheel and wait until the motion capture shows the robot at rest.

        A robot still coasting (a run aborted mid-spin just before, or someone pushing
        it) would drag the module about to be locked off its angle: the spins' data then
        fail with "the static module is not locked".  At rest: over the last
        :data:`REST_WINDOW` s (robot time) the least-squares speed and yaw rate
        (:func:`motion_rates`) are within ``limits.rest_speed`` / ``rest_yaw_rate``.
        """
        limits = self.config.limits
        ids = self.config.nominal.ids
        step = "braking every wheel: waiting for the robot to come to rest"
        self._enter(State.REST, step)
        for m in ids:
            self.robot.wheel_hold(m)
        window = REST_WINDOW
        t_brake = self.clock.now()
        deadline = self._deadline()
        while True:
            self._check(True, deadline)
            # the poses *sampled* over the last window after the brake (by their host
            # times: with late poses, from a slow mocap network or clock mode wall, the
            # newest pose at hand may have been sampled a while ago)
            latest = self.mocap.latest()
            if latest is not None and latest.t_host - t_brake >= window:
                poses = self.mocap.samples(since_host=latest.t_host - window)
                if poses.shape[0] >= 3 and poses[-1, 2] - poses[0, 2] >= 0.5 * window:
                    speed, rate = motion_rates(poses[:, 2], poses[:, 3], poses[:, 4], poses[:, 5])
                    if speed <= limits.rest_speed and abs(rate) <= limits.rest_yaw_rate:
                        return
                    with self._lock:
                        self.status.step = (
                            f"{step} (yaw rate {rate:.3f} rad/s, speed {speed:.3f} m/s)"
                        )
            self.clock.sleep(self._poll)

    def _settle_steering(self, module: int, angle: float, tol: float = math.radians(0.5)) -> None:
        self._wait_until(
            lambda: bool(abs(wrap_angle(self.robot.steering(module) - angle)) < tol),
            motion=True,
        )

    def _spin(self, k: int, done: int, total: int) -> None:
        proto, limits = self.config.protocol, self.config.limits
        sweep_target = math.radians(proto.sweep_deg)
        latest = self.mocap.latest()
        assert latest is not None
        t_spin = self.clock.now()
        deadline = self._deadline()
        window_start: float | None = None
        yaw_prev = latest.yaw
        yaw_acc = 0.0
        acc_at_start = 0.0
        rate_t, rate_acc = latest.t_host, 0.0
        while True:
            self._check(True, deadline)
            p = self.mocap.latest()
            assert p is not None
            yaw_acc += float(wrap_angle(p.yaw - yaw_prev))
            yaw_prev = p.yaw
            # yaw rate over YAW_RATE_WINDOW of the poses' own times (the mocap's spacing)
            robot_dt = p.t_host - rate_t
            if robot_dt >= YAW_RATE_WINDOW:
                rate = (yaw_acc - rate_acc) / robot_dt
                if abs(rate) > limits.max_yaw_rate:
                    raise RunFailedError(
                        f"yaw rate {rate:.2f} rad/s exceeds the limit {limits.max_yaw_rate:g}"
                    )
                rate_t, rate_acc = p.t_host, yaw_acc
            # the window opens at the first pose *sampled* settle_time after the spin began
            # (not the newest pose at that moment: with late poses, from a slow mocap
            # network or a starved ingest, that one was sampled before the spin was steady
            # and the window took in the spin-up; the VM under load saw it start at rest)
            settled = p.t_host - t_spin >= proto.settle_time
            if window_start is None and settled:
                window_start, acc_at_start = p.t_host, yaw_acc
            if window_start is not None:
                sweep = abs(yaw_acc - acc_at_start)
                with self._lock:
                    self.status.sweep_deg = math.degrees(sweep)
                    self.status.progress = min((done + min(sweep / sweep_target, 1.0)) / total, 1.0)
                    self.status.poses = self.mocap.counters.accepted
                if sweep >= sweep_target:
                    seg = Segment(k, window_start, p.t_host)
                    self.segments.append(seg)
                    self.status.segments = len(self.segments)
                    if self.recording is not None:
                        self.recording.add_segment(seg)
                    self._event(
                        logging.INFO,
                        "run.segment",
                        module=k,
                        start=seg.start,
                        end=seg.end,
                        sweep_deg=math.degrees(sweep),
                    )
                    return
            self.clock.sleep(self._poll)

    def dataset(self) -> Dataset:
        """The run's recorded data: its dataset directory, as written (the run's clock)."""
        return load_dataset(self.run_dir / "dataset")

    def _solve(self) -> None:
        assert self.recording is not None
        self._record(force=True)
        self.recording.close_dataset()
        self.result = solve_run(self.run_dir)

    def within_tolerance(self) -> bool:
        assert self.result is not None
        return within_tolerance(self.result, self.config.tolerances)

    def _write(self) -> None:
        assert self.result is not None
        res = self.result
        ok = self.within_tolerance()
        install = self.install == "always" or (self.install == "if-within-tolerance" and ok)
        prov = self._provenance(dataset_sha256(self.run_dir / "dataset"))
        prov["method"] = res.method
        prov["units"] = dict(UNITS)
        extra = {"provenance": prov, "quality": res.quality_document()}
        save_kinematics(self.run_dir / "kinematics.yaml", res.params, extra=extra)
        if install:
            self.backup = install_kinematics(self.kinematics_path, res, extra)
            self._event(
                logging.INFO,
                "run.install",
                path=str(self.kinematics_path),
                backup=None if self.backup is None else str(self.backup),
                within_tolerance=ok,
            )
        else:
            self._event(
                logging.WARNING if not ok else logging.INFO,
                "run.not_installed",
                within_tolerance=ok,
                install=self.install,
                result=str(self.run_dir / "kinematics.yaml"),
            )
        self.status.installed = install
        self.result_doc = result_document(
            self.id,
            res,
            self.config,
            run_dir=self.run_dir,
            kinematics_path=self.kinematics_path,
            within=ok,
            installed=install,
        )
