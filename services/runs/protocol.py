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
* PRECHECK: every node alive, no active errors, steering homed, the metrology's sensor
  live.
* REST: every wheel braked until the metrology shows the robot still (a robot coasting
  from an aborted run, or pushed, would drag the module being locked off its angle).
* LOCK k: steering of k position-held at the first angle, wheel braked.
* ALIGN: the other (dynamic) modules steer to their nominal trailing angle for a spin
  about k's contact point (so their transients are short), wheels free.
* FREE: the dynamic modules' steering is released (zero torque).
* SPIN: constant wheel torque on the dynamic wheels; after ``settle_time`` the segment
  window opens and stays open until the metrology has measured ``sweep_deg`` of yaw.
* STOP: torque off, wheels held, the robot spins down.
* RESTEER: k steers to its next angle (dynamic steering and wheels free so the body can
  follow), then SPIN again.
* RELEASE: k released; next module.
* SOLVE: the recorded poses, encoder feedback and segment windows are written as an
  offline dataset (docs/dataset-format.md) and solved by :func:`swpc_hw.calibration.solve` —
  exactly what ``swpc solve`` does offline.  Data or a result the solver's plausibility
  gates refuse end the run FAILED with the solver's reason; nothing is installed.
* WRITE: the kinematic file is installed atomically (previous one kept as a timestamped
  backup) unless the std devs exceed the configured tolerances (then reported only,
  unless the request said ``install: always``).

The metrology (:mod:`services.runs.metrology.base`) is a part of the run, not a subclass:
motion capture (:mod:`services.runs.metrology.mocap`), or the IMU's gyro, the encoders and a tape
(:mod:`services.runs.metrology.imu`), which adds STILL before every spin and STEER, MARK, DRIVE and
MEASURE after the last module (the transitions above list them).

Any fault (driver fault event, stale motion sensor during motion, yaw rate above the
limit, a step longer than ``step_timeout``, a recording that cannot be written, a state
that cannot be saved) or an abort: ``stop_all()`` first, then FAILED or ABORTED with the
reason.  A service that stops (SIGTERM) ends its run FAILED, not "aborted by the
operator".  Before PENDING -> CONNECT, the config's
:meth:`~services.config.robot.RobotConfig.run_problems` (the service refuses such a run
with 422 before it gets here).

This module is the protocol's steps.  The machinery under them (the run's thread, state
entry, the checks at every poll, waits on robot time, the end that stops the robot
first) is :class:`services.runs.machine.RunMachine`; the states, the operator's view of a
run and the errors that end one are :mod:`services.runs.state`.  What a run
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
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from services.config.robot import RobotConfig
from services.config.settings import KINEMATICS_BACKUPS
from services.runs.install import solve_run, within_tolerance, write_result
from services.runs.journal import RunJournal
from services.runs.machine import RunMachine
from services.runs.metrology.base import Metrology
from services.runs.probing import Prober
from services.runs.recording import SpaceGuard
from services.runs.state import (
    RunAbortedError,
    RunFailedError,
    State,
    now_iso,
)
from services.store.provenance import dataset_sha256
from swpc_hw.calibration.commission.analysis import precheck_problems
from swpc_hw.calibration.commission.probes import PRECHECK_TURN, driver_of
from swpc_hw.calibration.mocap.solver import CalibrationResult
from swpc_hw.calibration.plan.plan import TimeModel
from swpc_hw.clock import SYSTEM_CLOCK, Clock
from swpc_hw.drives.robot_io import RobotIO
from swpc_hw.errors import CalibrationError
from swpc_hw.files.dataset import Dataset, load_dataset
from swpc_hw.protocol import PRECHECK_TIME, has_fast_part
from swpc_hw.robot.model import FloatArray, contact_point, trailing_steering_angle, wrap_angle

TIME_MODEL = TimeModel()
"""The planner's time model with its measured defaults: a step's estimate before one was
measured (:meth:`CalibrationRun.planned`; asked at every poll, made once)."""


