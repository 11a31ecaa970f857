"""The drives' observation API: snapshots, feedback history, counters, events, waits,
recording.

A mixin of :class:`swpc_hw.drives.base.DriverBase` (state, locks and lifecycle live
there); a kind gives its modules (:meth:`DriverObservation.modules`,
:meth:`DriverObservation.module_state`) and each module's feedback ring
(:meth:`DriverObservation._ring`).  Waits are judged on the driver's clock
(:mod:`swpc_hw.clock`).
"""

from __future__ import annotations

import contextlib
import logging
import queue
import threading
from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import replace
from typing import Protocol, TypeVar

import can
import numpy as np
from numpy.typing import NDArray

from firmware_protocol.codec import Axis, AxisState
from swpc_hw.clock import Clock, wait_until
from swpc_hw.drives.errors import LifecycleError, NodeTimeoutError
from swpc_hw.drives.periodic import KernelRefresh
from swpc_hw.drives.recording import Recorder
from swpc_hw.drives.tracking import COLUMNS as HISTORY_COLUMNS
from swpc_hw.drives.tracking import FeedbackRing
from swpc_hw.drives.types import (
    AXIS_NAMES,
    AxisStatus,
    DriverEvent,
    DriverStats,
    EventKind,
    FeedbackSample,
    Lifecycle,
    ModuleState,
    Observation,
    Severity,
    axis_status_of_module,
)

log = logging.getLogger(__name__)


class _OnNode(Protocol):
    node: int


N = TypeVar("N", bound=_OnNode)


