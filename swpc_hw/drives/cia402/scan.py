"""Scanning a CANopen bus for CiA 402 drives, reading only (``swpc drives scan``).

What it sends: SDO uploads (reads) and, only when asked (``wake``), one NMT *reset
communication* to every node.  No SDO download, no PDO, no SYNC, no other NMT command:
nothing it sends can start, enable or move a motor.

1. Listen (``listen_s``, about 1 s) for heartbeats and boot-ups (``0x700 + node``): the NMT
   state of every node that sends one.
2. Probe every candidate node (1..127, or the config's nodes and a few more) at once: an
   SDO upload of 0x1000 to each (``0x600 + node``), the answers collected for
   ``probe_timeout_s``, the silent ones asked once more (waited for 3 x as long): 127
   nodes take about ``4 x probe_timeout_s`` (0.2 s), not 127 timeouts.  A node that
   answers one request twice is two devices on one node id; so is a node whose heartbeats
   come at twice the period its 0x1017 says.  (On a real bus two devices that answer with
   the same bytes at the same instant merge into one frame: the heartbeats tell then.)
3. Read each node that answered (canopen's SDO client, by index and sub-index: no object
   dictionary needed, the types are CiA 301's and 402's): device type 0x1000, identity
   0x1018 (vendor, product, revision, serial), device name 0x1008, software version
   0x100A, error register 0x1001, supported modes 0x6502, producer heartbeat 0x1017,
   consumer heartbeats 0x1016, statusword 0x6041 (the 402 power state) and, in FAULT or
   with an error register not 0, the error code 0x603F.  An object the drive lacks
   (abort 0x06020000, or 0x06090011 for a sub-index) is *absent*, never an error.

The pure parts (decoding, :func:`describe`) take what was read and heard; :func:`scan`
does the I/O on a connected :class:`canopen.Network`.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import can
import canopen
from canopen.sdo.constants import REQUEST_UPLOAD, SDO_STRUCT
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from firmware_protocol import cia402
from firmware_protocol.cia402 import Mode, PowerState
from swpc_hw.drives.cia402.config import ABSOLUTE, Cia402Drives
from swpc_hw.drives.cia402.setup import POSITION_MODES, TORQUE_MODES, VELOCITY_MODES, choose_modes
from swpc_hw.drives.errors import CanBusError
from swpc_hw.drives.scan import Expected, FoundNode

ABSENT = "absent"

MODE_BITS: dict[int, str] = {
    0: "PP",
    1: "VL",
    2: "PV",
    3: "PT",
    5: "HM",
    6: "IP",
    7: "CSP",
    8: "CSV",
    9: "CST",
    10: "CSTCA",
}
"""0x6502's bits (CiA 402-2): profile position, velocity (vl), profile velocity, profile
torque, homing, interpolated position, cyclic synchronous position, velocity, torque, and
torque with commutation angle; bit 4 and bits 11-15 are reserved, 16-31 the maker's."""

DEVICE_TYPES_402 = {1: "frequency converter", 2: "servo drive", 3: "stepper motor"}
"""0x1000 bits 16-23 of a CiA 402 device."""


FAULT_STATES = (PowerState.FAULT, PowerState.FAULT_REACTION_ACTIVE)


# ---------------------------------------------------------------------- pure decoding
def mode_names(value: int) -> list[str]:
    """0x6502 -> ``["HM", "CSP", "CSV", "CST"]`` (reserved and maker bits by number)."""
    out = []
    for bit in range(32):
        if not value >> bit & 1:
            continue
        if bit in MODE_BITS:
            out.append(MODE_BITS[bit])
        elif bit >= 16:
            out.append(f"maker bit {bit}")
        else:
            out.append(f"reserved bit {bit}")
    return out


def _short(mode: Mode) -> str:
    return MODE_BITS[int(mode) - 1]


