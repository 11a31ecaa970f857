"""The driver's observation API: snapshots, feedback history, counters, events, waits.

A mixin of :class:`swpc_hw.can.driver.CanDriver` (state, locks and lifecycle live there).
Waits are judged on the driver's clock (:mod:`swpc_hw.clock`).
"""

from __future__ import annotations

import queue
import threading
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from firmware_protocol import codec
from firmware_protocol.codec import Axis, AxisState
from swpc_hw.can.errors import NodeTimeoutError
from swpc_hw.can.history import COLUMNS as HISTORY_COLUMNS
from swpc_hw.can.node_tracking import NodeTrack
from swpc_hw.can.periodic import KernelRefresh
from swpc_hw.can.types import (
    AXIS_NAMES,
    DriverEvent,
    DriverStats,
    FeedbackSample,
    ModuleState,
    where,
)
from swpc_hw.clock import Clock, wait_until


class DriverObservation:
    """What the driver knows (mixin; state lives in the driver)."""

    clock: Clock
    _lock: threading.RLock
    _changed: threading.Condition
    _nodes: dict[int, NodeTrack]
    _stats: DriverStats
    _kernel: KernelRefresh | None
    _latency: deque[float]
    _events: queue.Queue[DriverEvent]
    _event_callbacks: list[Callable[[DriverEvent], None]]
    _feedback_callbacks: list[Callable[[int, FeedbackSample], None]]
    _io_thread: threading.Thread | None

    def _node(self, module: int) -> NodeTrack:
        raise NotImplementedError  # the driver's (DriverCommands)

    def module_state(self, module: int) -> ModuleState:
        nd = self._node(module)
        with self._lock:
            return nd.snapshot()

    def modules(self) -> list[int]:
        return list(self._nodes)

    def history(self, module: int) -> list[FeedbackSample]:
        """The kept feedback samples of a module, oldest first (objects made on demand;
        :meth:`history_arrays` for computation)."""
        nd = self._node(module)
        with self._lock:
            a = nd.history.array()
        samples = []
        for r in a.tolist():
            f = dict(zip(HISTORY_COLUMNS, r, strict=True))
            f["counter"], f["seq"] = int(f["counter"]), int(f["seq"])
            samples.append(FeedbackSample(**f))
        return samples

    def history_arrays(self, module: int) -> dict[str, NDArray[np.float64]]:
        """Feedback history as columns (the fields of :class:`FeedbackSample`); ``t`` is
        the arrival on the bus on the driver's clock."""
        nd = self._node(module)
        with self._lock:
            return nd.history.columns()

    def history_since(
        self, module: int, cursor: int, since: float = -np.inf
    ) -> tuple[NDArray[np.float64], int]:
        """Feedback rows ``(t, theta_hat, psi)`` appended after ``cursor`` (0: every row
        kept) with ``t >= since``, and the new cursor: a reader that keeps the cursor
        reads each sample once (a run records its feedback as it comes)."""
        nd = self._node(module)
        with self._lock:
            rows, cursor = nd.history.since(cursor)
        rows = rows[rows[:, 0] >= since] if since > -np.inf else rows
        return np.ascontiguousarray(rows[:, [0, 4, 5]]), cursor

    def clear_history(self) -> None:
        with self._lock:
            for nd in self._nodes.values():
                nd.history.clear()

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
        nd = self._node(module)
        deadline = self.clock.now() + timeout
        reached: list[ModuleState] = []

        def holds() -> bool:
            st = nd.snapshot()
            if predicate(st):
                reached.append(st)
                return True
            return False

        with self._changed:
            if wait_until(self.clock, self._changed, holds, deadline):
                return reached[-1]
            st = nd.snapshot()
        raise NodeTimeoutError(
            f"{where(nd.module, nd.node)}: {what} not reached within {timeout} s "
            f"(states {[s.name for s in st.states]}, errors "
            f"{[self._error_names(e) for e in st.errors]}, homed {st.homed}, "
            f"homing {st.homing.name})",
            node=nd.node,
        )

    def _error_names(self, bits: int) -> str:
        """An axis' error bits by name (the drive kind's own)."""
        return codec.error_names(bits)

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

    def iter_modules(self) -> Iterator[ModuleState]:
        for module in self._nodes:
            yield self.module_state(module)
