"""A ring buffer of float64 rows: the newest ``capacity`` rows, no Python object per row.

Per-sample data that a long-running process keeps (CAN feedback, motion-capture poses)
live here rather than in lists of objects: CPython's full garbage collections walk every
live container object, and millions of them paused the service for 0.5-2 s
(:mod:`swpc_hw.heap_freeze`).  Not thread-safe: the owner calls it under its own lock.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

KEEP_S = 600.0
"""How far back a long-running process keeps per-sample data (s of the time column):
longer than anything a run reads back (a spin, a rest), short enough that an always-on
service's memory levels off within its first runs."""


class RowRing:
    """The newest ``capacity`` rows of ``n_columns`` floats; the oldest are overwritten.

    Memory grows by doubling from ``initial`` rows up to ``capacity``, so a large capacity
    costs nothing until it is used.  With ``keep`` (s), a full ring grows only while its
    oldest row is less than ``keep`` older (column ``time_column``) than the row appended:
    else that oldest row is overwritten.  So memory follows the rate of the samples over
    ``keep`` seconds, not how long the process has run.
    """

    def __init__(
        self,
        n_columns: int,
        capacity: int,
        initial: int = 1024,
        *,
        keep: float | None = None,
        time_column: int = 0,
    ) -> None:
        if capacity < 1:
            raise ValueError(f"history capacity must be >= 1, not {capacity}")
        self.capacity = int(capacity)
        self.keep = keep
        self.time_column = time_column
        self._buf: NDArray[np.float64] = np.empty((min(self.capacity, initial), n_columns))
        self._start = 0  # index of the oldest row
        self._n = 0
        self.total = 0
        """Rows ever appended (a reader's cursor for :meth:`since`)."""

    def __len__(self) -> int:
        return self._n

    def _index(self, k: int) -> int:
        return (self._start + k) % int(self._buf.shape[0])

    def append(self, row: Sequence[float]) -> None:
        """Add a row; columns beyond ``len(row)`` are NaN."""
        size = self._buf.shape[0]
        if self._n == size and size < self.capacity and self._young(row):
            # grow: unroll into a larger array
            grown = np.empty((min(2 * size, self.capacity), self._buf.shape[1]))
            grown[:size] = self.array()
            self._buf, self._start = grown, 0
            size = grown.shape[0]
        i = self._index(self._n)
        self._buf[i, : len(row)] = row
        self._buf[i, len(row) :] = np.nan
        if self._n == size:
            self._start = (self._start + 1) % size
        else:
            self._n += 1
        self.total += 1

    def _young(self, row: Sequence[float]) -> bool:
        """The oldest row is within ``keep`` of ``row`` (always, without ``keep``)."""
        if self.keep is None:
            return True
        c = self.time_column
        return bool(row[c] - self._buf[self._start, c] < self.keep)

    def last(self) -> NDArray[np.float64]:
        """A copy of the newest row."""
        if not self._n:
            raise IndexError("empty ring")
        row: NDArray[np.float64] = self._buf[self._index(self._n - 1)].copy()
        return row

    def set_last(self, columns: slice, values: Sequence[float]) -> None:
        """Overwrite ``columns`` of the newest row."""
        if not self._n:
            raise IndexError("empty ring")
        self._buf[self._index(self._n - 1), columns] = values

    def clear(self) -> None:
        self._start = self._n = 0

    def since(self, cursor: int) -> tuple[NDArray[np.float64], int]:
        """A copy of the rows appended after ``cursor`` rows (a previous :attr:`total`),
        oldest first, and the new cursor: a reader that keeps the cursor reads each row
        once, however long the ring.  Rows already overwritten (or cleared) are skipped."""
        k = min(max(self.total - cursor, 0), self._n)
        size = self._buf.shape[0]
        first = self._index(self._n - k)
        if first + k <= size:
            rows = self._buf[first : first + k].copy()
        else:
            rows = np.concatenate((self._buf[first:], self._buf[: first + k - size]))
        return rows, self.total

    def array(self) -> NDArray[np.float64]:
        """A copy of the rows, oldest first, shape (len, n_columns)."""
        size = self._buf.shape[0]
        end = self._start + self._n
        if end <= size:
            return self._buf[self._start : end].copy()
        return np.concatenate((self._buf[self._start :], self._buf[: end - size]))
