"""A run's data as an MCAP file that Foxglove shows natively, written as it is recorded.

:class:`McapRecorder` appends messages while a run goes on and finishes one chunk per
:meth:`~McapRecorder.flush` (the run flushes every half second of robot time): a service
killed mid-run (``kill -9``, a power cut after the page cache reached the disk) leaves
every flushed chunk readable, without the file's summary (``mcap.reader.NonSeekingReader``
reads it; ``mcap recover`` rewrites it with an index).  :meth:`~McapRecorder.finish`
writes the summary.

Channels (JSON messages, ``jsonschema`` schemas, :mod:`services.runs.mcap_schemas`):

===========================  ==========================  =================================
topic                        schema                      what
===========================  ==========================  =================================
``/mocap/pose``              ``foxglove.PoseInFrame``    pose of R in W (frame ``W``)
``/tf``                      ``foxglove.FrameTransform``  the same pose as the transform
                                                         W -> R (Foxglove's 3D panel);
                                                         both with the first pose only
``/module<id>/encoders``     ``sensor_msgs/msg/JointState``  ``steer_<id>`` (reported
                                                         ``theta_hat``) and ``wheel_<id>``
                                                         (``psi``), the URDF's joints
``/calibration/segments``    ``swpc.Segment``            one message per spin window
``/calibration/events``      ``foxglove.Log``            the run's events (state changes,
                                                         faults, the result)
``/imu/gyro``                ``sensor_msgs/msg/Imu``     without motion capture: the
                                                         gyro's yaw rate (instead of the
                                                         poses)
``/tf_static``               ``foxglove.FrameTransform``  R -> ``base_link`` (the robot
                                                         config's), once at the start
``/robot_description``       ``std_msgs/msg/String``     the URDF of the nominal robot in
                                                         base_link (the exports'), once
``/calibration/circles``     ``foxglove.SceneUpdate``    each spin's fitted circle in W
                                                         (:func:`spin_circles`), at the
                                                         end of a run with poses
===========================  ==========================  =================================

Profile ``ros2`` (``SWPC_MCAP_PROFILE=ros2``, ``McapRecorder(profile="ros2")``) writes the
same topics for ROS tools instead: CDR messages (rosbags) with ``ros2msg`` schemas, MCAP
profile ``ros2``:

===========================  ====================================  ===========================
topic                        ROS 2 type                            what
===========================  ====================================  ===========================
``/mocap/pose``              ``geometry_msgs/msg/PoseStamped``     frame ``W``
``/tf``                      ``tf2_msgs/msg/TFMessage``            ``W -> R``
``/module<id>/encoders``     ``sensor_msgs/msg/JointState``        ``steer_<id>``
                                                                   (theta_hat, rad) and
                                                                   ``wheel_<id>`` (psi, rad)
                                                                   positions
``/calibration/segments``    ``std_msgs/msg/String``               the segment as JSON
``/calibration/events``      ``rcl_interfaces/msg/Log``            the run's events
``/imu/gyro``                ``sensor_msgs/msg/Imu``               the gyro's yaw rate
``/tf_static``               ``tf2_msgs/msg/TFMessage``            ``R -> base_link``
``/robot_description``       ``std_msgs/msg/String``               the URDF
``/calibration/circles``     ``visualization_msgs/msg/MarkerArray``  the fitted circles
===========================  ====================================  ===========================

Log and publish times are epoch nanoseconds: the dataset's clock times plus the run's
``wall_offset`` (:func:`services.runs.journal.log_wall_offset`: the run's first log time is
the host's time at its start, the API's ``started``, so a viewer lines the file up with the
API); each message's ``timestamp`` is the same instant.
Metadata records: ``robot-config`` (the run's robot config), ``provenance`` and, at the
end, ``outcome`` (state, reason) and ``result`` (within tolerance, installed);
attachments: the run's ``kinematics.yaml`` and ``result.json`` when there is a result.
"""

from __future__ import annotations

import contextlib
import json
import math
from collections.abc import Mapping
from pathlib import Path
from typing import IO, Any

import numpy as np
from mcap.writer import Writer

