"""What a scan of a robot's CAN bus found, set against what its config expects (pure).

A scan (``swpc drives scan``; each kind's ``scan`` module reads the bus) finds the nodes
that answer or send, and describes each as its kind does (:class:`FoundNode`: its state,
its fault, the columns of its kind).  :func:`compare` puts that beside the robot config's
``drives:`` (:class:`Expected`: each module's axes and their nodes): every expected node
found or missing, every node found that the config does not name (*unexpected*), and a
node id that two devices answer on, or that the config gives twice (*duplicate*).
:meth:`ScanReport.problems` is what is wrong, one clause each, naming the module, the
axis and the node: a missing node, a drive in FAULT, a duplicate node id.

No kind is imported here (each kind's ``scan`` module imports this one).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

FOUND = "found"
MISSING = "MISSING"
UNEXPECTED = "unexpected"
DUPLICATE = "DUPLICATE"


@dataclass(frozen=True)
class Expected:
    """One axis (or one dual-axis controller: ``axis`` empty) the config puts on ``node``."""

    module: int
    axis: str
    node: int

    def label(self) -> str:
        """``module 2 steer`` (``module 2`` for a dual-axis controller)."""
        return f"module {self.module} {self.axis}".rstrip()


@dataclass
class FoundNode:
    """A node the scan found, as its kind describes it.

    ``fields``: the kind's columns, label -> text, in table order (an object the drive
    lacks reads ``absent``); ``data``: the same for machines (numbers as numbers, None for
    what could not be read).  ``duplicate``: why the scan believes two devices share this
    node id (None: it does not)."""

    node: int
    state: str
    fault: str | None = None
    fields: dict[str, str] = field(default_factory=dict)
    data: dict[str, Any] = field(default_factory=dict)
    duplicate: str | None = None
    notes: list[str] = field(default_factory=list)


@dataclass(frozen=True)
class Row:
    """One node of the report: what the config expects on it, what was found, the verdict."""

    node: int
    expected: tuple[Expected, ...]
    found: FoundNode | None
    status: str

    def label(self) -> str:
        return ", ".join(e.label() for e in self.expected) or "-"


def compare(
    expected: Sequence[Expected], found: Iterable[FoundNode], *, configured: bool
) -> list[Row]:
    """Every node expected or found, by node id: found, MISSING, unexpected (found, not in
    a config: only when there is one, ``configured``), DUPLICATE (two devices answer on it,
    or the config names it twice)."""
    by_node: dict[int, list[Expected]] = {}
    for e in expected:
        by_node.setdefault(e.node, []).append(e)
    seen = {f.node: f for f in found}
    rows = []
    for node in sorted(set(by_node) | set(seen)):
        exp = tuple(by_node.get(node, ()))
        f = seen.get(node)
        if f is None:
            status = MISSING
        elif len(exp) > 1 or f.duplicate is not None:
            status = DUPLICATE
        elif not exp and configured:
            status = UNEXPECTED
        else:
            status = FOUND
        rows.append(Row(node, exp, f, status))
    return rows


@dataclass
class ScanReport:
    """A scan's result: the kind, the bus, the rows (:func:`compare`), how long it took."""

    kind: str
    bus: str
    rows: list[Row]
    configured: bool
    candidates: int
    elapsed_s: float
    notes: list[str] = field(default_factory=list)

    def problems(self) -> list[str]:
        """What is wrong, one clause each: an expected node missing, a duplicate node id,
        a node in FAULT.  Empty: every expected node answered and none is in FAULT.  An
        unexpected node is reported in the table, not here."""
        out = []
        for r in self.rows:
            where = f"{r.label()} (node {r.node})" if r.expected else f"node {r.node}"
            if r.status == MISSING:
                out.append(f"{where} missing")
            elif r.status == DUPLICATE:
                why = (
                    r.found.duplicate
                    if r.found is not None and r.found.duplicate
                    else "named twice in the config"
                )
                out.append(f"{where}: duplicate node id ({why})")
            if r.found is not None and r.found.fault is not None:
                out.append(f"{where} in FAULT: {r.found.fault}")
        return out

    def to_json(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "bus": self.bus,
            "configured": self.configured,
            "candidates": self.candidates,
            "elapsed_s": round(self.elapsed_s, 3),
            "ok": not self.problems(),
            "problems": self.problems(),
            "notes": list(self.notes),
            "nodes": [
                {
                    "node": r.node,
                    "status": r.status,
                    "expected": [{"module": e.module, "axis": e.axis} for e in r.expected],
                    "state": None if r.found is None else r.found.state,
                    "fault": None if r.found is None else r.found.fault,
                    "duplicate": None if r.found is None else r.found.duplicate,
                    "fields": {} if r.found is None else dict(r.found.fields),
                    "data": {} if r.found is None else dict(r.found.data),
                    "notes": [] if r.found is None else list(r.found.notes),
                }
                for r in self.rows
            ],
        }


def parse_nodes(text: str, lowest: int, highest: int) -> list[int]:
    """``"1,2,5-8"`` -> [1, 2, 5, 6, 7, 8]; :class:`ValueError` naming a bad item or a node
    outside ``lowest..highest``."""
    out: list[int] = []
    for item in (t.strip() for t in text.split(",")):
        if not item:
            continue
        lo, sep, hi = item.partition("-")
        try:
            first, last = int(lo), int(hi) if sep else int(lo)
        except ValueError:
            raise ValueError(f"{item!r} is not a node id or a range a-b") from None
        if not lowest <= first <= last <= highest:
            raise ValueError(f"{item!r}: node ids are {lowest}..{highest}")
        out.extend(range(first, last + 1))
    return sorted(set(out))
