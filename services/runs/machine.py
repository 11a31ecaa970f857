"""A run's machinery: its thread, states, checks, waits on robot time, and its end.

:class:`RunMachine` is what every step of a calibration (:mod:`services.runs.protocol`,
which subclasses it with the protocol's steps in :meth:`RunMachine._protocol`) relies on:

* :meth:`~RunMachine.enter` a state: only along :data:`~services.runs.state.TRANSITIONS`,
  saved by the owner (``on_change``: a state that cannot be saved fails the run), logged;
* :meth:`~RunMachine.check`, at every poll of every step: an abort, a shutdown, a robot
  fault, a motion sensor its metrology no longer trusts during motion, a step over
  ``limits.step_timeout``; the recordings are written from here too
  (:class:`~services.runs.journal.RunJournal`);
* :meth:`~RunMachine._end`: ``stop_all()`` first (its latency measured for an abort), then
  release, FAILED or ABORTED with the reason (and the state it happened in), the last
  samples recorded and the recordings closed.

An operator's :meth:`~RunMachine.abort` ends ABORTED; a stopping service's
:meth:`~RunMachine.shutdown` ends FAILED with its reason (SIGTERM is no operator's abort).
Every duration is robot time on the injected clock; against the in-process simulator the
run's thread is a participant of the simulated clock (lockstep).
"""

from __future__ import annotations

import contextlib
import logging
import math
import threading
import time
import traceback
import uuid
from collections.abc import Callable, Iterator
from typing import Any

from services.config.robot import RobotConfig
from services.runs.journal import RunJournal
from services.runs.metrology.base import Metrology
from services.runs.recording import RecordingError
from services.runs.state import (
    TERMINAL,
    TRANSITIONS,
    PersistError,
    RunAbortedError,
    RunFailedError,
    RunStatus,
    State,
    now_iso,
)
from swpc_hw.clock import SYSTEM_CLOCK, Clock, SimClock
from swpc_hw.drives.robot_io import RobotIO
from swpc_hw.files.dataset import Segment


