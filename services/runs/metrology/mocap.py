"""Motion capture as a run's metrology: the poses say when the robot rests and how far a
spin went (:mod:`services.runs.metrology.base`).

* PRECHECK: the pose stream live and its clock mapped (:meth:`MocapIngest.clock_problem`).
* During motion: a pose stream gone stale fails the run.
* REST: every wheel braked until, over the last :data:`REST_WINDOW` s after the brake
  (robot time), the least-squares speed and yaw rate of the poses
  (:func:`~services.runs.metrology.pose_motion.motion_rates`) are within ``limits.rest_speed`` /
  ``rest_yaw_rate``.
* SPIN: the yaw of the poses, unwrapped, from ``settle_time`` after the torque on
  (:class:`~services.runs.metrology.pose_motion.SpinWindow`); the segment ends once it has swept
  ``sweep_deg``; a yaw rate above ``limits.max_yaw_rate`` fails the run, and so does a
  robot or a trailing wheel turning the other way than commanded
  (:mod:`services.runs.metrology.direction`).  A planned run
  (``plan: auto``) stops sequentially instead (:class:`SequentialSpins`, docs/plan.md):
  every :data:`JUDGE_STEP` of sweep the poses so far are fitted and the forecast
  (:mod:`swpc_hw.calibration.plan.forecast`) says whether the spin may end.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from services.config.robot import RobotConfig
from services.runs.journal import SampleSource
from services.runs.metrology.base import RunSteps
from services.runs.metrology.direction import DirectionWatch
from services.runs.metrology.pose_motion import REST_WINDOW, SpinWindow, motion_rates
from services.runs.state import Forecast, RunFailedError, State
from services.sensors.mocap import MocapIngest
from swpc_hw.calibration.plan.forecast import JUDGE_STEP, Judgement, SpinSoFar, Stopping, so_far
from swpc_hw.files.dataset import Segment
from swpc_hw.robot.model import FloatArray


def within_rate_limit(run: RunSteps, spin: SpinWindow) -> None:
    """A yaw rate above ``limits.max_yaw_rate`` fails the run."""
    limits = run.config.limits
    if spin.rate is not None and abs(spin.rate) > limits.max_yaw_rate:
        raise RunFailedError(
            f"yaw rate {spin.rate:.2f} rad/s exceeds the limit {limits.max_yaw_rate:g}"
        )


def sweep_reached(run: RunSteps, spin: SpinWindow) -> float | None:
    """Judge a spin at a poll: the yaw-rate limit, the sweep so far for the operator; the
    sweep once ``sweep_deg`` is reached (None before).  (The run's progress is its share of
    the plan's robot time: :meth:`services.runs.machine.RunMachine.remaining`.)"""
    target = math.radians(run.config.protocol.sweep_deg)
    within_rate_limit(run, spin)
    if spin.start is None:
        return None
    sweep = spin.sweep
    run.set_status(sweep_deg=math.degrees(sweep))
    return sweep if sweep >= target else None


SPIN_TIME_SHARE = 0.8
"""The share of ``limits.step_timeout`` a planned run's spin may last before it ends
unmet (the run fails at the step timeout: ending the spin keeps its data)."""


def forecast_status(j: Judgement, stopping: Stopping) -> Forecast:
    """What the run's status shows of a judgement."""
    return Forecast(**j.document(stopping.requirement), targets=stopping.requirement.document())


class SequentialSpins:
    """A planned run's spins, each ended by the forecast (module docstring); what the
    spins done gave is kept for the next ones' forecasts."""

    def __init__(self, stopping: Stopping) -> None:
        self.stopping = stopping
        self.done: list[SpinSoFar] = []
        self._judged = -math.inf

    def begin(self) -> None:
        self._judged = -math.inf

    def judge(
        self, run: RunSteps, k: int, spin: SpinWindow, window: Callable[[float], FloatArray]
    ) -> float | None:
        """Judge the spin about module ``k`` at a poll (``window(start)``: the poses ``t, x,
        y, yaw`` since ``start``, read only when a judgement is due): the yaw-rate limit,
        the forecast every :data:`JUDGE_STEP` (the spin may last :data:`SPIN_TIME_SHARE`
        of the step timeout); the sweep once the spin may end (None before)."""
        within_rate_limit(run, spin)
        if spin.start is None:
            return None
        i = len(self.done)
        if i >= len(self.stopping.spins):
            raise RunFailedError(f"spin {i + 1}: the plan has {len(self.stopping.spins)}")
        ids = run.config.nominal.ids
        if ids[self.stopping.spins[i].module] != k:
            raise RunFailedError(
                f"spin {i + 1} locks module {k}; the plan's locks module "
                f"{ids[self.stopping.spins[i].module]}"
            )
        sweep, top = spin.sweep, self.stopping.max_sweep(i)
        planned = self.stopping.spins[i].sweep
        run.set_status(sweep_deg=math.degrees(sweep))
        if sweep - self._judged < JUDGE_STEP and sweep < top:
            return None
        poses = window(spin.start)
        if poses.shape[0] < 10:
            return None
        self._judged = sweep
        rows = np.column_stack([poses[:, 0], poses[:, 1], poses[:, 2], np.unwrap(poses[:, 3])])
        now = so_far(rows, sweep)
        spin_time = run.clock.now() - spin.t_spin
        most = SPIN_TIME_SHARE * run.config.limits.step_timeout
        j = self.stopping.judge([*self.done, now], spin_time, most)
        run.set_status(forecast=forecast_status(j, self.stopping))
        if not j.stop:
            return None
        self.done.append(now)
        level = logging.INFO if j.why == "met" else logging.WARNING
        run.event(
            level, "run.spin_judged", spin=i + 1, module=k, sweep_deg=round(math.degrees(sweep), 1),
            planned_deg=round(math.degrees(planned), 1), ratio=round(j.ratio, 3), why=j.why,
        )  # fmt: skip
        return sweep


class MocapMetrology:
    """The poses of the robot's rigid body R on ``mocap/<robot>/pose`` (module docstring)."""

    name = "mocap"
    sensor_name = "mocap"
    samples_field = "poses"

    def __init__(self, mocap: MocapIngest, key: str, stopping: Stopping | None = None) -> None:
        self.mocap = mocap
        self.key = key
        self.sequential = None if stopping is None else SequentialSpins(stopping)
        """A planned run's sequential stopping (None: every spin sweeps ``sweep_deg``)."""
        self._resets = mocap.counters.clock_resets  # at the run's start
        self._directions: set[int] = set()  # locked modules whose spin direction was judged
        self.drive: tuple[float, float] | None = None  # it never drives straight

    @property
    def sensor(self) -> SampleSource:
        return self.mocap

    def run_problems(self, config: RobotConfig) -> list[str]:
        return config.run_problems(self.name)

    def start_fields(self) -> dict[str, Any]:
        return {} if self.sequential is None else {"stopping": "sequential"}

    def poses(self, start: float) -> FloatArray:
        """The poses ``t, x, y, yaw`` sampled since ``start`` (run clock)."""
        return self.mocap.samples(since_host=start)[:, 2:6]

    def forecast(self) -> Forecast | None:
        """The plan's forecast before any spin (a planned run), for the run's status."""
        if self.sequential is None:
            return None
        st = self.sequential.stopping
        return forecast_status(st.before(), st)

    def precheck(self) -> list[str]:
        problems = []
        jump = self.mocap.clock_jump(self._resets, "motion-capture", self.key)
        if jump is not None:
            problems.append(jump)
        if self.mocap.is_stale():
            problems.append(f"motion capture not live (last pose {self.mocap.age():.2f} s ago)")
        clock = self.mocap.clock_problem()
        if clock is not None:
            problems.append(clock)
        return problems

    def problem(self) -> str | None:
        jump = self.mocap.clock_jump(self._resets, "motion-capture", self.key)
        if jump is not None:
            return jump
        if self.mocap.is_stale():
            return (
                f"motion capture stale: no pose for {self.mocap.age():.3f} s "
                f"(limit {self.mocap.stale_after:.3f} s)"
            )
        return None

    def waits_for(self, state: State) -> str | None:
        return None  # the poses need no operator

    def answer(
        self, run_id: str, state: State, what: str, entries: Sequence[dict[str, Any]] = ()
    ) -> None:
        raise ValueError(f"calibration {run_id} measures with motion capture: nothing to {what}")

    def come_to_rest(self, run: RunSteps) -> None:
        limits = run.config.limits
        step = "braking every wheel: waiting for the robot to come to rest"
        run.enter(State.REST, step)
        for m in run.config.nominal.ids:
            run.robot.wheel_hold(m)
        t_brake = run.clock.now()
        deadline = run.deadline()
        while True:
            run.check(True, deadline)
            # the poses *sampled* over the last window after the brake (by their host
            # times: with late poses, from a slow mocap network or clock mode wall, the
            # newest pose at hand may have been sampled a while ago)
            latest = self.mocap.latest()
            if latest is not None and latest.t_host - t_brake >= REST_WINDOW:
                poses = self.mocap.samples(since_host=latest.t_host - REST_WINDOW)
                if poses.shape[0] >= 3 and poses[-1, 2] - poses[0, 2] >= 0.5 * REST_WINDOW:
                    speed, rate = motion_rates(poses[:, 2], poses[:, 3], poses[:, 4], poses[:, 5])
                    if speed <= limits.rest_speed and abs(rate) <= limits.rest_yaw_rate:
                        return
                    run.set_status(
                        step=f"{step} (yaw rate {rate:.3f} rad/s, speed {speed:.3f} m/s)"
                    )
            run.clock.poll(run.poll)

    def before_spin(self, run: RunSteps, k: int, dyn: list[int]) -> None:
        """Nothing: the poses need no rest before a spin."""

    def spin(self, run: RunSteps, k: int) -> None:
        latest = self.mocap.latest()
        assert latest is not None
        spin = SpinWindow(
            run.clock.now(), run.config.protocol.settle_time, latest.t_host, latest.yaw
        )
        # judged on the first spin about each module, its trailing casters aligned (ALIGN):
        # after a re-steer they first swivel, and the robot may turn back a little
        direction = DirectionWatch(run, k, latest.t_host, latest.yaw)
        direction.decided = k in self._directions
        self._directions.add(k)
        deadline = run.deadline()
        seq = self.sequential
        if seq is not None:
            seq.begin()
        while True:
            run.check(True, deadline)
            p = self.mocap.latest()
            assert p is not None
            spin.add(p.t_host, p.yaw)
            direction.update(p.yaw, p.t_host)
            sweep = sweep_reached(run, spin) if seq is None else seq.judge(run, k, spin, self.poses)
            if spin.start is not None:
                run.set_status(poses=self.mocap.counters.accepted)
            if sweep is not None:
                assert spin.start is not None
                run.add_segment(Segment(k, spin.start, p.t_host), sweep)
                return
            run.clock.poll(run.poll)

    def after_spins(self, run: RunSteps) -> None:
        """Nothing: the poses measured everything the solver needs."""

    def before_solve(self, run: RunSteps) -> None:
        """Nothing: SOLVE closes the dataset."""
