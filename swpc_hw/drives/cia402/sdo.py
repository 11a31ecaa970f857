"""canopen's SDO client, waiting on the drives' clock.

canopen's :class:`~canopen.sdo.SdoClient` waits for each response on a queue in real time.
Against the in-process simulator (lockstep, :class:`swpc_hw.clock.SimClock`) time moves
only while someone waits *on the clock*, and the simulator answers a request only then:
a real-time wait would see no answer at all.  Here the wait is the clock's
(:meth:`swpc_hw.clock.Clock.wait`): on a robot the same real-time wait as canopen's, in
lockstep a wait that lets the simulation run until the response has been delivered.  The
response timeout is robot time: the drives' heartbeat loss window ``L`` of the timing budget
(:mod:`services.config.timing`; 0.3 s on a robot, canopen's own default, and floored like
it against a slow external simulator): a drive that has not answered within the time it
would take to be judged lost has not answered.  Everything else (expedited, segmented and block
transfers, aborts, retries) is canopen's.
"""

from __future__ import annotations

import queue
import struct
import threading
from typing import Any

import canopen
from canopen.sdo.client import SdoClient
from canopen.sdo.constants import RESPONSE_ABORTED
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from swpc_hw.clock import Clock, wait_until


class ClockedSdoClient(SdoClient):
    """:class:`~canopen.sdo.SdoClient` whose response wait is on ``clock`` (module
    docstring)."""

    MAX_RETRIES = 3
    """canopen's retry of a request that got no answer (its default: none): a drive, or a
    simulator on a slow machine, that missed one is asked again before the set-up fails."""

    def __init__(
        self, rx_cobid: int, tx_cobid: int, od: Any, clock: Clock, timeout: float
    ) -> None:
        super().__init__(rx_cobid, tx_cobid, od)
        self.clock = clock
        self.timeout = timeout
        self._arrived = threading.Condition()

    def on_response(self, can_id: int, data: bytearray, timestamp: float) -> None:
        with self._arrived:
            self.responses.put(bytes(data))
            self._arrived.notify_all()

    def read_response(self) -> bytes:
        with self._arrived:
            deadline = self.clock.now() + self.timeout
            got = wait_until(
                self.clock, self._arrived, lambda: not self.responses.empty(), deadline
            )
        if not got:
            raise SdoCommunicationError("No SDO response received")
        try:
            response = self.responses.get_nowait()
        except queue.Empty:
            raise SdoCommunicationError("No SDO response received") from None
        (command,) = struct.unpack_from("B", response)
        if command == RESPONSE_ABORTED:
            (code,) = struct.unpack_from("<L", response, 4)
            raise SdoAbortedError(code)
        return bytes(response)


class ClockedRemoteNode(canopen.RemoteNode):
    """A :class:`canopen.RemoteNode` whose SDO client waits on ``clock`` up to ``timeout``."""

    def __init__(
        self, node_id: int, object_dictionary: Any, clock: Clock, timeout: float
    ) -> None:
        self._clock = clock
        self._timeout = timeout
        super().__init__(node_id, object_dictionary)

    def add_sdo(self, rx_cobid: int, tx_cobid: int) -> ClockedSdoClient:
        client = ClockedSdoClient(
            rx_cobid, tx_cobid, self.object_dictionary, self._clock, self._timeout
        )
        self.sdo_channels.append(client)
        if self.has_network():
            self.network.subscribe(client.tx_cobid, client.on_response)
        return client
