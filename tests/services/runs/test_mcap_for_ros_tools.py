"""The run's MCAP for ROS tools (docs/ros2.md, "The run's MCAP for ROS tools"): profile
``ros2``, every message decoded by mcap-ros2-support (a reader this project did not write)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from services.config.settings import ServiceSettings
from services.runs.mcap import McapRecorder
from swpc_hw.errors import SwpcError


def test_the_ros2_profile_is_decoded_by_mcap_ros2_support(tmp_path: Path) -> None:
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    path = tmp_path / "run.mcap"
    rec = McapRecorder(path, [1, 2], wall_offset=1_700_000_000.0, profile="ros2")
    poses = np.array([[0.0, 0.1, 0.2, 0.3], [0.01, 0.11, 0.21, -0.4]])
    rec.poses(poses)
    rec.encoders(1, np.array([[0.0, 0.5, 10.0], [0.01, 0.51, 10.2]]))
    rec.encoders(2, np.array([[0.0, -0.5, 3.0]]))
    rec.segment(2, 0.0, 0.01)
    rec.event(0.01, "warning", "a slip")
    rec.gyro(np.array([[0.0, 0.25]]))
    rec.finish()

    got: dict[str, list[object]] = {}
    with path.open("rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        header = reader.get_header()
        summary = reader.get_summary()
        assert summary is not None
        assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
        assert {c.message_encoding for c in summary.channels.values()} == {"cdr"}
        for _s, channel, _m, msg in reader.iter_decoded_messages():
            got.setdefault(channel.topic, []).append(msg)
    assert header.profile == "ros2"
    assert sum(len(v) for v in got.values()) == rec.messages == 10
    p = got["/mocap/pose"][1]
    assert (p.header.frame_id, p.pose.position.x, p.pose.position.y) == ("W", 0.11, 0.21)
    assert 2 * math.atan2(p.pose.orientation.z, p.pose.orientation.w) == pytest.approx(-0.4)
    assert p.header.stamp.sec * 10**9 + p.header.stamp.nanosec == rec.ns(0.01)  # = log time
    tf = got["/tf"][0].transforms[0]
    assert (tf.header.frame_id, tf.child_frame_id, tf.transform.translation.x) == ("W", "R", 0.1)
    js = got["/module1/encoders"][1]
    assert list(js.name) == ["steer_1", "wheel_1"]  # the URDF's joints (/robot_description)
    assert list(js.position) == [0.51, 10.2]
    assert len(got["/module2/encoders"]) == 1
    assert '"static_module": 2' in got["/calibration/segments"][0].data
    log = got["/calibration/events"][0]
    assert (log.level, log.msg) == (30, "a slip")
    assert got["/imu/gyro"][0].angular_velocity.z == 0.25


def test_the_profile_is_a_setting_and_a_bad_one_is_refused(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    assert ServiceSettings().mcap_profile == "foxglove"
    monkeypatch.setenv("SWPC_MCAP_PROFILE", "ros2")
    assert ServiceSettings().mcap_profile == "ros2"
    with pytest.raises(SwpcError, match="MCAP profile must be one of foxglove, ros2"):
        McapRecorder(tmp_path / "x.mcap", [1], profile="ros1")
    assert not (tmp_path / "x.mcap").exists()
