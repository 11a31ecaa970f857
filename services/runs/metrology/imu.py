"""The IMU as a run's metrology: the robot's gyro, its wheel encoders and a tape measure.

:class:`ImuMetrology` is the metrology (:mod:`services.runs.metrology.base`) of a calibration
without motion capture: the protocol of :mod:`services.runs.protocol` reads the gyro
(:mod:`services.sensors.gyro`) where it would read the poses, and gains the steps the IMU
solver needs (docs/imu.md, and the simulated protocol
:data:`simulators.offline.datagen_imu.IMU_PROTOCOL`)::

    PENDING -> CONNECT -> PRECHECK -> REST -> LOCK -> ALIGN -> FREE -> STILL -> SPIN -> STOP
    STOP    -> RESTEER -> STILL -> SPIN ... | RELEASE
    RELEASE -> LOCK (next module) | STILL
    STILL   -> STEER -> MARK -> DRIVE -> MEASURE -> SOLVE -> WRITE -> DONE
    STILL   -> SOLVE (without a drive: the rest after the last spin)

* PRECHECK: nodes, errors, homing and a live gyro whose stamps are this host's time.
* REST: every wheel braked until the gyro and the wheel encoders show the robot still
  (over :data:`~services.runs.metrology.pose_motion.REST_WINDOW`).
* STILL: the dynamic wheels braked and the robot held still for ``protocol.rest_time``
  (still by the gyro and the encoders, else longer): the gyro's bias before every spin,
  measured again by the solver from the encoders' stillness.
* SPIN: as with motion capture; the sweep and the yaw-rate limit come from the gyro's
  rate minus the bias of the STILL before (:class:`~services.runs.metrology.gyro_motion.GyroYaw`).
* STILL, then STEER: still for ``rest_time`` (the rest after the last spin), the spins solved alone
  (:func:`swpc_hw.calibration.gyro.solver.solve_spins`) for every module's ``beta``, then
  every module steered to the straight drive's direction by them (the wheel trailing its
  axis for a drive along ``protocol.drive_heading_deg`` in R), wheels braked.  Steered by
  the nominal ``beta`` a robot with homing errors of a few degrees drives with its
  wheels fighting and turns (1.2 deg over 1 m with +-3 deg in the simulator); the
  nominal ones only when the spins cannot be solved (an event says why).
* MARK: the robot holds still (wheels braked, steering held) until the operator has
  marked the floor under the first module's steering axis and said so
  (``POST /calibrations/{id}/continue``); ``protocol.operator_timeout``.
* DRIVE: still for ``rest_time`` (the drive's start: the middle of that rest), every
  wheel at ``-limits.drive_torque`` (a torque, as in the spins: wheels of unequal true
  radii commanded one velocity would fight and slip, the encoders would not measure the
  rolling) until the wheels have rolled ``protocol.drive_length`` (nominal radii, never
  faster than ``limits.max_drive_speed``, never turning faster than
  ``limits.max_yaw_rate``), coasting to rest, braked, still again for ``rest_time`` (the
  end).  Steering held throughout.
* MEASURE: motion stopped and released, the dataset closed; the run waits for the tape
  measurement of the distance the first module's steering axis travelled between the
  two floor marks (``POST /calibrations/{id}/references``); ``protocol.operator_timeout``.
* SOLVE: ``imu.csv``, the encoders, the segments and ``references.yaml`` (the references
  given at the start plus the drive's) solved by the IMU solver, exactly as
  ``swpc solve`` does; the result is in the ``design-fit`` frame.

References given at the start are checked before any motion
(:func:`reference_problems`): the length scale needs an ``axis_distance``, the radii a
straight drive (``protocol.drive_length > 0``) or a ``wheel_radius``.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from services.config.robot import RobotConfig
from services.runs.journal import SampleSource
from services.runs.metrology.base import RunSteps
from services.runs.metrology.direction import DirectionWatch
from services.runs.metrology.gyro_motion import (
    GyroYaw,
    RecentRows,
    stillness,
    wheel_speed,
    wheel_travel,
)
from services.runs.metrology.mocap import sweep_reached
from services.runs.metrology.pose_motion import REST_WINDOW, SpinWindow
from services.runs.state import RunFailedError, State
from services.sensors.gyro import GyroIngest
from swpc_hw.clock import SimClock
from swpc_hw.errors import CalibrationError, DatasetError
from swpc_hw.files.dataset import Segment
from swpc_hw.files.references import (
    AxisDistance,
    Reference,
    StraightDrive,
    WheelRadius,
    parse_reference,
    reference_label,
)
from swpc_hw.robot.model import wrap_angle

COAST_LIMIT = 0.05
"""m/s: the drive's wheels are braked once they roll slower than this after the torque."""
OPERATOR_POLL = 0.05
"""Host seconds between two looks at an operator's answer while simulated time stands."""


