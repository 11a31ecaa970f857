"""The codec's exceptions: a frame that cannot be encoded or decoded.

Each is a :class:`ProtocolError` (a :class:`~firmware_protocol.errors.FirmwareProtocolError`
and a :class:`ValueError`) whose message names the node, the message and the signal.
"""

from __future__ import annotations

from firmware_protocol.errors import FirmwareProtocolError


class ProtocolError(FirmwareProtocolError, ValueError):
    """A frame cannot be encoded or decoded; the message names node, message and signal."""


class UnknownFrameError(ProtocolError):
    """The frame id is not in the DBC (or its node is not a controller node)."""


class FrameLengthError(ProtocolError):
    """The frame's DLC differs from the DBC length of its message."""


class SignalRangeError(ProtocolError):
    """A signal value lies outside the DBC range [minimum, maximum]."""

    def __init__(self, message: str, signal: str) -> None:
        super().__init__(message)
        self.signal = signal
