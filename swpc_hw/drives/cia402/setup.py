"""A CiA 402 drive's set-up over SDO, once per boot, before it is started.

In PRE-OPERATIONAL: heartbeat producer 0x1017 = ``heartbeat_period_s``, heartbeat
consumer 0x1016 on the host's heartbeat with the command watchdog (``watchdog_timeout_ms``)
as its time, quick-stop option 0x605A, homing method 0x6098, the motor's rated torque
0x6076 read, the factor group (0x608F, 0x6091) and the modes (0x6502) checked against the
config, the PDO mapping of :data:`firmware_protocol.cia402.RPDO_MAP` /
:data:`~firmware_protocol.cia402.TPDO_MAP` written (before anything uses it).
"""

from __future__ import annotations

import math

from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from firmware_protocol import cia402
from firmware_protocol.cia402 import Mode
from firmware_protocol.codec import Axis
from swpc_hw.drives.bus import CanConfig
from swpc_hw.drives.cia402.config import ABSOLUTE, Cia402Drives
from swpc_hw.drives.cia402.sdo import ClockedRemoteNode
from swpc_hw.drives.cia402.tracking import AxisTrack
from swpc_hw.drives.errors import NodeError
from swpc_hw.drives.types import AXIS_NAMES


def set_up(
    node: ClockedRemoteNode, a: AxisTrack, drives: Cia402Drives, cfg: CanConfig
) -> None:
    """One drive's set-up over SDO in PRE-OPERATIONAL (module docstring); the caller
    starts it (NMT) once its track is marked configured.  :class:`NodeError` names the
    object that failed and why."""
    node.nmt.send_command(cia402.NMT_ENTER_PRE_OPERATIONAL)
    axes = drives.axes()[a.module]
    ax = axes.steer if a.axis is Axis.STEER else axes.wheel
    step = "0x1000"
    try:
        step = "0x1017 producer heartbeat time"
        node.sdo[cia402.PRODUCER_HEARTBEAT].raw = round(1000 * cfg.heartbeat_period_s)
        step = "0x1016 consumer heartbeat time"
        node.sdo[cia402.CONSUMER_HEARTBEAT][1].raw = cia402.consumer_entry(
            drives.host_node, cfg.watchdog_timeout_ms
        )
        step = "0x605A quick stop option code"
        node.sdo[cia402.QUICK_STOP_OPTION].raw = drives.quick_stop_option
        step = "0x6502 supported drive modes"
        supported = int(node.sdo[cia402.SUPPORTED_MODES].raw)
        needed = [Mode.CYCLIC_SYNC_POSITION, Mode.CYCLIC_SYNC_TORQUE]
        homing = getattr(ax, "homing", ABSOLUTE)
        if homing != ABSOLUTE:
            needed.append(Mode.HOMING)
        missing = [m.name for m in needed if not supported & cia402.supported_modes_bit(m)]
        if missing:
            raise NodeError(
                f"{a.where()}: the drive does not support mode(s) {', '.join(missing)} "
                f"(0x6502 = 0x{supported:08X})",
                node=a.node,
                axis=int(a.axis),
            )
        if homing != ABSOLUTE:
            step = f"0x6098 homing method {homing}"
            node.sdo[cia402.HOMING_METHOD].raw = int(homing)
        step = "0x6076 motor rated torque"
        a.rated_torque = int(node.sdo[cia402.RATED_TORQUE].raw) / 1000.0
        od = node.object_dictionary
        if cia402.ENCODER_RESOLUTION in od:
            step = "0x608F position encoder resolution"
            inc = int(node.sdo[cia402.ENCODER_RESOLUTION][1].raw)
            rev = int(node.sdo[cia402.ENCODER_RESOLUTION][2].raw)
            _check_factor(a, "counts_per_turn", ax.counts_per_turn, inc / rev, step)
        if cia402.GEAR_RATIO in od:
            step = "0x6091 gear ratio"
            mot = int(node.sdo[cia402.GEAR_RATIO][1].raw)
            shaft = int(node.sdo[cia402.GEAR_RATIO][2].raw)
            _check_factor(a, "gear_ratio", ax.gear_ratio, mot / shaft, step)
        for maps, layout, base, ttype in (
            (node.tpdo, cia402.TPDO_MAP, cia402.TPDO_BASE, cia402.TPDO_ON_SYNC),
            (node.rpdo, cia402.RPDO_MAP, cia402.RPDO_BASE, cia402.RPDO_ASYNC),
        ):
            for i, entries in layout.items():
                step = f"PDO mapping {'TPDO' if maps is node.tpdo else 'RPDO'} {i}"
                p = maps[i]
                p.read()
                p.clear()
                for index, sub, bits in entries:
                    p.add_variable(index, sub, bits)
                p.cob_id = base[i - 1] + a.node
                p.trans_type = ttype
                p.event_timer = 0 if maps is node.tpdo else None
                p.enabled = True
                p.save()
    except (SdoAbortedError, SdoCommunicationError) as exc:
        raise NodeError(
            f"{a.where()}: set-up {step}: {exc}", node=a.node, axis=int(a.axis)
        ) from exc


def _check_factor(a: AxisTrack, key: str, mine: float, theirs: float, obj: str) -> None:
    if not math.isclose(mine, theirs, rel_tol=1e-9):
        raise NodeError(
            f"{a.where()}: drives.modules.{a.module}.{AXIS_NAMES[a.axis]}.{key} is {mine:g} "
            f"but the drive's {obj} says {theirs:g}: the units would be wrong",
            node=a.node,
            axis=int(a.axis),
        )
