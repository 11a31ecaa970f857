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
  exactly what ``swpc solve`` does offline.  Data or a result the solver's plausibility
  gates refuse end the run FAILED with the solver's reason; nothing is installed.
* WRITE: the kinematic file is installed atomically (previous one kept as a timestamped
  backup) unless the std devs exceed the configured tolerances (then reported only,
  unless the request said ``install: always``).

Any fault (driver fault event, stale mocap stream during motion, yaw rate above the
limit, a step longer than ``step_timeout``, a recording that cannot be written, a state
that cannot be saved) or an abort: ``stop_all()`` first, then FAILED or ABORTED with the
reason.  A service that stops (SIGTERM) ends its run FAILED, not "aborted by the
operator".  Before PENDING -> CONNECT, the config's
:meth:`~services.config.robot.RobotConfig.run_problems` (the service refuses such a run
with 422 before it gets here).

This module is the protocol's steps.  The machinery under them (the run's thread, state
entry, the checks at every poll, waits on robot time, the end that stops the robot
first) is :class:`services.runs.machine.RunMachine`; the states, the operator's view of a
run and the errors that end one are :mod:`services.runs.state`; the spin's yaw and the
rest test are pure functions of the poses (:mod:`services.runs.pose_motion`).  What a run
leaves behind is written by its
:class:`~services.runs.journal.RunJournal`: from the start it streams the poses and encoder
samples to the run's dataset directory and MCAP file every half second of robot time
(SOLVE solves what is on disk), and every event (state, segment, fault, result) is a
structured log line on the ``swpc.run`` logger and a ``foxglove.Log`` message in the
MCAP.

Time is an input: every duration is robot seconds on the injected clock
(:mod:`swpc_hw.clock`): the host's on a robot, the simulated one in lockstep against the
in-process simulator (the run's thread is then a participant: the simulation waits for it
at every step), a scaled one against an external time-scaled simulator.  Solving and
installing live in :mod:`services.runs.install`.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from services.config.robot import RobotConfig
from services.runs.install import solve_run, within_tolerance, write_result
from services.runs.journal import RECORD_PERIOD, RunJournal
from services.runs.machine import RunMachine
from services.runs.pose_motion import REST_WINDOW, SpinWindow, motion_rates
from services.runs.recording import SpaceGuard
from services.runs.state import (
    MOTION,
    TERMINAL,
    TRANSITIONS,
    PersistError,
    RunAbortedError,
    RunFailedError,
    RunStatus,
    State,
    now_iso,
)
from services.sensors.mocap import MocapIngest
from services.store.provenance import dataset_sha256
from swpc_hw.calibration.solver import CalibrationResult
from swpc_hw.clock import SYSTEM_CLOCK, Clock
from swpc_hw.dataset import Dataset, Segment, load_dataset
from swpc_hw.drives.robot_io import RobotIO
from swpc_hw.errors import CalibrationError
from swpc_hw.model import contact_point, trailing_steering_angle, wrap_angle

__all__ = [  # the run's vocabulary, importable from here as before the split
    "MOTION",
    "RECORD_PERIOD",
    "TERMINAL",
    "TRANSITIONS",
    "CalibrationRun",
    "PersistError",
    "RunAbortedError",
    "RunFailedError",
    "RunStatus",
    "State",
    "motion_rates",
]


