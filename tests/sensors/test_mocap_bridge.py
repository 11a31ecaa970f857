"""``swpc mocap`` (issue 46): a lab's motion capture onto the robot's pose key.

QTM's real-time protocol is tested both ways against a peer this project did not write:
the simulator's QTM server against Qualisys' own client library (qtm-rt), and the bridge,
which reads QTM through that library.  The other systems come through Bitcraze's
motioncapture library, whose mock backend (no bodies) is what runs here.  Zenoh on
loopback only: peer mode, scouting off, ``tcp/127.0.0.1:<free port>``.
"""

from __future__ import annotations

import asyncio
import math
import re
import threading
import time
import xml.etree.ElementTree as ET
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from services.cli import main as swpc
from services.sensors.bridge import NOT_SEEN_AFTER, Bridge, BridgeError, Source, zenoh_publisher
from simulators.sensors.qtm import QtmBody, QtmServer
from swpc_hw.sensors.bridge import FrameCount, rotation_rows, to_world
from swpc_hw.sensors.mocap import decode_native, pose_key
from swpc_hw.sensors.zenoh_session import (
    ZenohAuth,
    free_tcp_endpoint,
    open_session,
    publishers_acl,
)


def y_up_body(x: float, y: float, yaw: float) -> QtmBody:
    """A robot at (x, y) m, heading ``yaw``, as a y-up system in mm sees it: the floor is
    its x-z plane with its z towards the robot's -y, and a turn about the vertical is a
    turn about its y axis (the textbook matrix, column-major as QTM sends it)."""
    c, s = math.cos(yaw), math.sin(yaw)
    rot_y = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    return QtmBody((1000.0 * x, 0.0, -1000.0 * y), tuple(rot_y.flatten(order="F")))


PATH = [(1.2 + 0.01 * k, -0.4 + 0.005 * k, math.radians(30 + 2 * k)) for k in range(40)]
"""A robot's planar path: (x m, y m, yaw rad) per frame."""


@pytest.fixture
def qtm() -> Iterator[QtmServer]:
    srv = QtmServer(["wand", "swpc"], frequency=100.0)
    srv.start()
    try:
        yield srv
    finally:
        srv.stop()


def stream(srv: QtmServer, frames: list[int], stop: threading.Event) -> threading.Thread:
    """Publish the path's frames (numbered ``frames``; a NaN body at frame 7) every 5 ms
    until ``stop``, once a client streams."""

    def run() -> None:
        while not srv.streaming and not stop.is_set():
            time.sleep(0.005)
        for i, n in enumerate(frames):
            if stop.is_set():
                return
            x, y, yaw = PATH[i % len(PATH)]
            body = None if n == 7 else y_up_body(x, y, yaw)
            srv.publish(1_000_000 + 10_000 * n, n, [y_up_body(0.0, 0.0, 0.0), body])
            time.sleep(0.005)

    th = threading.Thread(target=run, daemon=True)
    th.start()
    return th


def test_the_simulators_qtm_server_speaks_to_qualisys_own_client(qtm: QtmServer) -> None:
    import qtm_rt

    stop = threading.Event()
    feeder = stream(qtm, list(range(1, 21)), stop)
    got: list[Any] = []

    async def client() -> str:
        conn = await qtm_rt.connect("127.0.0.1", port=qtm.port, version="1.25", timeout=5)
        assert conn is not None
        xml = await conn.get_parameters(parameters=["6d", "general"])
        names = [(n.text or "") for n in ET.fromstring(xml).findall("*/Body/Name")]
        assert ET.fromstring(xml).findtext("General/Frequency") == "100"
        ok = await conn.stream_frames(components=["6d"], on_packet=got.append)
        while len(got) < 20:
            await asyncio.sleep(0.01)
        await conn.stream_frames_stop()
        with pytest.raises(qtm_rt.QRTCommandException, match="not supported"):
            await conn.get_current_frame(components=["3d"])
        conn.disconnect()
        return f"{ok!r} {names}"

    try:
        assert asyncio.run(asyncio.wait_for(client(), 20)) == "b'Ok' ['wand', 'swpc']"
    finally:
        stop.set()
        feeder.join()
    assert [p.framenumber for p in got] == list(range(1, 21))
    assert got[0].timestamp == 1_010_000  # us, QTM's clock
    header, bodies = got[0].get_6d()
    assert header.body_count == 2
    position, rotation = bodies[1]
    x, y, yaw = PATH[0]
    np.testing.assert_allclose((position.x, position.y, position.z), (1200.0, 0.0, 400.0),
                               atol=1e-3)  # fmt: skip
    np.testing.assert_allclose(rotation.matrix, y_up_body(x, y, yaw).rotation, atol=1e-7)
    assert all(math.isnan(v) for v in (*got[6].get_6d()[1][1][0],))  # frame 7: not seen


