"""The odometry as ROS 2 over zenoh (docs/ros2.md, "Odometry and TF over zenoh").

The client is zenoh-ros2-sdk (PyPI, written by ROBOTIS, not by this project): a Python
implementation of rmw_zenoh's protocol.  It computes the type hashes itself from the
message definitions and subscribes on the key rmw_zenoh would; it receives only what is
published on exactly that key, and decodes CDR with its own type store.  Loopback only:
zenoh peer mode, multicast scouting off, tcp/127.0.0.1:<free port>.
"""

from __future__ import annotations

import math
import os
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from swpc_hw.files.kinematic_file import save_kinematics
from swpc_hw.onboard.ros2.covariance import (
    OdometryCovariance,
    measurement_covariance,
    twist_sensitivity,
)
from swpc_hw.onboard.ros2.messages import ODOMETRY, TF_MESSAGE
from swpc_hw.onboard.ros2.publisher import ZenohRos2Publisher
from swpc_hw.onboard.ros2.stream import Ros2OdometryStream
from swpc_hw.onboard.ros2.wire import TYPE_HASHES, Attachment, topic_key
from swpc_hw.robot.model import RobotParams
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED
from swpc_hw.sensors.zenoh_session import free_tcp_endpoint, open_session
from tests.onboard.test_odometry import make_stream

# Published for ROS 2 Jazzy (docs/ros2.md names where): std_msgs/String in rmw_zenoh's
# docs/design.md, TFMessage in a Jazzy rosbag2 metadata.yaml, Odometry by `ros2 topic info -v`.
PUBLISHED = {
    "std_msgs/msg/String":
        "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18",
    "tf2_msgs/msg/TFMessage":
        "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087",
    "nav_msgs/msg/Odometry":
        "RIHS01_3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0",
}  # fmt: skip


def _jazzy() -> Any:
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def msg_files(ros_type: str) -> dict[str, str]:
    """``{pkg/msg/Name: .msg text}`` of a type and its dependencies (rosbags' Jazzy store)."""
    text, _ = _jazzy().generate_msgdef(ros_type, ros_version=2)
    blocks = text.split("=" * 80 + "\n")
    out = {ros_type: blocks[0]}
    for b in blocks[1:]:
        head, _, body = b.partition("\n")
        pkg, name = head.removeprefix("MSG: ").split("/")
        out[f"{pkg}/msg/{name}"] = body
    return out


@pytest.mark.parametrize("ros_type", sorted(PUBLISHED))
def test_type_hashes_match_the_published_jazzy_values(ros_type: str) -> None:
    from zenoh_ros2_sdk.utils import compute_type_hash_from_msg

    files = msg_files(ros_type)
    deps = {k: v for k, v in files.items() if k != ros_type}
    assert _jazzy().hash_rihs01(ros_type) == PUBLISHED[ros_type]
    assert compute_type_hash_from_msg(ros_type, files[ros_type], deps) == PUBLISHED[ros_type]
    if ros_type in TYPE_HASHES:
        assert TYPE_HASHES[ros_type] == PUBLISHED[ros_type]


def test_the_diagnostics_type_hash_is_what_both_implementations_compute() -> None:
    """/diagnostics (the drift monitor's status): no published Jazzy value at hand, so the
    two implementations' agreement is the check."""
    from zenoh_ros2_sdk.utils import compute_type_hash_from_msg

    t = "diagnostic_msgs/msg/DiagnosticArray"
    files = msg_files(t)
    deps = {k: v for k, v in files.items() if k != t}
    assert _jazzy().hash_rihs01(t) == TYPE_HASHES[t]
    assert compute_type_hash_from_msg(t, files[t], deps) == TYPE_HASHES[t]


def test_key_expressions_and_attachment_are_rmw_zenohs() -> None:
    from zenoh_ros2_sdk.attachment import Attachment as SdkAttachment
    from zenoh_ros2_sdk.keyexpr import topic_keyexpr

    assert topic_key("/odom", ODOMETRY) == (
        "0/odom/nav_msgs::msg::dds_::Odometry_/" + PUBLISHED[ODOMETRY])
    assert topic_key("tf", TF_MESSAGE, domain_id=3, namespace="/robot1") == topic_keyexpr(
        3, "/robot1/tf", "tf2_msgs::msg::dds_::TFMessage_", PUBLISHED[TF_MESSAGE])
    gid = bytes(range(16))
    raw = Attachment(7, 1_700_000_000_123_456_789, gid).encode()
    assert len(raw) == 33 and raw[16] == 16
    theirs = SdkAttachment.from_bytes(raw)
    assert (theirs.sequence_id, theirs.timestamp_ns, theirs.gid) == (
        7, 1_700_000_000_123_456_789, gid)
    assert Attachment.decode(raw) == Attachment(7, 1_700_000_000_123_456_789, gid)


