"""Mocap ingest: validation counters, staleness, clock mapping, and real zenoh delivery."""

from __future__ import annotations

import math
import struct
import time

import pytest
import zenoh

from services.sensors.mocap import MocapIngest
from swpc_hw.clock import VirtualClock
from swpc_hw.sensors.mocap import PoseEncoding, PoseSample, encode_cdr, encode_native, encode_pose
from swpc_hw.sensors.zenoh_session import free_tcp_endpoint, open_session


def native(t: float, x: float = 0.0, yaw: float = 0.0) -> bytes:
    return encode_native(PoseSample.planar(t, x, 0.0, yaw))


def test_bad_samples_are_dropped_and_counted() -> None:
    ing = MocapIngest()
    assert ing.feed(native(1.0), t_recv=101.0)
    assert not ing.feed(native(1.0), t_recv=101.01)  # duplicate
    assert not ing.feed(native(0.5), t_recv=101.02)  # out of order
    assert not ing.feed(native(float("nan")), t_recv=101.03)
    bad_q = PoseSample(2.0, 0, 0, 0, 0, 0, 0.3, 0.3)  # |q| = 0.42
    assert not ing.feed(encode_native(bad_q), t_recv=101.04)
    assert not ing.feed(b"garbage!", t_recv=101.05)
    assert ing.feed(encode_cdr(PoseSample.planar(2.0, 1.0, 2.0, 0.5)), t_recv=102.0)
    c = ing.counters
    assert (c.received, c.accepted, c.dropped) == (7, 2, 5)
    assert (c.duplicates, c.out_of_order, c.non_finite) == (1, 1, 1)
    assert (c.non_unit_quaternion, c.decode_errors) == (1, 1)
    s = ing.samples()
    assert s.shape == (2, 6)
    assert s[1, 3:].tolist() == pytest.approx([1.0, 2.0, 0.5])


def test_a_source_clock_stepped_back_restarts_the_stream() -> None:
    """A mocap PC restarted (or re-synced) mid-session must not lock the stream out."""
    ing = MocapIngest(max_clock_step=1.0)
    for i in range(5):
        assert ing.feed(native(100.0 + 0.01 * i), t_recv=10.0 + 0.01 * i)
    assert not ing.feed(native(99.5), t_recv=10.06)  # 0.54 s back: reordering, dropped
    assert ing.feed(native(40.0), t_recv=10.07)  # 60 s back: the clock was reset
    assert ing.feed(native(40.01), t_recv=10.08)
    c = ing.counters
    assert (c.out_of_order, c.clock_resets, c.accepted) == (1, 1, 7)
    # the delay envelope restarted with the new clock instead of keeping the old minimum
    assert ing.clock_offset == pytest.approx(10.07 - 40.0)
    assert ing.samples()[-2:, 2].tolist() == pytest.approx([10.07, 10.08])


def test_a_source_clock_stepped_forward_is_a_jump_and_a_stalled_link_is_not() -> None:
    """Stamps that run ahead of their receipt by more than ``max_clock_step`` are a clock
    set anew (a new sequence, :meth:`clock_jump` says so); a link that stalls 2 s and then
    delivers its backlog at once moves the receipts, not the stamps, and is no jump."""
    ing = MocapIngest()  # the default step: 0.5 s
    t = 100.0
    for i in range(5):
        assert ing.feed(native(t + 0.01 * i), t_recv=10.0 + 0.01 * i)
    for i in range(5, 205):  # stalled: 2 s of poses arrive together at 12.1 s
        assert ing.feed(native(t + 0.01 * i), t_recv=12.1)
    assert ing.counters.clock_resets == 0 and ing.clock_jump(0, "mocap", "k") is None
    assert ing.feed(native(t + 2.05 + 3.0), t_recv=12.11)  # the mocap clock set 3 s on
    assert ing.counters.clock_resets == 1
    why = ing.clock_jump(0, "motion-capture", "mocap/swpc/pose") or ""
    assert why.startswith("motion-capture clock jumped forward by 3.000 s"), why
    assert ing.clock_offset == pytest.approx(12.11 - (t + 5.05))  # the envelope restarted


