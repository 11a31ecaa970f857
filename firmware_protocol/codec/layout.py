"""The hot path: a DBC message's layout compiled at import (:func:`frame_layout`: every
signal's start bit, length, sign, scaling and range) and :func:`pack_frame` /
:func:`unpack_frame`, which give exactly cantools' bytes and values for a valid frame
(anything else goes through cantools)."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any

from firmware_protocol.codec.dbc import _messages_by_id


@dataclass(frozen=True)
class SignalLayout:
    """Where one signal of a little-endian integer DBC message lives, and its scaling:
    ``raw = bits[start : start + length]`` (two's complement if signed) and
    ``value = raw`` (identity) or ``raw * scale + offset``."""

    name: str
    start: int
    length: int
    signed: bool
    identity: bool
    scale: float
    offset: float
    low: float
    high: float
    mux_ids: frozenset[int] | None
    """Multiplexed: present only when the multiplexer signal has one of these values."""
    is_mux: bool
    minimum: float | None
    maximum: float | None
    """The DBC range as written (decoded values are checked against it)."""

    @property
    def mask(self) -> int:
        return (1 << self.length) - 1


@functools.cache
def frame_layout(frame_id: int) -> tuple[SignalLayout, ...] | None:
    """The compiled layout of a DBC message (None when a signal is big-endian or float:
    such messages always go through cantools).  Ranges as cantools' strict encoding
    checks them (``minimum - |scale| 1e-6 <= value <= maximum + |scale| 1e-6``)."""
    msg = _messages_by_id()[frame_id]
    out = []
    for sig in msg.signals:
        if sig.byte_order != "little_endian" or sig.is_float:
            return None
        conv = sig.conversion
        tol = abs(conv.scale) * 1e-6
        out.append(
            SignalLayout(
                name=str(sig.name),
                start=int(sig.start),
                length=int(sig.length),
                signed=bool(sig.is_signed),
                identity=conv.scale == 1 and conv.offset == 0,
                scale=float(conv.scale),
                offset=float(conv.offset),
                low=-math.inf if sig.minimum is None else sig.minimum - tol,
                high=math.inf if sig.maximum is None else sig.maximum + tol,
                mux_ids=None if sig.multiplexer_ids is None else frozenset(sig.multiplexer_ids),
                is_mux=bool(sig.is_multiplexer),
                minimum=sig.minimum,
                maximum=sig.maximum,
            )
        )
    # multiplexers first: the others' presence depends on them
    return tuple(sorted(out, key=lambda s: not s.is_mux))


def pack_frame(layout: tuple[SignalLayout, ...], values: dict[str, Any]) -> int | None:
    """The frame's bits as an integer (little-endian), or None unless ``values`` certainly
    encodes: exactly the signals the multiplexer selects, each an int or float within its
    range.  ``raw = round(value)`` (identity) or ``round((value - offset) / scale)``, as
    cantools."""
    acc = 0
    used = 0
    mux: Any = None
    for s in layout:
        if s.mux_ids is not None and mux not in s.mux_ids:
            continue
        v = values.get(s.name)
        if not isinstance(v, int | float) or isinstance(v, bool):
            return None
        x = float(v)  # exact: signals are at most 53 bits wide
        if not s.low <= x <= s.high:
            return None
        if s.is_mux:
            mux = v
        raw = round(x) if s.identity else round((x - s.offset) / s.scale)
        acc |= (raw & s.mask) << s.start
        used += 1
    return acc if used == len(values) else None


def unpack_frame(layout: tuple[SignalLayout, ...], data: bytes) -> dict[str, Any]:
    """Every signal present in ``data`` (the multiplexer decides), scaled as cantools
    decodes with ``scaling=True``: identity signals as ints, the others
    ``raw * scale + offset``."""
    acc = int.from_bytes(data, "little")
    out: dict[str, Any] = {}
    mux: int | None = None
    for s in layout:
        if s.mux_ids is not None and mux not in s.mux_ids:
            continue
        raw = (acc >> s.start) & s.mask
        if s.signed and raw >> (s.length - 1):
            raw -= 1 << s.length
        if s.is_mux:
            mux = raw
        out[s.name] = raw if s.identity else raw * s.scale + s.offset
    return out
