"""Survey the published CiA 402 drive EDS files in this directory, as canopen reads them.

For each ``*.eds`` here (see README.md for where each came from) this prints, in Markdown:

* what the file says it is (``[DeviceInfo]``), the default of 0x6502 (supported drive modes)
  decoded into modes, and the default of 0x1017 (producer heartbeat time);
* which of the CiA 301/402 objects the swpc cia402 kind cares about exist, and whether the
  EDS marks them PDO-mappable;
* the RPDO/TPDO mapping parameter objects 0x1600-0x1603 and 0x1A00-0x1A03: the highest
  subindex the EDS defines, sub 0's default and HighLimit, and the default mapping;
* what canopen logged while importing the file, and what it passed over without a word
  (defaults it could not convert, node-id-relative defaults it did not flag as relative,
  DCF ParameterValues, sub-objects of an object it took for a variable, object lists and
  SubNumbers that disagree with the sections).

Everything comes from the files, read by ``canopen.import_od`` (node id 1) and, for the
checks canopen does not make, by the same ``configparser`` settings canopen uses.

Run: ``python tests/drives/cia402/eds/survey.py`` (from the repository root, with the venv).
"""

from __future__ import annotations

import logging
import re
import sys
from collections.abc import Iterator
from configparser import RawConfigParser
from contextlib import contextmanager
from dataclasses import dataclass, field
from importlib.metadata import version
from pathlib import Path

import canopen
from canopen.objectdictionary import ObjectDictionary, ODArray, ODRecord, ODVariable

from swpc_hw.drives.cia402.scan import MODE_BITS  # 0x6502's bits as CiA 402 names them

HERE = Path(__file__).resolve().parent
NODE_ID = 1

CYCLIC_BITS = (7, 8, 9)

OBJECTS: tuple[int, ...] = (
    0x1016, 0x1017, 0x1029,
    0x603F, 0x6040, 0x6041, 0x605A, 0x6060, 0x6061, 0x6064, 0x606C, 0x6071, 0x6072,
    0x6076, 0x6077, 0x607A, 0x607E, 0x607F, 0x6081, 0x6083, 0x6087, 0x608F, 0x6091,
    0x6098, 0x60FF, 0x6502,
)  # fmt: skip
MAPPINGS: tuple[int, ...] = (
    0x1600, 0x1601, 0x1602, 0x1603, 0x1A00, 0x1A01, 0x1A02, 0x1A03,
)  # fmt: skip
OBJECT_LISTS = ("MandatoryObjects", "OptionalObjects", "ManufacturerObjects")

Entry = ODVariable | ODRecord | ODArray


@dataclass
class Survey:
    """What one EDS file says, as canopen reads it."""

    path: Path
    od: ObjectDictionary
    log: list[str] = field(default_factory=list)


class _Collect(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(f"{record.levelname} {record.name}: {record.getMessage()}")


@contextmanager
def _collect_canopen_log() -> Iterator[_Collect]:
    logger = logging.getLogger("canopen")
    handler = _Collect()
    old_level = logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.DEBUG)
    try:
        yield handler
    finally:
        logger.removeHandler(handler)
        logger.setLevel(old_level)


def load(path: Path) -> Survey:
    with _collect_canopen_log() as handler:
        od = canopen.import_od(str(path), NODE_ID)
    return Survey(path, od, handler.lines)


def _entry(od: ObjectDictionary, index: int) -> Entry | None:
    return od.get(index)


def _var(od: ObjectDictionary, index: int, subindex: int = 0) -> ODVariable | None:
    entry = _entry(od, index)
    if isinstance(entry, ODVariable):
        return entry if subindex == 0 else None
    if entry is None:
        return None
    return entry.subindices.get(subindex)


def _default(var: ODVariable | None) -> str:
    """The default as the file writes it, and as canopen converted it."""
    if var is None:
        return "absent"
    raw: str | None = getattr(var, "default_raw", None)
    if raw is None:
        return "no DefaultValue"
    if var.default is None:
        return f"`{raw}` (canopen: not converted)"
    return f"`{raw}`" if str(var.default) == raw else f"`{raw}` = {var.default}"


def decode_modes(value: int) -> str:
    names = [name for bit, name in MODE_BITS.items() if value >> bit & 1]
    other = [bit for bit in range(32) if value >> bit & 1 and bit not in MODE_BITS]
    text = " ".join(names) if names else "none"
    if other:
        text += " + bits " + ",".join(str(bit) for bit in other)
    return text


def modes_cell(od: ObjectDictionary) -> tuple[str, str]:
    var = _var(od, 0x6502)
    if var is None or not isinstance(var.default, int):
        return "-", "unknown (no default)"
    cyclic = any(var.default >> bit & 1 for bit in CYCLIC_BITS)
    return decode_modes(var.default), "no" if cyclic else "**yes**"


