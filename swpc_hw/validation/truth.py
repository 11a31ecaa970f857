"""The true pose during validation: the simulator's truth key, or motion capture."""

from __future__ import annotations

import contextlib
import json
import threading
from collections import deque
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from swpc_hw.clock import SYSTEM_CLOCK, Clock, SimClock, wait_until
from swpc_hw.sensors.mocap import decode_pose
from swpc_hw.validation.errors import ValidationError

FloatArray = NDArray[np.float64]


def sim_truth_decoder(payload: bytes) -> tuple[float, float, float, float]:
    """``(t, x, y, yaw)`` of a simulator truth document (``sim/<robot>/truth/pose``)."""
    doc = json.loads(payload)
    x, y, yaw = (float(v) for v in doc["pose"])
    return float(doc["t"]), x, y, yaw


def mocap_decoder(payload: bytes) -> tuple[float, float, float, float]:
    """``(t, x, y, yaw)`` of a motion-capture pose (native or ROS 2 CDR)."""
    p = decode_pose(payload)
    return float(p.t), float(p.x), float(p.y), float(p.yaw)


class ZenohTruth:
    """The true pose from a zenoh key: rows ``(t_host, t_source, x, y, yaw)``, ``t_host``
    the receipt on ``clock`` (in lockstep every pose published up to now has arrived)."""

    def __init__(
        self,
        session: Any,
        key: str,
        decode: Callable[[bytes], tuple[float, float, float, float]] = sim_truth_decoder,
        maxlen: int = 1_000_000,
        *,
        clock: Clock = SYSTEM_CLOCK,
    ) -> None:
        self.key = key
        self.clock = clock
        self._decode = decode
        self._rows: deque[tuple[float, float, float, float, float]] = deque(maxlen=maxlen)
        self._cond = threading.Condition()
        self.errors = 0
        self._lockstep = isinstance(clock, SimClock)
        if isinstance(clock, SimClock):
            clock.subscribe(key)
        self._sub = session.declare_subscriber(key, self._on_sample)

    def _on_sample(self, sample: Any) -> None:
        try:
            self._store(sample)
        finally:
            if isinstance(self.clock, SimClock):
                self.clock.arrived(self.key)

    def _store(self, sample: Any) -> None:
        try:
            t, x, y, yaw = self._decode(bytes(sample.payload.to_bytes()))
        except Exception:  # a bad sample is counted, never fatal
            self.errors += 1
            return
        with self._cond:
            self._rows.append((self.clock.now(), t, x, y, yaw))
            self._cond.notify_all()

    def close(self) -> None:
        with contextlib.suppress(Exception):  # closing twice / session gone
            self._sub.undeclare()
        if self._lockstep and isinstance(self.clock, SimClock):
            self._lockstep = False
            self.clock.unsubscribe(self.key)

    def wait_first(self, timeout: float) -> None:
        deadline = self.clock.now() + timeout
        with self._cond:
            if not wait_until(self.clock, self._cond, lambda: bool(self._rows), deadline):
                raise ValidationError(f"no true pose on {self.key!r} within {timeout} s")

    def since(self, t_host: float) -> FloatArray:
        """Rows received at clock time >= ``t_host`` (K, 5)."""
        with self._cond:
            rows = [r for r in self._rows if r[0] >= t_host]
        return np.array(rows, dtype=float).reshape(-1, 5)

    def mean_pose(self, t_host: float) -> tuple[float, float, float]:
        """Mean pose of the rows received since ``t_host`` (the robot is still)."""
        rows = self.since(t_host)
        if rows.shape[0] == 0:
            raise ValidationError(f"no true pose on {self.key!r} in the still window")
        yaw = np.unwrap(rows[:, 4])
        return (float(rows[:, 2].mean()), float(rows[:, 3].mean()), float(yaw.mean()))
