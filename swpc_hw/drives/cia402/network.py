"""canopen's side of the ``cia402`` kind outside the set-up: the host's network on the
driver's bus, a remote node per axis, the host's NMT frames and the SDO requests of the
activation and the commands.

The set-up's requests (once per boot of a drive) are :mod:`swpc_hw.drives.cia402.setup`'s;
these are the driver's at other times: whether a drive answers at all (0x1000, else
:func:`unreachable`), its error code (0x603F) for the error of a fault that a reset does
not clear (:func:`fault_at_start`), the mode where 0x6060 is not PDO-mappable, the run's
limits.  Each goes through the axis's node
(:class:`~swpc_hw.drives.cia402.sdo.ClockedRemoteNode`: its SDO waits on the driver's
clock); the frames are built here and sent by
:class:`swpc_hw.drives.cia402.driver.Cia402Driver`.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable

import can
import canopen
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from firmware_protocol import cia402
from firmware_protocol.cia402 import Mode
from firmware_protocol.codec import Axis, Frame
from swpc_hw.clock import Clock
from swpc_hw.drives.cia402.config import Cia402Drives
from swpc_hw.drives.cia402.sdo import ClockedRemoteNode
from swpc_hw.drives.cia402.setup import OPTIONAL, PROFILE_VELOCITY
from swpc_hw.drives.cia402.tracking import AxisTrack
from swpc_hw.drives.errors import CanBusError, NodeError, NodeTimeoutError


class HostNetwork(canopen.Network):
    """canopen's network on the driver's bus: every frame it sends goes out through
    ``sender`` (the driver's: stamped with the driver clock's wall time, counted and
    logged; no notifier: the driver feeds it)."""

    def __init__(self, bus: can.BusABC, sender: Callable[[int, bytes], None]) -> None:
        super().__init__(bus)
        self.sender = sender

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        self.sender(can_id, bytes(data))


def read_eds(drives: Cia402Drives) -> None:
    """Every object dictionary of ``drives`` read (:class:`CanBusError` names one that is
    not an EDS/DCF), before the bus opens."""
    for eds in drives.eds_files():
        try:
            canopen.import_od(str(eds))
        except Exception as exc:
            raise CanBusError(
                f"drives.object_dictionary {eds}: cannot read it as an EDS/DCF: {exc}"
            ) from exc


def remote_node(
    drives: Cia402Drives, a: AxisTrack, clock: Clock, timeout: float
) -> ClockedRemoteNode:
    """``a``'s drive as canopen's remote node: its axis' object dictionary, its SDO
    waiting on ``clock`` up to ``timeout``."""
    mc = drives.axes()[a.module]
    return ClockedRemoteNode(
        a.node,
        str(drives.eds(mc.steer if a.axis == Axis.STEER else mc.wheel)),
        clock,
        timeout=timeout,
    )


def heartbeat_frame(host: int) -> Frame:
    """The host's heartbeat (node ``host``, OPERATIONAL)."""
    return Frame(cia402.HEARTBEAT_BASE + host, bytes([cia402.NMT_OPERATIONAL]))


def guard_frame(a: AxisTrack) -> Frame:
    """Node guarding's request of ``a``'s state (a remote frame, 1 byte)."""
    return Frame(cia402.HEARTBEAT_BASE + a.node, b"\x00", remote=True)


def answers(node: canopen.RemoteNode) -> bool:
    """The drive answers an SDO request (0x1000; an abort is an answer)."""
    try:
        node.sdo.upload(cia402.DEVICE_TYPE, 0)
    except SdoCommunicationError:
        return False
    except SdoAbortedError:
        pass  # an abort is an answer
    return True


def error_code(node: canopen.RemoteNode, a: AxisTrack) -> str:
    """The drive's error code 0x603F, named (or the one its EMCY gave)."""
    code = a.error_code
    if cia402.ERROR_CODE in node.object_dictionary:
        with contextlib.suppress(SdoAbortedError, SdoCommunicationError):
            code = int(node.sdo[cia402.ERROR_CODE].raw)
    return f"error code 0x603F = 0x{code:04X} ({cia402.emcy_name(code)})"


def unreachable(a: AxisTrack, timeout: float, channel: str) -> NodeTimeoutError:
    """A drive that answered no SDO request (0x1000), even after NMT reset communication
    and ``timeout`` s for its boot-up, on bus ``channel``."""
    return NodeTimeoutError(
        f"{a.where()}: no answer to an SDO request (0x1000) and no boot-up after NMT "
        f"reset communication within {timeout:g} s: check its power, its wiring "
        f"to this bus ({channel}) and its node id",
        node=a.node,
    )


def fault_at_start(node: canopen.RemoteNode, a: AxisTrack, timeout: float) -> NodeError:
    """A drive in FAULT since before the run that a fault reset did not clear within
    ``timeout`` s: its error code (0x603F) named."""
    return NodeError(
        f"{a.where()}: in FAULT since before the run, and a fault reset did "
        f"not clear it within {timeout:g} s: {error_code(node, a)}; "
        "its cause is still there (the drive's manual says what each code "
        "needs)",
        node=a.node,
        axis=int(a.axis),
    )


def write_mode(node: canopen.RemoteNode, a: AxisTrack) -> None:
    """0x6060 over SDO (a drive on which it is not PDO-mappable)."""
    try:
        node.sdo[cia402.MODES_OF_OPERATION].raw = int(a.mode)
    except (SdoAbortedError, SdoCommunicationError) as exc:
        raise NodeError(
            f"{a.where()}: mode {cia402.mode_name(a.mode)} (0x6060 over SDO): {exc}",
            node=a.node, axis=int(a.axis),
        ) from exc  # fmt: skip


def write_limits(
    node: canopen.RemoteNode, a: AxisTrack, torque: int, velocity: int, say: Callable[[str], None]
) -> None:
    """0x6072 max torque and 0x607F max profile velocity (the drive's units) where the
    drive has them (:attr:`AxisTrack.has_limits`: one its EDS has and the drive lacks is
    said, once, and left to the host's limit), and 0x6081 in profile position."""
    has = list(a.has_limits)
    for k, (index, value) in enumerate(
        ((cia402.MAX_TORQUE, torque), (cia402.MAX_PROFILE_VELOCITY, velocity))
    ):
        if not has[k]:
            continue
        try:
            node.sdo[index].raw = value
        except SdoAbortedError as exc:
            if exc.code not in cia402.SDO_ABSENT:
                raise NodeError(
                    f"{a.where()}: set limits 0x{index:04X}: {exc}", node=a.node, axis=int(a.axis)
                ) from exc
            has[k] = False  # its EDS has it, the drive does not: the host's limit only
            say(f"{a.where()}: no 0x{index:04X} on the drive: {OPTIONAL[index]}")
        except SdoCommunicationError as exc:
            raise NodeError(
                f"{a.where()}: set limits 0x{index:04X}: {exc}", node=a.node, axis=int(a.axis)
            ) from exc
    a.has_limits = (has[0], has[1])
    if a.position_mode is Mode.PROFILE_POSITION and a.has_profile_velocity:
        try:  # profile position travels at 0x6081: the run's velocity limit
            node.sdo[PROFILE_VELOCITY].raw = velocity
        except (SdoAbortedError, SdoCommunicationError) as exc:
            raise NodeError(
                f"{a.where()}: set limits 0x6081: {exc}", node=a.node, axis=int(a.axis)
            ) from exc
