"""Motion-capture pose messages: the native encoding and ROS 2 CDR ``PoseStamped``.

Two encodings travel on the pose key (``mocap/<robot>/pose``):

* **native** (``swpc-pose/1``, zenoh encoding ``application/x-swpc-pose``): 72 bytes,
  little endian::

      offset  type      field
      0       char[4]   magic "SWPP"
      4       uint32    seq        rolling sample counter
      8       float64   t          source timestamp (s, mocap clock)
      16      float64   x, y, z    position of R in W (m)
      40      float64   qx, qy, qz, qw   orientation of R in W (unit quaternion)

* **ros2-cdr** (zenoh encoding ``application/cdr``): a CDR-serialised
  ``geometry_msgs/msg/PoseStamped`` exactly as zenoh-bridge-ros2dds forwards it from a
  ROS 2 mocap driver; (de)serialised with rosbags' type store, never by hand.

:func:`decode_pose` detects the encoding from the payload (the native magic, or the
CDR encapsulation header) unless told.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from enum import StrEnum
from typing import Any

from swpc_hw.errors import SwpcError

NATIVE_MAGIC = b"SWPP"
_NATIVE = struct.Struct("<4sId3d4d")
NATIVE_ENCODING = "application/x-swpc-pose"
CDR_ENCODING = "application/cdr"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"


def pose_key(robot: str) -> str:
    """The zenoh key of a robot's poses."""
    return f"mocap/{robot}/pose"


def source_key(robot: str) -> str:
    """The zenoh key of the status of the bridge that puts a robot's poses (``swpc mocap``,
    JSON: its source, body, rate and counts; docs/mocap-bridge.md)."""
    return f"mocap/{robot}/source"


class PoseDecodeError(SwpcError, ValueError):
    """A pose payload could not be decoded."""


class PoseEncoding(StrEnum):
    NATIVE = "native"
    CDR = "ros2-cdr"
    AUTO = "auto"


@dataclass(frozen=True)
class PoseSample:
    """A 3-D pose of R in W with its source timestamp (s)."""

    t: float
    x: float
    y: float
    z: float
    qx: float
    qy: float
    qz: float
    qw: float
    seq: int = 0
    frame_id: str = ""

    @property
    def yaw(self) -> float:
        """Heading about z: ``atan2(2 (w z + x y), 1 - 2 (y^2 + z^2))``."""
        return yaw_from_quaternion(self.qx, self.qy, self.qz, self.qw)

    @property
    def quaternion_norm(self) -> float:
        return math.sqrt(self.qx**2 + self.qy**2 + self.qz**2 + self.qw**2)

    @classmethod
    def planar(cls, t: float, x: float, y: float, yaw: float, seq: int = 0) -> PoseSample:
        """A pose in the floor plane (z = 0) with heading ``yaw``."""
        qx, qy, qz, qw = quaternion_from_yaw(yaw)
        return cls(t, x, y, 0.0, qx, qy, qz, qw, seq)


def yaw_from_quaternion(qx: float, qy: float, qz: float, qw: float) -> float:
    """Yaw (rotation about z) of a unit quaternion."""
    return math.atan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))


def quaternion_from_yaw(yaw: float) -> tuple[float, float, float, float]:
    """``(qx, qy, qz, qw) = (0, 0, sin(yaw/2), cos(yaw/2))``."""
    return 0.0, 0.0, math.sin(yaw / 2.0), math.cos(yaw / 2.0)


# ---------------------------------------------------------------------- native


def encode_native(p: PoseSample) -> bytes:
    """72-byte native message (see the module docstring)."""
    return _NATIVE.pack(
        NATIVE_MAGIC, p.seq & 0xFFFFFFFF, p.t, p.x, p.y, p.z, p.qx, p.qy, p.qz, p.qw
    )