# --------------------------------------------------------------------------- covariance


def test_measurement_covariance_of_a_square_and_a_slipping_wheel() -> None:
    a, sigma = 0.25, 0.004
    qx, qy = [a, -a, -a, a], [a, a, -a, -a]
    cov = measurement_covariance(qx, qy, [1.0] * 4, sigma)
    # A^T A = diag(4, 4, 8 a^2)
    np.testing.assert_allclose(np.diag(cov), [sigma**2 / 4, sigma**2 / 4, sigma**2 / (8 * a * a)])
    slip = measurement_covariance(qx, qy, [1.0, 1.0, 1.0, 1e-9], sigma)
    assert slip[0, 0] > 1.3 * cov[0, 0] and slip[2, 2] > 1.3 * cov[2, 2]


def test_a_wheel_radius_error_grows_the_pose_covariance_with_the_distance() -> None:
    """Straight at v: v_x is the mean of the four wheels' r psi_dot, so
    var(v_x) = (v sigma_r / r)^2 / 4 and the systematic x std after D is D sigma_r / (2 r)."""
    p = PAPER_CALIBRATED
    v, rate, dur = 0.3, 100.0, 5.0
    t, th, ps, _ = make_stream(p, [(dur, (v, 0.0, 0.0))], rate=rate, jitter=0.0)
    from swpc_hw.onboard.odometry import Odometry, _Geometry

    sr = 1e-4
    n_mod = len(p.modules)
    sp = np.zeros((5 * n_mod, 5 * n_mod))
    for i in range(n_mod):
        sp[5 * i + 4, 5 * i + 4] = sr * sr
    cov = OdometryCovariance(sp)
    odo = Odometry(p)
    rows = _Geometry.of(p).rows
    odo.update(t[0], th[0], ps[0])
    for k in range(1, len(t)):
        p0 = odo.pose
        odo.update(t[k], th[k], ps[k])
        step = odo.last
        assert step is not None
        J = twist_sensitivity(rows, step.dt, th[k - 1], th[k], ps[k - 1], ps[k], step.weights)
        cov.step(p0, odo.pose, step.dt, np.zeros((3, 3)), J)
    r = float(np.mean([m.r for m in p.modules]))
    assert math.sqrt(cov.twist[0, 0]) == pytest.approx(v * sr / (2 * r), rel=0.02)
    assert math.sqrt(cov.pose[0, 0]) == pytest.approx(v * dur * sr / (2 * r), rel=0.02)


# --------------------------------------------------------------------------- over zenoh


@pytest.fixture()
def sdk_client(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Any]:
    """zenoh-ros2-sdk with the Jazzy .msg files in a local directory (no download) and its
    session on loopback only."""
    from zenoh_ros2_sdk import message_registry

    for ros_type in (ODOMETRY, TF_MESSAGE):
        for name, text in msg_files(ros_type).items():
            f = tmp_path / "msgs" / f"{name}.msg"
            f.parent.mkdir(parents=True, exist_ok=True)
            f.write_text(text)
    monkeypatch.setenv(
        "ZENOH_CONFIG_OVERRIDE",
        "listen/endpoints=[];scouting/multicast/enabled=false;scouting/gossip/enabled=false",
    )
    monkeypatch.setattr(message_registry, "_registry", None)
    message_registry.get_registry(str(tmp_path / "msgs"))
    import zenoh_ros2_sdk

    yield zenoh_ros2_sdk
    if zenoh_ros2_sdk.ZenohSession._instance is not None:
        zenoh_ros2_sdk.ZenohSession._instance.close()


def _scaled_radius(p: RobotParams, k: float) -> RobotParams:
    return p.model_copy(update={"modules": [m.model_copy(update={"r": m.r * k})
                                            for m in p.modules]})


def _listening(port: int) -> bool:
    import socket

    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) == 0


def _wait(cond: Any, what: str, limit: float = 20.0) -> None:
    """Wait for delivery (a safety limit only: nothing here asserts on wall time)."""
    end = time.monotonic() + limit
    while not cond():
        assert time.monotonic() < end, f"gave up waiting for {what}"
        time.sleep(0.01)


