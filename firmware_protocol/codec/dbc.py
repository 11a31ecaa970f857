"""The DBC: ``firmware_protocol/swpc.dbc`` loaded by cantools (:func:`database`), its
messages by id and command (:func:`message_for`), and what the codec reads from it: signal
scales and wrap spans (:func:`wrap`, :func:`unwrap`), the position resolutions and spans
(:data:`STEER_LSB`, :data:`STEER_SPAN`, ...), the heartbeat period and the power-up
feedback rate.  Importing it loads the DBC.
"""

from __future__ import annotations

import functools
import math
from pathlib import Path

import cantools
from cantools.database.can import Database, Message

from firmware_protocol.codec.exceptions import UnknownFrameError
from firmware_protocol.codec.ids import Command, frame_id

DBC_PATH = Path(__file__).parents[1] / "swpc.dbc"  # firmware_protocol/swpc.dbc


@functools.cache
def database() -> Database:
    """The protocol database loaded from ``swpc.dbc`` (strict)."""
    db = cantools.database.load_file(str(DBC_PATH), strict=True)
    assert isinstance(db, Database)
    return db


@functools.cache
def _messages_by_id() -> dict[int, Message]:
    return {m.frame_id: m for m in database().messages}


def _cycle_time_s(command: Command) -> float:
    """The DBC's ``GenMsgCycleTime`` of a periodic message, in s."""
    ms = database().get_message_by_frame_id(frame_id(1, command)).cycle_time
    assert ms, f"{command.name} has no cycle time in the DBC"
    return float(ms) / 1000.0


@functools.cache
def message_for(node: int, command: Command) -> Message:
    """The DBC message of ``command`` for ``node`` (cached; errors are not)."""
    try:
        return _messages_by_id()[frame_id(node, command)]
    except KeyError:
        raise UnknownFrameError(f"no DBC message for node {node} command {command.name}") from None


@functools.cache
def _signal_format(name: str, command: Command) -> tuple[float, int]:
    """``(scale, length)`` of a signal (identical in every node's copy of the message)."""
    sig = message_for(1, command).get_signal_by_name(name)
    return float(sig.scale), int(sig.length)


def signal_span(name: str, command: Command = Command.FEEDBACK_POSITION) -> float:
    """Physical span ``2**length * scale`` of a signal (the period of its wrap-around)."""
    scale, length = _signal_format(name, command)
    return float(2**length * scale)


def wrap(value: float, name: str, command: Command = Command.FEEDBACK_POSITION) -> float:
    """Wrap a physical value into a signed signal's range, as a two's-complement counter does.

    ``raw = round(value / scale)``; ``raw`` is reduced modulo ``2**length`` into
    ``[-2**(length-1), 2**(length-1))``; returns ``raw * scale``.
    """
    scale, length = _signal_format(name, command)
    raw = round(value / scale)
    half = 1 << (length - 1)
    raw = (raw + half) % (1 << length) - half
    return float(raw * scale)


def unwrap(previous: float, current: float, span: float) -> float:
    """Continuous angle from a wrapped reading.

    ``current + k * span`` with the integer ``k`` that puts it within ``span / 2`` of
    ``previous`` (the last unwrapped value): ``k = round((previous - current) / span)``.
    """
    return current + span * round((previous - current) / span)


def signal_scale(name: str, command: Command = Command.FEEDBACK_POSITION) -> float:
    """Physical value of one count of a signal (its DBC scale), e.g. rad per count."""
    return float(message_for(1, command).get_signal_by_name(name).scale)


STEER_LSB = signal_scale("SteerPosition")
"""Steering position resolution, rad per count: ``2*pi/2**17``."""
WHEEL_LSB = signal_scale("WheelPosition")
"""Wheel position resolution, rad per count: ``2*pi/2**17``."""
STEER_COUNTS_PER_TURN = round(2.0 * math.pi / STEER_LSB)
"""Steering position counts per turn (2**17)."""
WHEEL_COUNTS_PER_TURN = round(2.0 * math.pi / WHEEL_LSB)
"""Wheel position counts per turn (2**17)."""
STEER_SPAN = signal_span("SteerPosition")
"""Wrap period of the steering position signal, rad: ``2**20 * 2*pi/2**17`` = 8 turns."""
WHEEL_SPAN = signal_span("WheelPosition")
"""Wrap period of the wheel position signal, rad: ``2**36 * 2*pi/2**17`` = 2**19 turns."""


HEARTBEAT_PERIOD_S = _cycle_time_s(Command.HEARTBEAT)
"""The controllers' heartbeat period (s): the DBC's cycle time of Heartbeat."""
POWER_UP_FEEDBACK_RATE_HZ = round(1.0 / _cycle_time_s(Command.FEEDBACK_POSITION))
"""The feedback rate a controller starts with (Hz): the DBC's cycle time of
FeedbackPosition (the host sets its own with SetFeedback)."""
POWER_UP_WATCHDOG_MS = 100
"""The command watchdog a controller starts with, until the host sends SetWatchdog
(firmware_protocol/README.md; the C emulator's ctrl_init says the same)."""