def decode_native(payload: bytes) -> PoseSample:
    if len(payload) != _NATIVE.size:
        raise PoseDecodeError(f"native pose: expected {_NATIVE.size} bytes, got {len(payload)}")
    magic, seq, t, x, y, z, qx, qy, qz, qw = _NATIVE.unpack(payload)
    if magic != NATIVE_MAGIC:
        raise PoseDecodeError(f"native pose: bad magic {magic!r}")
    return PoseSample(t, x, y, z, qx, qy, qz, qw, seq)


# ------------------------------------------------------------------------- CDR

_TYPESTORE: Any = None


def ros2_typestore() -> Any:
    """rosbags' ROS 2 Humble type store (built once): every CDR message of swpc."""
    global _TYPESTORE
    if _TYPESTORE is None:
        from rosbags.typesys import Stores, get_typestore

        _TYPESTORE = get_typestore(Stores.ROS2_HUMBLE)
    return _TYPESTORE


_typestore = ros2_typestore


def encode_cdr(p: PoseSample, frame_id: str = "world") -> bytes:
    """CDR-serialised ``geometry_msgs/msg/PoseStamped`` (little endian, as ROS 2 sends)."""
    ts = _typestore()
    T = ts.types
    sec = math.floor(p.t)
    nanosec = min(round((p.t - sec) * 1e9), 999_999_999)
    msg = T[POSE_STAMPED](
        header=T["std_msgs/msg/Header"](
            stamp=T["builtin_interfaces/msg/Time"](sec=int(sec), nanosec=int(nanosec)),
            frame_id=p.frame_id or frame_id,
        ),
        pose=T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](x=p.x, y=p.y, z=p.z),
            orientation=T["geometry_msgs/msg/Quaternion"](x=p.qx, y=p.qy, z=p.qz, w=p.qw),
        ),
    )
    return bytes(ts.serialize_cdr(msg, POSE_STAMPED))


def decode_cdr(payload: bytes) -> PoseSample:
    try:
        msg = _typestore().deserialize_cdr(bytes(payload), POSE_STAMPED)
    except Exception as exc:  # rosbags raises several types for malformed input
        raise PoseDecodeError(f"ros2-cdr PoseStamped: {exc}") from exc
    st = msg.header.stamp
    pos, q = msg.pose.position, msg.pose.orientation
    return PoseSample(
        st.sec + st.nanosec * 1e-9, pos.x, pos.y, pos.z, q.x, q.y, q.z, q.w,
        frame_id=msg.header.frame_id,
    )


# ------------------------------------------------------------------- dispatch


def detect_encoding(payload: bytes) -> PoseEncoding:
    """Native magic, or a CDR encapsulation header (``00 00``/``00 01`` then ``00 00``)."""
    if payload[:4] == NATIVE_MAGIC:
        return PoseEncoding.NATIVE
    if len(payload) >= 4 and payload[0] == 0 and payload[1] in (0, 1):
        return PoseEncoding.CDR
    raise PoseDecodeError(f"unknown pose encoding (first bytes {payload[:4].hex()})")


def encode_pose(p: PoseSample, encoding: PoseEncoding | str) -> bytes:
    enc = PoseEncoding(encoding)
    if enc is PoseEncoding.NATIVE:
        return encode_native(p)
    if enc is PoseEncoding.CDR:
        return encode_cdr(p)
    raise ValueError("encode_pose needs a concrete encoding, not 'auto'")


def decode_pose(payload: bytes, encoding: PoseEncoding | str = PoseEncoding.AUTO) -> PoseSample:
    enc = PoseEncoding(encoding)
    if enc is PoseEncoding.AUTO:
        enc = detect_encoding(payload)
    return decode_native(payload) if enc is PoseEncoding.NATIVE else decode_cdr(payload)


def zenoh_encoding_name(encoding: PoseEncoding | str) -> str:
    return NATIVE_ENCODING if PoseEncoding(encoding) is PoseEncoding.NATIVE else CDR_ENCODING
