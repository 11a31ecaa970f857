"""The gyro: the simulator's model, its ROS 2 message, the service's ingest, the tape measure.

Pure and fast: the model's statistics on a few thousand samples without zenoh, the CDR
``sensor_msgs/msg/Imu`` through rosbags, the ingest fed payloads on a virtual clock; one
loopback zenoh hop.  The gyro inside the running simulator is checked against the
motion capture in ``tests/simulators/test_virtual_robot_contact_points_and_watchdog.py``,
and through the whole service in
``tests/services/whole_runs/test_calibration_without_mocap.py``.
"""

from __future__ import annotations

import math
import threading
import time

import numpy as np
import pytest

from services.sensors.gyro import GyroIngest
from simulators.sensors.gyro import (
    GyroSim,
    PoseHistory,
    axis_travel,
    check_gyro,
    gyro_reading,
    imu_key,
    tape_measure,
)
from swpc_hw.clock import VirtualClock
from swpc_hw.robot.model import rot
from swpc_hw.sensors.gyro import GyroOptions, GyroSample, ImuDecodeError, decode_imu, encode_imu
from swpc_hw.sensors.mocap import PoseSample, encode_cdr, encode_native
from swpc_hw.sensors.zenoh_session import free_tcp_endpoint, open_session

DEG = math.pi / 180.0


def readings(gs: GyroSim, omega: float, seconds: float, t0: float = 0.0) -> np.ndarray:
    """``(t, wz)`` of ``seconds`` of samples of a constant yaw rate ``omega``."""
    rows = []
    for t in gs.due_times(t0, t0 + seconds):
        rows.append((t, gs.sample(omega, t).wz))
    return np.array(rows)


# --------------------------------------------------------------------------- the model


def test_gyro_bias_scale_and_white_noise_are_the_settings() -> None:
    """200 Hz, 0.005 deg/s/sqrt(Hz) (0.0707 deg/s per sample), bias 0.1 deg/s, scale error
    0.3 %, no walk: 100 s at rest then 100 s at 1 rad/s.  The per-sample std dev is
    ``density sqrt(rate)``, the rest's mean the bias, the slope the scale."""
    opt = GyroOptions(bias_walk=0.0)
    gs = GyroSim("r", opt, seed=5)
    rest = readings(gs, 0.0, 100.0)
    turn = readings(gs, 1.0, 100.0, t0=100.0 + 1.0 / opt.rate)
    assert rest.shape[0] == 20001 and np.allclose(np.diff(rest[:, 0]), 0.005)
    sd = opt.noise_density * math.sqrt(opt.rate)
    se = sd / math.sqrt(rest.shape[0])  # std error of a mean
    assert np.std(rest[:, 1]) == pytest.approx(sd, rel=0.02)
    assert np.mean(rest[:, 1]) == pytest.approx(opt.bias, abs=4 * se)
    scale = np.mean(turn[:, 1]) - np.mean(rest[:, 1])
    assert scale == pytest.approx(1.0 + opt.scale_error, abs=6 * se)
    # white: neighbouring samples uncorrelated
    d = rest[:, 1] - rest[:, 1].mean()
    assert abs(float(d[1:] @ d[:-1]) / float(d @ d)) < 0.03
    assert gyro_reading(2.0, 0.1, 0.01, 0.5) == pytest.approx(3.11)


def test_gyro_bias_walks_with_the_set_intensity_from_the_set_bias() -> None:
    """No white noise: the readings at rest are the bias, a random walk that starts at the
    setting and steps ``bias_walk sqrt(dt)`` a sample."""
    opt = GyroOptions(noise_density=0.0, bias_walk=0.01, rate=100.0)
    gs = GyroSim("r", opt, seed=1)
    rest = readings(gs, 0.0, 200.0)
    assert rest[0, 1] == opt.bias  # the first sample: the bias as set
    steps = np.diff(rest[:, 1])
    assert np.mean(steps) == pytest.approx(0.0, abs=4 * 0.001 / math.sqrt(steps.size))
    assert np.std(steps) == pytest.approx(0.01 * math.sqrt(0.01), rel=0.03)
    assert gs.bias == rest[-1, 1]


def test_gyro_settings_no_gyro_has_are_refused() -> None:
    for bad, words in (
        (GyroOptions(rate=0.0), "rate"),
        (GyroOptions(rate=5000.0), "rate"),
        (GyroOptions(noise_density=-1.0), "noise_density"),
        (GyroOptions(bias_walk=math.nan), "bias_walk"),
        (GyroOptions(bias=math.inf), "bias"),
        (GyroOptions(scale_error=0.9), "scale_error"),
    ):
        with pytest.raises(ValueError, match=words):
            check_gyro(bad)
    from simulators.options import SimOptions

    with pytest.raises(ValueError, match="gyro rate"):
        SimOptions(gyro=GyroOptions(rate=-1.0))