def test_the_bridge_puts_qtms_body_on_the_robots_key_in_metres_z_up(qtm: QtmServer) -> None:
    """Frames 1-30 without 12-14 (never sent: dropped) and with frame 7's body not seen:
    every other frame arrives on ``mocap/swpc/pose`` as the path's planar pose in W, at
    QTM's capture time."""
    ep = free_tcp_endpoint()
    sub = open_session(listen=[ep])
    pub = open_session(connect=[ep])
    poses: list[Any] = []
    sub.declare_subscriber(pose_key("swpc"), lambda s: poses.append(decode_native(
        bytes(s.payload.to_bytes()))))  # fmt: skip
    probe = pub.declare_publisher(pose_key("swpc"))
    deadline = time.monotonic() + 10  # the subscription known to the bridge's session first
    while not probe.matching_status.matching and time.monotonic() < deadline:
        time.sleep(0.01)
    frames = [n for n in range(1, 31) if n not in (12, 13, 14)]
    lines: list[str] = []
    bridge = Bridge(Source.parse(f"qtm://127.0.0.1:{qtm.port}"), "swpc",
                    zenoh_publisher(pub, pose_key("swpc")), up="y", units="mm",
                    say=lines.append, report_every=0)  # fmt: skip
    stop = threading.Event()
    feeder = stream(qtm, frames, stop)
    runner = threading.Thread(target=bridge.run, daemon=True)
    runner.start()
    try:
        feeder.join(timeout=30)
        deadline = time.monotonic() + 10
        while len(poses) < len(frames) - 1 and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        bridge.stop()
        runner.join(timeout=10)
        stop.set()
        pub.close()
        sub.close()
    assert bridge.bodies == ["wand", "swpc"]
    c = bridge.count
    assert (c.frames, c.dropped, c.not_seen, c.sent) == (27, 3, 1, 26), c.line()
    assert len(poses) == 26 and [p.seq for p in poses] == list(range(26))
    sent = [n for n in frames if n != 7]
    for p, n in zip(poses, sent, strict=True):
        x, y, yaw = PATH[frames.index(n) % len(PATH)]
        assert p.t == pytest.approx(1.0 + 0.01 * n, abs=1e-9)  # QTM's capture time, s
        assert (p.x, p.y) == (pytest.approx(x, abs=1e-6), pytest.approx(y, abs=1e-6))
        assert math.remainder(p.yaw - yaw, math.tau) == pytest.approx(0.0, abs=1e-6)


def test_a_body_the_system_does_not_have_is_refused_naming_the_ones_it_has(
    qtm: QtmServer,
) -> None:
    bridge = Bridge(Source.parse(f"qtm://127.0.0.1:{qtm.port}"), "robot7",
                    lambda payload: None, report_every=0)  # fmt: skip
    with pytest.raises(BridgeError, match=r"no 6DOF body 'robot7' \(its bodies: wand, swpc\)"):
        bridge.run()


def test_no_qtm_at_the_address_is_said_plainly() -> None:
    port = int(free_tcp_endpoint().rsplit(":", 1)[1])
    bridge = Bridge(Source.parse(f"qtm://127.0.0.1:{port}"), "swpc", lambda p: None)
    with pytest.raises(BridgeError, match=f"QTM at 127.0.0.1:{port}: no connection"):
        bridge.run()


def test_motioncaptures_mock_has_no_body_and_the_bridge_says_so() -> None:
    """Bitcraze's library, mock backend: frames every 10 ms, no rigid body."""
    lines: list[str] = []
    sent: list[bytes] = []
    bridge = Bridge(Source.parse("mock://"), "swpc", sent.append, say=lines.append,
                    report_every=0)  # fmt: skip
    bridge.run(duration=NOT_SEEN_AFTER * 0.01 + 0.5)
    assert sent == [] and bridge.count.frames >= NOT_SEEN_AFTER
    assert bridge.count.not_seen == bridge.count.frames
    assert f"body 'swpc' not seen for {NOT_SEEN_AFTER} frames (the system has: no bodies)" in lines