class RunMachine:
    """A run's thread, states, checks and end (module docstring); the subclass sets
    :attr:`journal` and implements :meth:`_protocol`."""

    journal: RunJournal

    def __init__(
        self,
        robot: RobotIO,
        metrology: Metrology,
        config: RobotConfig,
        *,
        clock: Clock = SYSTEM_CLOCK,
        on_change: Callable[[Any], None] | None = None,
        poll: float = 0.02,
    ) -> None:
        self.robot = robot
        self.metrology = metrology
        """What measures the robot's motion (:mod:`services.runs.metrology.base`)."""
        self.config = config
        self.clock = clock
        self.status = RunStatus(id=uuid.uuid4().hex[:12], created=now_iso())
        self.status.metrology = metrology.name
        self.result_doc: dict[str, Any] | None = None
        self.abort_latency: float | None = None
        self.persist_error: str | None = None
        self.segments: list[Segment] = []
        self._on_change = on_change
        self.poll = poll
        self._abort = threading.Event()
        self._commit = threading.Lock()
        self._committed = False
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()
        self._t0 = 0.0
        self._stop_reason: str | None = None
        self.plan: list[State] = []
        """The protocol's planned steps, in order (the subclass's): what
        :meth:`remaining` estimates."""
        self._at = -1  # the plan's step the run is in (-1: before the plan)
        self._entered = 0.0  # when it entered its state (robot time)
        self._spent: dict[State, list[float]] = {}  # robot time each state took

    # ------------------------------------------------------------------ control
    @property
    def id(self) -> str:
        return self.status.id

    @property
    def clock_start(self) -> float:
        """The run's start on its clock (robot time; 0 before it starts)."""
        return self._t0

    @property
    def finished(self) -> bool:
        return self.status.state in TERMINAL

    def start(self) -> None:
        self._thread = threading.Thread(target=self._main, name=f"calib-{self.id}", daemon=True)
        self._thread.start()

    def abort(self) -> bool:
        """Stop motion at once (``stop_all()`` from the caller's thread) and end ABORTED;
        False when it is too late: the run has finished, or has begun installing its
        result (:meth:`committing`), which then stands."""
        return self._stop(None)

    def shutdown(self, reason: str = "the service was stopped during the run") -> None:
        """Stop motion at once and end FAILED with ``reason`` (the service is stopping:
        SIGTERM is no operator's abort); a run already installing its result finishes."""
        self._stop(reason)

    def _stop(self, reason: str | None) -> bool:
        with self._commit:  # held only while a result is being installed: milliseconds
            if self.finished or self._committed:
                return False
            self._stop_reason = reason
            self._abort.set()
        self.robot.stop_all()
        return True

    @contextlib.contextmanager
    def committing(self) -> Iterator[None]:
        """The point of no return: an abort or a shutdown accepted before it ends the run
        (raised here) and nothing is installed; one that comes after it is refused
        (:meth:`abort` is False) and what the block installs stands."""
        with self._commit:
            if self._abort.is_set():
                if self._stop_reason is not None:
                    raise RunFailedError(f"{self._stop_reason} (the result is not installed)")
                raise RunAbortedError("aborted by the operator (the result is not installed)")
            self._committed = True
            yield

    def join(self, timeout: float | None = None) -> None:
        if self._thread is not None:
            self._thread.join(timeout)

    # ---------------------------------------------------------------- the steps' API
    def enter(self, state: State, step: str) -> None:
        cur = self.status.state
        if state not in TERMINAL and state not in TRANSITIONS.get(cur, frozenset()):
            raise RuntimeError(f"illegal transition {cur} -> {state}")
        now = self.clock.now()
        with self._lock:
            self._spent.setdefault(cur, []).append(now - self._entered)
            self._entered = now
            later = range(self._at + 1, len(self.plan))
            nxt = next((i for i in later if self.plan[i] is state), None)
            if nxt is not None:
                self._at = nxt
            elif self._at >= 0:
                self._at = len(self.plan)  # past the plan
            self.status.state = state
            self.status.step = step
            self._times(now)
        self.event(
            logging.INFO, "run.state", state=str(state), step=step, module=self.status.module
        )
        self.changed()
        if state not in TERMINAL:
            # an abort or a fault since the last check ends the run before this state's
            # first command
            self.check(False, None)

    def set_status(self, **fields: Any) -> None:
        """Update the operator's view of the run (under its lock)."""
        with self._lock:
            for name, value in fields.items():
                setattr(self.status, name, value)

    def changed(self) -> None:
        """Tell the owner (the service saves the state); a failure to save fails a run
        still going (robot stopped first), and is kept in :attr:`persist_error`."""
        if self._on_change is None:
            return
        try:
            self._on_change(self)
        except Exception as exc:
            self.persist_error = f"{type(exc).__name__}: {exc}"
            self.event(logging.ERROR, "run.persist_failed", error=self.persist_error)
            if self.status.state not in TERMINAL:
                raise PersistError(f"cannot save the run's state: {self.persist_error}") from exc

    def event(self, level: int, name: str, **fields: Any) -> None:
        self.journal.event(level, name, **fields)

    def record(self, force: bool = False) -> None:
        """The samples since the last batch to the run's recordings (every half second of
        robot time, or now)."""
        counts = self.journal.record(self.metrology.sensor, self.robot, force)
        if counts is not None:
            self.set_status(
                **{self.metrology.samples_field: counts[0], "encoder_samples": counts[1]}
            )

    def add_segment(self, seg: Segment, sweep: float) -> None:
        """A finished spin's window (the solver's segment), logged and recorded."""
        self.segments.append(seg)
        self.status.segments = len(self.segments)
        self.journal.add_segment(seg)
        self.event(
            logging.INFO,
            "run.segment",
            module=seg.static_module,
            start=seg.start,
            end=seg.end,
            sweep_deg=math.degrees(sweep),
        )

    def planned(self, state: State) -> float | None:
        """The robot time a step of the plan should take before one was measured (s);
        None: unknown (the subclass's)."""
        return 0.0

    def remaining(self, now: float) -> float | None:
        """Robot time the plan's steps left should take (s): each as long as the mean of
        the same state's so far in this run, else :meth:`planned`; the current one less
        the time already in it.  None when one is unknown or the run is past its plan."""
        if self._at >= len(self.plan):
            return None

        def took(state: State) -> float | None:
            done = self._spent.get(state)
            return sum(done) / len(done) if done else self.planned(state)

        total = 0.0
        for i in range(max(self._at, 0), len(self.plan)):
            t = took(self.plan[i])
            if t is None:
                return None
            total += max(0.0, t - (now - self._entered)) if i == self._at else t
        return total

    def _times(self, now: float) -> None:
        """The status's elapsed and remaining robot time (under the run's lock)."""
        if self.status.started is None:
            return
        if self.status.state in TERMINAL:
            self.status.remaining_s = None
            return
        elapsed = now - self._t0
        self.status.elapsed_s = round(elapsed, 2)
        left = self.remaining(now)
        self.status.remaining_s = None if left is None else round(left, 1)
        if left is not None and elapsed + left > 0:
            # the share of the plan's robot time done: every step counts (a run without
            # motion capture was at 100 % with its drive and the operator's steps to come);
            # never backwards when a step takes longer than its estimate
            done = min(elapsed / (elapsed + left), 1.0)
            self.status.progress = round(max(self.status.progress, done), 3)

    def check(self, motion: bool, deadline: float | None) -> None:
        with self._lock:
            self._times(self.clock.now())
        if self._abort.is_set():
            if self._stop_reason is not None:
                raise RunFailedError(self._stop_reason)
            raise RunAbortedError("aborted by the operator")
        self.record()
        faults = self.robot.take_faults()
        if faults:
            raise RunFailedError(f"robot fault: {faults[0]}")
        problem = self.metrology.problem() if motion else None
        if problem is not None:
            raise RunFailedError(problem)
        if deadline is not None and self.clock.now() > deadline:
            raise RunFailedError(
                f"step timeout: {self.status.step} took longer than "
                f"{self.config.limits.step_timeout:g} s"
            )

    def deadline(self) -> float:
        """Now plus the step timeout."""
        return self.clock.now() + self.config.limits.step_timeout

    def wait(self, seconds: float, motion: bool = True) -> None:
        """Wait ``seconds`` of robot time, checking for faults and abort."""
        end = self.clock.now() + seconds
        deadline = self.deadline()
        while True:
            self.check(motion, deadline)
            left = end - self.clock.now()
            if left <= 0:
                return
            self.clock.poll(min(self.poll, left))

    def wait_until(self, cond: Callable[[], bool], motion: bool) -> None:
        """Poll until ``cond()``, checking at every poll (step timeout)."""
        deadline = self.deadline()
        while not cond():
            self.check(motion, deadline)
            self.clock.poll(self.poll)

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
        self._t0 = self._entered = self.clock.now()  # before `started`: who sees that sees this
        self.status.started = now_iso()
        self.event(logging.INFO, "run.start", **self._start_fields())
        try:
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
            self.status.finished = now_iso()
            self.status.elapsed_s = round(self.clock.now() - self._t0, 2)
            self.status.remaining_s = None
            self.status.state = state
            self.status.step = "stopped"
        level = logging.WARNING if state is State.ABORTED else logging.ERROR
        self.event(level, "run.end", state=str(state), reason=reason)
        with contextlib.suppress(Exception):  # best effort: the end is decided
            self.record(force=True)
        with contextlib.suppress(Exception):
            self.journal.finish({"state": str(state), "reason": reason}, self.result_doc)
        self.changed()

    # ---------------------------------------------------------------- the protocol's
    def _start_fields(self) -> dict[str, Any]:
        """The ``run.start`` log line's fields."""
        return {}

    def _protocol(self) -> None:
        """The run's steps, from PENDING to DONE (the subclass's)."""
        raise NotImplementedError