# --------------------------------------------------------------------------- references


def parse_references(
    entries: Sequence[dict[str, Any]],
    ids: Sequence[int],
    drive: tuple[float, float] | None = None,
    where: str = "references",
) -> list[Reference]:
    """The request's references as :mod:`swpc_hw.files.references` entries.  A ``straight_drive``
    has no times here: the run's ``drive`` ``(start, end)`` are its times, and it is
    refused without one.  :class:`~swpc_hw.errors.DatasetError` names the entry."""
    out: list[Reference] = []
    for i, e in enumerate(entries):
        doc = dict(e)
        here = f"{where}[{i}]"
        if doc.get("kind") == "straight_drive":
            if "start" in doc or "end" in doc:
                raise DatasetError(
                    f"{here} (straight_drive): no start or end: the run knows when it drove"
                )
            if drive is None:
                raise DatasetError(
                    f"{here} (straight_drive): the run has not driven yet: give it after the "
                    "drive (POST /calibrations/{id}/references, in MEASURE)"
                )
            doc["start"], doc["end"] = drive
        out.append(parse_reference(doc, here, set(ids)))
    return out


def reference_problems(config: RobotConfig, refs: Sequence[Reference]) -> list[str]:
    """Why the references given at the start cannot fix what the robot's own sensors
    cannot (empty when they can): the layout's length scale and the wheels' radii."""
    out = []
    if not any(isinstance(r, AxisDistance) for r in refs):
        out.append(
            "no axis_distance: nothing fixes the length scale of the module layout (measure "
            "at least one distance between two steering axes; the sides and diagonals best)"
        )
    if config.protocol.drive_length <= 0 and not any(isinstance(r, WheelRadius) for r in refs):
        out.append(
            "protocol.drive_length is 0 and no wheel_radius: nothing fixes the wheels' "
            "radius (drive straight, or give a wheel_radius)"
        )
    return out


# --------------------------------------------------------------------------- the metrology