def test_odometry_and_tf_reach_an_independent_ros2_client_and_a_new_file_reloads(
    tmp_path: Path, sdk_client: Any
) -> None:
    p = PAPER_CALIBRATED
    kin = tmp_path / "kinematics.yaml"
    save_kinematics(kin, p)
    v, rate = 0.2, 100.0
    t, th, ps, _ = make_stream(p, [(4.0, (v, 0.0, 0.0))], rate=rate, jitter=0.0)

    ep = free_tcp_endpoint()
    session = open_session(listen=[ep])
    port = int(ep.rsplit(":", 1)[1])
    odoms: list[Any] = []
    tfs: list[Any] = []
    lock = threading.Lock()

    def on_odom(m: Any) -> None:
        with lock:
            odoms.append(m)

    def on_tf(m: Any) -> None:
        with lock:
            tfs.append(m)

    publisher = ZenohRos2Publisher(session, block=True)  # counts every message
    # A plain zenoh subscriber on the same key for the attachments (the SDK hides them).
    atts: list[bytes] = []
    raw = session.declare_subscriber(
        publisher.key("/odom", ODOMETRY),
        lambda s: atts.append(bytes(s.attachment.to_bytes())) if s.attachment else None,
    )
    try:
        sub_odom = sdk_client.ROS2Subscriber(
            "/odom", ODOMETRY, on_odom, router_ip="127.0.0.1", router_port=port)
        sub_tf = sdk_client.ROS2Subscriber(
            "/tf", TF_MESSAGE, on_tf, router_ip="127.0.0.1", router_port=port)
        assert sub_odom.keyexpr == publisher.key("/odom", ODOMETRY)  # the SDK's own hash
        assert sub_tf.keyexpr == publisher.key("/tf", TF_MESSAGE)
        _wait(lambda: publisher.matched("/odom", ODOMETRY)
              and publisher.matched("/tf", TF_MESSAGE), "the client's subscriptions")

        stream = Ros2OdometryStream(kin, publisher, stamp_offset=1_700_000_000.0)
        half = len(t) // 2
        for k in range(half):
            stream.update(t[k], th[k], ps[k])
        # a calibration installs a new file: 10 % larger wheels, atomic rename
        new = tmp_path / "kinematics.yaml.new"
        save_kinematics(new, _scaled_radius(p, 1.1))
        os.replace(new, kin)
        for k in range(half, len(t)):
            stream.update(t[k], th[k], ps[k])
        assert stream.reloads == 1 and stream.reload_error is None
        n = stream.published
        _wait(lambda: len(odoms) >= n and len(tfs) >= n and len(atts) >= n, "all messages")
    finally:
        raw.undeclare()
        publisher.close()
        session.close()

    assert len(odoms) == len(tfs) == n == len(t) - 1
    stamps = np.array([m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 for m in odoms])
    span = stamps[-1] - stamps[0]
    assert (len(stamps) - 1) / span == pytest.approx(rate, rel=1e-6)  # the odometry's rate
    o = odoms[half - 5]
    assert (o.header.frame_id, o.child_frame_id) == ("odom", "base_link")
    assert o.twist.twist.linear.x == pytest.approx(v, rel=1e-6)
    assert odoms[-1].twist.twist.linear.x == pytest.approx(1.1 * v, rel=1e-6)
    assert len(o.pose.covariance) == 36 and o.pose.covariance[0] > 0.0
    tf = tfs[-1].transforms[0]
    assert (tf.header.frame_id, tf.child_frame_id) == ("odom", "base_link")
    assert tf.transform.translation.x == pytest.approx(odoms[-1].pose.pose.position.x)
    # x after the reload: half the run at v, the other half at 1.1 v
    assert odoms[-1].pose.pose.position.x == pytest.approx(
        v * (t[half - 1] - t[0]) + 1.1 * v * (t[-1] - t[half - 1]), rel=1e-6)
    decoded = [Attachment.decode(a) for a in atts]
    assert [d.sequence_number for d in decoded] == list(range(1, n + 1))
    assert decoded[0].source_timestamp == round(stamps[0] * 1e9)
    assert len({d.gid for d in decoded}) == 1


