"""The fleet store (SQLite, ``<fleet data dir>/fleet.sqlite``): every robot's state
documents, append-only, and when each robot was last heard.

A document is kept when it differs from the robot's last one in anything but its
``time`` (a repeat, the same state published again: it only moves ``last_seen``).  So the
store holds each robot's history of states, each once, and a restarted fleet service
lists every robot as it last was, with when it was last heard.  Checked when it opens
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


class FleetStore:
    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._lock = threading.Lock()
        try:
            self._db = open_database(self.path, _SCHEMA)
        except sqlite3.DatabaseError as exc:
            raise FleetStoreError(
                f"{self.path}: the fleet store is damaged ({exc}); move it aside and start "
                "again: the robots publish their state again, with their whole history of "
                "calibrations"
            ) from exc

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
            self._db.execute(
                "INSERT INTO documents (robot, received, digest, doc) VALUES (?, ?, ?, ?)",
                (robot, received, d, json.dumps(doc)),
            )
            return True

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
