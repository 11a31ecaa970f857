"""What the host keeps of each drive node, and the supervision every kind shares (pure cores).

No clock, no lock, no I/O: a kind's receive path and the base's I/O step
(:mod:`swpc_hw.drives.base`) call these under the driver's lock, the tests call them
directly.

* :class:`FeedbackRing` -- one node's feedback history: a :class:`swpc_hw.row_ring.RowRing`
  of samples.  The driver receives 2 frames per node per feedback period (4 nodes at
  200 Hz: 1600 frames a second) and keeps the samples of a whole calibration (minutes).
  Kept as Python objects (a dataclass per sample) that was millions of objects, which
  CPython's cyclic garbage collector walks on every full collection: 0.5-2 s pauses were
  measured with ~1.3 M live objects, long enough for the driver's supervisor to declare
  every node lost (heartbeat timeout 0.3 s on a robot).  Here a sample is one row of a
  float64 array.  Columns (:data:`COLUMNS`, the fields of
  :class:`swpc_hw.drives.types.FeedbackSample`): ``t`` arrival on the driver clock,
  ``t_bus`` bus time stamp, ``counter`` (mod 256), ``seq`` (unwrapped), ``theta_hat``,
  ``psi`` (unwrapped, rad), and the velocity/torque frame's four values (NaN until that
  frame arrives).
* :class:`NodeTrack` -- what the host knows of one node (a module's state as
  :class:`~swpc_hw.drives.types.ModuleState` snapshots it).
* :func:`frame_time` -- a frame's arrival on the driver clock.  A heartbeat's arrival is
  what supervision judges loss by, so a frame that waited in a receive queue still counts
  from when it arrived.
* :func:`check` -- heartbeat loss and the host's refresh at ``now``::

      lost(n)    <=>  now >= (t_heartbeat(n) or t_configured) + loss_after
      refresh(n) <=>  host refresh and refreshed(n) and now - last_tx(n) >= T_refresh

  ``loss_after`` is :attr:`swpc_hw.drives.bus.CanConfig.loss_after_s`.  The base calls it
  right after it has drained its receive queue, with a ``now`` taken *before* the queue
  was found empty, so every heartbeat that arrived by ``now`` has been applied.  A node
  is reported lost once (until its heartbeat is back).
* :func:`check_nodes` -- :func:`check` as a kind's supervision: a lost node a FAULT
  observation (:meth:`swpc_hw.drives.base.DriverBase._check_nodes`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import TypeVar

import can
import numpy as np
from numpy.typing import NDArray

from firmware_protocol.codec import Axis, AxisState, ControlMode, Frame, HomingState
from swpc_hw.drives.types import (
    DriverStats,
    EventKind,
    FeedbackSample,
    ModuleState,
    Observation,
    Severity,
    where,
)
from swpc_hw.row_ring import KEEP_S, RowRing

CAN_ERR_BUSOFF = 0x00000040
"""Linux SocketCAN error class bit (in the error frame's id) for bus-off."""

COLUMNS = (
    "t",
    "t_bus",
    "counter",
    "seq",
    "theta_hat",
    "psi",
    "steer_velocity",
    "wheel_velocity",
    "steer_torque",
    "wheel_torque",
)
_VT = slice(6, 10)  # the velocity/torque frame's columns


class FeedbackRing(RowRing):
    """Newest ``capacity`` feedback rows of one node (the driver's lock guards it)."""

    def __init__(self, capacity: int) -> None:
        super().__init__(len(COLUMNS), capacity, keep=KEEP_S)

    def set_last_velocity_torque(self, values: tuple[float, float, float, float]) -> None:
        """Fill the newest row's ``steer_velocity, wheel_velocity, steer_torque,
        wheel_torque``."""
        self.set_last(_VT, values)

    def columns(self) -> dict[str, NDArray[np.float64]]:
        """The rows as named columns (copies)."""
        a = self.array()
        return {name: np.ascontiguousarray(a[:, k]) for k, name in enumerate(COLUMNS)}


@dataclass
class NodeTrack:
    """What the host knows of one drive node (mutable state of the pure cores)."""

    module: int
    node: int
    history: FeedbackRing
    alive: bool = False
    lost_reported: bool = False
    states: tuple[AxisState, AxisState] = (AxisState.DISABLED, AxisState.DISABLED)
    modes: tuple[ControlMode, ControlMode] = (ControlMode.FREE, ControlMode.FREE)
    errors: tuple[int, int] = (0, 0)
    homed: bool = False
    homing: HomingState = HomingState.NOT_HOMED
    homing_seen: bool = False  # a heartbeat showed the steering HOMING since start_homing()
    t_heartbeat: float | None = None
    heartbeats: int = 0
    feedback_frames: int = 0
    last: FeedbackSample | None = None
    seq: int = -1
    last_tx: float = -math.inf
    commanded: dict[Axis, tuple[ControlMode, float]] = field(default_factory=dict)

    def snapshot(self) -> ModuleState:
        return ModuleState(
            module=self.module,
            node=self.node,
            alive=self.alive,
            states=self.states,
            modes=self.modes,
            errors=self.errors,
            homed=self.homed,
            homing=self.homing,
            feedback=self.last,
            t_heartbeat=self.t_heartbeat,
            heartbeats=self.heartbeats,
            feedback_frames=self.feedback_frames,
        )


@dataclass
class Applied:
    """The outcome of one frame: observations (in order), whether one is a fault, and the
    new feedback sample (for the feedback callbacks) if the frame completed one."""

    observations: list[Observation] = field(default_factory=list)
    fault: bool = False
    sample: tuple[int, FeedbackSample] | None = None


def error_frame(msg: can.Message, stats: DriverStats) -> Observation:
    """What an error frame says, counted in ``stats`` (every kind's receive path): a bus-off
    (class ``CAN_ERR_BUSOFF``) is a fault, any other class a warning."""
    stats.error_frames += 1
    if msg.arbitration_id & CAN_ERR_BUSOFF:
        stats.bus_off += 1
        return Observation(EventKind.BUS_OFF, Severity.FAULT, "CAN bus-off")
    return Observation(
        EventKind.ERROR_FRAME,
        Severity.WARNING,
        f"error frame class 0x{msg.arbitration_id:08x} data {bytes(msg.data).hex()}",
    )


def frame_time(stamp: float, handled: float, mapped: float, max_age: float = 5.0) -> float:
    """The frame's arrival on the driver clock: ``mapped`` (its bus stamp mapped) when it
    is plausible, i.e. ``handled - max_age <= mapped <= handled``, else ``handled``."""
    if stamp and math.isfinite(mapped) and handled - max_age <= mapped <= handled:
        return mapped
    return handled


T = TypeVar("T", bound=NodeTrack)


@dataclass
class CheckResult:
    lost: list[NodeTrack] = field(default_factory=list)
    refresh: list[Frame] = field(default_factory=list)
    next_deadline: float = math.inf


def check(
    nodes: Iterable[T],
    now: float,
    *,
    t_configured: float,
    loss_after: float,
    refresh_period: float,
    refresh: bool,
    refreshed: Callable[[T], bool],
    frames: Callable[[T], list[Frame]],
) -> CheckResult:
    """Heartbeat loss and host-side refresh at ``now`` (module docstring).

    ``refresh``: the drives are ACTIVE and refresh from the host (not through the
    kernel's broadcast manager); ``refreshed(n)``: node ``n`` has a setpoint to refresh,
    ``frames(n)`` the frames that refresh it (the kind's).  Lost nodes are marked
    (``alive = False``).
    """
    out = CheckResult()
    for nd in nodes:
        due = (nd.t_heartbeat if nd.t_heartbeat is not None else t_configured) + loss_after
        if now >= due:
            if nd.alive or not nd.lost_reported:
                nd.alive = False
                nd.lost_reported = True
                out.lost.append(nd)
        else:
            out.next_deadline = min(out.next_deadline, due)
        if refresh and refreshed(nd):
            if now - nd.last_tx >= refresh_period:
                out.refresh += frames(nd)
                out.next_deadline = min(out.next_deadline, now + refresh_period)
            else:
                out.next_deadline = min(out.next_deadline, nd.last_tx + refresh_period)
    if out.lost:
        out.refresh = []  # a fault: the motors stop, nothing is refreshed
    return out


@dataclass
class Supervision:
    """What a kind's :meth:`DriverBase._check` found at ``now``: observations (a lost drive
    is a FAULT one), how many drives were lost, the frames that refresh the commanded
    setpoints (sent only while ACTIVE and without a fault), and when to check again."""

    observations: list[Observation] = field(default_factory=list)
    lost: int = 0
    fault: bool = False
    refresh: list[Frame] = field(default_factory=list)
    next_deadline: float = math.inf


def check_nodes(
    nodes: Iterable[T],
    now: float,
    *,
    t_configured: float,
    loss_after: float,
    refresh_period: float,
    refresh: bool,
    refreshed: Callable[[T], bool],
    frames: Callable[[T], list[Frame]],
) -> Supervision:
    """:func:`check` on node tracks, a lost node a FAULT (module docstring)."""
    res = check(
        nodes,
        now,
        t_configured=t_configured,
        loss_after=loss_after,
        refresh_period=refresh_period,
        refresh=refresh,
        refreshed=refreshed,
        frames=frames,
    )
    lost = [
        Observation(
            EventKind.HEARTBEAT_LOST,
            Severity.FAULT,
            f"{where(nd.module, nd.node)}: no heartbeat for {loss_after:.3f} s",
            nd.module,
            nd.node,
        )
        for nd in res.lost
    ]
    return Supervision(lost, len(lost), bool(lost), res.refresh, res.next_deadline)
