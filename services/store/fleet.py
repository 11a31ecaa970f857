"""The fleet store (SQLite, ``<fleet data dir>/fleet.sqlite``): every robot's state
documents, append-only, and when each robot was last heard.

A document is kept when it differs from the robot's last one in anything but its
``time`` (a repeat, the same state published again: it only moves ``last_seen``).  So the
store holds each robot's history of states, each once, and a restarted fleet service
lists every robot as it last was, with when it was last heard.

The store is bounded: each robot keeps its last ``max_documents`` documents, and all of
them together at most ``max_bytes`` of JSON; beyond, the oldest are pruned first (never a
robot's last one, unless the robots' last ones alone exceed it: then the robots heard
longest ago go).  A robot's last document holds its whole history of calibrations, so
pruning loses no calibration of a robot still publishing.  Checked when it opens
(``quick_check``), as the run store: a damaged one is :class:`FleetStoreError`, one line
naming the file.
"""

from __future__ import annotations

import hashlib
import json
import sqlite3
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from services.store.sqlite import open_database
from swpc_hw.errors import SwpcError

_SCHEMA = """
CREATE TABLE IF NOT EXISTS robots (
    robot TEXT PRIMARY KEY,
    first_seen REAL NOT NULL,
    last_seen REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS documents (
    seq INTEGER PRIMARY KEY AUTOINCREMENT,
    robot TEXT NOT NULL,
    received REAL NOT NULL,
    digest TEXT NOT NULL,
    doc TEXT NOT NULL
);
CREATE INDEX IF NOT EXISTS documents_robot ON documents (robot, seq);
"""
VOLATILE = ("time",)
"""A document's fields left out of its digest: what changes at every repeat."""


class FleetStoreError(SwpcError):
    """The fleet store cannot be opened: damaged, or not a database."""


def digest(doc: dict[str, Any]) -> str:
    """SHA-256 of the document without :data:`VOLATILE` (canonical JSON)."""
    kept = {k: v for k, v in doc.items() if k not in VOLATILE}
    return hashlib.sha256(json.dumps(kept, sort_keys=True).encode()).hexdigest()


@dataclass(frozen=True)
class RobotRow:
    robot: str
    first_seen: float
    """Epoch seconds (the fleet's wall clock) of its first message."""
    last_seen: float
    """Epoch seconds of its last message (a repeat too)."""
    documents: int


@dataclass(frozen=True)
class StoredDocument:
    seq: int
    received: float
    doc: dict[str, Any]


MAX_DOCUMENTS = 100
"""Documents kept per robot (its states as they changed; a robot publishes a new one per
calibration, check or change of health)."""
MAX_BYTES = 128 << 20
"""JSON bytes of every robot's documents together."""


