"""What each command of the ``cia402`` kind changes in an axis's track (pure cores).

No clock, no lock, no I/O: :class:`swpc_hw.drives.cia402.driver.Cia402Driver`
calls them under its lock with the SYNC count it has sent (``sync_seq``) and times on its
clock, then sends the axis's RPDOs (:mod:`swpc_hw.drives.cia402.pdo`); the power state
machine takes the axis on from there, one transition per statusword
(:func:`swpc_hw.drives.cia402.tracking.supervise`).

* :func:`enable` -- closed loop at torque 0 (:func:`power`); a drive without a torque
  mode free with its power stage off instead (:func:`unpower`), powered again by the next
  position, velocity or homing command (:func:`powered`).
* :func:`position`, :func:`velocity`, :func:`torque`, :func:`homing` -- the mode and its
  target (velocity and torque within the run's limits); :func:`mode_changed` starts the
  window in which the drive must show a new mode (0x6061, :data:`MODE_TIMEOUT_S`), as
  :func:`power` starts those of the steps toward OPERATION ENABLED
  (:data:`POWER_TIMEOUT_S`).
* :func:`clear_fault` -- a fault reset asked; :func:`stop` -- what ``stop_all()`` leaves.

The SDO writes some commands need (the mode where 0x6060 is not PDO-mappable, the run's
limits) are :mod:`swpc_hw.drives.cia402.network`'s.
"""

from __future__ import annotations

from collections.abc import Callable

from firmware_protocol import cia402
from firmware_protocol.cia402 import Mode, PowerState
from firmware_protocol.codec import HomingState
from swpc_hw.drives.cia402.tracking import AxisTrack, ModuleTrack
from swpc_hw.drives.errors import NodeError

POWER_TIMEOUT_S = 1.0
"""An axis asked to enable that has not followed a step's controlword toward OPERATION
ENABLED in a statusword answering a SYNC sent this long after it has refused (robot time,
in SYNC periods; :func:`~swpc_hw.drives.cia402.tracking.supervise`)."""
MODE_TIMEOUT_S = 0.5
"""A mode whose display has not followed in a statusword answering a SYNC sent this long
after it was commanded was refused (robot time, in SYNC periods)."""

FAULTED = (PowerState.FAULT, PowerState.FAULT_REACTION_ACTIVE)


def power(a: AxisTrack, sync_seq: int) -> None:
    """OPERATION ENABLED asked (the power state machine moves one step per
    statusword)."""
    if not a.enable:
        a.enable, a.refused_reported = True, False
        a.enable_sync = a.enable_start = sync_seq
    a.unpowered = False


def powered(a: AxisTrack, sync_seq: int) -> None:
    """A command to an axis freed without a torque mode powers it again; one stopped
    stays off until :func:`enable`."""
    if a.unpowered:
        power(a, sync_seq)


def unpower(a: AxisTrack) -> None:
    """Free with its power stage off (disable voltage: no torque, the axis turns freely
    and its encoder still reports): a drive without a torque mode."""
    a.enable, a.unpowered, a.enable_sync, a.enable_start = False, True, -1, -1


def enable(a: AxisTrack, sync_seq: int, now: Callable[[], float]) -> None:
    """Closed loop at torque 0; a drive without a torque mode is free with its power
    stage off instead, powered by the next position, velocity or homing command."""
    if a.torque_mode is None:
        unpower(a)
        return
    power(a, sync_seq)
    a.mode, a.target_torque = a.torque_mode, 0
    nxt = cia402.host_controlword(a.state, True, a.reset, a.controlword)
    if nxt is not None:
        a.controlword, a.t_controlword = nxt, now()


def position(a: AxisTrack, position: float, sync_seq: int) -> None:
    """Its position mode (0x6502's choice), target ``position`` (rad)."""
    powered(a, sync_seq)
    a.mode, a.target_position, a.target_torque = (
        a.position_mode, a.to_units(position), 0
    )  # fmt: skip


def velocity(a: AxisTrack, velocity: float, sync_seq: int) -> None:
    """Its velocity mode, target ``velocity`` (rad/s) within the run's limit;
    :class:`NodeError` on a drive without one."""
    if a.velocity_mode is None:
        raise NodeError(
            f"{a.where()}: the drive has no velocity mode (0x6502) or no target "
            "velocity 0x60FF", node=a.node, axis=int(a.axis),
        )  # fmt: skip
    v = max(-a.max_velocity, min(a.max_velocity, velocity))
    powered(a, sync_seq)
    a.mode, a.target_velocity, a.target_torque = a.velocity_mode, a.to_units(v), 0


def torque(a: AxisTrack, torque: float) -> None:
    """Its torque mode, target ``torque`` (N.m at the output) within the run's limit;
    :class:`NodeError` on a drive without one."""
    if a.torque_mode is None:
        raise NodeError(
            f"{a.where()}: the drive has no torque mode (0x6502): drive it by "
            "velocity", node=a.node, axis=int(a.axis),
        )  # fmt: skip
    t = max(-a.max_torque, min(a.max_torque, torque))
    a.mode, a.target_torque = a.torque_mode, a.torque_units(t)


def homing(mt: ModuleTrack, a: AxisTrack, sync_seq: int) -> None:
    """Mode 6 and the start of the homing of ``mt``'s steering ``a`` (the power state
    machine sends the start edge of controlword bit 4 once the modes display shows
    homing; only statuswords answering a later SYNC than ``sync_seq`` tell)."""
    powered(a, sync_seq)
    a.mode = Mode.HOMING
    a.homing_start = True
    a.homing_sync = sync_seq
    mt.homing = HomingState.IN_PROGRESS


def mode_changed(a: AxisTrack, before: Mode, sync_seq: int) -> bool:
    """Whether a command changed ``a``'s mode from ``before``: if so, the drive's display
    of it is awaited from SYNC ``sync_seq`` on."""
    changed = a.mode is not before
    if changed:
        a.mode_sync = sync_seq
        a.refused_reported = False
        a.pp_acked = None  # profile position: the first target handed over
    return changed


def clear_fault(a: AxisTrack) -> None:
    """A fault reset, if ``a`` is in FAULT or has an error code."""
    # the code stays until the drive has left FAULT: a FAULT statusword
    # still on its way is then not taken for a new fault
    if a.state in FAULTED or a.error_code:
        a.reset = True


def stop(a: AxisTrack, now: float) -> None:
    """Every request of ``a`` dropped: disable voltage (its power stage off), torque 0."""
    a.enable = a.unpowered = False
    a.homing_start = False
    a.reset = False
    a.target_torque = 0
    a.controlword = cia402.CW_DISABLE_VOLTAGE
    a.t_controlword = now
    a.enable_sync = a.enable_start = -1