def test_configured_encoding_rejects_the_other() -> None:
    ing = MocapIngest(encoding=PoseEncoding.CDR)
    assert not ing.feed(native(1.0), t_recv=0.0)
    assert ing.counters.decode_errors == 1


def test_staleness_and_clock_mapping() -> None:
    clock = VirtualClock(start=1000.0)
    ing = MocapIngest(stale_after=0.1, clock=clock)
    assert ing.is_stale()
    for i, delay in enumerate([0.004, 0.002, 0.009, 0.003]):
        ing.feed(native(10.0 + 0.01 * i), t_recv=990.0 + 0.01 * i + delay)
    assert ing.clock_offset == pytest.approx(980.002)
    host = ing.samples()[:, 2]
    # each sample is mapped with the lower envelope known when it arrived
    assert host.tolist() == pytest.approx([990.004, 990.012, 990.022, 990.032])
    # age: clock time since the newest sample's receipt (990.033)
    assert not ing.is_stale(now=990.03 + 0.003 + 0.05)
    assert ing.is_stale(now=990.03 + 0.003 + 0.25)
    assert ing.age() == pytest.approx(1000.0 - 990.033)


@pytest.mark.parametrize(("mode", "bound"), [("source", 0.2), ("receive", 0.0011)])
def test_clock_modes_with_a_source_clock_that_changes_rate(mode: str, bound: float) -> None:
    """A simulator whose clock slows down (time scale 5 -> 4): only receive time follows."""
    ing = MocapIngest(source_rate=1 / 5.0, sync_window=0.5, clock_mode=mode)
    t_src, t_host = 0.0, 100.0
    errors = []
    for i in range(2000):  # 1 kHz of host time, source rate drops after 1 s
        scale = 5.0 if i < 1000 else 4.0
        t_host += 0.001
        t_src += 0.001 * scale
        delay = 0.0005 + 0.0005 * ((i * 7919) % 13) / 13  # jittery transport
        ing.feed(native(t_src), t_recv=t_host + delay)
        if i > 1500:
            errors.append(abs(ing.samples()[-1, 2] - t_host))
    assert 0.0 < max(errors) < bound
    if mode == "source":
        assert max(errors) > 0.05  # the lower envelope lags the rate change


def test_growth_keeps_every_sample() -> None:
    ing = MocapIngest()
    n = 70_000  # beyond the initial buffer
    for i in range(n):
        ing.feed(native(i * 1e-3, x=i * 1e-6), t_recv=i * 1e-3)
    s = ing.samples()
    assert s.shape[0] == n
    assert s[-1, 3] == pytest.approx((n - 1) * 1e-6)
    assert ing.samples(since_host=69.0).shape[0] == 1000


@pytest.mark.parametrize("encoding", [PoseEncoding.NATIVE, PoseEncoding.CDR])
def test_ingest_over_zenoh_detects_the_encoding(encoding: PoseEncoding) -> None:
    ep = free_tcp_endpoint()
    pub_s = open_session(listen=[ep])
    sub_s = open_session(connect=[ep])
    ing = MocapIngest()
    try:
        ing.subscribe(sub_s, "mocap/r1/pose")
        # BLOCK, as the simulator's publisher: zenoh's default drops what its queue cannot
        # take, and beside busy-host 2 all 500 of a burst were dropped once (2026-12-01)
        pub = pub_s.declare_publisher(
            "mocap/r1/pose", congestion_control=zenoh.CongestionControl.BLOCK
        )
        deadline = time.monotonic() + 5
        t = 0.0
        while ing.counters.accepted == 0 and time.monotonic() < deadline:
            t += 0.001
            pub.put(encode_pose(PoseSample.planar(t, 0, 0, 0), encoding))
            time.sleep(0.01)
        base = ing.counters.accepted
        for i in range(500):
            pub.put(encode_pose(PoseSample.planar(1.0 + i * 0.001, 0.1, 0.2, 0.3), encoding))
        deadline = time.monotonic() + 5
        while ing.counters.accepted < base + 500 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert ing.counters.accepted == base + 500
        assert ing.counters.dropped == 0
        assert ing.detected_encoding is encoding
        st = ing.stats()
        assert st["rate_hz"] > 0 and math.isfinite(st["latency_p99_s"])
    finally:
        ing.close()
        ing.close()  # idempotent
        pub_s.close()
        sub_s.close()


