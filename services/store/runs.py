"""Persistent run store (SQLite in the data dir): the runs (calibrations and checks,
their ``kind``), and every change of the kinematic file in force
(:meth:`RunStore.add_change`: a run's install at its end, an install of a run's result,
a roll-back, each with the file it replaced).  :meth:`RunStore.finished` gives every
finished run's result in time order: the robot's history (:mod:`services.runtime.history`).

A restarted service lists past runs and their results; a run that was in progress when
the service died is marked FAILED with the reason ``service restarted during the run`` and
the time it was found so.  The store is checked when it opens (SQLite's ``quick_check``):
a damaged one is :class:`RunStoreError`, one line naming the file and how to recover,
before the service touches anything else.
"""

from __future__ import annotations

import builtins
import json
import sqlite3
import threading
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from services.store.sqlite import open_database
from swpc_hw.errors import SwpcError

TERMINAL = ("DONE", "FAILED", "ABORTED")

_SCHEMA = """
CREATE TABLE IF NOT EXISTS runs (
    id TEXT PRIMARY KEY,
    created TEXT NOT NULL,
    updated TEXT NOT NULL,
    state TEXT NOT NULL,
    status TEXT NOT NULL,
    result TEXT,
    kind TEXT NOT NULL DEFAULT 'calibration'
);
CREATE TABLE IF NOT EXISTS changes (
    seq INTEGER PRIMARY KEY AUTOINCREMENT,
    time TEXT NOT NULL,
    action TEXT NOT NULL,
    run TEXT,
    file TEXT NOT NULL,
    replaced TEXT,
    replaced_run TEXT,
    replaced_text TEXT
);
"""
CHANGE_FIELDS = ("time", "action", "run", "file", "replaced", "replaced_run")
"""A change of the file in force as listed: when (UTC), ``action`` (``run``: a run
installed its result at its end; ``install``: a run's result installed later; ``rollback``:
a backup installed again), the run whose result it installed (a roll-back: the run the
restored file came from, if any), the file installed, the backup kept of the file it
replaced (None: no file was in force) and the run that one came from."""


class RunStoreError(SwpcError):
    """The run store cannot be opened: damaged, or not a database (module docstring)."""


def _add_kind(db: sqlite3.Connection) -> None:
    """A store from before checks: every run a calibration."""
    columns = {r[1] for r in db.execute("PRAGMA table_info(runs)")}
    if "kind" not in columns:
        db.execute("ALTER TABLE runs ADD COLUMN kind TEXT NOT NULL DEFAULT 'calibration'")
    db.execute("SELECT count(*) FROM runs").fetchone()


class RunStore:
    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._lock = threading.Lock()
        try:
            self._db = open_database(self.path, _SCHEMA, _add_kind)
        except sqlite3.DatabaseError as exc:
            raise RunStoreError(
                f"{self.path}: the run store is damaged ({exc}); move it aside (mv "
                f"{self.path} {self.path}.damaged) and start again: a new store is made, and "
                f"every run's data stays in {self.path.parent / 'runs'}"
            ) from exc

    def mark_interrupted(self, found: str) -> list[str]:
        """Mark every non-terminal run FAILED, finished at ``found`` (when the service
        found it so, at start-up); returns their ids."""
        with self._lock:
            rows = self._db.execute(
                "SELECT id, status FROM runs WHERE state NOT IN (?, ?, ?)", TERMINAL
            ).fetchall()
            for rid, status in rows:
                st = json.loads(status)
                st["state"] = "FAILED"
                st.setdefault("errors", []).append("service restarted during the run")
                st["reason"] = "service restarted during the run"
                st["finished"] = found
                self._db.execute(
                    "UPDATE runs SET state = 'FAILED', status = ?, updated = datetime('now') "
                    "WHERE id = ?",
                    (json.dumps(st), rid),
                )
            return [r[0] for r in rows]

    def upsert(self, run_id: str, created: str, status: dict[str, Any]) -> None:
        """Save a run's status (its ``kind``: ``calibration`` unless it says otherwise)."""
        kind = str(status.get("kind") or "calibration")
        with self._lock:
            self._db.execute(
                "INSERT INTO runs (id, created, updated, state, status, kind) "
                "VALUES (?, ?, datetime('now'), ?, ?, ?) ON CONFLICT(id) DO UPDATE SET "
                "updated = datetime('now'), state = excluded.state, status = excluded.status",
                (run_id, created, status["state"], json.dumps(status), kind),
            )

    def set_result(self, run_id: str, result: dict[str, Any]) -> None:
        with self._lock:
            self._db.execute(
                "UPDATE runs SET result = ? WHERE id = ?", (json.dumps(result), run_id)
            )

    def get(self, run_id: str) -> tuple[dict[str, Any], dict[str, Any] | None] | None:
        with self._lock:
            row = self._db.execute(
                "SELECT status, result FROM runs WHERE id = ?", (run_id,)
            ).fetchone()
        if row is None:
            return None
        return json.loads(row[0]), (json.loads(row[1]) if row[1] else None)

    def list(self, kind: str | None = None) -> Iterable[dict[str, Any]]:
        """Every run's status, oldest first (of ``kind`` only, if given)."""
        with self._lock:
            rows = self._db.execute(
                "SELECT status FROM runs WHERE ?1 IS NULL OR kind = ?1 ORDER BY created",
                (kind,),
            ).fetchall()
        return [json.loads(r[0]) for r in rows]

    def finished(self) -> builtins.list[tuple[dict[str, Any], dict[str, Any]]]:
        """``(status, result)`` of every DONE run with a result, calibrations and checks,
        in the order they finished."""
        with self._lock:
            rows = self._db.execute(
                "SELECT status, result FROM runs WHERE state = 'DONE' AND result IS NOT NULL"
            ).fetchall()
        out = [(json.loads(st), json.loads(res)) for st, res in rows]
        out.sort(key=lambda r: str(r[0].get("finished") or r[0].get("created") or ""))
        return out

    def add_change(self, change: dict[str, Any], replaced_text: str | None) -> None:
        """Record a change of the file in force (:data:`CHANGE_FIELDS`) with the text of
        the file it replaced (None: none was in force), kept for
        :meth:`replaced_by` even once its backup is pruned."""
        with self._lock:
            self._db.execute(
                f"INSERT INTO changes ({', '.join(CHANGE_FIELDS)}, replaced_text) "
                "VALUES (?, ?, ?, ?, ?, ?, ?)",
                (*(change.get(k) for k in CHANGE_FIELDS), replaced_text),
            )

    def changes(self) -> builtins.list[dict[str, Any]]:
        """Every change of the file in force, newest first (:data:`CHANGE_FIELDS`)."""
        with self._lock:
            rows = self._db.execute(
                f"SELECT {', '.join(CHANGE_FIELDS)} FROM changes ORDER BY seq DESC"
            ).fetchall()
        return [dict(zip(CHANGE_FIELDS, r, strict=True)) for r in rows]

    def replaced_by(self, run_id: str) -> tuple[dict[str, Any], str | None] | None:
        """The last install of ``run_id``'s result (at its end or later) and the text of
        the file it replaced (None: none was in force); None if it was never installed."""
        with self._lock:
            row = self._db.execute(
                f"SELECT {', '.join(CHANGE_FIELDS)}, replaced_text FROM changes "
                "WHERE run = ? AND action IN ('run', 'install') ORDER BY seq DESC LIMIT 1",
                (run_id,),
            ).fetchone()
        if row is None:
            return None
        return dict(zip(CHANGE_FIELDS, row[:-1], strict=True)), row[-1]

    def close(self) -> None:
        with self._lock:
            self._db.close()
