"""``references.yaml`` of an IMU dataset: known quantities with their std devs.

::

    references:
      - {kind: axis_distance, modules: [1, 2], value: 0.4301, stddev: 0.0005}
      - {kind: wheel_radius, module: 3, value: 0.05500, stddev: 0.0005}
      - {kind: straight_drive, start: 170.0, end: 186.0, value: 4.0003, stddev: 0.0005}

* ``axis_distance``: the distance (m) between the steering axes of two modules,
  ``|P_s,a - P_s,b|`` (a tape measure between the two steering bearings).
* ``wheel_radius``: the radius ``r`` (m) of one module's wheel.
* ``straight_drive``: between the times ``start`` and ``end`` (s, the encoders' clock;
  the robot still at both) the robot drove straight, a pure translation, between two floor
  marks ``value`` metres apart.  In a translation every point of the robot moves alike,
  so the marks may be taken at any point of it (swpc's simulator takes the steering axis
  of the first module).

Every entry has ``kind``, ``value`` (> 0) and ``stddev`` (> 0), finite numbers, plus the
keys of its kind and no others.  An unknown kind, a missing or extra key, a module that is
not in robot.yaml or a malformed value raises :class:`~swpc_hw.errors.DatasetError` with
a one-line message naming the file and the entry.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from swpc_hw.errors import DatasetError
from swpc_hw.files.kinematic_file import atomic_write_text


@dataclass(frozen=True)
class AxisDistance:
    """``|P_s,a - P_s,b| = value`` (m): a tape-measured distance between two steering axes."""

    modules: tuple[int, int]
    value: float
    stddev: float
    kind: str = "axis_distance"


@dataclass(frozen=True)
class WheelRadius:
    """``r = value`` (m) of module ``module``'s wheel."""

    module: int
    value: float
    stddev: float
    kind: str = "wheel_radius"


@dataclass(frozen=True)
class StraightDrive:
    """A pure translation of ``value`` metres between the times ``start`` and ``end`` (s)."""

    start: float
    end: float
    value: float
    stddev: float
    kind: str = "straight_drive"


Reference = AxisDistance | WheelRadius | StraightDrive

KIND_KEYS: dict[str, tuple[str, ...]] = {
    "axis_distance": ("modules",),
    "wheel_radius": ("module",),
    "straight_drive": ("start", "end"),
}
"""The keys of every kind besides ``kind``, ``value`` and ``stddev``."""
COMMON_KEYS = ("kind", "value", "stddev")


def _number(value: Any, where: str, key: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise DatasetError(f"{where}: {key} must be a finite number (got {value!r})")
    return float(value)


def _module(value: Any, where: str, ids: set[int] | None) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise DatasetError(f"{where}: a module id must be an integer (got {value!r})")
    if ids is not None and value not in ids:
        raise DatasetError(f"{where}: module {value} is not in robot.yaml {sorted(ids)}")
    return int(value)


def parse_reference(entry: Any, where: str, ids: set[int] | None = None) -> Reference:
    """One entry of the ``references:`` list (``where`` names it in errors)."""
    if not isinstance(entry, dict):
        raise DatasetError(f"{where}: must be a mapping with kind, value and stddev")
    kind = entry.get("kind")
    if kind not in KIND_KEYS:
        raise DatasetError(
            f"{where}: unknown kind {kind!r} (known: {', '.join(KIND_KEYS)})"
        )
    where = f"{where} ({kind})"
    allowed = (*COMMON_KEYS, *KIND_KEYS[kind])
    missing = [k for k in allowed if k not in entry]
    if missing:
        raise DatasetError(f"{where}: missing key(s) {', '.join(missing)}")
    extra = sorted(str(k) for k in entry if k not in allowed)
    if extra:
        raise DatasetError(
            f"{where}: unknown key(s) {', '.join(extra)} (a {kind} has {', '.join(allowed)})"
        )
    value = _number(entry["value"], where, "value")
    stddev = _number(entry["stddev"], where, "stddev")
    if value <= 0 or stddev <= 0:
        raise DatasetError(f"{where}: value and stddev must be > 0 (got {value}, {stddev})")
    if kind == "axis_distance":
        mods = entry["modules"]
        if not isinstance(mods, list) or len(mods) != 2:
            raise DatasetError(f"{where}: modules must be a list of two module ids (got {mods!r})")
        a, b = (_module(m, where, ids) for m in mods)
        if a == b:
            raise DatasetError(f"{where}: modules must be two different modules (got {a} twice)")
        return AxisDistance((a, b), value, stddev)
    if kind == "wheel_radius":
        return WheelRadius(_module(entry["module"], where, ids), value, stddev)
    start = _number(entry["start"], where, "start")
    end = _number(entry["end"], where, "end")
    if not end > start:
        raise DatasetError(f"{where}: end {end:g} must be after start {start:g}")
    return StraightDrive(start, end, value, stddev)


def parse_references(doc: Any, where: str, ids: set[int] | None = None) -> list[Reference]:
    """The whole document: a mapping with a ``references:`` list (may be empty)."""
    if not isinstance(doc, dict) or "references" not in doc:
        raise DatasetError(f"{where}: top level must be a mapping with a 'references' list")
    refs = doc["references"]
    if refs is None:
        return []
    if not isinstance(refs, list):
        raise DatasetError(f"{where}: references must be a list (got {type(refs).__name__})")
    return [parse_reference(e, f"{where}: references[{i}]", ids) for i, e in enumerate(refs)]


def load_references(path: str | os.PathLike[str], ids: set[int] | None = None) -> list[Reference]:
    """Load and check ``references.yaml`` (module ids checked against ``ids`` if given)."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise DatasetError(f"{p}: cannot read: {exc.strerror or exc}") from exc
    except UnicodeDecodeError as exc:
        raise DatasetError(f"{p}: not UTF-8 text") from exc
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise DatasetError(f"{p}: not valid YAML: {exc}".splitlines()[0]) from exc
    return parse_references(doc, str(p), ids)


def reference_document(ref: Reference) -> dict[str, Any]:
    """Plain-data form of one reference (the file's entry)."""
    out: dict[str, Any] = {"kind": ref.kind}
    if isinstance(ref, AxisDistance):
        out["modules"] = list(ref.modules)
    elif isinstance(ref, WheelRadius):
        out["module"] = ref.module
    else:
        out["start"] = round(ref.start, 6)
        out["end"] = round(ref.end, 6)
    out["value"] = round(ref.value, 9)
    out["stddev"] = ref.stddev
    return out


def save_references(path: str | os.PathLike[str], refs: list[Reference]) -> None:
    """Write ``references.yaml`` atomically (one flow mapping per entry)."""
    lines = ["references:"]
    for ref in refs:
        body = yaml.safe_dump(reference_document(ref), default_flow_style=True, sort_keys=False)
        lines.append(f"  - {body.strip()}")
    if not refs:
        lines[0] = "references: []"
    atomic_write_text(path, "\n".join(lines) + "\n")


def reference_label(ref: Reference) -> str:
    """Short label: ``axis_distance 1-2``, ``wheel_radius 3``, ``straight_drive 170-186 s``."""
    if isinstance(ref, AxisDistance):
        return f"axis_distance {ref.modules[0]}-{ref.modules[1]}"
    if isinstance(ref, WheelRadius):
        return f"wheel_radius {ref.module}"
    return f"straight_drive {ref.start:g}-{ref.end:g} s"
