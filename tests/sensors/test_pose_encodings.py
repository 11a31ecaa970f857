"""Pose encodings: native exact bytes, ROS 2 CDR through rosbags, detection, zenoh transport."""

from __future__ import annotations

import math
import threading
import time

import pytest

from swpc_hw.sensors.mocap import (
    PoseDecodeError,
    PoseEncoding,
    PoseSample,
    decode_pose,
    detect_encoding,
    encode_cdr,
    encode_native,
    encode_pose,
)
from swpc_hw.sensors.zenoh_session import free_tcp_endpoint, open_session


def test_native_exact_bytes() -> None:
    p = PoseSample(1.5, 1.0, -2.0, 0.0, 0.0, 0.0, 0.0, 1.0, seq=7)
    b = encode_native(p)
    assert len(b) == 72
    assert b[:8].hex() == "5357505007000000"  # "SWPP", seq 7 little endian
    assert b[8:16].hex() == "000000000000f83f"  # 1.5 as float64 LE
    assert b[16:24].hex() == "000000000000f03f"  # x = 1.0
    assert b[24:32].hex() == "00000000000000c0"  # y = -2.0
    assert decode_pose(b) == p


def test_cdr_round_trip_and_header() -> None:
    p = PoseSample.planar(12.25, 0.5, -0.25, math.radians(30.0), seq=0)
    b = encode_cdr(p)
    assert b[:4] == b"\x00\x01\x00\x00"  # CDR little-endian encapsulation
    q = decode_pose(b)
    assert detect_encoding(b) is PoseEncoding.CDR
    assert q.t == pytest.approx(12.25, abs=1e-9)
    assert (q.x, q.y) == (0.5, -0.25)
    assert q.yaw == pytest.approx(math.radians(30.0), abs=1e-12)
    assert q.frame_id == "world"


def test_decode_errors_are_clear() -> None:
    with pytest.raises(PoseDecodeError, match="unknown pose encoding"):
        decode_pose(b"\xff\xff\xff\xff")
    with pytest.raises(PoseDecodeError, match="expected 72 bytes"):
        decode_pose(b"SWPP" + b"\x00" * 10)
    with pytest.raises(PoseDecodeError, match="ros2-cdr"):
        decode_pose(b"\x00\x01\x00\x00\x01", PoseEncoding.CDR)


@pytest.mark.parametrize("encoding", [PoseEncoding.NATIVE, PoseEncoding.CDR])
def test_poses_cross_zenoh_on_loopback(encoding: PoseEncoding) -> None:
    ep = free_tcp_endpoint()
    pub_s = open_session(listen=[ep])
    sub_s = open_session(connect=[ep])
    got: list[PoseSample] = []
    done = threading.Event()

    def on_sample(sample: object) -> None:
        got.append(decode_pose(sample.payload.to_bytes()))  # type: ignore[attr-defined]
        if len(got) == 200:
            done.set()

    try:
        sub = sub_s.declare_subscriber("mocap/test/pose", on_sample)
        pub = pub_s.declare_publisher("mocap/test/pose")
        deadline = time.monotonic() + 5.0
        while not got and time.monotonic() < deadline:  # wait for the route
            pub.put(encode_pose(PoseSample.planar(-1.0, 0, 0, 0), encoding))
            time.sleep(0.02)
        got.clear()
        for i in range(200):
            pub.put(encode_pose(PoseSample.planar(i * 0.01, i * 1e-3, 0.0, 0.01 * i, i), encoding))
        assert done.wait(5.0)
        assert [round(p.t, 6) for p in got] == [round(i * 0.01, 6) for i in range(200)]
        assert got[150].yaw == pytest.approx(1.5, abs=1e-12)
        sub.undeclare()
    finally:
        pub_s.close()
        sub_s.close()
