"""A Qualisys Track Manager (QTM) as far as its real-time protocol goes: 6DOF bodies.

The subset a rigid-body client uses, on the little-endian port (22223 on a real QTM; any
free loopback port here), as Qualisys' own client library ``qtm-rt`` speaks it
(``tests/sensors/test_mocap_bridge.py`` runs it against this server):

* every packet: ``uint32 size`` (header included), ``uint32 type`` (0 error, 1 command,
  2 XML, 3 data, 4 no more data), then its body; command, error and XML bodies are text
  ending in a NUL.
* on connect the server says ``QTM RT Interface connected`` (a command packet);
  ``version X`` is answered ``Version set to X``; ``qtmversion`` its version;
  ``getparameters ...`` the XML of the 6D bodies (``<The_6D><Body><Name>``) and of the
  general settings (``<General><Frequency>``); ``streamframes <frames> 6d`` starts the
  stream (the client takes the first data packet for its answer), ``streamframes stop``
  ends it; ``getcurrentframe 6d`` sends one frame; anything else is an error packet.
* a data packet: ``int64 timestamp`` (us, QTM's capture clock), ``uint32 frame number``,
  ``uint32 component count`` (1), then the 6D component: ``uint32 size``, ``uint32 type``
  (5), ``int32 body count``, ``int16 2D drop rate``, ``int16 out of sync rate``, and per
  body ``float32 x, y, z`` (mm) and ``float32[9]`` its rotation matrix in column-major
  order; a body not seen this frame is all NaN.

Frames are what :meth:`QtmServer.publish` is given (the virtual robot's truth, or a test's
path): the server adds nothing of its own, so what a client receives is exactly that, in
float32.
"""

from __future__ import annotations

import asyncio
import math
import struct
import threading
from collections.abc import Sequence
from dataclasses import dataclass

HEADER = struct.Struct("<II")
DATA = struct.Struct("<qII")
COMPONENT = struct.Struct("<II")
SIX_D = struct.Struct("<ihh")
BODY = struct.Struct("<3f9f")
ERROR, COMMAND, XML, DATA_PACKET = 0, 1, 2, 3
COMPONENT_6D = 5
PROTOCOL_VERSION = "1.25"
WELCOME = "QTM RT Interface connected"


@dataclass(frozen=True)
class QtmBody:
    """One body in one frame: position (mm) and rotation (9 elements, column-major), or
    None when the system does not see it."""

    position: tuple[float, float, float]
    rotation: tuple[float, ...]


def text_packet(kind: int, text: str) -> bytes:
    body = text.encode() + b"\0"
    return HEADER.pack(HEADER.size + len(body), kind) + body


def data_packet(timestamp_us: int, frame: int, bodies: Sequence[QtmBody | None]) -> bytes:
    """A data packet with one 6D component (module docstring)."""
    nan = (math.nan,) * 12
    payload = b"".join(
        BODY.pack(*(nan if b is None else (*b.position, *b.rotation))) for b in bodies
    )
    six_d = SIX_D.pack(len(bodies), 0, 0) + payload
    component = COMPONENT.pack(COMPONENT.size + len(six_d), COMPONENT_6D) + six_d
    body = DATA.pack(timestamp_us, frame, 1) + component
    return HEADER.pack(HEADER.size + len(body), DATA_PACKET) + body


def parameters_xml(names: Sequence[str], frequency: float) -> str:
    """``getparameters``' answer: the 6D bodies and the general settings."""
    bodies = "".join(f"<Body><Name>{n}</Name><Enabled>true</Enabled></Body>" for n in names)
    return (
        f"<QTM_Parameters_Ver_{PROTOCOL_VERSION}><General><Frequency>{frequency:g}</Frequency>"
        f"</General><The_6D><Bodies>{len(names)}</Bodies>{bodies}</The_6D>"
        f"</QTM_Parameters_Ver_{PROTOCOL_VERSION}>"
    )


