"""A calibration without motion capture: the robot's encoders, its gyro and a tape measure.

:class:`ImuCalibrationRun` walks the protocol of :mod:`services.runs.protocol` with the
gyro (:mod:`services.sensors.gyro`) where that one reads the poses, and adds what the
IMU solver needs (docs/imu.md, and the simulated protocol
:data:`simulators.datagen_imu.IMU_PROTOCOL`)::

    PENDING -> CONNECT -> PRECHECK -> REST -> LOCK -> ALIGN -> FREE -> STILL -> SPIN -> STOP
    STOP    -> RESTEER -> STILL -> SPIN ... | RELEASE
    RELEASE -> LOCK (next module) | STEER | STILL (no drive)
    STEER   -> MARK -> DRIVE -> MEASURE -> SOLVE -> WRITE -> DONE
    STILL   -> SOLVE (without a drive: the rest after the last spin)

* PRECHECK: nodes, errors, homing and a live gyro whose stamps are this host's time.
* REST: every wheel braked until the gyro and the wheel encoders show the robot still
  (over :data:`~services.runs.pose_motion.REST_WINDOW`).
* STILL: the dynamic wheels braked and the robot held still for ``protocol.rest_time``
  (still by the gyro and the encoders, else longer): the gyro's bias before every spin,
  measured again by the solver from the encoders' stillness.
* SPIN: as with motion capture; the sweep and the yaw-rate limit come from the gyro's
  rate minus the bias of the STILL before (:class:`~services.runs.gyro_motion.GyroYaw`).
* STEER: every module steered to the straight drive's direction (the wheel trailing its
  axis for a drive along ``protocol.drive_heading_deg`` in R, nominal ``beta``), wheels
  braked.
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

import logging
import math
import threading
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from services.config.robot import RobotConfig
from services.runs.gyro_motion import GyroYaw, RecentRows, stillness, wheel_speed, wheel_travel
from services.runs.journal import SampleSource
from services.runs.pose_motion import REST_WINDOW, SpinWindow
from services.runs.protocol import CalibrationRun
from services.runs.state import RunFailedError, State
from services.sensors.gyro import GyroIngest
from services.sensors.mocap import MocapIngest
from swpc_hw.dataset import Segment
from swpc_hw.drives.robot_io import RobotIO
from swpc_hw.errors import DatasetError
from swpc_hw.model import wrap_angle
from swpc_hw.references import (
    AxisDistance,
    Reference,
    StraightDrive,
    WheelRadius,
    parse_reference,
    reference_label,
)

COAST_LIMIT = 0.05
"""m/s: the drive's wheels are braked once they roll slower than this after the torque."""


# --------------------------------------------------------------------------- references


