"""Feedback history of one controller node: a :class:`swpc_hw.row_ring.RowRing` of samples.

The driver receives 2 frames per node per feedback period (4 nodes at 200 Hz: 1600 frames
a second) and keeps the samples of a whole calibration (minutes).  Kept as Python objects
(a dataclass per sample) that was millions of objects, which CPython's cyclic garbage
collector walks on every full collection: 0.5-2 s pauses were measured with ~1.3 M live
objects, long enough for the driver's supervisor to declare every node lost (heartbeat
timeout 0.3 s on a robot).  Here a sample is one row of a float64 array.

Columns (:data:`COLUMNS`, the fields of :class:`swpc_hw.can.driver.FeedbackSample`):
``t`` host monotonic receive time, ``t_bus`` bus time stamp, ``counter`` (mod 256),
``seq`` (unwrapped), ``theta_hat``, ``psi`` (unwrapped, rad), and the velocity/torque
frame's four values (NaN until that frame arrives).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from swpc_hw.row_ring import RowRing

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


class FeedbackRing(RowRing):
    """Newest ``capacity`` feedback rows of one node (the driver's lock guards it)."""

    def __init__(self, capacity: int) -> None:
        super().__init__(len(COLUMNS), capacity)

    def set_last_velocity_torque(self, values: tuple[float, float, float, float]) -> None:
        """Fill the newest row's ``steer_velocity, wheel_velocity, steer_torque,
        wheel_torque``."""
        self.set_last(_VT, values)

    def columns(self) -> dict[str, NDArray[np.float64]]:
        """The rows as named columns (copies)."""
        a = self.array()
        return {name: np.ascontiguousarray(a[:, k]) for k, name in enumerate(COLUMNS)}
