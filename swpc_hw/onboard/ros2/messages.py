"""The odometry's ROS 2 messages, CDR-serialised with rosbags' type store (never by hand).

* ``nav_msgs/msg/Odometry`` on ``/odom``: header ``frame_id = odom``, ``child_frame_id =
  base_link``; pose of ``base_link`` in ``odom`` with its covariance, twist of ``base_link``
  in ``base_link`` with its covariance (:mod:`swpc_hw.onboard.ros2.covariance`);
* ``tf2_msgs/msg/TFMessage`` on ``/tf``: one transform ``odom -> base_link``, the same pose;
* ``diagnostic_msgs/msg/DiagnosticArray`` on ``/diagnostics`` when a calibration suspect is
  raised or cleared (:mod:`swpc_hw.onboard.drift`): one status ``swpc: calibration``, level WARN
  while any suspect stands (OK otherwise), a key/value per field of each suspect's evidence.

The odometry integrates the pose of the frame its parameters are in: base_link
(:func:`swpc_hw.onboard.ros2.stream.load_in_base_link`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from swpc_hw.sensors.mocap import ros2_typestore

ODOMETRY = "nav_msgs/msg/Odometry"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
DIAGNOSTIC_ARRAY = "diagnostic_msgs/msg/DiagnosticArray"
CALIBRATION_STATUS = "swpc: calibration"
ODOM_FRAME = "odom"
BASE_LINK = "base_link"


@dataclass(frozen=True)
class PlanarState:
    """Pose ``(x, y, yaw)`` of a frame in ``odom`` and its body twist ``(v_x, v_y, omega)``."""

    x: float
    y: float
    yaw: float
    vx: float
    vy: float
    omega: float


def stamp(t: float) -> tuple[int, int]:
    """``(sec, nanosec)`` of a time in seconds (nanosec in [0, 1e9))."""
    ns = round(t * 1e9)
    return ns // 1_000_000_000, ns % 1_000_000_000


def _header(t: float, frame_id: str) -> object:
    T = ros2_typestore().types
    sec, nsec = stamp(t)
    return T["std_msgs/msg/Header"](
        stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec), frame_id=frame_id
    )


def _quaternion(yaw: float) -> object:
    T = ros2_typestore().types
    return T["geometry_msgs/msg/Quaternion"](
        x=0.0, y=0.0, z=math.sin(yaw / 2.0), w=math.cos(yaw / 2.0)
    )


def odometry_cdr(t: float, s: PlanarState, pose_covariance: Sequence[float],
                 twist_covariance: Sequence[float]) -> bytes:
    """CDR ``nav_msgs/msg/Odometry`` (covariances: ROS's row-major 6 x 6, 36 values)."""
    ts = ros2_typestore()
    T = ts.types
    msg = T[ODOMETRY](
        header=_header(t, ODOM_FRAME),
        child_frame_id=BASE_LINK,
        pose=T["geometry_msgs/msg/PoseWithCovariance"](
            pose=T["geometry_msgs/msg/Pose"](
                position=T["geometry_msgs/msg/Point"](x=s.x, y=s.y, z=0.0),
                orientation=_quaternion(s.yaw),
            ),
            covariance=np.asarray(pose_covariance, dtype=np.float64),
        ),
        twist=T["geometry_msgs/msg/TwistWithCovariance"](
            twist=T["geometry_msgs/msg/Twist"](
                linear=T["geometry_msgs/msg/Vector3"](x=s.vx, y=s.vy, z=0.0),
                angular=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=s.omega),
            ),
            covariance=np.asarray(twist_covariance, dtype=np.float64),
        ),
    )
    return bytes(ts.serialize_cdr(msg, ODOMETRY))


def tf_cdr(t: float, s: PlanarState) -> bytes:
    """CDR ``tf2_msgs/msg/TFMessage`` with the one transform ``odom -> base_link``."""
    ts = ros2_typestore()
    T = ts.types
    msg = T[TF_MESSAGE](
        transforms=[
            T["geometry_msgs/msg/TransformStamped"](
                header=_header(t, ODOM_FRAME),
                child_frame_id=BASE_LINK,
                transform=T["geometry_msgs/msg/Transform"](
                    translation=T["geometry_msgs/msg/Vector3"](x=s.x, y=s.y, z=0.0),
                    rotation=_quaternion(s.yaw),
                ),
            )
        ]
    )
    return bytes(ts.serialize_cdr(msg, TF_MESSAGE))


def diagnostic_cdr(t: float, evidence: Sequence[Mapping[str, object]]) -> bytes:
    """CDR ``diagnostic_msgs/msg/DiagnosticArray``: the status :data:`CALIBRATION_STATUS`,
    WARN with ``evidence`` (each suspect's fields, keys prefixed ``<i>.``), OK if none."""
    ts = ros2_typestore()
    T = ts.types
    values = [
        T["diagnostic_msgs/msg/KeyValue"](key=f"{i}.{k}", value=str(v))
        for i, ev in enumerate(evidence) for k, v in ev.items()
    ]
    status = T["diagnostic_msgs/msg/DiagnosticStatus"](
        level=1 if evidence else 0,  # WARN / OK (a byte)
        name=CALIBRATION_STATUS,
        message="calibration suspect" if evidence else "calibration consistent",
        hardware_id="",
        values=values,
    )
    msg = T[DIAGNOSTIC_ARRAY](header=_header(t, ""), status=[status])
    return bytes(ts.serialize_cdr(msg, DIAGNOSTIC_ARRAY))


__all__ = [
    "BASE_LINK",
    "CALIBRATION_STATUS",
    "DIAGNOSTIC_ARRAY",
    "ODOMETRY",
    "ODOM_FRAME",
    "TF_MESSAGE",
    "PlanarState",
    "diagnostic_cdr",
    "odometry_cdr",
    "stamp",
    "tf_cdr",
]