def object_cell(od: ObjectDictionary, index: int) -> str:
    """``M`` mappable, ``s`` present but not mappable, ``·`` absent; records list their subs."""
    entry = _entry(od, index)
    if entry is None:
        return "·"
    if isinstance(entry, ODVariable):
        return "M" if entry.pdo_mappable else "s"
    subs = sorted(s for s in entry.subindices if s != 0)
    mappable = [s for s in subs if entry.subindices[s].pdo_mappable]
    kind = "rec" if isinstance(entry, ODRecord) else "arr"
    if not mappable:
        return f"{kind}{len(subs)} s"
    if mappable == subs:
        return f"{kind}{len(subs)} M"
    return f"{kind}{len(subs)} M:" + ",".join(str(s) for s in mappable)


def _mapped(value: int) -> str:
    index, subindex, bits = value >> 16, value >> 8 & 0xFF, value & 0xFF
    return f"{index:04X}:{subindex:02X}/{bits}"


def mapping_cell(od: ObjectDictionary, index: int) -> str:
    """``highest sub defined / sub 0 default / sub 0 HighLimit``."""
    entry = _entry(od, index)
    if entry is None:
        return "·"
    if isinstance(entry, ODVariable):
        return "VAR?"
    top = max(entry.subindices, default=0)
    sub0 = entry.subindices.get(0)
    default = "-" if sub0 is None or sub0.default is None else str(sub0.default)
    high = "-" if sub0 is None or sub0.max is None else str(sub0.max)
    return f"{top} / {default} / {high}"


def default_mapping(od: ObjectDictionary, index: int) -> str | None:
    entry = _entry(od, index)
    if entry is None or isinstance(entry, ODVariable):
        return None
    sub0 = entry.subindices.get(0)
    count = sub0.default if sub0 is not None and isinstance(sub0.default, int) else 0
    mapped: list[str] = []
    for subindex in range(1, count + 1):
        var = entry.subindices.get(subindex)
        if var is None or not isinstance(var.default, int):
            mapped.append(f"sub{subindex}?")
        else:
            mapped.append(_mapped(var.default))
    return ", ".join(mapped) if mapped else "(none)"


def _variables(od: ObjectDictionary) -> Iterator[ODVariable]:
    for entry in od.values():
        if isinstance(entry, ODVariable):
            yield entry
        else:
            yield from entry.subindices.values()


def _read_raw(path: Path) -> RawConfigParser:
    eds = RawConfigParser(inline_comment_prefixes=(";",))
    eds.optionxform = str  # type: ignore[assignment,method-assign]
    with path.open() as fp:
        eds.read_file(fp)
    return eds


def silent_findings(survey: Survey) -> list[str]:
    """What canopen passes over without logging."""
    eds = _read_raw(survey.path)
    od = survey.od
    notes: list[str] = []

    dropped: list[str] = []
    not_relative: list[str] = []
    values: list[str] = []
    for var in _variables(od):
        where = f"{var.index:04X}:{var.subindex:02X}"
        raw: str | None = getattr(var, "default_raw", None)
        if raw is not None and var.default is None:
            dropped.append(f"{where} `{raw}`")
        if raw is not None and "$NODEID" in raw.upper() and not var.relative:
            not_relative.append(f"{where} `{raw}`")
        value_raw: str | None = getattr(var, "value_raw", None)
        if value_raw is not None:
            values.append(f"{where}=`{value_raw}`")
    if dropped:
        shown = "; ".join(dropped[:6]) + ("; ..." if len(dropped) > 6 else "")
        notes.append(f"{len(dropped)} DefaultValue(s) canopen could not convert: {shown}")
    if not_relative:
        notes.append(
            f"{len(not_relative)} node-id-relative default(s) not spelled `$NODEID`: canopen "
            "converts them but leaves `relative` False: "
            + "; ".join(not_relative[:3])
            + ("; ..." if len(not_relative) > 3 else "")
        )
    if values:
        notes.append(f"{len(values)} ParameterValue(s) (DCF values): " + ", ".join(values))

    sections = eds.sections()
    indices = {int(s, 16) for s in sections if re.fullmatch(r"[0-9A-Fa-f]{4}", s)}
    ignored = sorted(
        {
            s
            for s in sections
            if (m := re.fullmatch(r"([0-9A-Fa-f]{4})[Ss]ub[0-9A-Fa-f]+", s))
            and isinstance(_entry(od, int(m.group(1), 16)), ODVariable)
        }
    )
    if ignored:
        notes.append("sub-sections of a VAR object, ignored by canopen: " + ", ".join(ignored))

    listed: set[int] = set()
    for name in OBJECT_LISTS:
        if not eds.has_section(name):
            notes.append(f"no [{name}] section")
            continue
        count = int(eds.get(name, "SupportedObjects"), 0)
        entries = [k for k in eds.options(name) if k != "SupportedObjects"]
        if len(entries) != count:
            notes.append(f"[{name}] SupportedObjects={count} but {len(entries)} entries")
        listed |= {int(eds.get(name, k), 0) for k in entries}
    if unlisted := sorted(indices - listed):
        notes.append("objects with a section but in no object list: " + _hexes(unlisted))
    if missing := sorted(listed - indices):
        notes.append("listed objects with no section: " + _hexes(missing))

    mismatched: list[str] = []
    for index in sorted(indices):
        section = f"{index:04X}" if eds.has_section(f"{index:04X}") else f"{index:04x}"
        if not eds.has_option(section, "SubNumber"):
            continue
        declared = int(eds.get(section, "SubNumber"), 0)
        present = sum(
            1 for s in sections if re.fullmatch(rf"{section}[Ss]ub[0-9A-Fa-f]+", s, re.IGNORECASE)
        )
        if declared != present:
            mismatched.append(f"{index:04X} ({declared} declared, {present} present)")
    if mismatched:
        notes.append("SubNumber differs from the sub-sections: " + ", ".join(mismatched))
    return notes