from services.runs.mcap_schemas import (
    ENCODERS,
    FRAME_TRANSFORM,
    GYRO,
    LOG,
    POSE_IN_FRAME,
    SCENE_UPDATE,
    SEGMENT,
    STRING,
)
from swpc_hw.calibration import geometry as geo
from swpc_hw.errors import SwpcError
from swpc_hw.files.dataset import Dataset
from swpc_hw.files.kinematic_file import KinematicFile
from swpc_hw.onboard.export.core import make_export
from swpc_hw.onboard.export.urdf import render_urdf, steer_joint, wheel_joint
from swpc_hw.robot.frames import BASE_LINK, BaseLink, base_link_transform
from swpc_hw.robot.model import FloatArray, RobotParams

CIRCLE_POINTS = 72
LOG_LEVELS = {"debug": 1, "info": 2, "warning": 3, "error": 4, "fatal": 5}
ROS_LOG_LEVELS = {"debug": 10, "info": 20, "warning": 30, "error": 40, "fatal": 50}
WORLD, ROBOT = "W", "R"
PROFILES = ("foxglove", "ros2")
"""``foxglove``: JSON messages with Foxglove's schemas (default); ``ros2``: CDR messages
with ROS 2 ``ros2msg`` schemas (module docstring)."""


class _Ros2:
    """The ``ros2`` profile's messages: rosbags' type store, CDR."""

    def __init__(self) -> None:
        from swpc_hw.sensors.mocap import ros2_typestore

        self.ts = ros2_typestore()
        self.T = self.ts.types

    def schema(self, ros_type: str) -> bytes:
        text, _ = self.ts.generate_msgdef(ros_type, ros_version=2)
        return str(text).encode()

    def header(self, ns: int, frame_id: str) -> Any:
        T = self.T
        return T["std_msgs/msg/Header"](
            stamp=T["builtin_interfaces/msg/Time"](
                sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000
            ),
            frame_id=frame_id,
        )

    def cdr(self, msg: Any, ros_type: str) -> bytes:
        return bytes(self.ts.serialize_cdr(msg, ros_type))


def _stamp(ns: int) -> dict[str, int]:
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


MODULE_COLOURS = ("#0b4fa8", "#b3001b", "#0a6b2d", "#6a1b9a", "#8a4b00", "#00607a")
"""Each module's colour, by its id (module k: ``MODULE_COLOURS[(k - 1) % 6]``), in the run's
plot, its MCAP's drawings and the console (served to it as ``/console/palette.js``): one
module, one colour."""


def module_colour(module_id: int) -> str:
    return MODULE_COLOURS[(module_id - 1) % len(MODULE_COLOURS)]


def _rgba(module_id: int) -> dict[str, float]:
    """Module ``module_id``'s colour (:data:`MODULE_COLOURS`) as Foxglove's and ROS's."""
    h = module_colour(module_id).lstrip("#")
    return {"r": int(h[0:2], 16) / 255, "g": int(h[2:4], 16) / 255,
            "b": int(h[4:6], 16) / 255, "a": 1.0}  # fmt: skip


def _num(x: float) -> str:
    """A JSON number (``null`` when not finite: JSON has no NaN)."""
    return repr(x) if math.isfinite(x) else "null"