def test_a_bad_new_file_keeps_the_running_parameters(tmp_path: Path) -> None:
    p = PAPER_CALIBRATED
    kin = tmp_path / "kinematics.yaml"
    save_kinematics(kin, p)
    got: list[tuple[str, float]] = []
    stream = Ros2OdometryStream(kin, lambda topic, _ty, stamp, _b: got.append((topic, stamp)))
    t, th, ps, _ = make_stream(p, [(0.2, (0.2, 0.0, 0.0))], rate=100.0, jitter=0.0)
    for k in range(10):
        stream.update(t[k], th[k], ps[k])
    bad = tmp_path / "bad.yaml"
    bad.write_text("format: swpc-kinematics/1\nrobot: x\n")
    os.replace(bad, kin)
    for k in range(10, len(t)):
        stream.update(t[k], th[k], ps[k])
    assert stream.reloads == 0 and stream.reload_error is not None
    assert "missing key 'frame'" in stream.reload_error
    assert stream.odometry.params.modules == p.modules  # in base_link = R: the same
    assert len(got) == 2 * (len(t) - 1)


def test_a_file_rewritten_in_place_is_used_whole_or_not_at_all(tmp_path: Path) -> None:
    """A writer that rewrites the file in place (the inode kept) first leaves a truncated
    radius that still parses (0.05 for 0.0557): it is never used; the whole file is, once
    it has stood SETTLE_S of the readings' time.  A rename is used at the next step."""
    from swpc_hw.onboard.ros2.stream import SETTLE_S

    p = PAPER_CALIBRATED
    kin = tmp_path / "kinematics.yaml"
    save_kinematics(kin, p)
    stream = Ros2OdometryStream(kin, lambda *_: None)
    t, th, ps, _ = make_stream(p, [(2.0, (0.2, 0.0, 0.0))], rate=100.0, jitter=0.0)
    whole = _scaled_radius(p, 1.1)
    save_kinematics(tmp_path / "whole.yaml", whole)
    text = (tmp_path / "whole.yaml").read_text()
    r1 = f"{whole.modules[0].r!r}"
    cut = text.replace(r1, r1[:4], 1)  # the first radius cut short, the rest there
    assert cut != text
    radii: list[float] = []
    for k in range(len(t)):
        if k == 10:
            with kin.open("r+") as fh:  # in place: the same inode, the half-written state
                fh.write(cut)
                fh.truncate()
        if k == 30:  # the writer finishes 0.2 s later
            with kin.open("r+") as fh:
                fh.write(text)
                fh.truncate()
        stream.update(t[k], th[k], ps[k])
        radii.append(stream.odometry.params.modules[0].r)
    assert {round(r, 9) for r in radii} == {round(p.modules[0].r, 9), round(whole.modules[0].r, 9)}
    first = radii.index(whole.modules[0].r)
    assert t[first] - t[30] == pytest.approx(SETTLE_S, abs=0.011)  # settled, then whole
    assert stream.reloads == 1 and stream.reload_error is None
    # an atomic rename is whole at once: the next step
    save_kinematics(tmp_path / "new.yaml", p)
    os.replace(tmp_path / "new.yaml", kin)
    stream.update(t[-1] + 0.01, th[-1], ps[-1])
    assert stream.reloads == 2 and stream.odometry.params.modules[0].r == p.modules[0].r