def lacking(supported: int, homing: object) -> list[str]:
    """What swpc's set-up would refuse a drive for in its 0x6502 (the set-up's own choice,
    :func:`swpc_hw.drives.cia402.setup.choose_modes`): no position mode swpc can use, no
    torque and no velocity mode (which a wheel needs: the scan does not know the axis, so
    it is said "for a wheel"), no homing for an axis that homes (``homing`` not
    ``absolute``: a wheel is given ``absolute``)."""
    chosen = choose_modes(supported)
    out = []
    if chosen["position"] is None:
        out.append(f"a position mode ({' or '.join(_short(m) for m in POSITION_MODES)})")
    if chosen["torque"] is None and chosen["velocity"] is None:
        both = " or ".join(_short(m) for m in TORQUE_MODES + VELOCITY_MODES)
        out.append(f"for a wheel, a torque or velocity mode ({both})")
    if homing != ABSOLUTE and not supported & cia402.supported_modes_bit(Mode.HOMING):
        out.append("homing (HM)")
    return out


def device_type_text(value: int) -> str:
    """``0x00020192 (CiA 402 servo drive)``."""
    profile = value & 0xFFFF
    if profile == 402:
        kind = DEVICE_TYPES_402.get(value >> 16 & 0xFF, f"type 0x{value >> 16 & 0xFF:02X}")
        return f"0x{value:08X} (CiA 402 {kind})"
    what = "no profile" if profile == 0 else f"CiA {profile}: not a 402 drive"
    return f"0x{value:08X} ({what})"


def consumers_text(entries: Sequence[int]) -> str:
    """0x1016 entries -> ``node 127: 200 ms`` (``none`` when no entry watches a node)."""
    parts = []
    for e in entries:
        node, ms = cia402.parse_consumer_entry(e)
        if ms and node:
            parts.append(f"node {node}: {ms} ms")
    return ", ".join(parts) or "none"


@dataclass(frozen=True)
class Unread:
    """An object not read: ``absent`` (the drive lacks it), an abort, or no answer."""

    why: str

    @property
    def absent(self) -> bool:
        return self.why == ABSENT


Value = int | str | Unread
"""What one SDO read gave: an integer, a string (0x1008, 0x100A), or why not."""


def unread(exc: Exception) -> Unread:
    if isinstance(exc, SdoAbortedError):
        if exc.code in cia402.SDO_ABSENT:
            return Unread(ABSENT)
        what = SdoAbortedError.CODES.get(exc.code)
        return Unread(f"abort 0x{exc.code:08X}" + (f": {what}" if what else ""))
    return Unread("no answer")


@dataclass
class Heard:
    """A node's heartbeats while the scan listened."""

    state: int
    count: int
    first: float
    last: float
    boot_ups: int = 0


def _text(v: Value | None, fmt: str = "0x{:08X}") -> str:
    if v is None:
        return "-"
    if isinstance(v, Unread):
        return v.why
    if isinstance(v, str):
        return v
    return fmt.format(v)


def _num(v: Value | None) -> int | str | None:
    if v is None or isinstance(v, Unread):
        return None
    return v