def test_sample_times_are_the_grid_of_the_rate() -> None:
    gs = GyroSim("r", GyroOptions(rate=200.0))
    assert gs.due_times(10.0, 10.012) == pytest.approx([10.0, 10.005, 10.01])
    assert gs.due_times(10.012, 10.02) == pytest.approx([10.015, 10.02])
    assert gs.due_times(10.02, 10.024) == []
    assert imu_key("swpc") == "imu/swpc/data"


# --------------------------------------------------------------------------- the message


def test_imu_message_round_trips_through_cdr() -> None:
    g = GyroSample(1234.5678, -0.25, wx=0.01, wy=-0.02, frame_id="imu_link", wz_variance=2e-6)
    b = encode_imu(g)
    assert b[:4] == b"\x00\x01\x00\x00"  # CDR little-endian encapsulation, as ROS 2
    back = decode_imu(b)
    assert back.t == pytest.approx(g.t, abs=1e-9)
    assert (back.wz, back.wx, back.wy, back.frame_id) == (-0.25, 0.01, -0.02, "imu_link")
    assert back.wz_variance == 2e-6
    from swpc_hw.sensors.mocap import ros2_typestore

    msg = ros2_typestore().deserialize_cdr(b, "sensor_msgs/msg/Imu")
    assert msg.orientation_covariance[0] == -1.0  # REP 145: not provided
    assert msg.linear_acceleration_covariance[0] == -1.0
    assert decode_imu(encode_imu(GyroSample(1.0, 0.0))).frame_id == "base_link"


def test_what_is_not_an_imu_message_is_a_clear_error() -> None:
    with pytest.raises(ImuDecodeError, match="not CDR"):
        decode_imu(encode_native(PoseSample.planar(1.0, 0, 0, 0)))
    with pytest.raises(ImuDecodeError, match="sensor_msgs/Imu"):
        decode_imu(b"\x00\x01\x00\x00\x01\x02")
    with pytest.raises(ImuDecodeError, match="sensor_msgs/Imu"):
        decode_imu(encode_cdr(PoseSample.planar(1.0, 0, 0, 0)))  # a pose is no Imu


# --------------------------------------------------------------------------- the ingest


def feed(ing: GyroIngest, clock: VirtualClock, t: float, wz: float) -> bool:
    """A sample stamped with the wall time of clock time ``t``, received now."""
    return ing.feed(encode_imu(GyroSample(clock.to_wall(t), wz)))


def test_ingest_maps_the_stamps_and_counts_what_it_drops() -> None:
    clock = VirtualClock(start=100.0)
    ing = GyroIngest(clock=clock, stale_after=0.5)
    assert ing.latest() is None and ing.age() == math.inf and ing.is_stale()
    for k in range(10):
        clock.advance(0.005)
        assert feed(ing, clock, clock.now() - 0.002, 0.1 * k)  # 2 ms transport delay
    rows = ing.samples()
    assert rows.shape == (10, 4)
    # t_host is the stamp on the clock's axis (from_wall), not the receipt
    np.testing.assert_allclose(rows[:, 2], rows[:, 1] - 0.002, atol=1e-9)
    assert ing.latest() == (pytest.approx(clock.now() - 0.002), pytest.approx(0.9))
    t_last = clock.now() - 0.002
    assert not feed(ing, clock, t_last, 5.0)  # duplicate
    assert not feed(ing, clock, t_last - 0.1, 5.0)  # older than the last
    assert not ing.feed(b"\x00\x01\x00\x00garbage")
    assert not ing.feed(encode_imu(GyroSample(clock.wall(), math.nan)))
    assert feed(ing, clock, t_last - 30.0, 7.0)  # stepped back 30 s: the IMU was reset
    c = ing.counters
    assert (c.received, c.accepted, c.duplicates, c.out_of_order) == (15, 11, 1, 1)
    assert (c.decode_errors, c.non_finite, c.clock_resets, c.dropped) == (1, 1, 1, 4)
    rows, cursor = ing.samples_since(0)
    assert rows.shape[0] == 11 and ing.samples_since(cursor)[0].shape[0] == 0
    st = ing.stats()
    assert st["accepted"] == 11 and st["decode_errors"] == 1