def _hexes(values: list[int]) -> str:
    text = ", ".join(f"{v:04X}" for v in values[:12])
    return text + (f", ... ({len(values)} in all)" if len(values) > 12 else "")


def _row(cells: list[str]) -> str:
    return "| " + " | ".join(cells) + " |"


def report(surveys: list[Survey]) -> Iterator[str]:
    yield f"canopen {version('canopen')}, node id {NODE_ID}; {len(surveys)} files"
    yield ""
    yield "### What each file says"
    yield ""
    yield _row(["file", "VendorName", "ProductName", "VendorNumber", "ProductNumber",
                "RevisionNumber", "RX/TX PDOs", "objects"])  # fmt: skip
    yield _row(["---"] * 8)
    for s in surveys:
        info = s.od.device_information
        yield _row([
            f"`{s.path.name}`",
            info.vendor_name or "-",
            info.product_name or "-",
            "-" if info.vendor_number is None else f"0x{info.vendor_number:X}",
            "-" if info.product_number is None else f"0x{info.product_number:X}",
            "-" if info.revision_number is None else f"0x{info.revision_number:X}",
            f"{info.nr_of_RXPDO}/{info.nr_of_TXPDO}",
            str(len(s.od)),
        ])  # fmt: skip
    yield ""
    yield "### Supported drive modes (0x6502) and heartbeat (0x1017)"
    yield ""
    yield _row(["file", "0x6502 default", "modes", "profile modes only", "0x1017 default"])
    yield _row(["---"] * 5)
    for s in surveys:
        modes, profile_only = modes_cell(s.od)
        yield _row([
            f"`{s.path.name}`",
            _default(_var(s.od, 0x6502)),
            modes,
            profile_only,
            _default(_var(s.od, 0x1017)),
        ])  # fmt: skip
    yield ""
    yield "### Objects"
    yield ""
    yield (
        "`M` present and PDO-mappable, `s` present and not mappable (SDO only), `·` absent; "
        "`recN`/`arrN` a record/array with N subindices above 0, `M:i,j` the mappable ones."
    )
    yield ""
    yield _row(["object", *(f"`{s.path.stem}`" for s in surveys)])
    yield _row(["---"] * (len(surveys) + 1))
    for index in OBJECTS:
        yield _row([f"0x{index:04X}", *(object_cell(s.od, index) for s in surveys)])
    yield ""
    yield "### PDO mapping parameters"
    yield ""
    yield "`highest subindex defined / sub 0 default / sub 0 HighLimit`, `·` absent."
    yield ""
    yield _row(["object", *(f"`{s.path.stem}`" for s in surveys)])
    yield _row(["---"] * (len(surveys) + 1))
    for index in MAPPINGS:
        yield _row([f"0x{index:04X}", *(mapping_cell(s.od, index) for s in surveys)])
    yield ""
    yield "### Default mappings (`index:sub/bits`)"
    for s in surveys:
        yield ""
        yield f"`{s.path.name}`"
        yield ""
        for index in MAPPINGS:
            mapped = default_mapping(s.od, index)
            if mapped is not None:
                yield f"- 0x{index:04X}: {mapped}"
    yield ""
    yield "### What canopen logged, and what it passed over silently"
    for s in surveys:
        yield ""
        yield f"`{s.path.name}`"
        yield ""
        notes = [f"canopen log: {line}" for line in s.log] or ["canopen logged nothing"]
        notes += silent_findings(s)
        for note in notes:
            yield f"- {note}"


def main() -> int:
    paths = sorted(HERE.glob("*.eds"))
    if not paths:
        print(f"no .eds files in {HERE}", file=sys.stderr)
        return 1
    for line in report([load(p) for p in paths]):
        print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