def parse_references(
    entries: Sequence[dict[str, Any]],
    ids: Sequence[int],
    drive: tuple[float, float] | None = None,
    where: str = "references",
) -> list[Reference]:
    """The request's references as :mod:`swpc_hw.references` entries.  A ``straight_drive``
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


# --------------------------------------------------------------------------- the run


class ImuCalibrationRun(CalibrationRun):
    """One calibration without motion capture (module docstring)."""

    metrology = "imu"
    sensor_name = "gyro"

    def __init__(
        self,
        robot: RobotIO,
        mocap: MocapIngest,
        imu: GyroIngest,
        config: RobotConfig,
        *,
        references: Sequence[Reference] = (),
        **kwargs: Any,
    ) -> None:
        self.imu = imu
        super().__init__(robot, mocap, config, **kwargs)
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
        keep = max(config.protocol.rest_time, REST_WINDOW) + 2.0
        self._gyro = RecentRows(2, keep)
        self._wheels = {m: RecentRows(3, keep) for m in ids}
        self._radius = dict(zip(ids, config.nominal.arrays().r.tolist(), strict=True))

    # ------------------------------------------------------------ the metrology
    @property
    def sensor(self) -> SampleSource:
        return self.imu

    def _sensor_problem(self) -> str | None:
        if self.imu.is_stale():
            return (
                f"gyro stale: no sample for {self.imu.age():.3f} s "
                f"(limit {self.imu.stale_after:.3f} s)"
            )
        return None

    def _sensor_precheck(self) -> list[str]:
        problems = []
        if self.imu.is_stale():
            problems.append(f"gyro not live (last sample {self.imu.age():.2f} s ago)")
        clock = self.imu.clock_problem()
        if clock is not None:
            problems.append(clock)
        return problems

    def _run_problems(self) -> list[str]:
        return self.config.run_problems("imu") + reference_problems(self.config, self.references)

    def _start_fields(self) -> dict[str, Any]:
        return {
            **super()._start_fields(),
            "references": ",".join(reference_label(r) for r in self.references),
        }

    # ------------------------------------------------------------ the operator
    @property
    def waits_for(self) -> str | None:
        """``"continue"`` in MARK, ``"references"`` in MEASURE (what the operator owes)."""
        if self.status.state is State.MARK and not self._marked.is_set():
            return "continue"
        if self.status.state is State.MEASURE and not self._measured.is_set():
            return "references"
        return None

    def mark_done(self) -> None:
        """The operator has marked the floor (MARK); ValueError in another state.  Called
        from another thread (an HTTP request): the run's thread logs and acts on it."""
        with self._answers:
            if self.waits_for != "continue":
                done = " (already continued)" if self._marked.is_set() else ""
                raise ValueError(
                    f"calibration {self.id} is {self.status.state}{done}: nothing to continue"
                )
            self._marked.set()

    def add_references(self, entries: Sequence[dict[str, Any]]) -> list[Reference]:
        """The operator's measurements (MEASURE): parsed with the drive's times, at least
        the straight drive.  ValueError in another state, DatasetError for an entry.
        Called from another thread (an HTTP request), as :meth:`mark_done`."""
        with self._answers:
            if self.waits_for != "references":
                if self._measured.is_set():
                    raise ValueError(
                        f"calibration {self.id} already has the drive's measurement"
                    )
                raise ValueError(
                    f"calibration {self.id} is {self.status.state}: it takes references in "
                    "MEASURE"
                )
            refs = parse_references(entries, self.config.nominal.ids, self.drive)
            if not any(isinstance(r, StraightDrive) for r in refs):
                raise DatasetError("references: the straight_drive's measurement is missing")
            self._measured_refs = refs
            self._measured.set()
        return refs

    def _wait_operator(self, done: threading.Event, what: str) -> None:
        end = self.clock.now() + self.config.protocol.operator_timeout
        while not done.is_set():
            self._check(False, None)
            if self.clock.now() > end:
                raise RunFailedError(
                    f"operator timeout: no {what} within "
                    f"{self.config.protocol.operator_timeout:g} s"
                )
            self.clock.sleep(self._poll)

    # ------------------------------------------------------------ the sensors
    def _read(self) -> None:
        """The gyro's and the encoders' new rows into the recent stores."""
        g = self._gyro
        rows, g.cursor = self.imu.samples_since(g.cursor, self.clock.now() - g.keep)
        g.add(rows[:, [2, 3]])
        for m, w in self._wheels.items():
            enc, w.cursor = self.robot.encoder_rows(m, w.cursor, self.clock.now() - w.keep)
            w.add(enc)

    def _stillness(self, window: float) -> Any:
        now = self.clock.now()
        return stillness(
            self._gyro.rows,
            {m: w.rows for m, w in self._wheels.items()},
            self._radius,
            now - window,
            now,
        )

    def _until_still(self, window: float, step: str) -> tuple[float, float, float]:
        """Wait until the last ``window`` s show the robot still (gyro and encoders, the
        limits' rest rates); returns the window and the gyro's mean over it."""
        lim = self.config.limits
        t0 = self.clock.now()
        deadline = self._deadline()
        while True:
            self._check(True, deadline)
            self._read()
            now = self.clock.now()
            if now - t0 >= window:
                st = self._stillness(window)
                if st.still(lim.rest_yaw_rate, lim.rest_speed):
                    return now - window, now, st.rate
                if st.covered:
                    with self._lock:
                        self.status.step = (
                            f"{step} (gyro {st.rate:.3f} rad/s, wheels {st.speed:.3f} m/s)"
                        )
            self.clock.sleep(self._poll)

    def _hold_still(self, what: str) -> tuple[float, float]:
        """STILL-like rest of ``protocol.rest_time`` (kept, its gyro mean the bias)."""
        a, b, self._bias = self._until_still(self.config.protocol.rest_time, what)
        self.rests.append((a, b))
        self._event(logging.INFO, "run.rest", start=a, end=b, gyro_mean=self._bias)
        return a, b

    # ------------------------------------------------------------ the steps
    def _come_to_rest(self) -> None:
        step = "braking every wheel: waiting for the robot to come to rest"
        self._enter(State.REST, step)
        for m in self.config.nominal.ids:
            self.robot.wheel_hold(m)
        self._until_still(REST_WINDOW, step)

    def _before_spin(self, k: int, dyn: list[int]) -> None:
        rest = self.config.protocol.rest_time
        step = f"holding still {rest:g} s for the gyro's bias"
        self._enter(State.STILL, step)
        for m in dyn:
            self.robot.wheel_hold(m)
        self._hold_still(step)  # SPIN's torque releases the brakes

    def _spin(self, k: int, done: int, total: int) -> None:
        proto, limits = self.config.protocol, self.config.limits
        sweep_target = math.radians(proto.sweep_deg)
        self._read()
        last = self._gyro.last
        assert last is not None  # the STILL before had samples
        yaw = GyroYaw(self._bias)
        yaw.add(float(last[0]), float(last[1]))
        spin = SpinWindow(self.clock.now(), proto.settle_time, float(last[0]), 0.0)
        seen = float(last[0])
        deadline = self._deadline()
        while True:
            self._check(True, deadline)
            self._read()
            rows = self._gyro.rows
            for t, wz in rows[rows[:, 0] > seen].tolist():
                spin.add(t, yaw.add(t, wz))
                seen = t
            if spin.rate is not None and abs(spin.rate) > limits.max_yaw_rate:
                raise RunFailedError(
                    f"yaw rate {spin.rate:.2f} rad/s exceeds the limit {limits.max_yaw_rate:g}"
                )
            if spin.start is not None:
                sweep = spin.sweep
                with self._lock:
                    self.status.sweep_deg = math.degrees(sweep)
                    self.status.progress = min((done + min(sweep / sweep_target, 1.0)) / total, 1.0)
                if sweep >= sweep_target:
                    self._segment(Segment(k, spin.start, seen), sweep)
                    return
            self.clock.sleep(self._poll)

    def _segment(self, seg: Segment, sweep: float) -> None:
        self.segments.append(seg)
        self.status.segments = len(self.segments)
        self.journal.add_segment(seg)
        self._event(
            logging.INFO,
            "run.segment",
            module=seg.static_module,
            start=seg.start,
            end=seg.end,
            sweep_deg=math.degrees(sweep),
        )

    def _after_spins(self) -> None:
        if self.config.protocol.drive_length > 0:
            self._steer()
            self._mark()
            self._drive()
            self._measure()
        else:
            step = f"holding still {self.config.protocol.rest_time:g} s after the last spin"
            self._enter(State.STILL, step)
            for m in self.config.nominal.ids:
                self.robot.wheel_hold(m)
            self._hold_still(step)
            self.robot.stop_all()
            self.robot.release()
            self._close_dataset()

    def _steer(self) -> None:
        p = self.config.protocol
        nominal = self.config.nominal
        heading = math.radians(p.drive_heading_deg)
        self._enter(
            State.STEER,
            f"steering every module for a straight drive along {p.drive_heading_deg:g} deg "
            "in R, wheels braked",
        )
        targets = {}
        for m, beta in zip(nominal.ids, nominal.arrays().beta.tolist(), strict=True):
            # the wheel trailing its axis: u = -(cos h, sin h), the contact moves along -u
            targets[m] = float(wrap_angle(heading + math.pi - beta))
            self.robot.wheel_hold(m)
            self.robot.steer_to(m, targets[m])
        tol = math.radians(0.5)
        self._wait_until(
            lambda: all(
                abs(float(wrap_angle(self.robot.steering(m) - a))) < tol for m, a in targets.items()
            ),
            motion=True,
        )

    def _mark(self) -> None:
        first = self.config.nominal.ids[0]
        self._enter(
            State.MARK,
            f"mark the floor under module {first}'s steering axis, then continue "
            f"(POST /calibrations/{self.id}/continue); the robot holds still, wheels braked, "
            "and drives off once you continue",
        )
        self._wait_operator(self._marked, "floor mark before the straight drive")
        self._event(logging.INFO, "run.marked")

    def _drive(self) -> None:
        p, lim = self.config.protocol, self.config.limits
        ids = self.config.nominal.ids
        length = p.drive_length
        self._enter(State.DRIVE, f"holding still {p.rest_time:g} s before the straight drive")
        a0, b0 = self._hold_still(f"holding still {p.rest_time:g} s before the straight drive")
        start = 0.5 * (a0 + b0)
        psi0 = {m: float(w.rows[-1, 2]) for m, w in self._wheels.items()}
        with self._lock:
            self.status.step = f"driving {length:g} m straight"
            self.status.drive_m = 0.0
        self._changed()
        for m in ids:
            self.robot.wheel_torque(m, -lim.drive_torque)
        self._roll(lambda: self._travel(psi0) >= length, psi0, "driving")
        for m in ids:  # torque off: the wheels roll on until the robot has coasted down
            self.robot.wheel_free(m)
        self._roll(lambda: self._speed() <= COAST_LIMIT, psi0, "coasting to a stop")
        for m in ids:
            self.robot.wheel_hold(m)
        step = f"holding still {p.rest_time:g} s after the straight drive"
        with self._lock:
            self.status.step = step
        a1, b1 = self._hold_still(step)
        self.drive = (round(start, 6), round(0.5 * (a1 + b1), 6))
        self._event(
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

    def _speed(self, window: float = 0.2) -> float:
        now = self.clock.now()
        return wheel_speed(
            {m: w.between(now - window, now) for m, w in self._wheels.items()}, self._radius
        )

    def _roll(self, done: Callable[[], bool], psi0: dict[int, float], what: str) -> None:
        """Poll the moving robot until ``done()``: its speed and yaw rate within limits."""
        lim = self.config.limits
        deadline = self._deadline()
        while True:
            self._check(True, deadline)
            self._read()
            speed = self._speed()
            if speed > lim.max_drive_speed:
                raise RunFailedError(
                    f"drive speed {speed:.2f} m/s exceeds limits.max_drive_speed "
                    f"{lim.max_drive_speed:g}"
                )
            now = self.clock.now()
            g = self._gyro.between(now - 0.2, now)
            rate = float(np.mean(g[:, 1])) - self._bias if g.shape[0] else 0.0
            if abs(rate) > lim.max_yaw_rate:
                raise RunFailedError(
                    f"yaw rate {rate:.2f} rad/s exceeds the limit {lim.max_yaw_rate:g} while "
                    f"{what}"
                )
            with self._lock:
                self.status.drive_m = self._travel(psi0)
            if done():
                return
            self.clock.sleep(self._poll)

    def _measure(self) -> None:
        self.robot.stop_all()  # nothing moves while someone measures next to the robot
        self.robot.release()
        self._close_dataset()
        first = self.config.nominal.ids[0]
        self._enter(
            State.MEASURE,
            f"measure the distance module {first}'s steering axis travelled between the two "
            f"floor marks (the one you made and one under the axis now), then POST it with "
            f"its std dev to /calibrations/{self.id}/references",
        )
        self._wait_operator(self._measured, "tape measurement of the straight drive")
        self.references += self._measured_refs
        self._event(
            logging.INFO,
            "run.references",
            references=",".join(
                f"{reference_label(r)}={r.value:.6f}" for r in self._measured_refs
            ),
        )
        self.journal.save_references(self.references)

    def _close_dataset(self) -> None:
        """The recorded samples closed, with the references known so far (a run that
        ends later keeps a dataset that ``swpc solve`` reads and judges)."""
        self._record(force=True)  # the last samples, counted in the status
        self.journal.close_dataset(self.sensor, self.robot)
        self.journal.save_references(self.references)

    def _solve(self) -> None:
        self._close_dataset()
        super()._solve()