@pytest.mark.parametrize(
    ("text", "words"),
    [
        ("natnet://10.0.0.1", "the kind must be one of qtm, vicon, optitrack, vrpn"),
        ("vicon://", "no host (e.g. vicon://192.0.2.10)"),
        ("qtm://h:99999", "Port out of range"),
    ],
)
def test_a_source_that_is_not_one_is_refused_naming_what_is(text: str, words: str) -> None:
    with pytest.raises(BridgeError, match=re.escape(words)):
        Source.parse(text)


def test_swpc_mocap_bridges_until_its_duration_and_counts(
    qtm: QtmServer, capsys: pytest.CaptureFixture[str]
) -> None:
    stop = threading.Event()
    feeder = stream(qtm, list(range(1, 41)), stop)
    ep = free_tcp_endpoint()
    try:
        rc = swpc(["mocap", "--source", f"qtm://127.0.0.1:{qtm.port}", "--body", "swpc",
                   "--up", "y", "--zenoh-listen", ep, "--duration", "1.5",
                   "--report-every", "0"])  # fmt: skip
    finally:
        stop.set()
        feeder.join()
    out = capsys.readouterr().out
    assert rc == 0, out
    assert f"qtm://127.0.0.1:{qtm.port} body 'swpc' (y up, mm) -> mocap/swpc/pose" in out
    assert "40 frames" in out and "0 dropped, 1 without the body, 39 poses sent" in out


def test_y_up_turns_into_z_up_by_a_quarter_turn_about_x() -> None:
    """The conversion itself: a y-up system's up axis is W's z, its z is W's -y; a body
    turned about the vertical keeps its yaw; a quaternion's matrix is a rotation."""
    p, r = to_world((100.0, 2000.0, 300.0), ((1, 0, 0), (0, 1, 0), (0, 0, 1)), "y", 1e-3)
    assert p == pytest.approx((0.1, -0.3, 2.0)) and r == ((1, 0, 0), (0, 1, 0), (0, 0, 1))
    q = rotation_rows(math.cos(0.3), 0.0, 0.0, math.sin(0.3))  # 0.6 rad about z
    m = np.array(q)
    np.testing.assert_allclose(m @ m.T, np.eye(3), atol=1e-12)
    assert math.atan2(m[1, 0], m[0, 0]) == pytest.approx(0.6)
    assert all(math.isnan(v) for row in rotation_rows(0, 0, 0, 0) for v in row)
    c = FrameCount(window=1.0)
    for k, n in enumerate((1, 2, 5, 6)):  # 3 and 4 never came
        c.frame(n, 0.1 * k, seen=k != 1)
    assert (c.frames, c.dropped, c.not_seen, c.last_frame) == (4, 2, 1, 6)
    assert c.rate() == pytest.approx(10.0)


def test_the_bridge_logs_in_as_the_service_asks_and_a_wrong_password_gets_nothing_in(
    qtm: QtmServer, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A robot's service that listens requires a user and password of its peers, and
    lets only SWPC_ZENOH_PUBLISHERS (``mocap``) publish its poses; the bridge presents
    them from a file."""
    users = tmp_path / "users.txt"
    users.write_text("mocap:right-password\n")
    ep = free_tcp_endpoint()
    service = open_session(
        listen=[ep], auth=ZenohAuth(users_file=str(users)),
        acl=publishers_acl([pose_key("swpc")], ["mocap"]),
    )  # fmt: skip
    got: list[float] = []
    service.declare_subscriber(pose_key("swpc"), lambda s: got.append(
        decode_native(bytes(s.payload.to_bytes())).t))  # fmt: skip
    stop = threading.Event()
    feeder = stream(qtm, list(range(1, 10_000)), stop)
    try:
        for password, expect in (("wrong-password", False), ("right-password", True)):
            (tmp_path / "pw").write_text(password + "\n")
            got.clear()
            rc = swpc(["mocap", "--source", f"qtm://127.0.0.1:{qtm.port}", "--body", "swpc",
                       "--up", "y", "--zenoh-connect", ep, "--zenoh-user", "mocap",
                       "--zenoh-password-file", str(tmp_path / "pw"), "--duration", "1.0",
                       "--report-every", "0", "--link-timeout", "2"])  # fmt: skip
            out = capsys.readouterr()
            assert rc == (0 if expect else 2), (out.out, out.err)
            assert bool(got) == expect, (password, len(got), out.out, out.err)
            if not expect:  # refused: said, not bridged into the void
                assert f"no zenoh link to {ep} within 2 s: a refused user or password" in out.err
    finally:
        stop.set()
        feeder.join()
        service.close()
