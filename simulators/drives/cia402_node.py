"""The CANopen side of a virtual CiA 402 axis (:mod:`simulators.drives.cia402`): canopen's
:class:`canopen.LocalNode` on the virtual robot's simulated time, with what CiA 301 asks of
it beside the drive profile.

* :class:`SimNetwork`: a network of one node whose sends are collected (the virtual robot
  stamps them and puts them on its bus) and whose periodic sends (the library's heartbeat
  producer, :class:`SimPeriodic`) run on the simulated time, never on a thread;
* :class:`SimNode`: the node on it, its object dictionary read and written as the drive
  itself does (:meth:`SimNode._store`, :meth:`SimNode._read`), its PDOs (RPDOs applied on
  reception, a refused value dropped; TPDOs on SYNC, transmission types 1..240), node
  guarding with life guarding (0x100C, 0x100D) and the error behaviour after a
  communication error (0x1029 sub 1: 0 pre-operational, 1 no change, 2 stopped).
  :class:`~simulators.drives.cia402.VirtualAxis` is one, with the 402 drive around it.
"""

from __future__ import annotations

import math
import struct
from pathlib import Path

import can
import canopen
from canopen.network import PeriodicMessageTask
from canopen.objectdictionary import ODVariable
from canopen.pdo.base import PdoMap
from canopen.sdo.exceptions import SdoAbortedError

from firmware_protocol import cia402

ERROR_BEHAVIOUR = 0x1029
"""CiA 301's error behaviour object: sub 1, the NMT state a communication error leads to."""
NMT_STOP = 0x02
NMT_CODES = {v: k for k, v in canopen.nmt.NMT_STATES.items()}
"""canopen's NMT state names -> CiA 301's state codes (a guard answer's bits 0-6)."""


class SimPeriodic(PeriodicMessageTask):
    """A periodic send (canopen's heartbeat producer) on the simulated time of
    :class:`SimNetwork` instead of a thread."""

    def __init__(self, can_id: int, data: bytes, period: float, start: float) -> None:
        self.can_id = can_id
        self.data = bytes(data)
        self.period = period
        self.next = start + period
        self.stopped = False

    def stop(self) -> None:
        self.stopped = True

    def update(self, data: bytes) -> None:
        self.data = bytes(data)


class SimNetwork(canopen.Network):
    """A canopen network of one node inside the virtual robot: what the node sends is
    collected (the robot stamps it and puts it on its bus), periodic sends run on the
    simulated time ``now``."""

    def __init__(self) -> None:
        super().__init__(None)
        self.outbox: list[can.Message] = []
        self.tasks: list[SimPeriodic] = []
        self.now = 0.0

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        self.outbox.append(
            can.Message(arbitration_id=can_id, data=bytes(data), is_extended_id=False)
        )

    def send_periodic(
        self, can_id: int, data: bytes, period: float, remote: bool = False
    ) -> PeriodicMessageTask:
        task = SimPeriodic(can_id, data, period, self.now)
        self.tasks = [t for t in self.tasks if not t.stopped] + [task]
        return task

    def run_periodic(self, now: float) -> None:
        for t in self.tasks:
            if not t.stopped and t.next <= now + 1e-9:
                self.send_message(t.can_id, t.data)
                t.next = max(t.next + t.period, now + 0.5 * t.period)

    def next_due(self) -> float:
        return min((t.next for t in self.tasks if not t.stopped), default=math.inf)

    def take(self) -> list[can.Message]:
        out, self.outbox = self.outbox, []
        return out


