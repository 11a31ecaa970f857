"""Opening a store's SQLite database: one way for the run store and the fleet's."""

from __future__ import annotations

import sqlite3
from collections.abc import Callable
from pathlib import Path


def open_database(
    path: Path, schema: str, migrate: Callable[[sqlite3.Connection], None] | None = None
) -> sqlite3.Connection:
    """``path`` (its directory made) in autocommit and WAL mode, ``schema`` applied, then
    ``migrate`` (an older store brought up to date), then SQLite's ``quick_check``.  A
    damaged file or one that is no database raises :class:`sqlite3.DatabaseError` with the
    connection closed: the caller names what to do."""
    path.parent.mkdir(parents=True, exist_ok=True)
    db = sqlite3.connect(path, check_same_thread=False, isolation_level=None)
    try:
        db.execute("PRAGMA journal_mode=WAL")
        db.executescript(schema)
        if migrate is not None:
            migrate(db)
        check = db.execute("PRAGMA quick_check").fetchone()
        if check is None or check[0] != "ok":
            raise sqlite3.DatabaseError(f"quick_check: {check[0] if check else 'no answer'}")
    except sqlite3.DatabaseError:
        db.close()
        raise
    return db
