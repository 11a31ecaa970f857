"""A CiA 402 drive's set-up over SDO, once per boot, before it is started.

In PRE-OPERATIONAL: heartbeat producer 0x1017 = ``heartbeat_period_s``, heartbeat
consumer 0x1016 on the host's heartbeat with the command watchdog (``watchdog_timeout_ms``)
as its time (node guarding instead on a drive without 0x1016: :func:`_guarding`),
quick-stop option 0x605A, homing method 0x6098, the motor's rated torque
0x6076 read, the factor group (0x608F, 0x6091) checked against the config, the modes
chosen from 0x6502 (:func:`choose_modes`), the PDO mapping of
:data:`firmware_protocol.cia402.RPDO_MAP` / :data:`~firmware_protocol.cia402.TPDO_MAP`
written and read back (before anything uses it).

Real drives differ in what they have (``tests/drives/cia402/eds/``: seven published EDS
files).  What a drive lacks is found from its object dictionary (the EDS) and from the
drive itself (an SDO abort 0x06020000 "object does not exist" or 0x06090011 "subindex does
not exist"): an object the run needs (:data:`NEEDED`) refuses the drive before any motion,
naming node, object and what to do; one it can do without (:data:`OPTIONAL`) is skipped
and said once, in the notes :func:`set_up` returns.  Never a ``KeyError``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

from canopen.objectdictionary import ODRecord, ODVariable
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from firmware_protocol import cia402
from firmware_protocol.cia402 import Mode
from firmware_protocol.codec import Axis
from swpc_hw.drives.bus import CanConfig
from swpc_hw.drives.cia402.config import ABSOLUTE, Cia402Drives
from swpc_hw.drives.cia402.sdo import ClockedRemoteNode
from swpc_hw.drives.cia402.tracking import AxisTrack
from swpc_hw.drives.errors import NodeError
from swpc_hw.drives.types import AXIS_NAMES

PROFILE_VELOCITY = 0x6081
"""Profile position's travel speed: the run's velocity limit where the drive has it."""

NEEDED: dict[int, str] = {
    cia402.PRODUCER_HEARTBEAT: "swpc watches every drive by its heartbeat; a drive without "
    "a heartbeat producer cannot be supervised",
    cia402.CONSUMER_HEARTBEAT: "the drive's own dead-man on the host's heartbeat: without "
    "it (or node guarding, 0x100C and 0x100D) the drive would keep its last command when "
    "the host stops; use a drive (or firmware) with a heartbeat consumer or node guarding",
    cia402.CONTROLWORD: "the 402 power state machine",
    cia402.STATUSWORD: "the 402 power state machine",
    cia402.MODES_OF_OPERATION: "the modes swpc commands",
    cia402.MODES_DISPLAY: "swpc reads the mode in force back",
    cia402.POSITION_ACTUAL: "the encoder feedback",
    cia402.TARGET_POSITION: "the steering's and a held wheel's position",
    cia402.TARGET_TORQUE: "the drive's torque mode: swpc spins the robot by wheel torque "
    "and frees an axis by a torque of 0",
}
"""Objects without which a drive is refused, and why."""

OPTIONAL: dict[int, str] = {
    cia402.QUICK_STOP_OPTION: "the drive's own quick-stop reaction stays",
    cia402.MAX_TORQUE: "the run's torque limit is applied by the host only",
    cia402.MAX_PROFILE_VELOCITY: "the run's velocity limit is applied by the host only",
    cia402.ENCODER_RESOLUTION: "the units are not checked against the drive",
    cia402.GEAR_RATIO: "the units are not checked against the drive",
    cia402.VELOCITY_ACTUAL: "no velocity feedback (the solver uses positions)",
    cia402.TORQUE_ACTUAL: "no torque feedback",
    cia402.TARGET_VELOCITY: "no velocity mode (swpc's calibration does not use it)",
    cia402.SUPPORTED_MODES: "the modes are tried and judged by the modes display",
    cia402.ERROR_CODE: "faults are named by their EMCY only",
}
"""Objects a drive may lack, and what that costs (said once)."""

POSITION_MODES = (Mode.CYCLIC_SYNC_POSITION, Mode.PROFILE_POSITION)
VELOCITY_MODES = (Mode.CYCLIC_SYNC_VELOCITY, Mode.PROFILE_VELOCITY)
TORQUE_MODES = (Mode.CYCLIC_SYNC_TORQUE, Mode.PROFILE_TORQUE)
"""The modes swpc can command for each setpoint, preferred first: the cyclic synchronous
ones (the target every SYNC), else the profile modes: torque and velocity take the target
as it comes, position with the set-point handshake (controlword bit 4, statusword bit 12;
:func:`swpc_hw.drives.cia402.tracking.supervise`)."""


def choose_modes(supported: int | None) -> dict[str, Mode | None]:
    """For ``position``, ``velocity`` and ``torque``: the first mode of its list the drive
    supports (0x6502 bits), ``None`` if none; every first choice when 0x6502 is unknown."""
    out: dict[str, Mode | None] = {}
    for name, modes in (
        ("position", POSITION_MODES), ("velocity", VELOCITY_MODES), ("torque", TORQUE_MODES)
    ):  # fmt: skip
        ok = [m for m in modes if supported is None or supported & cia402.supported_modes_bit(m)]
        out[name] = ok[0] if ok else None
    return out


class _Drive:
    """What one drive has, asked once: its object dictionary, then the drive itself."""

    def __init__(self, node: ClockedRemoteNode, a: AxisTrack) -> None:
        self.node, self.a = node, a
        self.od = node.object_dictionary
        self.notes: list[str] = []
        self.step = ""

    def declared(self, index: int, sub: int = 0) -> bool:
        if index not in self.od:
            return False
        obj = self.od[index]
        return isinstance(obj, ODVariable) or sub in obj

    def variable(self, index: int, sub: int = 0) -> Any:
        obj = self.node.sdo[index]
        return obj[sub] if isinstance(self.od[index], ODRecord) or sub else obj

    def refuse(self, index: int, why: str, sub: int | None = None) -> NodeError:
        at = f"0x{index:04X}" + (f" sub {sub}" if sub is not None else "")
        return NodeError(
            f"{self.a.where()}: the drive has no {at} ({_name(self.od, index)}): {why}",
            node=self.a.node,
            axis=int(self.a.axis),
        )

    def skip(self, index: int) -> None:
        self.notes.append(
            f"{self.a.where()}: no 0x{index:04X} ({_name(self.od, index)}): "
            f"{OPTIONAL.get(index, 'skipped')}"
        )

    def access(self, index: int, sub: int, fn: Callable[[Any], Any], step: str) -> Any:
        """``fn(variable)`` over SDO; ``None`` when the drive has no such object (skipped
        if optional, refused if needed)."""
        self.step = step
        if not self.declared(index, sub):
            return self._absent(index, sub)
        try:
            return fn(self.variable(index, sub))
        except SdoAbortedError as exc:
            if exc.code in cia402.SDO_ABSENT:
                return self._absent(index, sub)
            raise

    def _absent(self, index: int, sub: int) -> None:
        if index == cia402.TARGET_TORQUE and self.a.torque_mode is None:
            return None  # no torque mode: said once with the modes
        if index in NEEDED:
            raise self.refuse(index, NEEDED[index], sub or None)
        self.skip(index)
        return None


def _name(od: Any, index: int) -> str:
    try:
        return str(od[index].name)
    except KeyError:
        return {v: k for k, v in vars(cia402).items() if isinstance(v, int)}.get(
            index, "object"
        ).lower().replace("_", " ")


def set_up(
    node: ClockedRemoteNode, a: AxisTrack, drives: Cia402Drives, cfg: CanConfig
) -> list[str]:
    """One drive's set-up over SDO in PRE-OPERATIONAL (module docstring); the caller
    starts it (NMT) once its track is marked configured.  Returns what was skipped (to be
    said once); :class:`NodeError` names the object that failed or is missing, and why."""
    node.nmt.send_command(cia402.NMT_ENTER_PRE_OPERATIONAL)
    axes = drives.axes()[a.module]
    ax = axes.steer if a.axis is Axis.STEER else axes.wheel
    d = _Drive(node, a)

    def write(value: int) -> Callable[[Any], None]:
        def fn(var: Any) -> None:
            var.raw = value

        return fn

    def read(var: Any) -> int:
        return int(var.raw)

    try:
        guarding = not d.declared(cia402.CONSUMER_HEARTBEAT, 1) and all(
            d.declared(i) for i in (cia402.GUARD_TIME, cia402.LIFE_TIME_FACTOR)
        )
        if guarding:
            _guarding(d, cfg, write)
        else:
            d.access(cia402.PRODUCER_HEARTBEAT, 0, write(round(1000 * cfg.heartbeat_period_s)),
                     "0x1017 producer heartbeat time")  # fmt: skip
            entry = cia402.consumer_entry(drives.host_node, cfg.watchdog_timeout_ms)
            d.access(cia402.CONSUMER_HEARTBEAT, 1, write(entry), "0x1016 consumer heartbeat time")
        d.access(cia402.QUICK_STOP_OPTION, 0, write(drives.quick_stop_option),
                 "0x605A quick stop option code")  # fmt: skip
        supported = d.access(cia402.SUPPORTED_MODES, 0, read, "0x6502 supported drive modes")
        homing = getattr(ax, "homing", ABSOLUTE)
        _modes(d, supported, homing)
        if homing != ABSOLUTE:
            if not d.declared(cia402.HOMING_METHOD):
                raise d.refuse(cia402.HOMING_METHOD, "the steering's homing method; with an "
                               "absolute encoder, set its `homing: absolute`")  # fmt: skip
            d.access(cia402.HOMING_METHOD, 0, write(int(homing)), f"0x6098 homing method {homing}")
        if a.torque_mode is not None:
            _rated_torque(d, ax.rated_torque, read)
        inc = d.access(cia402.ENCODER_RESOLUTION, 1, read, "0x608F position encoder resolution")
        rev = d.access(cia402.ENCODER_RESOLUTION, 2, read, d.step) if inc is not None else None
        if inc is not None and rev:
            _check_factor(a, "counts_per_turn", ax.counts_per_turn, inc / rev, d.step)
        mot = d.access(cia402.GEAR_RATIO, 1, read, "0x6091 gear ratio")
        shaft = d.access(cia402.GEAR_RATIO, 2, read, d.step) if mot is not None else None
        if mot is not None and shaft and mot == shaft:
            d.notes.append(
                f"{a.where()}: 0x6091 gear ratio is 1:1 ({mot}:{shaft}, the factory "
                "default): positions in motor counts, as swpc computes them; not checked"
            )
        elif mot is not None and shaft:
            _check_factor(a, "gear_ratio", ax.gear_ratio, mot / shaft, d.step)
        a.has_limits = (
            d.declared(cia402.MAX_TORQUE), d.declared(cia402.MAX_PROFILE_VELOCITY)
        )  # fmt: skip
        if not d.declared(cia402.ERROR_CODE):
            d.skip(cia402.ERROR_CODE)
        _map_pdos(d)
    except (SdoAbortedError, SdoCommunicationError) as exc:
        raise NodeError(
            f"{a.where()}: set-up {d.step}: {exc}", node=a.node, axis=int(a.axis)
        ) from exc
    return d.notes


def _guarding(d: _Drive, cfg: CanConfig, write: Callable[[int], Callable[[Any], None]]) -> None:
    """Node guarding, CiA 301's other error control, for a drive without a heartbeat
    consumer: its heartbeat producer off (the two are not used together), guard time
    0x100C = the host's heartbeat period, life time factor 0x100D = the command watchdog
    over it (rounded up).  The host asks the drive's state every guard time (a remote
    request, :attr:`AxisTrack.guarded`) and watches the answers as heartbeats; the drive
    stops ``0x100C x 0x100D`` ms (the watchdog) after the host's last request, the bound
    the heartbeat consumer gives."""
    guard_ms = max(1, round(1000 * cfg.refresh_period_s))
    factor = min(255, max(2, math.ceil(cfg.watchdog_timeout_ms / guard_ms)))
    if d.declared(cia402.PRODUCER_HEARTBEAT):
        d.access(cia402.PRODUCER_HEARTBEAT, 0, write(0), "0x1017 producer heartbeat time 0")
    d.access(cia402.GUARD_TIME, 0, write(guard_ms), f"0x100C guard time {guard_ms} ms")
    d.access(cia402.LIFE_TIME_FACTOR, 0, write(factor), f"0x100D life time factor {factor}")
    d.a.guarded = True
    d.notes.append(
        f"{d.a.where()}: no 0x1016 (consumer heartbeat): node guarding instead, the drive "
        f"stops {guard_ms * factor} ms after the host's last guard request (0x100C "
        f"{guard_ms} ms x 0x100D {factor})"
    )


def _modes(d: _Drive, supported: int | None, homing: object) -> None:
    """The axis's modes from 0x6502: a position mode (the steering, a held wheel), homing
    unless the steering's encoder is absolute, and for a wheel a torque or a velocity
    mode (the spins).  A drive without a torque mode is free with its power stage off,
    and its wheel spins the robot by velocity (said once)."""
    a = d.a
    chosen = choose_modes(supported)
    missing = [] if chosen["position"] is not None else ["position"]
    if a.axis is Axis.WHEEL and chosen["torque"] is None and chosen["velocity"] is None:
        missing.append("torque or velocity")
    bit = cia402.supported_modes_bit
    if homing != ABSOLUTE and supported is not None and not supported & bit(Mode.HOMING):
        missing.append("homing")
    has = [m.name for m in Mode if m and supported and supported & bit(m)]
    if missing:
        raise NodeError(
            f"{a.where()}: the drive has no {' and no '.join(missing)} mode swpc can use "
            f"(0x6502 = 0x{supported or 0:08X}: {', '.join(has) or 'none swpc knows'}); "
            "swpc needs a position mode (cyclic synchronous or profile), for a wheel a "
            "torque or a velocity mode (the spins), and homing unless the encoder is "
            "absolute",
            node=a.node,
            axis=int(a.axis),
        )
    a.position_mode = chosen["position"] or Mode.CYCLIC_SYNC_POSITION
    a.has_profile_velocity = d.declared(PROFILE_VELOCITY)
    a.torque_mode = chosen["torque"]
    a.velocity_mode = chosen["velocity"]
    if a.torque_mode is None:
        d.notes.append(
            f"{a.where()}: no torque mode (0x6502 = 0x{supported or 0:08X}: {', '.join(has)}):"
            " free is its power stage off"
            + (", and its wheel spins the robot by velocity" if a.axis is Axis.WHEEL else "")
        )


def _rated_torque(d: _Drive, configured: float | None, read: Callable[[Any], int]) -> None:
    """The torque unit: 0x6076 (thousandths of it), else the config's ``rated_torque``."""
    a = d.a
    d.step = "0x6076 motor rated torque"
    value = None
    if d.declared(cia402.RATED_TORQUE):
        try:
            value = read(d.variable(cia402.RATED_TORQUE)) / 1000.0
        except SdoAbortedError as exc:
            if exc.code not in cia402.SDO_ABSENT:
                raise
    if value is None or value <= 0:
        if configured is None:
            raise NodeError(
                f"{a.where()}: the drive has no 0x6076 (motor rated torque), the unit of its "
                f"torque objects: set drives.modules.{a.module}.{AXIS_NAMES[a.axis]}"
                ".rated_torque (N.m at the motor, from its data sheet)",
                node=a.node,
                axis=int(a.axis),
            )
        value = configured
    a.rated_torque = value


