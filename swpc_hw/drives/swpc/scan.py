"""Scanning a bus of swpc's own controllers, listening only (``swpc drives scan``).

What ``swpc can monitor`` shows of each node, as a scan: every controller's heartbeat
(both axes' state, control mode and latched errors, homed), its rate, and the fault
reports heard while listening.  Nothing is sent (a frame to a controller would feed its
command watchdog).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import can

from firmware_protocol import codec
from firmware_protocol.codec import AxisState, ProtocolError
from swpc_hw.drives.scan import Expected, FoundNode
from swpc_hw.drives.swpc.config import SwpcDrives


@dataclass
class ControllerHeard:
    heartbeat: codec.Heartbeat | None = None
    heartbeats: int = 0
    first: float = 0.0
    last: float = 0.0
    feedback_frames: int = 0
    faults: list[codec.FaultReport] = field(default_factory=list)


def describe(node: int, heard: ControllerHeard) -> FoundNode:
    """A controller as ``swpc can monitor`` shows it."""
    hb = heard.heartbeat
    assert hb is not None
    axes = [f"{s.name}/{m.name}" for s, m in zip(hb.states, hb.modes, strict=True)]
    errors = [codec.error_names(e) for e in hb.errors]
    faulted = [
        f"{name} {errors[i] if hb.errors[i] else 'FAULT'}"
        for i, name in enumerate(("steer", "wheel"))
        if hb.states[i] is AxisState.FAULT or hb.errors[i]
    ]
    span = max(heard.last - heard.first, 0.0)
    rate = f"{(heard.heartbeats - 1) / span:.1f} Hz" if heard.heartbeats > 1 and span else "-"
    fields = {
        "steer": axes[0],
        "wheel": axes[1],
        "errors steer/wheel": f"{errors[0]} / {errors[1]}",
        "homed": "yes" if hb.homed else "no",
        "heartbeat": rate,
        "feedback": "yes" if heard.feedback_frames else "none",
    }
    data: dict[str, object] = {
        "states": [s.name for s in hb.states],
        "modes": [m.name for m in hb.modes],
        "errors": list(hb.errors),
        "error_names": errors,
        "homed": hb.homed,
        "heartbeats": heard.heartbeats,
        "fault_reports": [
            {"axis": f.axis.name.lower(), "new": f.new_errors, "active": f.active_errors}
            for f in heard.faults
        ],
    }
    state = f"steer {axes[0]}, wheel {axes[1]}"
    return FoundNode(node, state, "; ".join(faulted) or None, fields, data)


def expected(drives: SwpcDrives) -> list[Expected]:
    return [Expected(m, "", n) for m, n in drives.node_map().items()]


@dataclass
class SwpcScan:
    found: list[FoundNode]
    candidates: int
    elapsed_s: float
    notes: list[str] = field(default_factory=list)


def scan(bus: can.BusABC, *, listen_s: float = 1.0) -> SwpcScan:
    """Listen for ``listen_s`` and describe every controller whose heartbeat came."""
    t0 = time.monotonic()
    heard: dict[int, ControllerHeard] = {}
    end = t0 + listen_s
    while (left := end - time.monotonic()) > 0:
        msg = bus.recv(timeout=min(left, 0.05))
        if msg is None or msg.is_error_frame or msg.is_extended_id or msg.is_remote_frame:
            continue
        try:
            dec = codec.parse(msg.arbitration_id, bytes(msg.data))
        except ProtocolError:
            continue
        node = getattr(dec, "node", 0)
        if not node:
            continue
        h = heard.setdefault(node, ControllerHeard())
        if isinstance(dec, codec.Heartbeat):
            now = time.monotonic()
            if not h.heartbeats:
                h.first = now
            h.heartbeat, h.last = dec, now
            h.heartbeats += 1
        elif isinstance(dec, codec.FaultReport):
            h.faults.append(dec)
        elif isinstance(dec, codec.FeedbackPosition | codec.FeedbackVelocityTorque):
            h.feedback_frames += 1
    found = [describe(n, h) for n, h in sorted(heard.items()) if h.heartbeat is not None]
    return SwpcScan(found, 0, time.monotonic() - t0)
