"""The ``cia402`` kind's process data: the RPDOs built from an axis's track, the TPDOs read
into it (pure builders apart from the transport).

No clock, no lock, no I/O: :class:`swpc_hw.drives.cia402.driver.Cia402Driver` sends the
RPDOs these build (the targets', then the command's), and hands each TPDO canopen
received to :func:`on_tpdo` under its lock with the frame's arrival on its clock; the
driver keeps the samples.  canopen packs the PDOs: a builder sets the objects of the
node's PDO maps (the mapping the set-up wrote, :func:`swpc_hw.drives.cia402.setup.place`:
:attr:`~swpc_hw.drives.cia402.tracking.AxisTrack.rpdos` says which carry which group) and
reads their data back.

* :func:`command_frames` -- the command group (RPDO 1 on most drives): controlword, mode,
  target torque.
* :func:`target_frames` -- the targets group (RPDO 2 on most drives): position and
  velocity; :func:`streams_targets` says whether they go before every SYNC.
* :func:`on_tpdo` -- a TPDO into the track: the sample group completes a statusword and
  position (:func:`swpc_hw.drives.cia402.tracking.on_statusword`), and the module's
  sample once both axes answered the same SYNC (:func:`~swpc_hw.drives.cia402.tracking.
  pair`); the velocity and torque group fills them in that sample
  (:func:`with_velocity_torque`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import canopen
from canopen.pdo.base import PdoMap

from firmware_protocol import cia402
from firmware_protocol.cia402 import Mode, PowerState
from firmware_protocol.codec import Frame
from swpc_hw.drives.cia402.tracking import AxisTrack, ModuleTrack, on_statusword, pair
from swpc_hw.drives.types import FeedbackSample, Observation

CYCLIC = (Mode.CYCLIC_SYNC_POSITION, Mode.CYCLIC_SYNC_VELOCITY)
"""The modes whose drive takes a target in every SYNC cycle (:func:`streams_targets`)."""


def pdo_frames(
    node: canopen.RemoteNode, a: AxisTrack, group: int, values: dict[int, int]
) -> list[Frame]:
    """The RPDOs of one group of ``a`` (:attr:`AxisTrack.rpdos`), each object it maps
    set from ``values`` (an object the drive lacks is in no map)."""
    out = []
    for i in a.rpdos[group]:
        p = node.rpdo[i]
        for v in p.map:
            if v.index in values:
                p[f"0x{v.index:04X}"].raw = values[v.index]
        out.append(Frame(p.cob_id or cia402.RPDO_BASE[i - 1] + a.node, bytes(p.data)))
    return out


def target_frames(node: canopen.RemoteNode, a: AxisTrack) -> list[Frame]:
    """The targets' RPDOs of ``a`` (RPDO 2 on most drives): position and velocity."""
    values = {cia402.TARGET_POSITION: a.target_position,
              cia402.TARGET_VELOCITY: a.target_velocity}  # fmt: skip
    return pdo_frames(node, a, 1, values)


def command_frames(node: canopen.RemoteNode, a: AxisTrack) -> list[Frame]:
    """The command's RPDOs of ``a`` (RPDO 1 on most drives): controlword, mode (unless
    over SDO), target torque (where it has a torque mode)."""
    values = {cia402.CONTROLWORD: a.controlword, cia402.MODES_OF_OPERATION: int(a.mode),
              cia402.TARGET_TORQUE: a.target_torque}  # fmt: skip
    return pdo_frames(node, a, 0, values)


def streams_targets(a: AxisTrack) -> bool:
    """Whether ``a``'s targets go before each SYNC: its cyclic synchronous mode is in
    force.  Such a drive takes the target received in each SYNC cycle, and extrapolates or
    holds when none came (CiA 402), so the target is sent every cycle, not only when it
    changes; before the mode is in force a target is not taken."""
    enabled = a.state is PowerState.OPERATION_ENABLED
    return a.enable and enabled and a.mode in CYCLIC and a.mode_display == a.mode


@dataclass
class Received:
    """What one TPDO told: observations (in order), the SYNC whose module sample it
    completed (None: none), and whether it completed the velocity and torque group."""

    observations: list[Observation] = field(default_factory=list)
    sample: int | None = None
    velocity_torque: bool = False


def on_tpdo(mt: ModuleTrack, a: AxisTrack, i: int, p: PdoMap, t: float) -> Received:
    """TPDO ``i`` of ``a`` (module ``mt``), arrived at ``t``: its objects kept; the last
    TPDO of the sample group completes a statusword and position (:attr:`AxisTrack.tpdos`),
    the last of the velocity and torque group those."""
    out = Received()
    mt.feedback_frames += 1
    got = a.tpdo_values
    for v in p.map:
        got[v.index] = int(v.raw)
    if i == a.tpdos[0][-1]:
        sw = got.get(cia402.STATUSWORD, 0)
        pos = got.get(cia402.POSITION_ACTUAL, 0)
        disp = got.get(cia402.MODES_DISPLAY, 0)
        a.answered += 1
        seq = a.sync_base + a.answered
        out.observations = on_statusword(mt, a, sw, disp, pos, seq, t)
        out.sample = pair(mt)
    elif len(a.tpdos) > 1 and i == a.tpdos[1][-1]:
        if cia402.VELOCITY_ACTUAL in got:  # 0x606C and 0x6077 are optional
            a.velocity = got[cia402.VELOCITY_ACTUAL] / a.counts_per_rad
        if cia402.TORQUE_ACTUAL in got:
            a.torque = a.torque_si(got[cia402.TORQUE_ACTUAL])
        out.velocity_torque = True
    return out


def with_velocity_torque(
    mt: ModuleTrack, a: AxisTrack, last: FeedbackSample | None
) -> FeedbackSample | None:
    """The module's latest sample ``last`` with its axes' velocities and torques, once
    ``a``'s velocity and torque group answered that sample's SYNC (None otherwise: the
    sample keeps NaN)."""
    if last is None or last.seq != a.seq:
        return None
    return dataclasses.replace(
        last, steer_velocity=mt.steer.velocity, wheel_velocity=mt.wheel.velocity,
        steer_torque=mt.steer.torque, wheel_torque=mt.wheel.torque,
    )  # fmt: skip