class DriverObservation(ABC):
    """What the drives know (mixin; state lives in the driver)."""

    clock: Clock
    _state: Lifecycle
    _lock: threading.RLock
    _changed: threading.Condition
    _stats: DriverStats
    _kernel: KernelRefresh | None
    _bus: object
    _recorder: Recorder | None
    _logger: Recorder | None
    _latency: deque[float]
    _events: queue.Queue[DriverEvent]
    _event_callbacks: list[Callable[[DriverEvent], None]]
    _feedback_callbacks: list[Callable[[int, FeedbackSample], None]]
    _io_thread: threading.Thread | None
    _log_counts: dict[EventKind, int]
    last_exception: BaseException | None

    @abstractmethod
    def modules(self) -> list[int]:
        """The module ids, in the robot's order."""

    @abstractmethod
    def module_state(self, module: int) -> ModuleState:
        """The latest known state of one module's drives (a snapshot)."""

    def axis_status(self, module: int, axis: Axis) -> AxisStatus | None:
        """What the host knows now of one axis' drive (:class:`AxisStatus`); None here: a
        kind reports its axes one by one by overriding this (a kind whose module is one
        controller on one node returns :meth:`_module_axis_status`)."""
        return None

    def _module_axis_status(self, module: int, axis: Axis) -> AxisStatus:
        """One axis as its module's snapshot tells it: right for a kind whose module is one
        dual-axis controller on one node (the swpc kind); the error named by
        :meth:`_error_names` (:func:`swpc_hw.drives.types.axis_status_of_module`)."""
        return axis_status_of_module(self.module_state(module), axis, self._error_names)

    @abstractmethod
    def _ring(self, module: int) -> FeedbackRing:
        """The module's feedback history (:class:`CanCommandError` for an unknown one)."""

    def history(self, module: int) -> list[FeedbackSample]:
        """The kept feedback samples of a module, oldest first (objects made on demand;
        :meth:`history_arrays` for computation)."""
        ring = self._ring(module)
        with self._lock:
            a = ring.array()
        samples = []
        for r in a.tolist():
            f = dict(zip(HISTORY_COLUMNS, r, strict=True))
            f["counter"], f["seq"] = int(f["counter"]), int(f["seq"])
            samples.append(FeedbackSample(**f))
        return samples

    def history_arrays(self, module: int) -> dict[str, NDArray[np.float64]]:
        """Feedback history as columns (the fields of :class:`FeedbackSample`); ``t`` is
        the arrival on the bus on the driver's clock."""
        ring = self._ring(module)
        with self._lock:
            return ring.columns()

    def history_since(
        self, module: int, cursor: int, since: float = -np.inf
    ) -> tuple[NDArray[np.float64], int]:
        """Feedback rows ``(t, theta_hat, psi)`` appended after ``cursor`` (0: every row
        kept) with ``t >= since``, and the new cursor: a reader that keeps the cursor
        reads each sample once (a run records its feedback as it comes)."""
        ring = self._ring(module)
        with self._lock:
            rows, cursor = ring.since(cursor)
        rows = rows[rows[:, 0] >= since] if since > -np.inf else rows
        return np.ascontiguousarray(rows[:, [0, 4, 5]]), cursor

    def clear_history(self) -> None:
        with self._lock:
            for m in self.modules():
                self._ring(m).clear()

    def stats(self) -> DriverStats:
        with self._lock:
            st = replace(self._stats)
        if self._kernel is not None:
            st.periodic_renewals = self._kernel.renewals
        return st

    def latencies(self) -> NDArray[np.float64]:
        """Receive latencies (clock's wall time when handled minus the bus stamp), s."""
        with self._lock:
            return np.array(self._latency, dtype=float)

    def clear_latencies(self) -> None:
        with self._lock:
            self._latency.clear()

    def events(self) -> list[DriverEvent]:
        """Drain the event queue."""
        out: list[DriverEvent] = []
        while True:
            try:
                out.append(self._events.get_nowait())
            except queue.Empty:
                return out

    def add_event_callback(self, fn: Callable[[DriverEvent], None]) -> None:
        """``fn(event)`` on every event, on the thread that raised it, in the order added."""
        with self._lock:
            self._event_callbacks = [*self._event_callbacks, fn]

    def remove_event_callback(self, fn: Callable[[DriverEvent], None]) -> None:
        """Undo :meth:`add_event_callback` (no-op for a callback not registered)."""
        with self._lock:
            self._event_callbacks = [f for f in self._event_callbacks if f != fn]

    def add_feedback_callback(self, fn: Callable[[int, FeedbackSample], None]) -> None:
        """``fn(module, sample)`` on every position frame, on the receive path.

        An exception in ``fn`` is a listener error: counted, reported, and a fault.
        """
        with self._lock:
            self._feedback_callbacks = [*self._feedback_callbacks, fn]

    def threads(self) -> list[threading.Thread]:
        """The driver's own thread (receive and supervision; none in lockstep)."""
        return [self._io_thread] if self._io_thread is not None else []

    def wait_for(
        self,
        module: int,
        predicate: Callable[[ModuleState], bool],
        timeout: float,
        what: str = "condition",
    ) -> ModuleState:
        """Block until ``predicate(module_state)`` holds; :class:`NodeTimeoutError` otherwise."""
        self.module_state(module)  # an unknown module: CanCommandError
        deadline = self.clock.now() + timeout
        reached: list[ModuleState] = []

        def holds() -> bool:
            st = self.module_state(module)
            if predicate(st):
                reached.append(st)
                return True
            return False

        with self._changed:
            if wait_until(self.clock, self._changed, holds, deadline):
                return reached[-1]
        raise self._not_reached(module, what, timeout)

    def _not_reached(self, module: int, what: str, timeout: float) -> NodeTimeoutError:
        """wait_for()'s error: what was not reached, and the module's state."""
        st = self.module_state(module)
        return NodeTimeoutError(
            f"module {module} (node {st.node}): {what} not reached within {timeout} s "
            f"(states {[s.name for s in st.states]}, errors "
            f"{[self._error_names(e) for e in st.errors]}, homed {st.homed}, "
            f"homing {st.homing.name})",
            node=st.node,
        )

    def _error_names(self, bits: int) -> str:
        """An axis' error bits by name (the drive kind's own)."""
        return f"0x{bits:x}"

    def wait_axis_state(
        self, module: int, axis: Axis, state: AxisState, timeout: float = 1.0
    ) -> None:
        axis = Axis(axis)
        self.wait_for(
            module,
            lambda s: s.states[axis] == state,
            timeout,
            f"axis {int(axis)} ({AXIS_NAMES[axis]}) state {state.name}",
        )

    def _wait_all(
        self,
        what: str,
        tracks: Callable[[], Iterable[N]],
        ok: Callable[[N], bool],
        name: Callable[[N], str],
        timeout: float,
    ) -> None:
        """Wait (on the clock) until ``ok`` holds for every track; else
        :class:`NodeTimeoutError` naming those it does not hold for."""
        deadline = self.clock.now() + timeout
        with self._changed:
            if not wait_until(
                self.clock, self._changed, lambda: all(ok(a) for a in tracks()), deadline
            ):
                bad = [a for a in tracks() if not ok(a)]
                raise NodeTimeoutError(
                    f"activate(): no {what} from {', '.join(name(a) for a in bad)} within "
                    f"{timeout:g} s",
                    node=bad[0].node,
                )

    def iter_modules(self) -> Iterator[ModuleState]:
        for module in self.modules():
            yield self.module_state(module)

    # ================================================================ recording
    def start_recording(self, path: str) -> None:
        """Record every frame in and out to ``path`` until :meth:`stop_recording`.

        python-can's Logger picks the format from the suffix (``.log``: candump, which
        ``cantools decode`` reads with the kind's DBC).  Independent of
        ``CanConfig.log_path``.  Frames the kernel sends for the refresh are not in it
        (candump sees them).
        """
        with self._lock:
            if self._bus is None or self._state == Lifecycle.FINALIZED:
                raise LifecycleError("start_recording() needs an open bus (configure() first)")
        self.stop_recording()
        rec = Recorder(path)
        with self._lock:
            self._recorder = rec

    def stop_recording(self) -> str | None:
        """Stop the recording started by :meth:`start_recording` (idempotent); returns why
        it stopped early (a failed write), if it did."""
        with self._lock:
            rec, self._recorder = self._recorder, None
        if rec is None:
            return None
        rec.stop()
        return rec.error

    def _log(self, msg: can.Message) -> None:
        """A frame in or out to the recording, if one is on, and to the rolling log: every
        frame while recording, else as ``CanConfig.log_idle_period_s`` samples them."""
        recorder = self._recorder
        if recorder is not None:
            recorder.write(msg)
        if self._logger is not None:
            self._logger.write(msg, sample=recorder is None)

    def log_error(self) -> str | None:
        """Why the log of ``CanConfig.log_path`` stopped (a failed write), if it did."""
        return None if self._logger is None else self._logger.error

    # ================================================================ events
    def _emit(self, kind: EventKind, severity: Severity, message: str) -> None:
        self._notify(self._record(Observation(kind, severity, message)))

    def _record(self, obs: Observation) -> DriverEvent:
        """Stamp, log and queue an observation as an event (cheap; under the lock is fine)."""
        ev = DriverEvent(
            self.clock.now(), obs.kind, obs.severity, obs.message, obs.module, obs.node, obs.axis
        )
        if obs.severity != Severity.INFO:
            self._log_counts[obs.kind] = n = self._log_counts.get(obs.kind, 0) + 1
            if n <= 5 or obs.severity == Severity.FAULT:
                log.warning("%s%s", obs.message, " (further ones counted only)" if n == 5 else "")
        with contextlib.suppress(queue.Full):
            self._events.put_nowait(ev)
        return ev

    def _notify(self, ev: DriverEvent) -> None:
        """Call the event callbacks (outside the driver's lock)."""
        for fn in self._event_callbacks:
            try:
                fn(ev)
            except Exception as exc:  # a broken callback must not stop the fault path
                with self._lock:
                    self._stats.listener_errors += 1
                    self.last_exception = exc
                log.error("event callback %r raised %s", fn, exc)