def describe(
    node: int,
    reads: dict[tuple[int, int], Value],
    heard: Heard | None,
    *,
    listened_s: float,
    answers: int = 1,
    homing: object = None,
) -> FoundNode:
    """A node as the scan shows it, from what it answered (``reads``: (index, sub) ->
    value) and its heartbeats (``heard``, None: none while listening for ``listened_s``).
    ``answers``: how many answers its first probe got; ``homing``: the config's axis'
    homing (``absolute`` for a wheel), whose modes are checked as swpc's set-up would
    (:func:`lacking`; None: no config, no check)."""
    r = reads.get
    if not reads:  # a heartbeat, no SDO server answering
        state = cia402.nmt_name(heard.state) if heard else "unknown"
        f = FoundNode(node, state, fields={"NMT": state, "SDO": "no answer"})
        f.data = {"nmt": state, "sdo": False, "boot_ups": 0 if heard is None else heard.boot_ups}
        if heard is not None and heard.state & 0x7F == cia402.NMT_STOPPED:
            f.notes.append("STOPPED: a node in STOPPED answers no SDO")
        else:
            f.notes.append("heartbeat only: not a drive's SDO server (another master?)")
        return f
    producer = r((cia402.PRODUCER_HEARTBEAT, 0))
    if heard is not None and heard.state == cia402.NMT_BOOT_UP and producer == 0:
        nmt = "boot-up heard (no heartbeat: 0x1017 = 0)"
    elif heard is not None:
        nmt = cia402.nmt_name(heard.state)
    elif producer == 0:
        nmt = "unknown (no heartbeat: 0x1017 = 0)"
    elif isinstance(producer, int):
        nmt = f"unknown (no heartbeat in {listened_s:.1f} s; 0x1017 = {producer} ms)"
    else:
        nmt = f"unknown (no heartbeat; 0x1017 {_text(producer)})"
    sw = r((cia402.STATUSWORD, 0))
    power = cia402.power_state(sw) if isinstance(sw, int) else None
    fault = None
    code = r((cia402.ERROR_CODE, 0))
    if power in FAULT_STATES:
        fault = cia402.emcy_name(code) if isinstance(code, int) else f"0x603F {_text(code)}"
    modes = r((cia402.SUPPORTED_MODES, 0))
    entries = [
        v for k, v in sorted(reads.items())
        if k[0] == cia402.CONSUMER_HEARTBEAT and k[1] > 0 and isinstance(v, int)
    ]  # fmt: skip
    consumers = r((cia402.CONSUMER_HEARTBEAT, 0))
    dev = r((cia402.DEVICE_TYPE, 0))
    reg = r((cia402.ERROR_REGISTER, 0))
    fields = {
        "NMT": nmt,
        "402 state": power.value if power is not None else _text(sw),
        "error code": fault or ("-" if not isinstance(code, int) or code == 0
                                else cia402.emcy_name(code)),
        "error register": _text(reg, "0x{:02X}"),
        "device type": device_type_text(dev) if isinstance(dev, int) else _text(dev),
        "vendor": _text(r((0x1018, 1))),
        "product": _text(r((0x1018, 2))),
        "revision": _text(r((0x1018, 3))),
        "serial": _text(r((0x1018, 4))),
        "name": _text(r((0x1008, 0))),
        "software": _text(r((0x100A, 0))),
        "modes": (" ".join(mode_names(modes)) or "none") if isinstance(modes, int)
        else _text(modes),
        "heartbeat": f"{producer} ms" if isinstance(producer, int) else _text(producer),
        "consumers": consumers_text(entries) if isinstance(consumers, int)
        else _text(consumers),
    }  # fmt: skip
    data = {
        "nmt": nmt,
        "nmt_state": None if heard is None else heard.state & 0x7F,
        "boot_ups": 0 if heard is None else heard.boot_ups,
        "statusword": _num(sw),
        "power_state": None if power is None else power.name,
        "error_code": _num(code),
        "error_register": _num(reg),
        "device_type": _num(dev),
        "vendor_id": _num(r((0x1018, 1))),
        "product_code": _num(r((0x1018, 2))),
        "revision": _num(r((0x1018, 3))),
        "serial": _num(r((0x1018, 4))),
        "device_name": _num(r((0x1008, 0))),
        "software_version": _num(r((0x100A, 0))),
        "supported_modes": _num(modes),
        "modes": mode_names(modes) if isinstance(modes, int) else None,
        "producer_heartbeat_ms": _num(producer),
        "consumers": [list(cia402.parse_consumer_entry(e)) for e in entries],
        "absent": sorted(
            f"0x{i:04X}" + (f" sub {s}" if s else "")
            for (i, s), v in reads.items() if isinstance(v, Unread) and v.absent
        ),
    }  # fmt: skip
    state = nmt if power is None else f"{nmt.split(' ')[0]} / {power.value}"
    found = FoundNode(node, state, fault, fields, data)
    if answers > 1:
        found.duplicate = f"{answers} answers to one SDO request"
    elif heard is not None and isinstance(producer, int) and producer > 0:
        span = max(heard.last - heard.first, 0.0)
        allowed = span / (producer / 1000.0) + 1
        if heard.count >= 4 and heard.count > 1.5 * allowed + 1:
            found.duplicate = (
                f"{heard.count} heartbeats in {span:.2f} s, 0x1017 = {producer} ms allows "
                f"{math.floor(allowed)}"
            )
    if isinstance(modes, int) and homing is not None:
        lacks = lacking(modes, homing)
        if lacks:
            found.notes.append(f"lacks what swpc needs: {', '.join(lacks)}")
    if isinstance(dev, int) and dev & 0xFFFF != 402:
        found.notes.append("not a CiA 402 drive (0x1000)")
    return found


