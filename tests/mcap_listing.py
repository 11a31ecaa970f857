"""What a run's MCAP holds, as a viewer lists it: its topics with their schemas and message
counts, and the frame tree (the transforms of ``/tf`` and ``/tf_static``, then the
joints of the URDF on ``/robot_description``), read by mcap's own reader (Foxglove's
library).  Used by the whole-run tests of a motion-capture and of a gyro run."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from pathlib import Path

from mcap.reader import make_reader


def mcap_listing(path: Path) -> tuple[dict[str, tuple[str, int]], set[tuple[str, str]], str]:
    """``(topic -> (schema, messages), frame tree edges (parent, child), printed)`` of
    the default (JSON) profile's file at ``path``."""
    topics: dict[str, tuple[str, int]] = {}
    edges: set[tuple[str, str]] = set()
    with path.open("rb") as fh:
        reader = make_reader(fh)
        for schema, channel, message in reader.iter_messages():
            name = schema.name if schema is not None else "-"
            topics[channel.topic] = (name, topics.get(channel.topic, (name, 0))[1] + 1)
            if channel.topic in ("/tf", "/tf_static"):
                doc = json.loads(message.data)
                edges.add((doc["parent_frame_id"], doc["child_frame_id"]))
            elif channel.topic == "/robot_description":
                urdf = ET.fromstring(json.loads(message.data)["data"])
                for joint in urdf.iter("joint"):
                    parent, child = joint.find("parent"), joint.find("child")
                    assert parent is not None and child is not None
                    edges.add((parent.attrib["link"], child.attrib["link"]))
    lines = [f"{t}: {s} ({n} messages)" for t, (s, n) in sorted(topics.items())]
    lines += ["frame tree: " + ", ".join(f"{p} -> {c}" for p, c in sorted(edges))]
    return topics, edges, "\n".join(lines)