class ImuMetrology:
    """The gyro, the encoders and a tape (module docstring): one per run."""

    name = "imu"
    sensor_name = "gyro"
    samples_field = "gyro_samples"

    def __init__(
        self, gyro: GyroIngest, config: RobotConfig, references: Sequence[Reference] = ()
    ) -> None:
        self.gyro = gyro
        self.key = config.imu_key
        self._resets = gyro.counters.clock_resets  # at the run's start
        self.references: list[Reference] = list(references)
        self.drive: tuple[float, float] | None = None
        """The straight drive's ``(start, end)`` on the run's clock (the middles of the
        rests before and after it), once driven."""
        self.rests: list[tuple[float, float]] = []
        self._bias = 0.0
        self._marked = threading.Event()
        self._measured = threading.Event()
        self._measured_refs: list[Reference] = []
        self._answers = threading.Lock()  # one operator answer at a time
        ids = config.nominal.ids
        self._ids = ids
        self._directions: set[int] = set()  # locked modules whose spin wheels were judged
        keep = max(config.protocol.rest_time, REST_WINDOW) + 2.0
        self._gyro = RecentRows(2, keep)
        self._wheels = {m: RecentRows(3, keep) for m in ids}
        self._radius = dict(zip(ids, config.nominal.arrays().r.tolist(), strict=True))

    # ------------------------------------------------------------ the sensor
    @property
    def sensor(self) -> SampleSource:
        return self.gyro

    def run_problems(self, config: RobotConfig) -> list[str]:
        return config.run_problems(self.name) + reference_problems(config, self.references)

    def start_fields(self) -> dict[str, Any]:
        return {"references": ",".join(reference_label(r) for r in self.references)}

    def precheck(self) -> list[str]:
        problems = []
        jump = self.gyro.clock_jump(self._resets, "gyro", self.key)
        if jump is not None:
            problems.append(jump)
        if self.gyro.is_stale():
            problems.append(f"gyro not live (last sample {self.gyro.age():.2f} s ago)")
        clock = self.gyro.clock_problem()
        if clock is not None:
            problems.append(clock)
        return problems

    def problem(self) -> str | None:
        jump = self.gyro.clock_jump(self._resets, "gyro", self.key)
        if jump is not None:
            return jump
        if self.gyro.is_stale():
            return (
                f"gyro stale: no sample for {self.gyro.age():.3f} s "
                f"(limit {self.gyro.stale_after:.3f} s)"
            )
        return None

    @property
    def bias(self) -> float:
        """rad/s: the gyro's bias, its mean over the last rest (0 before one)."""
        return self._bias

    # ------------------------------------------------------------ the operator
    def waits_for(self, state: State) -> str | None:
        """``"continue"`` in MARK, ``"references"`` in MEASURE: what the operator owes a
        run in ``state``."""
        if state is State.MARK and not self._marked.is_set():
            return "continue"
        if state is State.MEASURE and not self._measured.is_set():
            return "references"
        return None

    def answer(
        self, run_id: str, state: State, what: str, entries: Sequence[dict[str, Any]] = ()
    ) -> None:
        """The operator's answer to a run in ``state`` (from another thread: an HTTP
        request; the run's thread logs and acts on it): ``continue`` once the floor is
        marked (MARK), ``references`` with the tape measurements (MEASURE: parsed with the
        drive's times, at least the straight drive).  ValueError when the run does not
        wait for it, DatasetError for an entry."""
        with self._answers:
            if what == "continue" and self.waits_for(state) == "continue":
                self._marked.set()
                return
            if what == "references" and self.waits_for(state) == "references":
                refs = parse_references(entries, self._ids, self.drive)
                if not any(isinstance(r, StraightDrive) for r in refs):
                    raise DatasetError("references: the straight_drive's measurement is missing")
                self._measured_refs = refs
                self._measured.set()
                return
            if what == "continue":
                done = " (already continued)" if self._marked.is_set() else ""
                raise ValueError(f"calibration {run_id} is {state}{done}: nothing to continue")
            if self._measured.is_set():
                raise ValueError(f"calibration {run_id} already has the drive's measurement")
            raise ValueError(f"calibration {run_id} is {state}: it takes references in MEASURE")

    def _wait_operator(self, run: RunSteps, done: threading.Event, what: str) -> None:
        """Wait for the operator's answer, ``protocol.operator_timeout`` of robot time.

        Against the in-process simulator (a :class:`~swpc_hw.clock.SimClock`) the run
        waits without yielding to the clock, so simulated time stands still until the
        answer: it arrives at the simulated instant the run asked for it, whenever the
        person (or script) gives it, and a run is reproducible bit for bit; the timeout
        then counts host seconds."""
        run.set_status(waits_for=self.waits_for(run.status.state))
        run.changed()
        try:
            self._await_answer(run, done, what)
        finally:
            run.set_status(waits_for=None)

    def _await_answer(self, run: RunSteps, done: threading.Event, what: str) -> None:
        timeout = run.config.protocol.operator_timeout
        if isinstance(run.clock, SimClock):
            end_host = time.monotonic() + timeout
            while not done.wait(OPERATOR_POLL):
                run.check(False, None)
                if time.monotonic() > end_host:
                    raise RunFailedError(
                        f"operator timeout: no {what} within {timeout:g} s (host time: the "
                        "simulated robot waits with its time stopped)"
                    )
            return
        end = run.clock.now() + timeout
        while not done.is_set():
            run.check(False, None)
            if run.clock.now() > end:
                raise RunFailedError(f"operator timeout: no {what} within {timeout:g} s")
            run.clock.poll(run.poll)

    # ------------------------------------------------------------ the sensors
    def _read(self, run: RunSteps) -> None:
        """The gyro's and the encoders' new rows into the recent stores."""
        g = self._gyro
        now = run.clock.now()
        rows, g.cursor = self.gyro.samples_since(g.cursor, now - g.keep)
        g.add(rows[:, [2, 3]])
        for m, w in self._wheels.items():
            enc, w.cursor = run.robot.encoder_rows(m, w.cursor, run.clock.now() - w.keep)
            w.add(enc)

    def _until_still(self, run: RunSteps, window: float, step: str) -> tuple[float, float, float]:
        """Wait until the last ``window`` s show the robot still (gyro and encoders, the
        limits' rest rates); returns the window and the gyro's mean over it."""
        lim = run.config.limits
        t0 = run.clock.now()
        deadline = run.deadline()
        while True:
            run.check(True, deadline)
            self._read(run)
            now = run.clock.now()
            if now - t0 >= window:
                st = stillness(
                    self._gyro.rows,
                    {m: w.rows for m, w in self._wheels.items()},
                    self._radius,
                    now - window,
                    now,
                )
                if st.still(lim.rest_yaw_rate, lim.rest_speed):
                    return now - window, now, st.rate
                if st.covered:
                    run.set_status(
                        step=f"{step} (gyro {st.rate:.3f} rad/s, wheels {st.speed:.3f} m/s)"
                    )
            run.clock.poll(run.poll)

    def _hold_still(self, run: RunSteps, what: str) -> tuple[float, float]:
        """STILL-like rest of ``protocol.rest_time`` (kept, its gyro mean the bias)."""
        a, b, self._bias = self._until_still(run, run.config.protocol.rest_time, what)
        self.rests.append((a, b))
        run.event(logging.INFO, "run.rest", start=a, end=b, gyro_mean=self._bias)
        return a, b

    # ------------------------------------------------------------ the steps
    def come_to_rest(self, run: RunSteps) -> None:
        step = "braking every wheel: waiting for the robot to come to rest"
        run.enter(State.REST, step)
        for m in self._ids:
            run.robot.wheel_hold(m)
        # the gyro's mean at rest: its bias for the fast part's turns (a STILL's after)
        self._bias = self._until_still(run, REST_WINDOW, step)[2]

    def before_spin(self, run: RunSteps, k: int, dyn: list[int]) -> None:
        rest = run.config.protocol.rest_time
        step = f"holding still {rest:g} s for the gyro's bias"
        run.enter(State.STILL, step)
        for m in dyn:
            run.robot.wheel_hold(m)
        self._hold_still(run, step)  # SPIN's torque releases the brakes

    def spin(self, run: RunSteps, k: int) -> None:
        self._read(run)
        last = self._gyro.last
        assert last is not None  # the STILL before had samples
        yaw = GyroYaw(self._bias)
        yaw.add(float(last[0]), float(last[1]))
        spin = SpinWindow(run.clock.now(), run.config.protocol.settle_time, float(last[0]), 0.0)
        seen = float(last[0])
        # the wheels against the turn the gyro integrates (first spin about each module)
        direction = DirectionWatch(run, k, seen, 0.0)
        direction.decided = k in self._directions
        self._directions.add(k)
        turned = 0.0
        deadline = run.deadline()
        while True:
            run.check(True, deadline)
            self._read(run)
            rows = self._gyro.rows
            for t, wz in rows[rows[:, 0] > seen].tolist():
                turned = yaw.add(t, wz)
                spin.add(t, turned)
                seen = t
            direction.update(turned, seen)
            sweep = sweep_reached(run, spin)
            if sweep is not None:
                assert spin.start is not None
                run.add_segment(Segment(k, spin.start, seen), sweep)
                return
            run.clock.poll(run.poll)

    def after_spins(self, run: RunSteps) -> None:
        if run.config.protocol.drive_length > 0:
            self._steer(run)
            self._mark(run)
            self._drive(run)
            self._measure(run)
        else:
            step = f"holding still {run.config.protocol.rest_time:g} s after the last spin"
            run.enter(State.STILL, step)
            for m in self._ids:
                run.robot.wheel_hold(m)
            self._hold_still(run, step)
            run.robot.stop_all()
            run.robot.release()
            self._close_dataset(run)

    def _steer(self, run: RunSteps) -> None:
        p = run.config.protocol
        heading = math.radians(p.drive_heading_deg)
        step = f"holding still {p.rest_time:g} s after the last spin"
        run.enter(State.STILL, step)
        for m in self._ids:
            run.robot.wheel_hold(m)
        self._hold_still(run, step)  # the rest after the last spin, which its solve needs
        betas, how = self._spin_betas(run)
        run.enter(
            State.STEER,
            f"steering every module for a straight drive along {p.drive_heading_deg:g} deg "
            f"in R by the {how} betas, wheels braked",
        )
        targets = {}
        for m, beta in zip(self._ids, betas, strict=True):
            # the wheel trailing its axis: u = -(cos h, sin h), the contact moves along -u
            targets[m] = float(wrap_angle(heading + math.pi - beta))
            run.robot.steer_to(m, targets[m])
        tol = math.radians(0.5)
        run.wait_until(
            lambda: all(
                abs(float(wrap_angle(run.robot.steering(m) - a))) < tol
                for m, a in targets.items()
            ),
            motion=True,
        )

    def _spin_betas(self, run: RunSteps) -> tuple[list[float], str]:
        """Every module's ``beta`` as the spins just recorded say
        (:func:`swpc_hw.calibration.gyro.solver.solve_spins`: their differences to ~1 mdeg,
        all that keeps the wheels of a drive parallel), and ``"measured"``; the nominal
        ones and ``"nominal"`` when the spins cannot be solved (the reason an event: the
        final solve will judge the same data)."""
        from swpc_hw.calibration.gyro.solver import solve_spins

        run.record(force=True)
        try:
            ds = dataclasses.replace(run.dataset(), references=list(self.references))
            res = solve_spins(ds, source="the spins")
        except (CalibrationError, DatasetError) as exc:
            run.event(logging.WARNING, "run.steer", betas="nominal", reason=str(exc))
            note = (
                "the straight drive is steered by the nominal betas (the spins could not be "
                f"solved yet: {exc}); a homing error turns it, and a drive that turns too "
                "much is refused"
            )
            run.set_status(notes=[*run.status.notes, note])
            run.changed()
            return run.config.nominal.arrays().beta.tolist(), "nominal"
        betas = res.params.arrays().beta.tolist()
        run.event(
            logging.INFO,
            "run.steer",
            betas="measured",
            beta_deg=",".join(f"{math.degrees(b):.4f}" for b in betas),
        )
        return betas, "measured"

    def _mark(self, run: RunSteps) -> None:
        first = self._ids[0]
        run.enter(
            State.MARK,
            f"mark the floor under module {first}'s steering axis, then continue: the robot "
            "holds still, wheels braked, and drives off once you continue",
        )
        self._wait_operator(run, self._marked, "floor mark before the straight drive")
        run.event(logging.INFO, "run.marked")

    def _drive(self, run: RunSteps) -> None:
        p, lim = run.config.protocol, run.config.limits
        length = p.drive_length
        step = f"holding still {p.rest_time:g} s before the straight drive"
        run.enter(State.DRIVE, step)
        a0, b0 = self._hold_still(run, step)
        start = 0.5 * (a0 + b0)
        psi0 = {m: float(w.rows[-1, 2]) for m, w in self._wheels.items()}
        run.set_status(step=f"driving {length:g} m straight", drive_m=0.0)
        run.changed()
        for m in self._ids:
            run.robot.wheel_torque(m, -lim.drive_torque)
        self._roll(run, lambda: self._travel(psi0) >= length, psi0, "driving")
        for m in self._ids:  # torque off: the wheels roll on until the robot has coasted down
            run.robot.wheel_free(m)
        self._roll(run, lambda: self._speed(run) <= COAST_LIMIT, psi0, "coasting to a stop")
        for m in self._ids:
            run.robot.wheel_hold(m)
        step = f"holding still {p.rest_time:g} s after the straight drive"
        run.set_status(step=step)
        a1, b1 = self._hold_still(run, step)
        self.drive = (round(start, 6), round(0.5 * (a1 + b1), 6))
        run.event(
            logging.INFO,
            "run.drive",
            start=self.drive[0],
            end=self.drive[1],
            wheels_m=self._travel(psi0),
        )

    def _travel(self, psi0: dict[int, float]) -> float:
        return wheel_travel(
            psi0, {m: float(w.rows[-1, 2]) for m, w in self._wheels.items()}, self._radius
        )

    def _speed(self, run: RunSteps, window: float = 0.2) -> float:
        now = run.clock.now()
        return wheel_speed(
            {m: w.between(now - window, now) for m, w in self._wheels.items()}, self._radius
        )

    def _roll(
        self, run: RunSteps, done: Callable[[], bool], psi0: dict[int, float], what: str
    ) -> None:
        """Poll the moving robot until ``done()``: its speed and yaw rate within limits."""
        lim = run.config.limits
        deadline = run.deadline()
        while True:
            run.check(True, deadline)
            self._read(run)
            speed = self._speed(run)
            if speed > lim.max_drive_speed:
                raise RunFailedError(
                    f"drive speed {speed:.2f} m/s exceeds limits.max_drive_speed "
                    f"{lim.max_drive_speed:g}"
                )
            now = run.clock.now()
            g = self._gyro.between(now - 0.2, now)
            rate = float(np.mean(g[:, 1])) - self._bias if g.shape[0] else 0.0
            if abs(rate) > lim.max_yaw_rate:
                raise RunFailedError(
                    f"yaw rate {rate:.2f} rad/s exceeds the limit {lim.max_yaw_rate:g} while "
                    f"{what}"
                )
            run.set_status(drive_m=self._travel(psi0))
            if done():
                return
            run.clock.poll(run.poll)

    def _measure(self, run: RunSteps) -> None:
        run.robot.stop_all()  # nothing moves while someone measures next to the robot
        run.robot.release()
        self._close_dataset(run)
        first = self._ids[0]
        run.enter(
            State.MEASURE,
            f"measure the distance module {first}'s steering axis travelled between the two "
            "floor marks (the one you made and one under the axis now), then send it with "
            "its std dev",
        )
        self._wait_operator(run, self._measured, "tape measurement of the straight drive")
        self.references += self._measured_refs
        run.event(
            logging.INFO,
            "run.references",
            references=",".join(
                f"{reference_label(r)}={r.value:.6f}" for r in self._measured_refs
            ),
        )
        run.journal.save_references(self.references)

    def _close_dataset(self, run: RunSteps) -> None:
        """The recorded samples closed, with the references known so far (a run that
        ends later keeps a dataset that ``swpc solve`` reads and judges)."""
        run.record(force=True)  # the last samples, counted in the status
        run.journal.close_dataset(self.gyro, run.robot)
        run.journal.save_references(self.references)

    def before_solve(self, run: RunSteps) -> None:
        self._close_dataset(run)
