"""The run's MCAP carries the robot (issue 45, item 7): ``/tf_static`` R -> base_link (the
robot config's) and ``/robot_description`` the URDF the exports write, in both profiles,
so Foxglove's frame tree goes on from W -> R to the robot's own frames and draws it.
Read back by mcap's reader and, for ``ros2``, decoded by mcap-ros2-support (a reader this
project did not write); the URDF loaded by yourdfpy, its wheels where swpc's model puts
them."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader

from services.runs.mcap import McapRecorder
from swpc_hw.robot.frames import BaseLinkPose, to_base_link
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED
from tests.onboard.test_export_in_base_link import urdf_contact_error

BASE_LINK = BaseLinkPose(x=0.1, y=-0.05, yaw=0.3)


def read(path: Path, ros2: bool) -> dict[str, list[Any]]:
    got: dict[str, list[Any]] = {}
    with path.open("rb") as fh:
        if ros2:
            from mcap_ros2.decoder import DecoderFactory

            reader = make_reader(fh, decoder_factories=[DecoderFactory()])
            for _s, channel, _m, msg in reader.iter_decoded_messages():
                got.setdefault(channel.topic, []).append(msg)
        else:
            for _s, channel, m in make_reader(fh).iter_messages():
                got.setdefault(channel.topic, []).append(json.loads(m.data))
    return got


@pytest.mark.parametrize("profile", ["foxglove", "ros2"])
def test_the_mcap_holds_the_frame_tree_to_base_link_and_the_urdf(
    tmp_path: Path, profile: str
) -> None:
    path = tmp_path / "run.mcap"
    rec = McapRecorder(path, list(PAPER_CALIBRATED.ids), wall_offset=1.7e9, profile=profile)
    rec.robot_description(PAPER_CALIBRATED, BASE_LINK, 2.0)
    rec.poses(np.array([[2.0, 0.3, 0.4, 0.5]]))
    rec.finish()
    got = read(path, profile == "ros2")
    (tf,) = got["/tf_static"]
    (desc,) = got["/robot_description"]
    if profile == "ros2":
        t = tf.transforms[0]
        frames = (t.header.frame_id, t.child_frame_id)
        xy = (t.transform.translation.x, t.transform.translation.y)
        q = t.transform.rotation
        yaw = 2 * math.atan2(q.z, q.w)
        urdf = desc.data
    else:
        frames = (tf["parent_frame_id"], tf["child_frame_id"])
        xy = (tf["translation"]["x"], tf["translation"]["y"])
        yaw = 2 * math.atan2(tf["rotation"]["z"], tf["rotation"]["w"])
        urdf = desc["data"]
    assert frames == ("R", "base_link")  # W -> R from the poses, then R -> base_link
    assert xy == pytest.approx((0.1, -0.05), abs=1e-12) and yaw == pytest.approx(0.3)
    params, _ = to_base_link(PAPER_CALIBRATED, None, BASE_LINK)
    assert urdf_contact_error(urdf, params, tmp_path) < 1e-9
    assert urdf.count('<joint name="steer_') == len(PAPER_CALIBRATED.ids)


@pytest.mark.parametrize("profile", ["foxglove", "ros2"])
def test_each_spins_fitted_circle_is_drawn_in_w(tmp_path: Path, profile: str) -> None:
    """A robot turning about C_W = (0.5, -0.2) with its origin 0.3 m from it: the circle
    :func:`spin_circles` fits and :meth:`McapRecorder.circles` draws, decoded back."""
    from services.runs.mcap import CIRCLE_POINTS, spin_circles
    from swpc_hw.files.dataset import Dataset, Segment

    yaw = np.linspace(0.0, 0.8, 50)
    C_R = np.array([0.3, 0.0])
    xy = np.array([0.5, -0.2]) - np.stack(
        [np.cos(yaw) * C_R[0] - np.sin(yaw) * C_R[1], np.sin(yaw) * C_R[0] + np.cos(yaw) * C_R[1]],
        axis=1,
    )
    poses = np.column_stack([np.linspace(0.0, 4.9, 50), xy, yaw])
    ds = Dataset(robot=PAPER_CALIBRATED, poses=poses, encoders={},
                 segments=[Segment(static_module=2, start=0.0, end=4.9)])  # fmt: skip
    (circle,) = spin_circles(ds)
    assert circle == pytest.approx((2, 0.5, -0.2, 0.3), abs=1e-9)
    path = tmp_path / "run.mcap"
    rec = McapRecorder(path, list(PAPER_CALIBRATED.ids), profile=profile)
    rec.circles(4.9, [circle])
    rec.finish()
    (msg,) = read(path, profile == "ros2")["/calibration/circles"]
    if profile == "ros2":
        (marker,) = msg.markers
        assert (marker.header.frame_id, marker.type) == ("W", 4)  # LINE_STRIP, closed
        pts = [(p.x, p.y) for p in marker.points]
        assert len(pts) == CIRCLE_POINTS + 1 and pts[0] == pts[-1]
    else:
        (entity,) = msg["entities"]
        assert entity["frame_id"] == "W" and entity["lines"][0]["type"] == 1  # LINE_LOOP
        pts = [(p["x"], p["y"]) for p in entity["lines"][0]["points"]]
        assert len(pts) == CIRCLE_POINTS
    radii = np.hypot(*(np.array(pts) - [0.5, -0.2]).T)
    assert radii == pytest.approx(0.3, abs=1e-12)


def test_encoders_and_gyro_are_ros_joint_states_and_imu_in_json(tmp_path: Path) -> None:
    """The default profile's encoders and gyro in ROS's standard types (JSON): joint names
    those of the URDF, the gyro's rate on ``angular_velocity.z``, every message valid
    against its channel's schema."""
    import jsonschema_rs

    path = tmp_path / "run.mcap"
    rec = McapRecorder(path, [3], wall_offset=1.7e9)
    rec.encoders(3, np.array([[1.0, 0.25, 7.5]]))
    rec.gyro(np.array([[1.0, -0.125]]))
    rec.finish()
    with path.open("rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        assert summary is not None
        names = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
        for schema, channel, m in reader.iter_messages():
            doc = json.loads(m.data)
            assert schema is not None
            errors = list(jsonschema_rs.validator_for(json.loads(schema.data)).iter_errors(doc))
            assert errors == [], (channel.topic, doc)
            if channel.topic == "/module3/encoders":
                assert (doc["name"], doc["position"]) == (["steer_3", "wheel_3"], [0.25, 7.5])
            else:
                assert doc["angular_velocity"]["z"] == -0.125
                assert doc["orientation_covariance"][0] == -1.0  # not provided
    assert (names["/module3/encoders"], names["/imu/gyro"]) == (
        "sensor_msgs/msg/JointState", "sensor_msgs/msg/Imu"
    )  # fmt: skip
