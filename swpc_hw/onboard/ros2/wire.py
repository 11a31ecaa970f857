"""rmw_zenoh's wire format: key expressions, the attachment and liveliness tokens.

Followed: **rmw_zenoh_cpp 0.2.x for ROS 2 Jazzy** (:data:`RMW_ZENOH_VERSION`), as its
``docs/design.md`` describes it, from the release that carries "Change serialization
format in attachment_helpers.cpp" (ros2/rmw_zenoh#601, in Jazzy's 0.2 line as in Humble's
0.1.2).  A ROS 2 node with ``RMW_IMPLEMENTATION=rmw_zenoh_cpp`` subscribes to exactly these
keys.

Data key of a topic (``design.md``, "Topic and Service name mapping to Zenoh key
expressions")::

    <domain_id>/<fully_qualified_name without its leading '/'>/<type_name>/<type_hash>

with ``type_name`` the DDS name (``nav_msgs/msg/Odometry`` ->
``nav_msgs::msg::dds_::Odometry_``) and ``type_hash`` the REP-2016 hash ``RIHS01_<sha256>``
of the type description (:data:`TYPE_HASHES`).  The payload is the CDR-serialised message
(with its 4-byte encapsulation header, as ``rmw_serialize`` produces it).

Attachment of every put (``design.md``, "Publishers"; zenoh's ``ext`` serializer, little
endian)::

    offset  size  field
    0       8     sequence_number   int64, 1 for the first message of the publisher
    8       8     source_timestamp  int64, ns since the UNIX epoch
    16      1     length of the GID (LEB128: 16 -> 0x10)
    17      16    publisher GID     16 bytes, random per publisher

Liveliness tokens (``design.md``, "Graph Cache"), so that ``ros2 topic list`` on a
rmw_zenoh host sees the node and its publishers (names mangled: ``/`` -> ``%``)::

    @ros2_lv/<domain_id>/<zid>/<node_id>/<node_id>/NN/%/<namespace>/<node>
    @ros2_lv/<domain_id>/<zid>/<node_id>/<entity_id>/MP/%/<namespace>/<node>/<topic>/<type_name>/<type_hash>/<qos>

``qos`` in rmw_zenoh's compact form ``<reliability>:<durability>:<history>,<depth>:...``;
empty fields are the defaults (reliable, volatile, keep last), e.g. ``::,10:,:,:,,``.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from swpc_hw.errors import SwpcError

RMW_ZENOH_VERSION = "rmw_zenoh_cpp 0.2.x (ROS 2 Jazzy), docs/design.md"
"""The rmw_zenoh release whose wire format this module follows (module docstring)."""

ADMIN_SPACE = "@ros2_lv"
GID_SIZE = 16  # RMW_GID_STORAGE_SIZE in Jazzy

TYPE_HASHES: dict[str, str] = {
    # REP-2016 hashes of the Jazzy type descriptions.  tests/onboard/test_ros2_odometry.py
    # recomputes
    # them (rosbags' Jazzy type store, and zenoh-ros2-sdk's own implementation) and checks
    # them against values published for Jazzy (docs/ros2.md).
    "nav_msgs/msg/Odometry":
        "RIHS01_3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0",
    "tf2_msgs/msg/TFMessage":
        "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087",
    # the two implementations agree on this one; no published value checked yet
    "diagnostic_msgs/msg/DiagnosticArray":
        "RIHS01_5a8a36efb05fb25070fa0fb3810290c0e6cd4862b54a8fb975a1ee8dc55a333e",
}  # fmt: skip

_ATTACHMENT = struct.Struct("<qqB")


class Ros2WireError(SwpcError, ValueError):
    """A name, a type or an attachment does not fit rmw_zenoh's format."""


def dds_type_name(ros_type: str) -> str:
    """``pkg/msg/Name`` -> ``pkg::msg::dds_::Name_`` (the type name rmw_zenoh puts in keys)."""
    parts = ros_type.split("/")
    if len(parts) != 3 or not all(parts):
        raise Ros2WireError(f"ROS 2 type {ros_type!r}: expected 'package/msg/Name'")
    pkg, kind, name = parts
    return f"{pkg}::{kind}::dds_::{name}_"


