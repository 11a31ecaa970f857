"""What the host keeps of a ``cia402`` module and of each of its axes, and how the drives'
snapshots say it (pure builders).

No clock, no lock, no I/O: :class:`swpc_hw.drives.cia402.driver.Cia402Driver` calls these
under its lock on the tracks of :mod:`swpc_hw.drives.cia402.tracking`.

* :func:`module_tracks` -- the tracks from the config: one per module, one per axis.
* :func:`module_state` -- the module's :class:`~swpc_hw.drives.types.ModuleState` (what a
  run and its waits see): alive while both axes are, its heartbeat the older of theirs.
* :func:`axis_status` -- one axis' :class:`~swpc_hw.drives.types.AxisStatus` (the
  console's drives view) in CiA 402's words: power state, NMT state, modes display,
  error code.
* :func:`not_reached` -- the error of a wait whose condition a module did not reach.
"""

from __future__ import annotations

from firmware_protocol import cia402
from firmware_protocol.cia402 import PowerState
from firmware_protocol.codec import Axis, HomingState
from swpc_hw.drives.cia402.config import ABSOLUTE, Cia402Drives
from swpc_hw.drives.cia402.tracking import AxisTrack, ModuleTrack
from swpc_hw.drives.errors import NodeTimeoutError
from swpc_hw.drives.types import AxisStatus, FeedbackSample, ModuleState


def module_tracks(drives: Cia402Drives) -> dict[int, ModuleTrack]:
    """A track per module of ``drives``, in the robot's order (an absolute steering is
    homed from the start)."""
    out: dict[int, ModuleTrack] = {}
    for m, mod in drives.axes().items():
        tracks = []
        for axis, a in ((Axis.STEER, mod.steer), (Axis.WHEEL, mod.wheel)):
            tracks.append(AxisTrack(m, axis, a.node, a.counts_per_rad(), a.gear_ratio))
        mt = ModuleTrack(m, tracks[0], tracks[1])
        if mod.steer.homing == ABSOLUTE:
            mt.homed, mt.homing = True, HomingState.DONE
        out[m] = mt
    return out


def module_state(mt: ModuleTrack, feedback: FeedbackSample | None) -> ModuleState:
    """Module ``mt``'s snapshot, ``feedback`` its latest sample."""
    s, w = mt.steer, mt.wheel
    beats = [a.t_heartbeat for a in mt.axes if a.t_heartbeat is not None]
    return ModuleState(
        module=mt.module,
        node=s.node,
        alive=s.alive and w.alive,
        states=(s.axis_state(), w.axis_state()),
        modes=(s.control_mode(), w.control_mode()),
        errors=(s.error_code, w.error_code),
        homed=mt.homed,
        homing=mt.homing,
        feedback=feedback,
        t_heartbeat=min(beats) if len(beats) == 2 else None,
        heartbeats=s.heartbeats + w.heartbeats,
        feedback_frames=mt.feedback_frames,
    )


def axis_status(mt: ModuleTrack, a: AxisTrack) -> AxisStatus:
    """What the host knows now of axis ``a`` of module ``mt``: its power state, NMT
    state, modes display and error code, in CiA 402's words."""
    faulted = a.state in (PowerState.FAULT, PowerState.FAULT_REACTION_ACTIVE)
    return AxisStatus(
        module=mt.module,
        axis=a.axis,
        node=a.node,
        alive=a.alive,
        t_heartbeat=a.t_heartbeat,
        heartbeats=a.heartbeats,
        state=a.state.value,
        nmt=None if a.nmt is None else cia402.nmt_name(a.nmt),
        mode=cia402.mode_name(a.mode_display),
        error=a.error_code,
        error_name=cia402.emcy_name(a.error_code) if a.error_code else "none",
        fault=faulted or a.error_code != 0,  # the EMCY comes before the statusword
        homed=mt.homed if a.axis is Axis.STEER else None,
        torque_mode=a.torque_mode is not None,
    )


def not_reached(mt: ModuleTrack, what: str, timeout: float) -> NodeTimeoutError:
    """``wait_for()``'s error: what module ``mt`` did not reach, and its axes' states."""
    states = ", ".join(f"{a.where()} {a.state.value}" for a in mt.axes)
    return NodeTimeoutError(
        f"module {mt.module}: {what} not reached within {timeout} s ({states}, homed "
        f"{mt.homed})",
        node=mt.steer.node,
    )
