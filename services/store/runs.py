"""Persistent run store (SQLite in the data dir).

A restarted service lists past runs and their results; a run that was in progress when
the service died is marked FAILED with the reason ``service restarted during the run``.
"""

from __future__ import annotations

import json
import sqlite3
import threading
from collections.abc import Iterable
from pathlib import Path
from typing import Any

TERMINAL = ("DONE", "FAILED", "ABORTED")

_SCHEMA = """
CREATE TABLE IF NOT EXISTS runs (
    id TEXT PRIMARY KEY,
    created TEXT NOT NULL,
    updated TEXT NOT NULL,
    state TEXT NOT NULL,
    status TEXT NOT NULL,
    result TEXT
);
"""


class RunStore:
    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._lock = threading.Lock()
        self._db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute(_SCHEMA)

    def mark_interrupted(self) -> list[str]:
        """Mark every non-terminal run FAILED (called at start-up); returns their ids."""
        with self._lock:
            rows = self._db.execute(
                "SELECT id, status FROM runs WHERE state NOT IN (?, ?, ?)", TERMINAL
            ).fetchall()
            for rid, status in rows:
                st = json.loads(status)
                st["state"] = "FAILED"
                st.setdefault("errors", []).append("service restarted during the run")
                st["reason"] = "service restarted during the run"
                self._db.execute(
                    "UPDATE runs SET state = 'FAILED', status = ?, updated = datetime('now') "
                    "WHERE id = ?",
                    (json.dumps(st), rid),
                )
            return [r[0] for r in rows]

    def upsert(self, run_id: str, created: str, status: dict[str, Any]) -> None:
        with self._lock:
            self._db.execute(
                "INSERT INTO runs (id, created, updated, state, status) "
                "VALUES (?, ?, datetime('now'), ?, ?) ON CONFLICT(id) DO UPDATE SET "
                "updated = datetime('now'), state = excluded.state, status = excluded.status",
                (run_id, created, status["state"], json.dumps(status)),
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

    def list(self) -> Iterable[dict[str, Any]]:
        with self._lock:
            rows = self._db.execute("SELECT status FROM runs ORDER BY created").fetchall()
        return [json.loads(r[0]) for r in rows]

    def close(self) -> None:
        with self._lock:
            self._db.close()
