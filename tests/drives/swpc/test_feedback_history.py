"""Feedback history: a numpy ring (no per-sample Python objects), through the real driver."""

from __future__ import annotations

import gc
import math
import time
import uuid

import can
import numpy as np
import pytest

from firmware_protocol import codec
from swpc_hw.drives.bus import CanConfig
from swpc_hw.drives.swpc.driver import SwpcDriver
from swpc_hw.drives.tracking import COLUMNS, FeedbackRing


def row(i: int, dt: float = 0.01) -> tuple[float, ...]:
    """Sample ``i`` of a node's feedback at 1 / ``dt`` Hz."""
    return (dt * i, 1e9 + i, float(i % 256), float(i), 0.01 * i, -0.02 * i)


def test_ring_keeps_the_newest_rows_in_order_across_growth_and_wrap() -> None:
    ring = FeedbackRing(3000)
    for i in range(2500):  # grows 1024 -> 2048 -> 3000
        ring.append(row(i))
    a = ring.array()
    assert a.shape == (2500, len(COLUMNS))
    assert a[:, 3].tolist() == list(range(2500))
    assert np.isnan(a[:, 6:]).all()
    for i in range(2500, 7001):  # wraps: only the newest 3000 stay
        ring.append(row(i))
    ring.set_last_velocity_torque((1.5, -2.5, 0.25, -0.125))
    cols = ring.columns()
    assert len(ring) == 3000
    assert cols["seq"].tolist() == list(range(4001, 7001))
    assert cols["psi"][-1] == pytest.approx(-0.02 * 7000)
    assert [cols[c][-1] for c in COLUMNS[6:]] == [1.5, -2.5, 0.25, -0.125]
    assert np.isnan(cols["steer_velocity"][:-1]).all()
    ring.clear()
    assert len(ring) == 0 and ring.array().shape == (0, len(COLUMNS))
    with pytest.raises(IndexError):
        ring.set_last_velocity_torque((0.0, 0.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="capacity"):
        FeedbackRing(0)


def test_the_ring_keeps_ten_minutes_and_no_more_memory_than_they_need() -> None:
    """An always-on service's feedback at 100 Hz for 15 min (the ring's capacity, 200,000
    rows, is 33 min of it): the ring stops growing once it holds KEEP_S (600 s), so
    memory levels off within the first runs instead of growing to the capacity."""
    from swpc_hw.row_ring import KEEP_S

    ring = FeedbackRing(200_000)
    for i in range(90_000):
        ring.append(row(i))
    a = ring.array()
    assert len(ring) == 65_536 and ring._buf.shape[0] == 65_536  # 2^16 rows cover 655 s
    assert a[-1, 0] - a[0, 0] >= KEEP_S
    assert a[:, 3].tolist() == list(range(90_000 - 65_536, 90_000))  # the newest, in order
    for i in range(90_000, 150_000):  # the rate doubles: it grows once 600 s no longer fit
        r = row(i)
        ring.append((900.0 + 0.005 * (i - 90_000), *r[1:]))
        if i == 95_000:
            assert ring._buf.shape[0] == 65_536  # still 630 s in it: no growth
    assert ring._buf.shape[0] == 131_072
    b = ring.array()
    assert b[-1, 0] - b[0, 0] >= KEEP_S and len(ring) < 131_072  # 600 s and some, growing
    assert ring.since(149_000)[0][:, 3].tolist() == list(range(149_000, 150_000))


def test_driver_history_holds_no_object_per_sample() -> None:
    """6000 feedback frames into the driver: the history keeps its newest 2000 samples,
    paired and unwrapped, and the number of objects the garbage collector tracks does not
    grow with them (the old deque of dataclasses added one per sample: ~2000 here, millions
    in a calibration, and full collections long enough to miss heartbeats)."""
    channel = f"swpc-test-{uuid.uuid4().hex[:8]}"
    n = 3000
    with SwpcDriver(CanConfig(interface="virtual", channel=channel, modules={1: 1},
                             history_len=2000)) as drv, \
            can.Bus(interface="virtual", channel=channel) as ctrl:
        gc.collect()  # the context manager configured the driver: it receives
        tracked0 = len(gc.get_objects())
        for i in range(n):
            wheel = 0.05 * i
            for f in (
                codec.make_feedback_position(1, 0.001 * i, wheel, i % 256),
                codec.make_feedback_velocity_torque(1, 0.1, 10.0, 0.01, -0.02, i % 256),
            ):
                ctrl.send(can.Message(arbitration_id=f.arbitration_id, data=f.data,
                                      is_extended_id=False))
        deadline = time.monotonic() + 10.0
        while drv.module_state(1).feedback_frames < 2 * n and time.monotonic() < deadline:
            time.sleep(0.01)
        assert drv.module_state(1).feedback_frames == 2 * n
        gc.collect()
        growth = len(gc.get_objects()) - tracked0
        h = drv.history_arrays(1)
    assert growth < 500, growth
    assert len(h["seq"]) == 2000
    assert h["seq"].tolist() == list(range(n - 2000, n))
    assert h["counter"].tolist() == [i % 256 for i in range(n - 2000, n)]
    assert np.diff(h["t"]).min() >= 0.0
    assert h["psi"][-1] == pytest.approx(0.05 * (n - 1), abs=1e-3)
    assert h["wheel_velocity"] == pytest.approx(np.full(2000, 10.0), abs=0.01)
    assert not any(math.isnan(v) for v in h["wheel_torque"])
