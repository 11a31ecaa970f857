"""The zenoh edge: puts the stream's messages where a rmw_zenoh node subscribes.

:class:`ZenohRos2Publisher` is a :data:`~swpc_hw.onboard.ros2.stream.Sink` on an open zenoh session
(:func:`swpc_hw.sensors.zenoh_session.open_session`: peer mode, multicast scouting off, explicit
endpoints).  Per topic it declares a zenoh publisher on the rmw_zenoh data key and a
liveliness token; per put it attaches the sequence number, the source timestamp and the
publisher's GID (:mod:`swpc_hw.onboard.ros2.wire`).  A ROS 2 host reaches it through its zenoh
router (``ros2 run rmw_zenoh_cpp rmw_zenohd``) by connecting one of them to the other.
"""

from __future__ import annotations

import uuid
from typing import Any

import zenoh

from swpc_hw.onboard.ros2.wire import Attachment, node_token, publisher_token, topic_key

NODE = "swpc_odometry"
DEPTHS = {"/tf": 100}  # tf2's broadcaster QoS; every other topic keeps 10


class ZenohRos2Publisher:
    """rmw_zenoh publishers of one node on a zenoh session (module docstring)."""

    def __init__(self, session: Any, *, domain_id: int = 0, namespace: str = "",
                 node: str = NODE, block: bool = False) -> None:
        """``block``: a full transmission queue blocks the put (zenoh's congestion control
        BLOCK) instead of dropping the message (DROP, the default: rmw_zenoh's for a
        keep-last history, what odometry and TF publishers use; the odometry never waits
        on the network).  A test that counts every message blocks."""
        self._session = session
        self.block = block
        self.domain_id = domain_id
        self.namespace = namespace
        self.node = node
        self._zid = str(session.info.zid())
        self._tokens = [session.liveliness().declare_token(
            node_token(self._zid, node, domain_id=domain_id, namespace=namespace)
        )]  # fmt: skip
        self._pubs: dict[str, tuple[Any, bytes, list[int]]] = {}

    def key(self, topic: str, ros_type: str) -> str:
        return topic_key(topic, ros_type, domain_id=self.domain_id, namespace=self.namespace)

    def _publisher(self, topic: str, ros_type: str) -> tuple[Any, bytes, list[int]]:
        found = self._pubs.get(topic)
        if found is None:
            entity = len(self._pubs) + 1
            self._tokens.append(self._session.liveliness().declare_token(publisher_token(
                self._zid, self.node, topic, ros_type, entity_id=entity,
                depth=DEPTHS.get(topic, 10), domain_id=self.domain_id,
                namespace=self.namespace,
            )))  # fmt: skip
            pub = self._session.declare_publisher(
                self.key(topic, ros_type),
                congestion_control=zenoh.CongestionControl.BLOCK
                if self.block else zenoh.CongestionControl.DROP,
            )
            found = (pub, uuid.uuid4().bytes, [0])
            self._pubs[topic] = found
        return found

    def matched(self, topic: str, ros_type: str) -> bool:
        """Whether a subscriber (a ROS 2 node, a router) matches the topic's key now."""
        pub, _, _ = self._publisher(topic, ros_type)
        return bool(pub.matching_status.matching)

    def __call__(self, topic: str, ros_type: str, stamp: float, payload: bytes) -> None:
        pub, gid, seq = self._publisher(topic, ros_type)
        seq[0] += 1
        att = Attachment(seq[0], round(stamp * 1e9), gid).encode()
        pub.put(payload, attachment=att)

    def close(self) -> None:
        for pub, _, _ in self._pubs.values():
            pub.undeclare()
        for tok in self._tokens:
            tok.undeclare()
        self._pubs.clear()
        self._tokens.clear()


__all__ = ["NODE", "ZenohRos2Publisher"]