class SimNode:
    """A :class:`canopen.LocalNode` on its own :class:`SimNetwork` (module docstring)."""

    def __init__(self, node_id: int, object_dictionary: Path) -> None:
        self.node_id = node_id
        self.net = SimNetwork()
        od = canopen.import_od(str(object_dictionary), node_id)
        self.node = canopen.LocalNode(node_id, od)
        self.net.add_node(self.node)
        assert self.node.rpdo.map is not None and self.node.tpdo.map is not None
        for pdo in self.node.rpdo.map.values():
            pdo.add_callback(self._on_rpdo)
        self._formats: dict[int, struct.Struct] = {}
        self.guard_toggle = 0
        self.guarded_at: float | None = None
        """Life guarding: the last guard request, once 0x100C and 0x100D are both set."""
        self.life_time = 0.0
        """s: 0x100C x 0x100D as they were at the last guard request."""

    # ------------------------------------------------------------------ object dictionary
    def _od_default(self, index: int, sub: int = 0) -> int:
        obj = self.node.object_dictionary[index]
        var = obj if isinstance(obj, ODVariable) else obj[sub]
        return int(var.default or 0)

    def _store(self, index: int, value: int) -> None:
        if index not in self.node.object_dictionary:
            return  # an object this drive (its personality) does not have
        fmt = self._formats.get(index)
        if fmt is None:
            var = self.node.object_dictionary[index]
            assert isinstance(var, ODVariable)
            fmt = var.STRUCT_TYPES[int(var.data_type or 0)]
            self._formats[index] = fmt
        self.node.data_store.setdefault(index, {})[0] = fmt.pack(value)

    def _read(self, index: int, sub: int = 0) -> int:
        obj = self.node.object_dictionary[index]
        var = obj if isinstance(obj, ODVariable) else obj[sub]
        return int(var.decode_raw(self.node.get_data(index, sub)))

    # ------------------------------------------------------------------ PDOs
    def _on_rpdo(self, pdo: PdoMap) -> None:
        for var in pdo.map:
            try:
                self.node.set_data(var.index, var.subindex, var.get_data())
            except SdoAbortedError:
                continue  # a refused value (e.g. a mode): the drive keeps its own

    def _transmit_tpdos(self, sync_count: int) -> None:
        """At the ``sync_count``-th SYNC: every enabled TPDO of transmission type 1..240
        that is due, with what the object dictionary holds now."""
        get = self.node.get_data
        assert self.node.tpdo.map is not None
        for pdo in self.node.tpdo.map.values():
            every = pdo.trans_type or 0
            if not pdo.enabled or not 1 <= every <= 240 or sync_count % every:
                continue
            # the mapped objects' bytes, in map order (swpc maps whole bytes: no bit packing)
            pdo.data = bytearray(b"".join(get(v.index, v.subindex) for v in pdo.map))
            pdo.transmit()

    # ------------------------------------------------------------------ CiA 301 error control
    def _guard_time(self) -> float:
        """Life guarding's time, s: 0x100C ms x 0x100D (0: off, or no such objects)."""
        od = self.node.object_dictionary
        if cia402.GUARD_TIME not in od or cia402.LIFE_TIME_FACTOR not in od:
            return 0.0
        return self._read(cia402.GUARD_TIME) * self._read(cia402.LIFE_TIME_FACTOR) / 1000.0

    def _guard(self, now: float) -> None:
        """Node guarding (CiA 301): the answer is the NMT state with a toggle bit 7 that
        alternates from 0; life guarding starts with the first request while 0x100C and
        0x100D are both non-zero.  A drive without them does not answer."""
        od = self.node.object_dictionary
        if cia402.GUARD_TIME not in od or self.node.nmt.state == "INITIALISING":
            return
        state = NMT_CODES.get(self.node.nmt.state, cia402.NMT_PRE_OPERATIONAL)
        self.net.send_message(cia402.HEARTBEAT_BASE + self.node_id,
                              bytes([self.guard_toggle | state]))  # fmt: skip
        self.guard_toggle ^= 0x80
        self.life_time = self._guard_time()  # as the objects say at this request
        self.guarded_at = now if self.life_time > 0 else None

    def _error_behaviour(self) -> None:
        """After a communication error in OPERATIONAL: the NMT state 0x1029 sub 1 says."""
        if self.node.nmt.state == "OPERATIONAL":
            behaviour = (
                self._read(ERROR_BEHAVIOUR, 1)
                if ERROR_BEHAVIOUR in self.node.object_dictionary
                else 0
            )
            if behaviour == 0:
                self.node.nmt.send_command(cia402.NMT_ENTER_PRE_OPERATIONAL)
            elif behaviour == 2:
                self.node.nmt.send_command(NMT_STOP)
