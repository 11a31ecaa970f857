"""The watchdog refresh in the kernel: SocketCAN's broadcast manager, with a dead-man.

On a real robot the service shares its computer with navigation and perception; a
Python thread can be held off the CPU (GIL, garbage collection, a loaded core) for
longer than the controllers' watchdog.  Refreshing from a Python thread then trips the
watchdog and aborts a calibration for nothing.  Here the kernel sends each node's last
SetControl frames every ``period`` (python-can ``send_periodic`` -> BCM ``TX_SETUP``):
a stall of the process does not starve the controllers.

Dead-man: every task is set up with a finite count, ``deadman / period`` frames, and
the driver renews it (restarts the count) every ``deadman / 2``.  A hung or stopped
service (``kill -STOP``, a deadlock) therefore stops feeding the controllers at most
``deadman`` after its last renewal, and every axis is free (watchdog FAULT) within
``deadman + watchdog`` -- while a stall shorter than ``deadman / 2`` goes unnoticed.

A node's task cycles through its commanded axes' frames, one per ``period`` (the
watchdog is per node: any valid command restarts it).
"""

from __future__ import annotations

import contextlib
import logging
import time
from dataclasses import dataclass

import can

from firmware_protocol import codec
from swpc_hw.drives.bus import deadman_problem
from swpc_hw.drives.errors import CanConfigError

log = logging.getLogger(__name__)


@dataclass
class _Task:
    task: can.broadcastmanager.CyclicSendTaskABC
    frames: tuple[codec.Frame, ...]


def frame_message(
    f: codec.Frame, channel: str | int | None, timestamp: float = 0.0
) -> can.Message:
    """python-can's message of ``f`` (a remote request: its length as DLC, no data)."""
    if f.remote:
        return can.Message(
            arbitration_id=f.arbitration_id, is_remote_frame=True, dlc=len(f.data),
            is_extended_id=False, is_rx=False, channel=channel, timestamp=timestamp,
        )  # fmt: skip
    return can.Message(
        arbitration_id=f.arbitration_id, data=f.data, is_extended_id=False, is_rx=False,
        channel=channel, timestamp=timestamp,
    )  # fmt: skip


class KernelRefresh:
    """Per-node periodic tasks on a bus that schedules them in the kernel (SocketCAN).

    Not thread-safe: the driver calls it under its transmit lock.
    """

    def __init__(self, bus: can.BusABC, period: float, deadman: float) -> None:
        problem = deadman_problem(deadman, period)
        if problem is not None:
            raise CanConfigError(problem)
        self.bus = bus
        self.period = float(period)
        self.deadman = float(deadman)
        self._tasks: dict[int, _Task] = {}
        self.renewals = 0

    @property
    def renew_every(self) -> float:
        return self.deadman / 2.0

    def set_node(self, node: int, frames: list[codec.Frame]) -> None:
        """Refresh ``node`` with ``frames`` from now on (none: stop refreshing it)."""
        new = tuple(frames)
        cur = self._tasks.get(node)
        if cur is not None and cur.frames == new:
            return
        same_ids = cur is not None and [f.arbitration_id for f in cur.frames] == [
            f.arbitration_id for f in new
        ]
        if cur is not None and same_ids and new:
            # python-can changes a task's data, never its ids (an ODrive axis' refresh goes
            # from Set_Input_Torque to Set_Input_Pos): other ids take a new task, below
            msgs = [frame_message(f, self.bus.channel_info) for f in new]
            cur.task.modify_data(msgs)  # type: ignore[attr-defined]
            cur.frames = new
            return
        # the new task starts before the old one stops: the node's refresh has no gap, however
        # long this thread is held off the CPU in between (both send for that moment)
        task = None
        if new:
            msgs = [frame_message(f, self.bus.channel_info) for f in new]
            task = self.bus.send_periodic(msgs, self.period, duration=self.deadman)
        if cur is not None:
            self._stop(node)
        if task is not None:
            self._tasks[node] = _Task(task, new)

    def renew(self) -> None:
        """Restart every task's count (the dead-man's renewal).

        The kernel's broadcast manager restarts a task's count on every ``TX_SETUP``
        (python-can ``start()``).  python-can's thread-based fallback (any other bus)
        starts a new period only once its thread has ended; a task still running gets its
        end moved instead, so that both keep sending without a gap while renewed."""
        for t in self._tasks.values():
            task = t.task
            if isinstance(task, can.broadcastmanager.ThreadBasedCyclicSendTask) and (
                task.thread is not None and task.thread.is_alive() and not task.stopped
            ):
                task.end_time = time.perf_counter() + self.deadman
            else:
                task.start()  # type: ignore[attr-defined]
        self.renewals += 1

    def _stop(self, node: int) -> None:
        t = self._tasks.pop(node, None)
        if t is not None:
            try:
                t.task.stop()
            except (can.CanError, OSError) as exc:
                log.error("cannot stop the periodic refresh of node %d: %s", node, exc)

    def stop_all(self) -> None:
        """Delete every task (before the stop frames go out: no refresh after them)."""
        for node in list(self._tasks):
            self._stop(node)

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.stop_all()

    def nodes(self) -> list[int]:
        return sorted(self._tasks)