class CalibrationRun(RunMachine):
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
        super().__init__(robot, mocap, config, clock=clock, on_change=on_change, poll=poll)
        self.status.metrology = self.metrology
        self.install = install
        self.run_dir = Path(data_dir) / "runs" / self.status.id
        self.kinematics_path = Path(kinematics_path)
        self.result: CalibrationResult | None = None
        self.segments: list[Segment] = []
        modules = config.protocol.modules or config.nominal.ids
        self.modules = [m for m in config.nominal.ids if m in modules]
        self.status.modules_total = len(self.modules)
        self.status.angles_total = len(config.protocol.angles_deg)
        self.journal = RunJournal(
            self.id,
            self.run_dir,
            config,
            clock,
            space=space,
            mcap=mcap,
            robot_config_path=robot_config_path,
            metrology=self.metrology,
        )
        self.backup: Path | None = None

    def _start_fields(self) -> dict[str, Any]:
        return {
            "metrology": self.metrology,
            "install": self.install,
            "modules": ",".join(map(str, self.modules)),
            "angles_deg": ",".join(f"{a:g}" for a in self.config.protocol.angles_deg),
            "config_sha256": self.journal.config_sha256[:16],
            "dir": str(self.run_dir),
        }

    # ------------------------------------------------------------------ protocol
    def _protocol(self) -> None:
        cfg = self.config
        problems = self._run_problems()
        if problems:  # the service refuses these with 422: never reached through it
            raise RunFailedError("refused before any motion: " + "; ".join(problems))
        self.journal.open(t0=self._t0, install=self.install, created=self.status.created)
        self._record(force=True)
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
        self._enter(State.PRECHECK, f"checking nodes, errors, homing and {self.sensor_name}")
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
            self.status.module, self.status.module_index, self.status.sweep_deg = k, mi + 1, 0.0
            self.status.angle_index, self.status.angle_deg = 1, cfg.protocol.angles_deg[0]
            self._enter(State.LOCK, f"locking module {k} at {cfg.protocol.angles_deg[0]:g} deg")
            for m in dyn:
                self.robot.wheel_hold(m)
            self.robot.lock(k, angles[0])
            self._settle_steering(k, angles[0])
            for ai, a in enumerate(angles):
                self.status.angle_index, self.status.angle_deg = ai + 1, cfg.protocol.angles_deg[ai]
                self.status.sweep_deg = 0.0
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
                self._before_spin(k, dyn)
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
        self._after_spins()
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
            self.status.finished = now_iso()
        self.journal.finish(
            {"state": "DONE", "installed": self.status.installed, "reason": ""}, self.result_doc
        )
        self._enter(State.DONE, "done")

    # ------------------------------------------------------- what the metrology changes
    sensor_name = "mocap"

    def _run_problems(self) -> list[str]:
        """What makes the run impossible, found before any motion."""
        return self.config.run_problems()

    def _sensor_precheck(self) -> list[str]:
        """Why the motion sensor is not ready (PRECHECK)."""
        problems = []
        if self.mocap.is_stale():
            problems.append(f"motion capture not live (last pose {self.mocap.age():.2f} s ago)")
        clock = self.mocap.clock_problem()
        if clock is not None:
            problems.append(clock)
        return problems

    def _before_spin(self, k: int, dyn: list[int]) -> None:
        """Between the alignment (or re-steering) and a spin about module ``k``."""

    def _after_spins(self) -> None:
        """After the last spin's RELEASE, before SOLVE."""

    # ------------------------------------------------------------------ the steps
    def _precheck(self) -> None:
        deadline = self.clock.now() + min(5.0, self.config.limits.step_timeout)
        while True:
            problems = self.robot.problems() + self._sensor_precheck()
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
        spin = SpinWindow(self.clock.now(), proto.settle_time, latest.t_host, latest.yaw)
        deadline = self._deadline()
        while True:
            self._check(True, deadline)
            p = self.mocap.latest()
            assert p is not None
            spin.add(p.t_host, p.yaw)
            if spin.rate is not None and abs(spin.rate) > limits.max_yaw_rate:
                raise RunFailedError(
                    f"yaw rate {spin.rate:.2f} rad/s exceeds the limit {limits.max_yaw_rate:g}"
                )
            if spin.start is not None:
                sweep = spin.sweep
                with self._lock:
                    self.status.sweep_deg = math.degrees(sweep)
                    self.status.progress = min((done + min(sweep / sweep_target, 1.0)) / total, 1.0)
                    self.status.poses = self.mocap.counters.accepted
                if sweep >= sweep_target:
                    seg = Segment(k, spin.start, p.t_host)
                    self.segments.append(seg)
                    self.status.segments = len(self.segments)
                    self.journal.add_segment(seg)
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
        run_dir = self.journal.close_dataset(self.sensor, self.robot)
        try:
            self.result = solve_run(run_dir)
        except CalibrationError as exc:  # data or result refused: a reason, not a bug
            raise RunFailedError(f"calibration refused: {exc}") from exc

    def within_tolerance(self) -> bool:
        assert self.result is not None
        return within_tolerance(self.result, self.config.tolerances)

    def _write(self) -> None:
        assert self.result is not None
        prov = self.journal.provenance(dataset_sha256(self.run_dir / "dataset"), self.result.method)
        out = write_result(
            self.id,
            self.result,
            self.config,
            run_dir=self.run_dir,
            kinematics_path=self.kinematics_path,
            install=self.install,
            provenance=prov,
        )
        self.backup = out.backup
        if out.installed:
            self._event(
                logging.INFO,
                "run.install",
                path=str(self.kinematics_path),
                backup=None if out.backup is None else str(out.backup),
                within_tolerance=out.within,
            )
        else:
            self._event(
                logging.WARNING if not out.within else logging.INFO,
                "run.not_installed",
                within_tolerance=out.within,
                install=self.install,
                result=str(self.run_dir / "kinematics.yaml"),
            )
        self.status.installed = out.installed
        self.result_doc = out.document
