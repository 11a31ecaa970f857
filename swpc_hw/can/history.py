"""Feedback history of one controller node, as a fixed-capacity numpy ring buffer.

The driver receives 2 frames per node per feedback period (4 nodes at 200 Hz: 1600 frames
a second) and keeps the samples of a whole calibration (minutes).  Kept as Python objects
(one dataclass and ten floats per sample) that is millions of objects, which CPython's
cyclic garbage collector walks on every full collection: 0.5-2 s pauses were measured
with ~1.3 M live objects, long enough for the driver's supervisor to declare every node
lost (heartbeat timeout 0.3 s on a robot).  Here a sample is one row of a preallocated
float64 array: no per-sample object survives the receive call.

Columns (:data:`COLUMNS`): ``t`` host monotonic receive time, ``t_bus`` bus time stamp,
``counter`` (mod 256), ``seq`` (unwrapped), ``theta_hat``, ``psi`` (unwrapped, rad), and
the velocity/torque frame's four values (NaN until that frame arrives).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

COLUMNS = (
    "t",
    "t_bus",
    "counter",
    "seq",
    "theta_hat",
    "psi",
    "steer_velocity",
    "wheel_velocity",
    "steer_torque",
    "wheel_torque",
)
_VT = slice(6, 10)  # the velocity/torque frame's columns


class FeedbackRing:
    """Newest ``capacity`` feedback rows; the oldest are overwritten.  Not thread-safe:
    the driver calls it under its lock.

    Memory grows by doubling up to ``capacity`` rows (80 bytes a row), so an idle driver
    with the default 200 000-row capacity does not hold 16 MB per node.
    """

    def __init__(self, capacity: int) -> None:
        if capacity < 1:
            raise ValueError(f"history capacity must be >= 1, not {capacity}")
        self.capacity = int(capacity)
        self._buf: NDArray[np.float64] = np.empty((min(self.capacity, 1024), len(COLUMNS)))
        self._start = 0  # index of the oldest row
        self._n = 0

    def __len__(self) -> int:
        return self._n

    def append(self, row: tuple[float, ...]) -> None:
        """Add a sample (``t, t_bus, counter, seq, theta_hat, psi``; the rest NaN)."""
        size = self._buf.shape[0]
        if self._n == size and size < self.capacity:  # grow: unroll into a larger array
            grown = np.empty((min(2 * size, self.capacity), len(COLUMNS)))
            grown[:size] = self.array()
            self._buf, self._start = grown, 0
            size = grown.shape[0]
        i = (self._start + self._n) % size
        self._buf[i, : len(row)] = row
        self._buf[i, len(row) :] = np.nan
        if self._n == size:
            self._start = (self._start + 1) % size
        else:
            self._n += 1

    def set_last_velocity_torque(self, values: tuple[float, float, float, float]) -> None:
        """Fill the newest row's ``steer_velocity, wheel_velocity, steer_torque,
        wheel_torque``."""
        if not self._n:
            raise IndexError("empty history")
        i = (self._start + self._n - 1) % self._buf.shape[0]
        self._buf[i, _VT] = values

    def clear(self) -> None:
        self._start = self._n = 0

    def array(self) -> NDArray[np.float64]:
        """A copy of the rows, oldest first, shape (len, len(COLUMNS))."""
        size = self._buf.shape[0]
        end = self._start + self._n
        if end <= size:
            return self._buf[self._start : end].copy()
        return np.concatenate((self._buf[self._start :], self._buf[: end - size]))

    def columns(self) -> dict[str, NDArray[np.float64]]:
        """The rows as named columns (copies)."""
        a = self.array()
        return {name: np.ascontiguousarray(a[:, k]) for k, name in enumerate(COLUMNS)}