class _Client(asyncio.Protocol):
    def __init__(self, server: QtmServer) -> None:
        self.server = server
        self.transport: asyncio.Transport | None = None
        self.streaming = False
        self._buf = b""

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport
        self.server._clients.add(self)
        transport.write(text_packet(COMMAND, WELCOME))

    def connection_lost(self, exc: Exception | None) -> None:
        self.server._clients.discard(self)
        self.transport = None

    def data_received(self, data: bytes) -> None:
        self._buf += data
        while len(self._buf) >= HEADER.size:
            size, _kind = HEADER.unpack_from(self._buf)
            if size < HEADER.size or len(self._buf) < size:
                return
            body, self._buf = self._buf[HEADER.size : size], self._buf[size:]
            self._command(body.rstrip(b"\0").decode(errors="replace").strip())

    def _command(self, text: str) -> None:
        assert self.transport is not None
        words = text.lower().split()
        s = self.server
        if not words:
            self.transport.write(text_packet(ERROR, "Parse error"))
        elif words[0] == "version" and len(words) == 2:
            self.transport.write(text_packet(COMMAND, f"Version set to {words[1]}"))
        elif words[0] == "qtmversion":
            self.transport.write(text_packet(COMMAND, "QTM Version is swpc simulator"))
        elif words[0] == "getparameters":
            self.transport.write(text_packet(XML, parameters_xml(s.names, s.frequency)))
        elif words[:2] == ["streamframes", "stop"]:
            self.streaming = False
        elif words[0] == "streamframes" and "6d" in words[2:]:
            self.streaming = True
        elif words[0] == "getcurrentframe" and "6d" in words[1:]:
            self.transport.write(s._last)
        else:
            self.transport.write(text_packet(ERROR, f"Parse error: {text!r} is not supported"))


class QtmServer:
    """The QTM real-time server of the module docstring, on its own thread and event loop.

    ``names``: the 6D bodies, in the order :meth:`publish` gives them; ``frequency``: what
    the general settings say (Hz)."""

    def __init__(
        self, names: Sequence[str], host: str = "127.0.0.1", port: int = 0,
        frequency: float = 100.0,
    ) -> None:  # fmt: skip
        self.names = list(names)
        self.frequency = frequency
        self._host, self._port = host, port
        self._clients: set[_Client] = set()
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, name="qtm", daemon=True)
        self._server: asyncio.Server | None = None
        self._last = data_packet(0, 0, [None] * len(self.names))
        self.port = 0

    def start(self) -> int:
        """Listen; the port (a free one when 0 was asked)."""
        self._thread.start()
        fut = asyncio.run_coroutine_threadsafe(
            self._loop.create_server(lambda: _Client(self), self._host, self._port),
            self._loop,
        )
        self._server = fut.result(timeout=10)
        self.port = int(self._server.sockets[0].getsockname()[1])
        return self.port

    def publish(self, timestamp_us: int, frame: int, bodies: Sequence[QtmBody | None]) -> None:
        """Send one frame to every streaming client (thread-safe)."""
        if len(bodies) != len(self.names):
            raise ValueError(f"{len(bodies)} bodies for the {len(self.names)} named")
        packet = data_packet(timestamp_us, frame, bodies)
        self._loop.call_soon_threadsafe(self._send, packet)

    def _send(self, packet: bytes) -> None:
        self._last = packet
        for c in list(self._clients):
            if c.streaming and c.transport is not None:
                c.transport.write(packet)

    @property
    def streaming(self) -> int:
        """Clients streaming now."""
        return sum(c.streaming for c in list(self._clients))

    def stop(self) -> None:
        """Close every connection and the listener (idempotent)."""
        if not self._thread.is_alive():
            return

        async def close() -> None:
            for c in list(self._clients):
                if c.transport is not None:
                    c.transport.close()
            if self._server is not None:
                self._server.close()
                await self._server.wait_closed()

        asyncio.run_coroutine_threadsafe(close(), self._loop).result(timeout=10)
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(timeout=10)
        self._loop.close()