def expected(drives: Cia402Drives) -> list[Expected]:
    """Each configured axis on its node (the default numbering filled in first)."""
    return [
        Expected(m, name, ax.node)
        for m, md in drives.axes().items()
        for name, ax in (("steer", md.steer), ("wheel", md.wheel))
    ]


# ---------------------------------------------------------------------- the bus
class _Log(can.Listener):
    """Every heartbeat, and every SDO answer's arrival, as the scan goes."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.heard: dict[int, Heard] = {}
        self.answers: dict[int, list[float]] = {}

    def on_message_received(self, msg: can.Message) -> None:
        if msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id:
            return
        cob, now = msg.arbitration_id, time.monotonic()
        base, node = cob & 0x780, cob & 0x7F
        if not node:
            return
        with self.lock:
            if base == cia402.HEARTBEAT_BASE and len(msg.data) >= 1:
                state = msg.data[0] & 0x7F
                h = self.heard.get(node)
                if h is None:
                    h = self.heard[node] = Heard(state, 0, now, now)
                h.state, h.last = state, now
                h.count += 1
                h.boot_ups += state == cia402.NMT_BOOT_UP
            elif base == cia402.SDO_TX_BASE:
                self.answers.setdefault(node, []).append(now)


@dataclass
class Cia402Scan:
    """What :func:`scan` found: every node that answered or sent a heartbeat."""

    found: list[FoundNode]
    candidates: int
    elapsed_s: float
    probe_s: float
    """How long the probe of every candidate took (both rounds)."""
    notes: list[str] = field(default_factory=list)


OBJECTS: tuple[tuple[int, int, str], ...] = (
    (cia402.DEVICE_TYPE, 0, "u32"),
    (cia402.ERROR_REGISTER, 0, "u8"),
    (0x1018, 1, "u32"),
    (0x1018, 2, "u32"),
    (0x1018, 3, "u32"),
    (0x1018, 4, "u32"),
    (0x1008, 0, "str"),
    (0x100A, 0, "str"),
    (cia402.SUPPORTED_MODES, 0, "u32"),
    (cia402.PRODUCER_HEARTBEAT, 0, "u16"),
    (cia402.CONSUMER_HEARTBEAT, 0, "u8"),
    (cia402.STATUSWORD, 0, "u16"),
    (cia402.ERROR_CODE, 0, "u16"),
)
"""What is read of each node that answered the probe, with CiA 301 / 402's types."""
MAX_CONSUMERS = 16
"""At most this many 0x1016 entries are read (a drive has 1 to a few)."""


def _decode(data: bytes, kind: str) -> int | str:
    if kind == "str":
        return data.split(b"\0", 1)[0].decode("latin-1").strip()
    size = {"u8": 1, "u16": 2, "u32": 4}[kind]
    return int.from_bytes(data[:size].ljust(size, b"\0"), "little")


def read_node(node: canopen.RemoteNode) -> dict[tuple[int, int], Value]:
    """Every object of :data:`OBJECTS` (0x603F only in FAULT; 0x1016's entries as many as
    its sub 0 says), by SDO upload."""
    out: dict[tuple[int, int], Value] = {}

    def get(index: int, sub: int, kind: str) -> Value:
        try:
            v: Value = _decode(node.sdo.upload(index, sub), kind)
        except (SdoAbortedError, SdoCommunicationError) as exc:
            v = unread(exc)
        out[(index, sub)] = v
        return v

    for index, sub, kind in OBJECTS:
        if index == cia402.ERROR_CODE:
            sw = out.get((cia402.STATUSWORD, 0))
            reg = out.get((cia402.ERROR_REGISTER, 0))
            in_fault = isinstance(sw, int) and cia402.power_state(sw) in FAULT_STATES
            if not in_fault and not (isinstance(reg, int) and reg):
                continue
        v = get(index, sub, kind)
        if index == cia402.CONSUMER_HEARTBEAT and isinstance(v, int):
            for k in range(1, min(v, MAX_CONSUMERS) + 1):
                get(index, k, "u32")
    return out