def test_ingest_goes_stale_and_names_an_unsynchronised_clock() -> None:
    clock = VirtualClock()
    ing = GyroIngest(clock=clock, stale_after=0.5, max_clock_error=1.0)
    feed(ing, clock, clock.now(), 0.0)
    clock.advance(0.4)
    assert not ing.is_stale() and ing.age() == pytest.approx(0.4)
    clock.advance(0.2)
    assert ing.is_stale() and ing.clock_problem() is None
    feed(ing, clock, clock.now() - 2.0, 0.0)  # stamped 2 s before its receipt
    problem = ing.clock_problem()
    assert problem is not None and "gyro stamps are +2.000 s off" in problem


def test_gyro_samples_cross_zenoh_into_the_ingest() -> None:
    """The simulator's publisher and the service's subscriber on a loopback endpoint; with
    no subscriber the samples are not even encoded (the service listens to the gyro only
    for runs without motion capture)."""
    ep = free_tcp_endpoint()
    pub_s, sub_s = open_session(listen=[ep]), open_session(connect=[ep])
    try:
        exact = GyroOptions(noise_density=0.0, bias=0.0, bias_walk=0.0, scale_error=0.0)
        gs = GyroSim("t", exact, pub_s)
        for i in range(10):
            gs.sample(0.0, 0.005 * i)
        assert (gs.counters.unheard, gs.counters.published) == (10, 0)
        ing = GyroIngest(clock=VirtualClock(epoch=0.0))
        ing.subscribe(sub_s, imu_key("t"))
        deadline = time.monotonic() + 5.0
        k = 0
        while ing.counters.accepted == 0 and time.monotonic() < deadline:  # the route
            gs.sample(0.0, float(k))
            k += 1
            time.sleep(0.02)
        n0 = ing.counters.accepted
        for i in range(200):
            gs.sample(0.5, 1000.0 + i * 0.005)
        done = threading.Event()
        while ing.counters.accepted < n0 + 200 and time.monotonic() < deadline + 5:
            done.wait(0.01)
        rows = ing.samples(since_host=1000.0)
        assert rows.shape[0] == 200 and np.all(rows[:, 3] == 0.5)
        np.testing.assert_allclose(rows[:, 0], 1000.0 + 0.005 * np.arange(200), atol=1e-8)
        c = gs.counters
        assert c.published + c.unheard == c.sampled and c.put_errors == 0
        assert c.published >= 200 and ing.counters.accepted <= c.published
        ing.close()
        gs.close()
    finally:
        pub_s.close()
        sub_s.close()


# --------------------------------------------------------------------------- tape measure


def test_the_tape_measures_the_first_axis_travel_with_its_error() -> None:
    P_s = np.array([0.215, 0.125])
    assert axis_travel(np.zeros(3), np.array([4.0, 0.0, 0.0]), P_s) == pytest.approx(4.0)
    # a turn about the axis itself moves it nowhere; about the origin it moves a chord
    about_axis = np.array([*(P_s - rot(1.0) @ P_s), 1.0])
    assert axis_travel(np.zeros(3), about_axis, P_s) == pytest.approx(0.0, abs=1e-12)
    chord = 2 * np.linalg.norm(P_s) * math.sin(0.5)
    assert axis_travel(np.zeros(3), np.array([0, 0, 1.0]), P_s) == pytest.approx(chord)
    rng = np.random.default_rng(0)
    reads = np.array([tape_measure(4.0, 0.5e-3, rng) for _ in range(4000)])
    assert reads.mean() == pytest.approx(4.0, abs=4 * 0.5e-3 / math.sqrt(4000))
    assert reads.std() == pytest.approx(0.5e-3, rel=0.05)
    assert tape_measure(4.0, 0.0, rng) == 4.0
    with pytest.raises(ValueError, match="stddev"):
        tape_measure(4.0, -1.0, rng)


def test_pose_history_answers_the_pose_nearest_a_time() -> None:
    h = PoseHistory(period=0.05)
    for k in range(400):
        t = k * 0.01
        h.add(t, np.array([t, 0.0, 0.0]))
    assert h.at(1.0)[0] == pytest.approx(1.0)
    assert h.at(1.02)[0] == pytest.approx(1.0)  # recorded every 0.05 s
    assert abs(h.at(3.99)[0] - 3.99) < 0.05 and abs(h.at(2.5)[0] - 2.5) <= 0.025 + 1e-9
    with pytest.raises(ValueError, match=r"no true pose at 10\.000 s"):
        h.at(10.0)