def test_native_layout_is_documented_size() -> None:
    assert struct.calcsize("<4sId3d4d") == 72


def test_wall_mode_maps_each_stamp_exactly_despite_a_late_publisher() -> None:
    """A source stamping the host's wall clock, every pose 12-23 ms late on arrival.

    'source' maps with the lower envelope (here >= 12 ms), so every pose sits >= 12 ms late
    against the CAN bus stamps; 'wall' maps each stamp exactly.
    """
    epoch = 1.7e9  # wall minus monotonic
    results: dict[str, float] = {}
    for mode in ("source", "wall"):
        clock = VirtualClock(start=500.0, epoch=epoch)
        ing = MocapIngest(clock_mode=mode, clock=clock)
        worst = 0.0
        for i in range(300):
            t_sample = 500.0 + 0.01 * i  # host monotonic moment of the sample
            delay = 0.012 + 0.011 * ((i * 7919) % 17) / 17
            clock.sleep_until(t_sample + delay)
            assert ing.feed(native(t_sample + epoch, x=0.001 * i))
            worst = max(worst, abs(ing.samples()[-1, 2] - t_sample))
        results[mode] = worst
        assert ing.clock_problem() is None
    assert results["wall"] < 1e-6
    assert 0.012 <= results["source"] < 0.024


def test_wall_mode_reports_an_unsynchronised_source() -> None:
    clock = VirtualClock(start=100.0, epoch=1000.0)
    ing = MocapIngest(clock_mode="wall", clock=clock, max_clock_error=0.5)
    assert ing.clock_problem() is None  # nothing received yet: staleness reports that
    ing.feed(native(1100.0 - 2.5))  # stamped 2.5 s behind this host's wall clock
    msg = ing.clock_problem()
    assert msg is not None and "+2.500 s" in msg and "limit 0.5 s" in msg
    ing.feed(native(1100.0 - 0.1))
    assert ing.clock_problem() is None
    # the other modes do not trust the source clock, so they have nothing to report
    other = MocapIngest(clock_mode="source", clock=clock)
    other.feed(native(5.0))
    assert other.clock_problem() is None


def test_unknown_clock_mode_is_refused() -> None:
    with pytest.raises(ValueError, match="clock_mode must be one of"):
        MocapIngest(clock_mode="host")


def test_the_frame_rate_is_the_mocaps_own_whatever_the_transport_does() -> None:
    """360 Hz stamps received in bursts, with a frame lost: 360 Hz (the plan then assumes
    it: services/http/calibrations.py plan_request); too few poses: no rate."""
    clock = VirtualClock(start=50.0)
    ing = MocapIngest(clock=clock, clock_mode="receive")
    assert ing.frame_rate() is None
    for k in range(720):
        if k == 300:
            continue  # lost on the way
        clock.advance(1 / 360 if k % 4 == 0 else 0.0)  # four at a time
        assert ing.feed(native(1000.0 + k / 360.0), t_recv=clock.now())
    assert ing.frame_rate() == pytest.approx(360.0, rel=1e-9)
    clock.advance(10.0)  # nothing for 10 s: the stream is gone
    assert ing.frame_rate() is None