def _send(net: canopen.Network, cob: int, data: bytes) -> None:
    """One frame, retried for a while when the interface's queue is full (a burst of 127
    requests on a SocketCAN with its default txqueuelen of 10)."""
    deadline = time.monotonic() + 0.5
    while True:
        try:
            net.send_message(cob, data)
            return
        except can.CanError as exc:
            if time.monotonic() > deadline:
                raise CanBusError(f"send 0x{cob:03X} failed: {exc}") from exc
            time.sleep(0.002)


def probe(
    net: canopen.Network, log: _Log, nodes: Sequence[int], timeout_s: float
) -> dict[int, int]:
    """An SDO upload of 0x1000 to every node at once, the answers collected for
    ``timeout_s`` after the last request; the silent ones asked once more, waited for three
    times as long (a busy drive, or host).  Node -> answers to its first request (two: two
    devices on one node id; a node found by the second request counts one, since a late
    answer to the first may be among its answers)."""
    request = SDO_STRUCT.pack(REQUEST_UPLOAD, cia402.DEVICE_TYPE, 0) + bytes(4)
    answered: dict[int, int] = {}
    pending = list(nodes)
    for wait in (timeout_s, 3 * timeout_s):
        if not pending:
            break
        sent: dict[int, float] = {}
        for n in pending:
            sent[n] = time.monotonic()
            _send(net, cia402.SDO_RX_BASE + n, request)
        time.sleep(wait)
        with log.lock:
            for n in pending:
                got = [t for t in log.answers.get(n, []) if t >= sent[n]]
                if got:
                    answered[n] = len(got) if wait == timeout_s else 1
        pending = [n for n in pending if n not in answered]
    return answered


def scan(
    net: canopen.Network,
    candidates: Sequence[int],
    *,
    listen_s: float = 1.0,
    probe_timeout_s: float = 0.05,
    sdo_timeout_s: float = 0.3,
    wake: bool = False,
    homing: dict[int, object] | None = None,
) -> Cia402Scan:
    """Scan the bus ``net`` is connected to (module docstring).  ``candidates``: the nodes
    to probe (any node heard is probed too); ``wake``: NMT reset communication to every
    node first, and a listen long enough for their boot-ups; ``homing``: node -> its
    axis' homing in the config (``absolute`` for a wheel): a mode swpc needs and the drive
    lacks is noted."""
    if net.notifier is None:
        raise CanBusError("scan(): the canopen network is not connected")
    t0 = time.monotonic()
    log = _Log()
    net.notifier.add_listener(log)
    notes = []
    try:
        if wake:
            _send(net, cia402.NMT_ID, bytes([cia402.NMT_RESET_COMMUNICATION, 0]))
            notes.append("sent NMT reset communication to every node (--wake)")
            listen_s = max(listen_s, 2.0)
        t_listen = time.monotonic()
        time.sleep(listen_s)
        with log.lock:
            heard_first = sorted(log.heard)
        nodes = sorted(set(candidates) | set(heard_first))
        t_probe = time.monotonic()
        answered = probe(net, log, nodes, probe_timeout_s)
        probe_s = time.monotonic() - t_probe
        reads: dict[int, dict[tuple[int, int], Value]] = {}
        for n in sorted(answered):
            remote = canopen.RemoteNode(n, canopen.ObjectDictionary())
            remote.sdo.RESPONSE_TIMEOUT = sdo_timeout_s
            remote.sdo.MAX_RETRIES = 2
            net.add_node(remote)
            try:
                reads[n] = read_node(remote)
            finally:
                del net[n]
        listened = time.monotonic() - t_listen
        with log.lock:
            heard = dict(log.heard)
        found = [
            describe(
                n, reads.get(n, {}), heard.get(n), listened_s=listened,
                answers=answered.get(n, 0), homing=(homing or {}).get(n),
            )
            for n in sorted(set(answered) | set(heard))
        ]  # fmt: skip
    finally:
        net.notifier.remove_listener(log)
    return Cia402Scan(found, len(nodes), time.monotonic() - t0, probe_s, notes)


