"""The error root of the CAN protocol package (frames are pure data: no other import)."""

from __future__ import annotations


class FirmwareProtocolError(Exception):
    """Root of every error raised by :mod:`firmware_protocol`."""