PdoEntry = tuple[int, int, int]


def place(
    groups: list[list[PdoEntry]], rooms: dict[int, int]
) -> list[list[tuple[int, list[PdoEntry]]]] | None:
    """The PDOs each group of entries goes to: group by group, each from the next PDO not
    taken, its entries in order into PDOs of ``rooms`` entries (PDO number -> room), one
    group never sharing a PDO with another (so each is sent on its own).  swpc's groups fit
    PDOs 1 and 2 of most drives; one with smaller mapping objects spreads them over PDOs
    3 and 4.  None when they do not fit.

    >>> place([[(1, 0, 16), (2, 0, 8)], [(3, 0, 32)]], {1: 1, 2: 2, 3: 2})
    [[(1, [(1, 0, 16)]), (2, [(2, 0, 8)])], [(3, [(3, 0, 32)])]]
    """
    free = sorted(rooms)
    out: list[list[tuple[int, list[PdoEntry]]]] = []
    for entries in groups:
        placed: list[tuple[int, list[PdoEntry]]] = []
        rest = list(entries)
        while rest:
            if not free:
                return None
            n = free.pop(0)
            if rooms[n] > 0:
                placed.append((n, rest[: rooms[n]]))
                rest = rest[rooms[n] :]
        out.append(placed)
    return out