class CalibrationRun(RunMachine):
    """One calibration: runs the protocol on its own thread (see the module docstring),
    measuring the robot's motion through ``metrology`` (:mod:`services.runs.metrology.base`).
    A check (:class:`services.runs.check.CheckRun`) is the same run with its own SOLVE
    and WRITE."""

    write_step = "writing the kinematic file"
    """WRITE's step text."""

    def __init__(
        self,
        robot: RobotIO,
        metrology: Metrology,
        config: RobotConfig,
        *,
        clock: Clock = SYSTEM_CLOCK,
        data_dir: Path,
        kinematics_path: Path,
        install: str = "if-within-tolerance",
        keep_backups: int = KINEMATICS_BACKUPS,
        on_change: Callable[[CalibrationRun], None] | None = None,
        poll: float = 0.02,
        space: SpaceGuard | None = None,
        robot_config_path: str | None = None,
        mcap: bool = True,
        mcap_profile: str = "foxglove",
        log_after: float | None = None,
    ) -> None:
        """``log_after``: where the previous run's log times ended
        (:func:`~services.runs.journal.log_wall_offset`)."""
        super().__init__(robot, metrology, config, clock=clock, on_change=on_change, poll=poll)
        self.install = install
        self.keep_backups = keep_backups
        self.run_dir = Path(data_dir) / "runs" / self.status.id
        self.kinematics_path = Path(kinematics_path)
        self.result: CalibrationResult | None = None
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
            mcap_profile=mcap_profile,
            robot_config_path=robot_config_path,
            metrology=metrology.name,
            log_after=log_after,
        )
        self.backup: Path | None = None
        still = [State.STILL] if metrology.name == "imu" else []
        first = [State.LOCK, State.ALIGN, State.FREE, *still, State.SPIN, State.STOP]
        again = [State.RESTEER, *still, State.SPIN, State.STOP]
        per_module = first + again * (len(config.protocol.angles_deg) - 1) + [State.RELEASE]
        fast = has_fast_part(len(config.nominal.ids), metrology.name, config.protocol.precheck)
        probe = [State.PROBE] * len(config.nominal.ids) if fast else []
        self.plan = probe + per_module * len(self.modules)
        if metrology.name == "imu" and config.protocol.drive_length > 0:
            # the rest after the last spin, the drive and the operator's two steps (theirs:
            # counted as steps, their time is the operator's)
            self.plan += [State.STILL, State.STEER, State.MARK, State.DRIVE, State.MEASURE]

    def _pivot(self, k: int, angle: float) -> FloatArray:
        """C, module ``k``'s contact point in R (nominal) with its steering at ``angle``:
        the point a spin about ``k`` turns the robot around."""
        nominal = self.config.nominal.arrays()
        ki = self.config.nominal.ids.index(k)
        return contact_point(nominal.P_s[ki], np.array(nominal.b[ki]), angle + nominal.beta[ki])

    def _spin_wheels(self, k: int, dyn: Sequence[int], angle: float, torque: float) -> None:
        """The dynamic wheels spin the robot counter-clockwise about module ``k``'s
        contact point C: trailing wheels roll backwards, ``r dpsi = -D dyaw``.

        By torque (``-torque`` on each) when every dynamic wheel's drive has a torque
        mode.  Otherwise by velocity: velocity-held wheels would fight each other over
        the robot's unknown geometry, so one wheel drives, the one whose steering axis is
        farthest from C (nominal), at ``dpsi = -D omega / r`` with ``omega`` the time
        model's yaw rate of the spin torque (the same time the run plans), and the others
        are free (power stage off where a drive has no torque mode)."""
        if all(self.robot.spins_by_torque(mod) for mod in dyn):
            for mod in dyn:
                self.robot.wheel_torque(mod, -torque)
            return
        nominal = self.config.nominal.arrays()
        ids = self.config.nominal.ids
        C = self._pivot(k, angle)
        reach = {mod: float(np.hypot(*(nominal.P_s[ids.index(mod)] - C))) for mod in dyn}
        driver = max(dyn, key=lambda mod: reach[mod])
        omega = TIME_MODEL.yaw_rate(self.config.limits.spin_torque)
        for mod in dyn:
            if mod != driver:
                self.robot.wheel_free(mod)
        self.robot.wheel_velocity(driver, -reach[driver] * omega / nominal.r[ids.index(driver)])

    def planned(self, state: State) -> float | None:
        """A step's robot time from the protocol's settings before one was measured: the
        align, stop, re-steer and rest times; a lock as long as a re-steer; a spin and the
        straight drive as the planner's time model predicts them
        (:class:`swpc_hw.calibration.plan.plan.TimeModel`: the settle time and the sweep at
        the yaw rate of the spin torque; both rests, the length at its cruise speed and
        the steer, ramp and coast); the operator's steps 0 (theirs)."""
        p, lim = self.config.protocol, self.config.limits
        tm = TIME_MODEL
        return {
            State.LOCK: p.resteer_time,
            State.PROBE: PRECHECK_TIME,
            State.ALIGN: p.align_time,
            State.STOP: p.stop_time,
            State.RESTEER: p.resteer_time,
            State.STILL: p.rest_time,
            State.SPIN: p.settle_time + math.radians(p.sweep_deg) / tm.yaw_rate(lim.spin_torque),
            State.DRIVE: 2 * p.rest_time + p.drive_length / tm.drive_speed + tm.drive_extra,
        }.get(state, 0.0)

    def _start_fields(self) -> dict[str, Any]:
        return {
            "metrology": self.metrology.name,
            "install": self.install,
            "modules": ",".join(map(str, self.modules)),
            "angles_deg": ",".join(f"{a:g}" for a in self.config.protocol.angles_deg),
            "config_sha256": self.journal.config_sha256[:16],
            "dir": str(self.run_dir),
            **self.metrology.start_fields(),
        }

    # ------------------------------------------------------------------ the operator
    @property
    def waits_for(self) -> str | None:
        """What the operator owes the run now (``continue``, ``references``), if anything:
        its metrology's."""
        return self.metrology.waits_for(self.status.state)

    def answer(self, what: str, entries: Sequence[dict[str, Any]] = ()) -> None:
        """The operator's answer (:meth:`services.runs.metrology.base.Metrology.answer`)."""
        self.metrology.answer(self.id, self.status.state, what, entries)

    # ------------------------------------------------------------------ protocol
    def _protocol(self) -> None:
        cfg = self.config
        m = self.metrology
        problems = self.run_problems()
        if problems:  # the service refuses these with 422: never reached through it
            raise RunFailedError("refused before any motion: " + "; ".join(problems))
        self.journal.open(t0=self._t0, install=self.install, created=self.status.created)
        self.record(force=True)
        angles = [math.radians(a) for a in cfg.protocol.angles_deg]
        self._connect()
        if has_fast_part(len(cfg.nominal.ids), m.name, cfg.protocol.precheck):
            self._fast_part(angles[0])
        nominal = cfg.nominal.arrays()
        ids = cfg.nominal.ids
        torque = cfg.limits.spin_torque
        for mi, k in enumerate(self.modules):
            dyn = [mod for mod in ids if mod != k]
            self.status.module, self.status.module_index, self.status.sweep_deg = k, mi + 1, 0.0
            self.status.angle_index, self.status.angle_deg = 1, cfg.protocol.angles_deg[0]
            self.enter(State.LOCK, f"locking module {k} at {cfg.protocol.angles_deg[0]:g} deg")
            for mod in dyn:
                self.robot.wheel_hold(mod)
            self.robot.lock(k, angles[0])
            self.settle_steering(k, angles[0])
            for ai, a in enumerate(angles):
                self.status.angle_index, self.status.angle_deg = ai + 1, cfg.protocol.angles_deg[ai]
                self.status.sweep_deg = 0.0
                if ai > 0:
                    self.enter(
                        State.RESTEER,
                        f"re-steering module {k} to {cfg.protocol.angles_deg[ai]:g} deg",
                    )
                    for mod in dyn:
                        self.robot.free_steer(mod)
                        self.robot.wheel_free(mod)
                    self.robot.steer_to(k, a)
                    self.settle_steering(k, a)
                    self.wait(cfg.protocol.resteer_time * 0.2)
                else:
                    # dynamic modules to their nominal trailing angle for a CCW spin about C
                    self.enter(State.ALIGN, "aligning the dynamic modules")
                    C = self._pivot(k, a)
                    v = -np.array([-C[1], C[0]])  # v = -omega x C with omega = 1
                    targets = trailing_steering_angle(nominal, v, 1.0)
                    for mod in dyn:
                        self.robot.wheel_free(mod)
                        self.robot.steer_to(mod, float(targets[ids.index(mod)]))
                    self.wait(cfg.protocol.align_time)
                    self.enter(State.FREE, "releasing the dynamic steering")
                    for mod in dyn:
                        self.robot.free_steer(mod)
                m.before_spin(self, k, dyn)
                self.enter(State.SPIN, f"spinning about module {k} ({ai + 1}/{len(angles)})")
                self._spin_wheels(k, dyn, a, torque)
                m.spin(self, k)
                self.enter(State.STOP, "spinning down")
                for mod in dyn:
                    self.robot.wheel_hold(mod)
                self.wait(cfg.protocol.stop_time)
            self.enter(State.RELEASE, f"releasing module {k}")
            self.robot.free_steer(k)
            self.robot.wheel_hold(k)
        m.after_spins(self)
        self.robot.stop_all()
        self.robot.release()
        self.enter(State.SOLVE, "solving")
        m.before_solve(self)
        self._solve()
        if self._abort.is_set():  # nothing moves any more, but nothing is installed either
            if self._stop_reason is not None:
                raise RunFailedError(f"{self._stop_reason} (the result is not installed)")
            raise RunAbortedError("aborted by the operator (the result is not installed)")
        self.enter(State.WRITE, self.write_step)
        with self.committing():  # an abort from here on is refused: the result stands
            self._write()
        with self._lock:
            self.status.progress = 1.0
            self.status.finished = now_iso()
            self.status.elapsed_s = round(self.clock.now() - self._t0, 2)
        self.journal.finish(
            {"state": "DONE", "installed": self.status.installed, "reason": ""}, self.result_doc
        )
        self.enter(State.DONE, "done")

    def _connect(self) -> None:
        """CONNECT (the drives activated, the steering homed), PRECHECK and REST."""
        self.enter(State.CONNECT, "activating the controllers")
        self.robot.activate()
        unhomed = self.robot.unhomed()
        if unhomed:
            self.status.step = f"homing the steering of modules {unhomed}"
            self.changed()
            for mod in unhomed:
                self.robot.start_homing(mod)
            self.wait_until(lambda: not self.robot.unhomed(), motion=False)
        m = self.metrology
        self.enter(State.PRECHECK, f"checking nodes, errors, homing and {m.sensor_name}")
        self._precheck()
        m.come_to_rest(self)

    def _fast_part(self, angle: float) -> None:
        """PROBE: every module locked at ``angle`` and turned
        :data:`~swpc_hw.calibration.commission.probes.PRECHECK_TURN` about by its driver
        (:mod:`services.runs.probing`); a robot that disagrees with its config is refused
        before the first spin, the axis named
        (:func:`~swpc_hw.calibration.commission.analysis.precheck_problems`)."""
        ids = self.config.nominal.ids
        prober = Prober(self)
        probes = []
        for m in ids:
            rolled = prober.pivot_probe(m, angle, driver_of(ids, m), PRECHECK_TURN, retry=False)
            if rolled is None:  # a steering moved the pinned robot
                mv = prober.steer_moves[-1]
                how = (
                    f"moved the robot {1000 * mv.moved:.0f} mm" if mv.moved > mv.budget
                    else f"turned the robot {math.degrees(mv.turned):.1f} deg"
                )  # fmt: skip
                raise RunFailedError(
                    f"refused before the first spin: module {mv.module}'s steering {how} "
                    "with the robot pinned: it turns a wheel; swpc commission names the fix"
                )
            probes.extend(rolled)
            self.robot.free_steer(m)
            self.robot.wheel_hold(m)
        problems = precheck_problems(self.config.nominal, probes, self.metrology.name == "mocap")
        turned = round(math.degrees(prober.largest_turn), 2)
        level = logging.ERROR if problems else logging.INFO
        self.event(level, "run.precheck", ok=not problems, largest_turn_deg=turned)
        if problems:
            raise RunFailedError(
                "refused before the first spin: the robot does not match its config: "
                + "; ".join(problems) + " (swpc commission names each fix)"
            )

    def run_problems(self) -> list[str]:
        """What makes this run impossible, before any motion (its metrology's view of the
        config)."""
        return self.metrology.run_problems(self.config)

    # ------------------------------------------------------------------ the steps
    def _precheck(self) -> None:
        deadline = self.clock.now() + min(5.0, self.config.limits.step_timeout)
        while True:
            problems = self.robot.problems() + self.metrology.precheck()
            if not problems:
                return
            if self.clock.now() > deadline:
                raise RunFailedError("precheck failed: " + "; ".join(problems))
            self.check(False, None)
            self.clock.poll(0.01)

    def settle_steering(self, module: int, angle: float, tol: float = math.radians(0.5)) -> None:
        """Wait until module's steering is within ``tol`` of ``angle`` (step timeout)."""
        self.wait_until(
            lambda: bool(abs(wrap_angle(self.robot.steering(module) - angle)) < tol),
            motion=True,
        )

    def dataset(self) -> Dataset:
        """The run's recorded data: its dataset directory, as written (the run's clock)."""
        return load_dataset(self.run_dir / "dataset")

    def _solve(self) -> None:
        run_dir = self.journal.close_dataset(self.metrology.sensor, self.robot)
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
            keep_backups=self.keep_backups,
        )
        self.backup = out.backup
        if out.installed:
            self.event(
                logging.INFO,
                "run.install",
                path=str(self.kinematics_path),
                backup=None if out.backup is None else str(out.backup),
                within_tolerance=out.within,
            )
        else:
            self.event(
                logging.WARNING if not out.within else logging.INFO,
                "run.not_installed",
                within_tolerance=out.within,
                install=self.install,
                result=str(self.run_dir / "kinematics.yaml"),
                held=out.held,
            )
        self.status.installed = out.installed
        self.result_doc = out.document