def test_a_watched_file_is_parsed_off_the_update_loop(tmp_path: Path) -> None:
    """With watch(), update() never opens the file: a new file reaches the odometry
    through the watcher's thread, a bad one is reported and the parameters stay."""
    from swpc_hw.clock import SystemClock

    p = PAPER_CALIBRATED
    kin = tmp_path / "kinematics.yaml"
    save_kinematics(kin, p)
    stream = Ros2OdometryStream(kin, lambda *_: None)
    t, th, ps, _ = make_stream(p, [(1.0, (0.2, 0.0, 0.0))], rate=100.0, jitter=0.0)
    stream.watch(SystemClock(), period=0.01)
    try:
        save_kinematics(tmp_path / "new.yaml", _scaled_radius(p, 1.1))
        os.replace(tmp_path / "new.yaml", kin)
        deadline = time.monotonic() + 10
        k = 0
        while stream.reloads == 0 and time.monotonic() < deadline:
            stream.update(t[k % len(t)] + k // len(t), th[k % len(t)], ps[k % len(t)])
            k += 1
            time.sleep(0.001)
        assert stream.reloads == 1
        assert stream.odometry.params.modules[0].r == pytest.approx(1.1 * p.modules[0].r)
        os.replace(_bad(tmp_path), kin)
        while stream.reload_error is None and time.monotonic() < deadline:
            time.sleep(0.01)
        assert stream.reload_error is not None and "missing key 'frame'" in stream.reload_error
        assert stream.reloads == 1
    finally:
        stream.close()


def _bad(tmp_path: Path) -> Path:
    bad = tmp_path / "bad.yaml"
    bad.write_text("format: swpc-kinematics/1\nrobot: x\n")
    return bad


def test_swpc_odometry_replays_a_datasets_encoders_to_a_ros2_client(
    tmp_path: Path, sdk_client: Any
) -> None:
    """``swpc odometry --encoders DIR`` on loopback: one /odom message per reading after
    the first, received by the independent client."""
    from services.cli import main
    from swpc_hw.files.dataset import Dataset, Segment, save_dataset

    p = PAPER_CALIBRATED
    kin = tmp_path / "kinematics.yaml"
    save_kinematics(kin, p)
    t, th, ps, truth = make_stream(p, [(1.0, (0.1, 0.0, 0.2))], rate=50.0, jitter=0.0)
    enc = {m.id: np.column_stack([t, th[:, i], ps[:, i]]) for i, m in enumerate(p.modules)}
    ds = Dataset(p, np.column_stack([t, truth]), enc, [Segment(1, 0.1, 0.9)])
    save_dataset(tmp_path / "ds", ds)
    ep = free_tcp_endpoint()
    port = int(ep.rsplit(":", 1)[1])
    got: list[Any] = []
    # the command listens, waits for a subscriber of /odom, replays; the client connects
    codes: list[int] = []
    cmd = threading.Thread(target=lambda: codes.append(main([
        "odometry", "--kinematics", str(kin), "--encoders", str(tmp_path / "ds"),
        "--zenoh-listen", ep, "--wait-subscriber", "20"])))
    cmd.start()
    try:
        _wait(lambda: _listening(port), "the command's endpoint")
        sub = sdk_client.ROS2Subscriber("/odom", ODOMETRY, got.append,
                                        router_ip="127.0.0.1", router_port=port)
        _wait(lambda: bool(codes), "the command")
        _wait(lambda: len(got) >= len(t) - 1, "the replay")
        sub.close()
    finally:
        cmd.join(30)
    assert codes == [0]
    assert len(got) == len(t) - 1
    assert got[-1].twist.twist.angular.z == pytest.approx(0.2, rel=1e-6)


def test_the_stream_publishes_base_links_motion_from_the_robot_config(tmp_path: Path) -> None:
    """A spin of R about its own origin, with base_link at (0.2, 0.1) yawed 0.3 rad in R:
    the published twist is base_link's, ``v_b = R(-yaw_b) (v_R + omega x p_b)``, in
    base_link's axes (decoded from the CDR with rosbags' own type store)."""
    from swpc_hw.robot.frames import BaseLinkPose
    from swpc_hw.sensors.mocap import ros2_typestore

    p = PAPER_CALIBRATED
    kin = tmp_path / "kinematics.yaml"
    save_kinematics(kin, p)
    got: list[bytes] = []
    bl = BaseLinkPose(x=0.2, y=0.1, yaw=0.3)

    def sink(topic: str, _ty: str, _stamp: float, cdr: bytes) -> None:
        if topic == "/odom":
            got.append(cdr)

    stream = Ros2OdometryStream(kin, sink, base_link=bl)
    om = 0.5
    t, th, ps, _ = make_stream(p, [(1.0, (0.0, 0.0, om))], rate=100.0, jitter=0.0)
    for k in range(len(t)):
        stream.update(t[k], th[k], ps[k])
    msg = ros2_typestore().deserialize_cdr(got[-1], ODOMETRY)
    v_r = np.array([-om * bl.y, om * bl.x])  # omega x p_b, R's axes
    c, s = math.cos(bl.yaw), math.sin(bl.yaw)
    v_b = np.array([[c, s], [-s, c]]) @ v_r
    tw = msg.twist.twist
    assert (tw.linear.x, tw.linear.y) == pytest.approx(tuple(v_b), abs=1e-9)
    assert tw.angular.z == pytest.approx(om, abs=1e-9)
    assert msg.child_frame_id == "base_link" and msg.header.frame_id == "odom"
    # and without base_link, the same readings give R's own twist: a spin in place
    plain: list[bytes] = []
    r_stream = Ros2OdometryStream(
        kin, lambda tp, _t, _s, b: plain.append(b) if tp == "/odom" else None
    )
    for k in range(len(t)):
        r_stream.update(t[k], th[k], ps[k])
    tw_r = ros2_typestore().deserialize_cdr(plain[-1], ODOMETRY).twist.twist
    assert math.hypot(tw_r.linear.x, tw_r.linear.y) < 1e-9


# The stream on the drives' CAN feedback while the in-process simulator drives squares:
# tests/validation/test_square_path.py::test_swpc_odometry_follows_the_drives_on_can_while_
# the_robot_drives, which shares the square-path test's drive (one simulator run for both).