def _map_pdos(d: _Drive) -> None:
    """The PDO maps written (:func:`place`), then read back: an object the drive lacks is
    left out when optional and refused when needed; one it cannot map is refused; a map
    that came out shorter than asked is refused, never used.  Records on the axis which
    PDOs carry each group (:attr:`AxisTrack.rpdos`, :attr:`AxisTrack.tpdos`)."""
    node, a = d.node, d.a
    for maps, layout, base, ttype, kind in (
        (node.tpdo, cia402.TPDO_MAP, cia402.TPDO_BASE, cia402.TPDO_ON_SYNC, "TPDO"),
        (node.rpdo, cia402.RPDO_MAP, cia402.RPDO_BASE, cia402.RPDO_ASYNC, "RPDO"),
    ):
        groups = [_wanted(d, entries) for entries in layout.values()]
        rooms = {n: _entries(maps[n].map_array.od) for n in maps.map or {} if n <= len(base)}
        placed = place(groups, rooms)
        if placed is None:
            raise NodeError(
                f"{a.where()}: {kind} {min(layout)}'s mapping 0x"
                f"{maps[min(layout)].map_array.od.index:04X} has room for "
                f"{rooms.get(min(layout), 0)} entries, swpc maps {len(groups[0])} "
                f"({', '.join(f'0x{x:04X}' for x, _, _ in groups[0])}); spread over its "
                f"{kind}s ({', '.join(f'{n}: {r}' for n, r in sorted(rooms.items()))} "
                f"entries), swpc's {len(groups)} groups of "
                f"{' and '.join(str(len(g)) for g in groups)} entries, each in PDOs of its "
                "own, do not fit",
                node=a.node,
                axis=int(a.axis),
            )
        for group in placed:
            for i, wanted in group:
                _write_map(d, maps, i, wanted, base[i - 1] + a.node, ttype, kind)
        numbers = tuple(tuple(i for i, _ in group) for group in placed)
        if numbers != tuple((i,) for i in layout):
            d.notes.append(
                f"{a.where()}: its {kind} maps are small: swpc's spread over {kind}s "
                + "; ".join("+".join(map(str, g)) for g in numbers)
            )
        if maps is node.tpdo:
            a.tpdos = numbers
        else:
            a.rpdos = numbers