class FleetStore:
    def __init__(
        self, path: str | Path, *, max_documents: int = MAX_DOCUMENTS, max_bytes: int = MAX_BYTES
    ) -> None:
        if max_documents < 1 or max_bytes < 1:
            raise ValueError("max_documents and max_bytes must be positive")
        self.path = Path(path)
        self.max_documents = max_documents
        self.max_bytes = max_bytes
        self.pruned = 0
        """Documents pruned since it opened (the bounds above)."""
        self._lock = threading.Lock()
        try:
            self._db = open_database(self.path, _SCHEMA)
        except sqlite3.DatabaseError as exc:
            raise FleetStoreError(
                f"{self.path}: the fleet store is damaged ({exc}); move it aside and start "
                "again: the robots publish their state again, with their whole history of "
                "calibrations"
            ) from exc
        with self._lock:
            self._bytes = self._total()

    def record(self, robot: str, received: float, doc: dict[str, Any]) -> bool:
        """``robot`` was heard at ``received`` with ``doc``: its ``last_seen`` moves, and
        the document is appended unless it is its last one again; returns whether it
        was."""
        d = digest(doc)
        with self._lock, self._db:
            self._db.execute("BEGIN")
            self._db.execute(
                "INSERT INTO robots (robot, first_seen, last_seen) VALUES (?, ?, ?) "
                "ON CONFLICT(robot) DO UPDATE SET last_seen = max(last_seen, excluded.last_seen)",
                (robot, received, received),
            )
            last = self._db.execute(
                "SELECT digest FROM documents WHERE robot = ? ORDER BY seq DESC LIMIT 1",
                (robot,),
            ).fetchone()
            if last is not None and last[0] == d:
                return False
            text = json.dumps(doc)
            self._db.execute(
                "INSERT INTO documents (robot, received, digest, doc) VALUES (?, ?, ?, ?)",
                (robot, received, d, text),
            )
            self._bytes += len(text)
            self._prune(robot)
            return True

    def _prune(self, robot: str) -> None:
        """(lock and transaction held) Keep within the bounds (module docstring)."""
        db = self._db
        cur = db.execute(
            "DELETE FROM documents WHERE robot = ? AND seq NOT IN (SELECT seq FROM documents "
            "WHERE robot = ? ORDER BY seq DESC LIMIT ?)",
            (robot, robot, self.max_documents),
        )
        self.pruned += max(cur.rowcount, 0)
        if cur.rowcount > 0:
            self._bytes = self._total()
        if self._bytes <= self.max_bytes:
            return
        excess, doomed = self._bytes - self.max_bytes, []
        rows = db.execute(  # oldest first, never a robot's newest
            "SELECT seq, length(doc) FROM documents d WHERE seq < (SELECT max(seq) FROM "
            "documents WHERE robot = d.robot) ORDER BY seq"
        )
        for seq, size in rows:
            if excess <= 0:
                break
            doomed.append((seq,))
            excess -= size
        db.executemany("DELETE FROM documents WHERE seq = ?", doomed)
        self.pruned += len(doomed)
        while excess > 0:  # only the robots' newest documents left: the robot heard longest ago
            gone, size = db.execute(
                "SELECT r.robot, (SELECT coalesce(sum(length(doc)), 0) FROM documents d "
                "WHERE d.robot = r.robot) FROM robots r ORDER BY r.last_seen, r.robot LIMIT 1"
            ).fetchone()
            cur = db.execute("DELETE FROM documents WHERE robot = ?", (gone,))
            db.execute("DELETE FROM robots WHERE robot = ?", (gone,))
            self.pruned += max(cur.rowcount, 0)
            excess -= size
        self._bytes = self._total()

    def _total(self) -> int:
        (n,) = self._db.execute("SELECT coalesce(sum(length(doc)), 0) FROM documents").fetchone()
        return int(n)

    def robots(self) -> list[RobotRow]:
        """Every robot ever heard, by name."""
        with self._lock:
            rows = self._db.execute(
                "SELECT r.robot, r.first_seen, r.last_seen, "
                "(SELECT count(*) FROM documents d WHERE d.robot = r.robot) "
                "FROM robots r ORDER BY r.robot"
            ).fetchall()
        return [RobotRow(str(a), float(b), float(c), int(n)) for a, b, c, n in rows]

    def robot(self, robot: str) -> RobotRow | None:
        return next((r for r in self.robots() if r.robot == robot), None)

    def last_seq(self) -> dict[str, int]:
        """Each robot's newest document's number (what a cache of its view is keyed by)."""
        with self._lock:
            rows = self._db.execute("SELECT robot, max(seq) FROM documents GROUP BY robot")
            return {str(r): int(n) for r, n in rows.fetchall()}

    def delete(self, seqs: list[int]) -> None:
        """Forget documents ``seqs`` (ones that no longer pass the checks of today)."""
        with self._lock, self._db:
            self._db.executemany("DELETE FROM documents WHERE seq = ?", [(q,) for q in seqs])
            self._db.execute(
                "DELETE FROM robots WHERE robot NOT IN (SELECT DISTINCT robot FROM documents)"
            )
            self._bytes = self._total()

    @property
    def bytes(self) -> int:
        """JSON bytes of the documents kept."""
        return self._bytes

    def latest(self, robot: str) -> StoredDocument | None:
        docs = self._select(robot, "ORDER BY seq DESC LIMIT 1")
        return docs[0] if docs else None

    def documents(self, robot: str) -> list[StoredDocument]:
        """``robot``'s documents, oldest first."""
        return self._select(robot, "ORDER BY seq")

    def _select(self, robot: str, tail: str) -> list[StoredDocument]:
        with self._lock:
            rows = self._db.execute(
                f"SELECT seq, received, doc FROM documents WHERE robot = ? {tail}", (robot,)
            ).fetchall()
        return [StoredDocument(int(s), float(r), json.loads(d)) for s, r, d in rows]

    def close(self) -> None:
        with self._lock:
            self._db.close()
