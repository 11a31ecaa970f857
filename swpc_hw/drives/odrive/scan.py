"""Scanning a bus of ODrive axes (CAN Simple), reading only (``swpc drives scan``).

It listens (``listen_s``) to every axis' heartbeat (state, axis error, 0.5.x's motor /
encoder / controller flags, 0.6.x's procedure result) and counts its encoder estimates.
On 0.6.x, whose DBC has ``Get_Version``, it then asks each axis heard (and each one the
config expects) for its version with a remote frame: a read, as ODrive's CAN protocol
defines it (it feeds no 0.6.x watchdog); two answers to one request are two axes on one
node id, and an axis whose heartbeat is off is found by its answer.  0.5.x defines no
version message: its firmware version is "not reported by this firmware".  Nothing else
is sent: no state request, no setpoint, no ``Clear_Errors``.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import can

from firmware_protocol.codec import ProtocolError
from firmware_protocol.odrive import can_simple as cs
from swpc_hw.drives.errors import CanBusError
from swpc_hw.drives.odrive.config import ODriveDrives
from swpc_hw.drives.scan import Expected, FoundNode

NOT_REPORTED = "not reported by this firmware"


@dataclass
class AxisHeard:
    """What one node sent while the scan listened."""

    heartbeat: cs.Heartbeat | None = None
    heartbeats: int = 0
    first: float = 0.0
    last: float = 0.0
    estimates: int = 0
    versions: list[cs.Version] = field(default_factory=list)


def _state_name(state: int) -> str:
    try:
        return cs.AxisState(state).name
    except ValueError:
        return f"state {state}"


def describe(
    codec: cs.CanSimple, node: int, heard: AxisHeard, *, listened_s: float, asked: bool
) -> FoundNode:
    """An axis as the scan shows it (``asked``: its version was requested)."""
    hb = heard.heartbeat
    if hb is None:
        state = "unknown (no heartbeat: <axis>.config.can.heartbeat_msg_rate_ms = 0?)"
        fault = None
        errors = "-"
    else:
        state = _state_name(hb.state)
        errors = codec.error_names(hb.axis_error)
        other = hb.axis_error & ~codec.watchdog_bit
        fault = codec.error_names(other) if other else None
    if not codec.has_version:
        firmware = NOT_REPORTED
    elif heard.versions:
        v = heard.versions[0]
        firmware = f"{v.firmware} (hardware {v.hardware})"
    else:
        firmware = "no answer to Get_Version" if asked else "-"
    span = max(heard.last - heard.first, 0.0)
    rate = f"{(heard.heartbeats - 1) / span:.1f} Hz" if heard.heartbeats > 1 and span else "-"
    fields = {"state": state, "axis error": errors}
    data: dict[str, object] = {
        "state": None if hb is None else hb.state,
        "state_name": None if hb is None else _state_name(hb.state),
        "axis_error": None if hb is None else hb.axis_error,
        "axis_error_names": None if hb is None else errors,
        "heartbeats": heard.heartbeats,
        "estimates": heard.estimates,
    }
    if codec.line == "0.5":
        flags = 0 if hb is None else hb.component_errors
        names = [n for b, n in ((1, "motor"), (2, "encoder"), (4, "controller")) if flags & b]
        fields["error flags"] = ", ".join(names) or "none"
        data["component_errors"] = flags
    else:
        result = None if hb is None else hb.procedure_result
        fields["procedure result"] = codec.procedure_name(result)
        data["procedure_result"] = None if hb is None else hb.procedure_result
    fields["heartbeat"] = rate
    fields["estimates"] = (
        f"{heard.estimates / listened_s:.0f} /s" if listened_s > 0 and heard.estimates else "none"
    )
    fields["firmware"] = firmware
    data["firmware"] = None if not heard.versions else heard.versions[0].firmware
    data["hardware"] = None if not heard.versions else heard.versions[0].hardware
    found = FoundNode(node, state, fault, fields, data)
    if len(heard.versions) > 1:
        found.duplicate = f"{len(heard.versions)} answers to one Get_Version request"
    if hb is not None and hb.axis_error & codec.watchdog_bit and codec.line == "0.5":
        found.notes.append(
            "WATCHDOG_TIMER_EXPIRED: a 0.5.x axis left alone reports it between runs"
        )
    return found


def expected(drives: ODriveDrives) -> list[Expected]:
    return [
        Expected(m, name, ax.node)
        for m, md in drives.module_map().items()
        for name, ax in (("steer", md.steer), ("wheel", md.wheel))
    ]


@dataclass
class ODriveScan:
    found: list[FoundNode]
    candidates: int
    """How many nodes were asked for their version (0 on 0.5.x)."""
    elapsed_s: float
    notes: list[str] = field(default_factory=list)


def _take(codec: cs.CanSimple, heard: dict[int, AxisHeard], msg: can.Message) -> None:
    if msg.is_error_frame or msg.is_extended_id or msg.is_remote_frame:
        return
    try:
        dec = codec.decode(msg.arbitration_id, bytes(msg.data))
    except ProtocolError:
        return
    if isinstance(dec, cs.Heartbeat | cs.EncoderEstimates | cs.Version):
        h = heard.setdefault(dec.node, AxisHeard())
        now = time.monotonic()
        if isinstance(dec, cs.Heartbeat):
            if not h.heartbeats:
                h.first = now
            h.heartbeat, h.last = dec, now
            h.heartbeats += 1
        elif isinstance(dec, cs.EncoderEstimates):
            h.estimates += 1
        else:
            h.versions.append(dec)


def _listen(bus: can.BusABC, codec: cs.CanSimple, heard: dict[int, AxisHeard], s: float) -> None:
    end = time.monotonic() + s
    while (left := end - time.monotonic()) > 0:
        msg = bus.recv(timeout=min(left, 0.05))
        if msg is not None:
            _take(codec, heard, msg)


def scan(
    bus: can.BusABC,
    firmware: str,
    candidates: Sequence[int] = (),
    *,
    listen_s: float = 1.0,
    version_timeout_s: float = 0.1,
) -> ODriveScan:
    """Listen for ``listen_s``, then (0.6.x) ask every axis heard and every one of
    ``candidates`` for its version (module docstring)."""
    codec = cs.can_simple(firmware)
    t0 = time.monotonic()
    heard: dict[int, AxisHeard] = {}
    _listen(bus, codec, heard, listen_s)
    asked: set[int] = set()
    notes = []
    if codec.has_version:
        for h in heard.values():
            h.versions.clear()  # answers to someone else's request
        for n in sorted(set(heard) | set(candidates)):
            frame = codec.version_request(n)
            try:
                bus.send(can.Message(arbitration_id=frame.arbitration_id, is_extended_id=False,
                                     is_remote_frame=True, dlc=8))  # fmt: skip
            except can.CanError as exc:
                raise CanBusError(f"Get_Version to node {n}: send failed: {exc}") from exc
            asked.add(n)
        _listen(bus, codec, heard, version_timeout_s)
    else:
        notes.append(f"ODrive firmware {firmware}: its CAN protocol has no version message")
    listened = time.monotonic() - t0
    found = [
        describe(codec, n, heard[n], listened_s=listened, asked=n in asked)
        for n in sorted(heard)
        if heard[n].heartbeat is not None or heard[n].versions
    ]
    return ODriveScan(found, len(asked), listened, notes)