def _wanted(d: _Drive, entries: tuple[PdoEntry, ...]) -> list[PdoEntry]:
    """The entries of one group the drive can map (module docstring)."""
    a = d.a
    wanted = []
    for index, sub, bits in entries:
        if not d.declared(index, sub):
            d._absent(index, sub)
            continue
        var = d.od[index]
        var = var if isinstance(var, ODVariable) else var[sub]
        if not var.pdo_mappable and index == cia402.MODES_OF_OPERATION:
            a.mode_by_sdo = True  # a mode changes seldom: over SDO, not mapped
            d.notes.append(
                f"{a.where()}: 0x6060 ({var.name}) is not PDO-mappable on this "
                "drive: each mode is written over SDO when it changes"
            )
            continue
        if not var.pdo_mappable:
            why = NEEDED.get(index) or OPTIONAL.get(index, "")
            if index in NEEDED:
                raise NodeError(
                    f"{a.where()}: 0x{index:04X} ({var.name}) is not PDO-mappable "
                    f"on this drive (its object dictionary): {why}",
                    node=a.node,
                    axis=int(a.axis),
                )
            d.skip(index)
            continue
        wanted.append((index, sub, bits))
    return wanted


def _write_map(
    d: _Drive, maps: Any, i: int, wanted: list[PdoEntry], cob_id: int, ttype: int, kind: str
) -> None:
    """One PDO's map over SDO (:func:`_save`), then read back and compared."""
    a = d.a
    d.step = f"PDO mapping {kind} {i}"
    p = maps[i]
    p.read()
    p.clear()
    for index, sub, bits in wanted:
        p.add_variable(index, sub, bits)
    p.cob_id = cob_id
    p.trans_type = ttype
    p.event_timer = 0 if kind == "TPDO" else None
    p.enabled = True
    _save(p, wanted)
    p.read()
    got = [(v.index, v.subindex) for v in p.map]
    if got != [(index, sub) for index, sub, _ in wanted]:
        raise NodeError(
            f"{a.where()}: {kind} {i} read back as "
            f"{', '.join(f'0x{x:04X}:{s}' for x, s in got) or 'empty'} where swpc "
            f"mapped {', '.join(f'0x{x:04X}:{s}' for x, s, _ in wanted)}: the drive "
            "took a shorter map (too many entries, or objects it cannot map)",
            node=a.node,
            axis=int(a.axis),
        )


