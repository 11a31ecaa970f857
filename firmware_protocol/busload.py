"""Bus-load budget of the SWPC protocol with worst-case bit stuffing (classic CAN, 11-bit ids).

Worst-case length of a data frame with ``n`` data bytes, including the 3-bit interframe
space (Davis, Burns, Bril & Lukkien, "Controller Area Network (CAN) schedulability
analysis", Real-Time Systems 35, 2007)::

    C(n) = 8 n + 47 + floor((34 + 8 n - 1) / 4)   bits     (C(8) = 135, C(1) = 65)

At 1 Mbit/s, 8-byte frames therefore fit at most 1e6 / 135 = 7407 times per second.
"""

from __future__ import annotations

from dataclasses import dataclass

from firmware_protocol import codec
from firmware_protocol.codec import Command


def frame_bits(n_bytes: int) -> int:
    """Worst-case stuffed length (bits) of a standard-id data frame with ``n_bytes`` of data."""
    return 8 * n_bytes + 47 + (34 + 8 * n_bytes - 1) // 4


def _bits(command: Command) -> int:
    node = 0 if command == Command.SYNC else 1
    return frame_bits(codec.message_for(node, command).length)


@dataclass(frozen=True)
class Budget:
    """Bus load (bit/s) of each traffic class and the total as a fraction of the bitrate."""

    feedback: float
    heartbeat: float
    commands: float
    sync: float
    bitrate: float

    @property
    def total(self) -> float:
        return self.feedback + self.heartbeat + self.commands + self.sync

    @property
    def load(self) -> float:
        return self.total / self.bitrate


def budget(
    nodes: int = 4,
    feedback_hz: float = 200.0,
    heartbeat_hz: float = 10.0,
    command_hz: float = 100.0,
    sync: bool = False,
    bitrate: float = 1e6,
) -> Budget:
    """Load of ``nodes`` controllers streaming both feedback frames at ``feedback_hz``,
    heartbeats at ``heartbeat_hz``, and the host sending one SetControl per axis at
    ``command_hz`` (plus one SYNC per sample if ``sync``)::

        load = [nodes (2 f C_fb + h C_hb + 2 c C_cmd) + s f C_sync] / bitrate
    """
    fb = nodes * feedback_hz * (
        _bits(Command.FEEDBACK_POSITION) + _bits(Command.FEEDBACK_VELOCITY_TORQUE)
    )
    hb = nodes * heartbeat_hz * _bits(Command.HEARTBEAT)
    cmd = nodes * 2 * command_hz * _bits(Command.SET_CONTROL)
    sy = feedback_hz * _bits(Command.SYNC) if sync else 0.0
    return Budget(fb, hb, cmd, sy, bitrate)


def max_feedback_rate(
    limit: float = 0.8,
    nodes: int = 4,
    heartbeat_hz: float = 10.0,
    command_hz: float = 100.0,
    sync: bool = False,
    bitrate: float = 1e6,
) -> float:
    """Highest feedback rate f (Hz) with ``budget(...).load <= limit`` (load is linear in f)."""
    fixed = budget(nodes, 0.0, heartbeat_hz, command_hz, False, bitrate).total
    per_hz = budget(nodes, 1.0, 0.0, 0.0, sync, bitrate).total
    return (limit * bitrate - fixed) / per_hz


def main() -> None:
    for sync in (False, True):
        b = budget(sync=sync)
        print(
            f"4 nodes, 200 Hz feedback, 10 Hz heartbeat, 100 Hz commands/axis, sync={sync}: "
            f"{b.total / 1e3:.1f} kbit/s = {100 * b.load:.1f} % of 1 Mbit/s; "
            f"highest feedback rate under 80 %: {max_feedback_rate(sync=sync):.0f} Hz"
        )


if __name__ == "__main__":
    main()