def type_hash(ros_type: str) -> str:
    """The RIHS01 hash of a type this module knows (:data:`TYPE_HASHES`)."""
    try:
        return TYPE_HASHES[ros_type]
    except KeyError:
        raise Ros2WireError(f"no type hash known for {ros_type!r}") from None


def fully_qualified_name(topic: str, namespace: str = "") -> str:
    """``/ns/topic`` of a topic name (absolute names stay as they are)."""
    if not topic or topic.endswith("/") or "//" in topic:
        raise Ros2WireError(f"topic name {topic!r} is not a ROS 2 name")
    if topic.startswith("/"):
        return topic
    ns = "/" + namespace.strip("/") if namespace.strip("/") else ""
    return f"{ns}/{topic}"


def topic_key(topic: str, ros_type: str, *, domain_id: int = 0, namespace: str = "") -> str:
    """The data key expression of a topic (module docstring), e.g.
    ``0/odom/nav_msgs::msg::dds_::Odometry_/RIHS01_3cc9...``."""
    if domain_id < 0:
        raise Ros2WireError(f"ROS domain id must be >= 0 (got {domain_id})")
    fq = fully_qualified_name(topic, namespace)
    return f"{domain_id}/{fq.lstrip('/')}/{dds_type_name(ros_type)}/{type_hash(ros_type)}"


def mangle(name: str) -> str:
    """A name in a liveliness token: ``/`` -> ``%``; the empty (global) namespace is ``%``."""
    return name.replace("/", "%") if name.strip("/") else "%"


def node_token(zid: str, node: str, *, domain_id: int = 0, namespace: str = "",
               node_id: int = 0) -> str:
    """The liveliness token of a node (module docstring)."""
    ns = mangle("/" + namespace.strip("/") if namespace.strip("/") else "")
    return f"{ADMIN_SPACE}/{domain_id}/{zid}/{node_id}/{node_id}/NN/%/{ns}/{node}"


def publisher_token(zid: str, node: str, topic: str, ros_type: str, *, entity_id: int,
                    depth: int = 10, domain_id: int = 0, namespace: str = "",
                    node_id: int = 0) -> str:
    """The liveliness token of a publisher (reliable, volatile, keep last ``depth``)."""
    ns = mangle("/" + namespace.strip("/") if namespace.strip("/") else "")
    fq = mangle(fully_qualified_name(topic, namespace))
    return (
        f"{ADMIN_SPACE}/{domain_id}/{zid}/{node_id}/{entity_id}/MP/%/{ns}/{node}/{fq}/"
        f"{dds_type_name(ros_type)}/{type_hash(ros_type)}/::,{depth}:,:,:,,"
    )


@dataclass(frozen=True)
class Attachment:
    """What rmw_zenoh attaches to every message (module docstring)."""

    sequence_number: int
    source_timestamp: int  # ns since the UNIX epoch
    gid: bytes

    def encode(self) -> bytes:
        if len(self.gid) != GID_SIZE:
            raise Ros2WireError(f"a GID has {GID_SIZE} bytes (got {len(self.gid)})")
        return _ATTACHMENT.pack(self.sequence_number, self.source_timestamp, GID_SIZE) + bytes(
            self.gid
        )

    @classmethod
    def decode(cls, data: bytes) -> Attachment:
        if len(data) != _ATTACHMENT.size + GID_SIZE:
            raise Ros2WireError(
                f"rmw_zenoh attachment: expected {_ATTACHMENT.size + GID_SIZE} bytes, "
                f"got {len(data)}"
            )
        seq, ts, n = _ATTACHMENT.unpack_from(data)
        if n != GID_SIZE:
            raise Ros2WireError(f"rmw_zenoh attachment: GID length {n}, expected {GID_SIZE}")
        return cls(seq, ts, bytes(data[_ATTACHMENT.size:]))


__all__ = [
    "RMW_ZENOH_VERSION",
    "TYPE_HASHES",
    "Attachment",
    "Ros2WireError",
    "dds_type_name",
    "fully_qualified_name",
    "node_token",
    "publisher_token",
    "topic_key",
    "type_hash",
]