def _entries(mapping: Any) -> int:
    """How many entries a PDO mapping object (0x1600.., 0x1A00..) declares room for."""
    return len([k for k in mapping.subindices if k > 0])


def _save(p: Any, wanted: list[tuple[int, int, int]]) -> None:
    """One PDO's communication and mapping parameters over SDO, CiA 301's sequence: the
    PDO disabled (COB-ID bit 31), the transmission type (and event timer), the mapping's
    count 0, its entries, its count, the PDO enabled.  Not canopen's ``PdoMap.save()``:
    with a mapping object typed ARRAY in the EDS (as some drives' are) it iterates the
    entries by the count it has just set to 0, and writes none."""
    com, mapping = p.com_record, p.map_array
    com[1].raw = p.cob_id | 0x80000000
    com[2].raw = p.trans_type
    if p.event_timer is not None and 5 in com.od and com[5].writable:
        com[5].raw = p.event_timer
    mapping[0].raw = 0
    for k, (index, sub, bits) in enumerate(wanted, start=1):
        mapping[k].raw = index << 16 | sub << 8 | bits
    mapping[0].raw = len(wanted)
    com[1].raw = p.cob_id


def _check_factor(a: AxisTrack, key: str, mine: float, theirs: float, obj: str) -> None:
    if not math.isclose(mine, theirs, rel_tol=1e-9):
        raise NodeError(
            f"{a.where()}: drives.modules.{a.module}.{AXIS_NAMES[a.axis]}.{key} is {mine:g} "
            f"but the drive's {obj} says {theirs:g}: the units would be wrong",
            node=a.node,
            axis=int(a.axis),
        )