class McapRecorder:
    """An MCAP file written as a run records (module docstring).

    ``wall_offset``: epoch seconds minus clock seconds (module docstring), so log times
    are epoch time.
    """

    def __init__(
        self,
        path: str | Path,
        module_ids: list[int],
        *,
        wall_offset: float = 0.0,
        library: str = "swpc",
        profile: str = "foxglove",
    ) -> None:
        if profile not in PROFILES:
            raise SwpcError(f"MCAP profile must be one of {', '.join(PROFILES)} (got {profile!r})")
        self.path = Path(path)
        self.wall_offset = float(wall_offset)
        self.profile = profile
        self.messages = 0
        self._ros2 = _Ros2() if profile == "ros2" else None
        self._fh: IO[bytes] = self.path.open("wb")
        self._w = Writer(self._fh)
        self._w.start(profile="ros2" if self._ros2 else "", library=library)
        # registered with the first pose: a run without motion capture declares no pose
        # topic (an empty 3D panel in Foxglove, issue 45 item 7)
        self._pose = self._tf = -1
        self._enc = {
            m: self._channel(f"/module{m}/encoders", ENCODERS, "sensor_msgs/msg/JointState")
            for m in module_ids
        }
        self._seg = self._channel("/calibration/segments", SEGMENT, "std_msgs/msg/String")
        self._log = self._channel("/calibration/events", LOG, "rcl_interfaces/msg/Log")
        self._gyro: int | None = None  # registered with the first gyro sample
        self._finished = False

    def _channel(self, topic: str, schema: Mapping[str, object], ros_type: str) -> int:
        if self._ros2 is not None:
            sid = self._w.register_schema(
                name=ros_type, encoding="ros2msg", data=self._ros2.schema(ros_type)
            )
            return int(
                self._w.register_channel(topic=topic, message_encoding="cdr", schema_id=sid)
            )
        sid = self._w.register_schema(
            name=str(schema["title"]), encoding="jsonschema", data=json.dumps(schema).encode()
        )
        return int(self._w.register_channel(topic=topic, message_encoding="json", schema_id=sid))

    def ns(self, t: float) -> int:
        """Epoch nanoseconds of clock time ``t``."""
        return max(0, round((t + self.wall_offset) * 1e9))

    def _bytes(self, channel: int, ns: int, data: bytes) -> None:
        self._w.add_message(channel_id=channel, log_time=ns, publish_time=ns, data=data)
        self.messages += 1

    def _add(self, channel: int, ns: int, doc: dict[str, Any]) -> None:
        self._raw(channel, ns, json.dumps(doc))

    def _raw(self, channel: int, ns: int, text: str) -> None:
        self._w.add_message(channel_id=channel, log_time=ns, publish_time=ns, data=text.encode())
        self.messages += 1

    def poses(self, rows: FloatArray) -> None:
        """Rows ``t, x, y, yaw`` (clock s, m, m, rad): a ``foxglove.PoseInFrame`` and a
        ``foxglove.FrameTransform`` each (formatted directly: the hot path of a run)."""
        if self._pose < 0:
            if not len(rows):
                return
            self._pose = self._channel(
                "/mocap/pose", POSE_IN_FRAME, "geometry_msgs/msg/PoseStamped"
            )
            self._tf = self._channel("/tf", FRAME_TRANSFORM, "tf2_msgs/msg/TFMessage")
        if self._ros2 is not None:
            self._ros2_poses(self._ros2, rows)
            return
        for t, x, y, yaw in rows.tolist():
            ns = self.ns(t)
            stamp = f'{{"sec":{ns // 1_000_000_000},"nsec":{ns % 1_000_000_000}}}'
            p = f'{{"x":{_num(x)},"y":{_num(y)},"z":0.0}}'
            q = f'{{"x":0.0,"y":0.0,"z":{_num(math.sin(yaw / 2))},"w":{_num(math.cos(yaw / 2))}}}'
            self._raw(
                self._pose,
                ns,
                f'{{"timestamp":{stamp},"frame_id":"{WORLD}",'
                f'"pose":{{"position":{p},"orientation":{q}}}}}',
            )
            self._raw(
                self._tf,
                ns,
                f'{{"timestamp":{stamp},"parent_frame_id":"{WORLD}","child_frame_id":"{ROBOT}",'
                f'"translation":{p},"rotation":{q}}}',
            )

    def _ros2_poses(self, r: _Ros2, rows: FloatArray) -> None:
        T = r.T
        for t, x, y, yaw in rows.tolist():
            ns = self.ns(t)
            q = T["geometry_msgs/msg/Quaternion"](
                x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)
            )
            pose = T["geometry_msgs/msg/PoseStamped"](
                header=r.header(ns, WORLD),
                pose=T["geometry_msgs/msg/Pose"](
                    position=T["geometry_msgs/msg/Point"](x=x, y=y, z=0.0), orientation=q
                ),
            )
            self._bytes(self._pose, ns, r.cdr(pose, "geometry_msgs/msg/PoseStamped"))
            tf = T["tf2_msgs/msg/TFMessage"](transforms=[T["geometry_msgs/msg/TransformStamped"](
                header=r.header(ns, WORLD), child_frame_id=ROBOT,
                transform=T["geometry_msgs/msg/Transform"](
                    translation=T["geometry_msgs/msg/Vector3"](x=x, y=y, z=0.0), rotation=q
                ),
            )])  # fmt: skip
            self._bytes(self._tf, ns, r.cdr(tf, "tf2_msgs/msg/TFMessage"))

    def robot_description(self, params: RobotParams, base_link: BaseLink | None, t: float) -> None:
        """The robot as the exports see it, once at clock time ``t``: ``/tf_static`` the
        transform R -> ``base_link`` (the robot config's, :func:`~swpc_hw.robot.frames.
        base_link_transform`; the identity when it sets none) and ``/robot_description``
        the URDF of ``params`` in base_link (``swpc export --to urdf``'s), so the frame
        tree goes on from W -> R to the robot's own frames and Foxglove draws the modules."""
        urdf = render_urdf(make_export(
            KinematicFile(params=params, created=""), base_link, "the run's nominal robot"
        ))  # fmt: skip
        phi, tr, _ = base_link_transform(params.arrays().P_s, base_link)
        # base_link's pose in R: p_bl = rot(phi) p_R + t, so its origin is -rot(-phi) t
        c, s_ = math.cos(phi), math.sin(phi)
        ox, oy = -(c * tr[0] + s_ * tr[1]), -(-s_ * tr[0] + c * tr[1])
        qz, qw = math.sin(-phi / 2), math.cos(-phi / 2)
        ns = self.ns(t)
        tf = self._channel("/tf_static", FRAME_TRANSFORM, "tf2_msgs/msg/TFMessage")
        desc = self._channel("/robot_description", STRING, "std_msgs/msg/String")
        if self._ros2 is not None:
            r, T = self._ros2, self._ros2.T
            msg = T["tf2_msgs/msg/TFMessage"](transforms=[T["geometry_msgs/msg/TransformStamped"](
                header=r.header(ns, ROBOT), child_frame_id=BASE_LINK,
                transform=T["geometry_msgs/msg/Transform"](
                    translation=T["geometry_msgs/msg/Vector3"](x=ox, y=oy, z=0.0),
                    rotation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=qz, w=qw),
                ),
            )])  # fmt: skip
            self._bytes(tf, ns, r.cdr(msg, "tf2_msgs/msg/TFMessage"))
            text = T["std_msgs/msg/String"](data=urdf)
            self._bytes(desc, ns, r.cdr(text, "std_msgs/msg/String"))
            return
        self._add(tf, ns, {
            "timestamp": _stamp(ns), "parent_frame_id": ROBOT, "child_frame_id": BASE_LINK,
            "translation": {"x": ox, "y": oy, "z": 0.0},
            "rotation": {"x": 0.0, "y": 0.0, "z": qz, "w": qw},
        })  # fmt: skip
        self._add(desc, ns, {"data": urdf})

    def circles(self, t: float, circles: list[tuple[int, float, float, float]]) -> None:
        """The fitted circle of each spin, once at clock time ``t``: ``(module, cx, cy,
        radius)``, the path of R's origin about the spin's fixed point in W (a line loop of
        :data:`CIRCLE_POINTS` points in the module's colour, the run plot's)."""
        if not circles:
            return
        ns = self.ns(t)
        ch = self._channel(
            "/calibration/circles", SCENE_UPDATE, "visualization_msgs/msg/MarkerArray"
        )
        a = np.linspace(0.0, 2 * math.pi, CIRCLE_POINTS, endpoint=False)
        loops = [
            (m, [(cx + r * math.cos(x), cy + r * math.sin(x)) for x in a.tolist()])
            for m, cx, cy, r in circles
        ]
        if self._ros2 is not None:
            rs, T = self._ros2, self._ros2.T
            markers = [T["visualization_msgs/msg/Marker"](
                header=rs.header(ns, WORLD), ns="swpc_spins", id=k, type=4, action=0,  # strip
                pose=T["geometry_msgs/msg/Pose"](
                    position=T["geometry_msgs/msg/Point"](x=0.0, y=0.0, z=0.0),
                    orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
                ),
                scale=T["geometry_msgs/msg/Vector3"](x=0.005, y=0.0, z=0.0),
                color=T["std_msgs/msg/ColorRGBA"](**_rgba(m)),
                lifetime=T["builtin_interfaces/msg/Duration"](sec=0, nanosec=0),
                frame_locked=False,
                points=[T["geometry_msgs/msg/Point"](x=x, y=y, z=0.0) for x, y in pts + pts[:1]],
                colors=[], texture_resource="", texture=T["sensor_msgs/msg/CompressedImage"](
                    header=rs.header(ns, ""), format="", data=np.zeros(0, dtype=np.uint8)),
                uv_coordinates=[], text="", mesh_resource="",
                mesh_file=T["visualization_msgs/msg/MeshFile"](
                    filename="", data=np.zeros(0, dtype=np.uint8)),
                mesh_use_embedded_materials=False,
            ) for k, (m, pts) in enumerate(loops)]  # fmt: skip
            msg = T["visualization_msgs/msg/MarkerArray"](markers=markers)
            self._bytes(ch, ns, rs.cdr(msg, "visualization_msgs/msg/MarkerArray"))
            return
        ident = {"position": {"x": 0.0, "y": 0.0, "z": 0.0},
                 "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}}  # fmt: skip
        entities = [{
            "timestamp": _stamp(ns), "frame_id": WORLD, "id": f"spin{k + 1}",
            "lifetime": {"sec": 0, "nsec": 0}, "frame_locked": False, "metadata": [],
            "arrows": [], "cubes": [], "spheres": [], "cylinders": [], "triangles": [],
            "texts": [], "models": [],
            "lines": [{
                "type": 1, "pose": ident, "thickness": 0.005, "scale_invariant": False,
                "points": [{"x": x, "y": y, "z": 0.0} for x, y in pts],
                "color": _rgba(m), "colors": [], "indices": [],
            }],
        } for k, (m, pts) in enumerate(loops)]  # fmt: skip
        self._add(ch, ns, {"deletions": [], "entities": entities})

    def gyro(self, rows: FloatArray) -> None:
        """Rows ``t, wz`` (clock s, rad/s) of the gyro."""
        if not rows.shape[0]:
            return
        if self._gyro is None:
            self._gyro = self._channel("/imu/gyro", GYRO, "sensor_msgs/msg/Imu")
        if self._ros2 is not None:
            from swpc_hw.sensors.gyro import GyroSample, encode_imu

            for t, wz in rows.tolist():
                ns = self.ns(t)
                self._bytes(self._gyro, ns, encode_imu(GyroSample(ns * 1e-9, wz), ROBOT))
            return
        unknown = "[-1.0,0,0,0,0,0,0,0,0]"
        for t, wz in rows.tolist():
            ns = self.ns(t)
            self._raw(
                self._gyro,
                ns,
                f'{{"header":{{"stamp":{{"sec":{ns // 1_000_000_000},'
                f'"nsec":{ns % 1_000_000_000}}},"frame_id":"{ROBOT}"}},'
                f'"orientation":{{"x":0.0,"y":0.0,"z":0.0,"w":1.0}},'
                f'"orientation_covariance":{unknown},'
                f'"angular_velocity":{{"x":0.0,"y":0.0,"z":{_num(wz)}}},'
                f'"angular_velocity_covariance":[0,0,0,0,0,0,0,0,0],'
                f'"linear_acceleration":{{"x":0.0,"y":0.0,"z":0.0}},'
                f'"linear_acceleration_covariance":{unknown}}}',
            )

    def encoders(self, module: int, rows: FloatArray) -> None:
        """Rows ``t, theta_hat, psi`` of one module."""
        ch = self._enc[module]
        names = [steer_joint(module), wheel_joint(module)]
        if self._ros2 is not None:
            r = self._ros2
            for t, th, psi in rows.tolist():
                ns = self.ns(t)
                msg = r.T["sensor_msgs/msg/JointState"](
                    header=r.header(ns, ROBOT), name=names,
                    position=np.array([th, psi], dtype=np.float64),
                    velocity=np.zeros(0), effort=np.zeros(0),
                )  # fmt: skip
                self._bytes(ch, ns, r.cdr(msg, "sensor_msgs/msg/JointState"))
            return
        head = f',"frame_id":"{ROBOT}"}},"name":{json.dumps(names)},"position":['
        for t, th, psi in rows.tolist():
            ns = self.ns(t)
            self._raw(
                ch,
                ns,
                f'{{"header":{{"stamp":{{"sec":{ns // 1_000_000_000},'
                f'"nsec":{ns % 1_000_000_000}}}{head}{_num(th)},{_num(psi)}],'
                '"velocity":[],"effort":[]}',
            )

    def segment(self, static_module: int, start: float, end: float) -> None:
        ns = self.ns(start)
        doc = {"static_module": static_module, "start": start, "end": end,
               "start_time": _stamp(ns), "end_time": _stamp(self.ns(end))}  # fmt: skip
        if self._ros2 is not None:
            msg = self._ros2.T["std_msgs/msg/String"](data=json.dumps(doc))
            self._bytes(self._seg, ns, self._ros2.cdr(msg, "std_msgs/msg/String"))
            return
        self._add(self._seg, ns, {"timestamp": _stamp(ns), **doc})

    def event(self, t: float, level: str, message: str) -> None:
        ns = self.ns(t)
        if self._ros2 is not None:
            r = self._ros2
            msg = r.T["rcl_interfaces/msg/Log"](
                stamp=r.header(ns, "").stamp, level=ROS_LOG_LEVELS.get(level, 20),
                name="swpc.run", msg=message, file="", function="", line=0,
            )  # fmt: skip
            self._bytes(self._log, ns, r.cdr(msg, "rcl_interfaces/msg/Log"))
            return
        self._add(
            self._log,
            ns,
            {
                "timestamp": _stamp(ns),
                "level": LOG_LEVELS.get(level, 2),
                "message": message,
                "name": "swpc.run",
                "file": "",
                "line": 0,
            },
        )

    def metadata(self, name: str, values: Mapping[str, object]) -> None:
        """A metadata record (MCAP metadata values are strings: others as JSON)."""
        self._w.add_metadata(
            name, {k: v if isinstance(v, str) else json.dumps(v) for k, v in values.items()}
        )

    def attach(self, name: str, data: bytes, media_type: str, t: float) -> None:
        ns = self.ns(t)
        self._w.add_attachment(
            create_time=ns, log_time=ns, name=name, media_type=media_type, data=data
        )

    def flush(self) -> None:
        """Close the chunk in progress and hand everything to the OS (a killed process
        keeps it)."""
        if not self._finished:
            self._w.flush()  # type: ignore[no-untyped-call]  # mcap: untyped

    def finish(self) -> None:
        """Write the summary and close (idempotent)."""
        if self._finished:
            return
        self._finished = True
        try:
            self._w.finish()  # type: ignore[no-untyped-call]  # mcap: untyped
        finally:
            self._fh.close()

    def abandon(self) -> None:
        """Close without a summary (after a write failed: the file is kept as it is)."""
        if not self._finished:
            self._finished = True
            with contextlib.suppress(OSError):
                self._fh.close()


def spin_circles(ds: Dataset) -> list[tuple[int, float, float, float]]:
    """``(module, cx, cy, radius)`` of each spin of ``ds`` with 3 poses or more: the
    fixed point ``C_W`` its poses give (:func:`swpc_hw.calibration.geometry.fixed_point`)
    and ``|C_R|``, the radius of R's origin's path about it."""
    out = []
    P = np.asarray(ds.poses)
    for seg in ds.segments:
        sel = (P[:, 0] >= seg.start) & (P[:, 0] <= seg.end) if P.size else np.zeros(0, bool)
        if int(sel.sum()) < 3:
            continue
        pp = P[sel, 1:].copy()
        pp[:, 2] = np.unwrap(pp[:, 2])
        C_R, C_W = geo.fixed_point(pp)
        out.append((seg.static_module, float(C_W[0]), float(C_W[1]), float(np.hypot(*C_R))))
    return out


def write_mcap(
    path: str | Path, ds: Dataset, wall_offset: float = 0.0, profile: str = "foxglove"
) -> int:
    """Write dataset ``ds`` to ``path`` in one go; returns the number of messages."""
    rec = McapRecorder(path, list(ds.robot.ids), wall_offset=wall_offset, profile=profile)
    try:
        rec.poses(np.asarray(ds.poses))
        for mid, enc in ds.encoders.items():
            rec.encoders(mid, enc)
        for s in ds.segments:
            rec.segment(s.static_module, s.start, s.end)
        if ds.segments:
            rec.circles(ds.segments[-1].end, spin_circles(ds))
    except BaseException:
        rec.abandon()
        raise
    rec.finish()
    return rec.messages
