"""A run's data as an MCAP file (opens in Foxglove): JSON channels with JSON schemas.

Channels: ``/mocap/pose`` (x, y, yaw of R in W), ``/module<id>/encoders`` (reported
steering angle and cumulative wheel angle), ``/calibration/segments`` (one message per
spin window).  Log times are the dataset's times in nanoseconds.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path

from mcap.writer import Writer

from swpc_hw.dataset import Dataset

_POSE = {
    "type": "object",
    "title": "swpc.Pose2D",
    "properties": {"x": {"type": "number"}, "y": {"type": "number"}, "yaw": {"type": "number"}},
}
_ENC = {
    "type": "object",
    "title": "swpc.ModuleEncoders",
    "properties": {"theta_hat": {"type": "number"}, "psi": {"type": "number"}},
}
_SEG = {
    "type": "object",
    "title": "swpc.Segment",
    "properties": {
        "static_module": {"type": "integer"},
        "start": {"type": "number"},
        "end": {"type": "number"},
    },
}


def _ns(t: float) -> int:
    return max(0, round(t * 1e9))


def write_mcap(path: str | Path, ds: Dataset) -> int:
    """Write ``ds`` to ``path``; returns the number of messages."""
    n = 0
    with Path(path).open("wb") as fh:
        w = Writer(fh)
        w.start(profile="", library="swpc")

        def channel(topic: str, schema: Mapping[str, object]) -> int:
            sid = w.register_schema(
                name=str(schema["title"]), encoding="jsonschema", data=json.dumps(schema).encode()
            )
            return int(w.register_channel(topic=topic, message_encoding="json", schema_id=sid))

        pose = channel("/mocap/pose", _POSE)
        for t, x, y, yaw in ds.poses.tolist():
            w.add_message(
                channel_id=pose,
                log_time=_ns(t),
                publish_time=_ns(t),
                data=json.dumps({"x": x, "y": y, "yaw": yaw}).encode(),
            )
            n += 1
        for mid, enc in ds.encoders.items():
            ch = channel(f"/module{mid}/encoders", _ENC)
            for t, th, psi in enc.tolist():
                w.add_message(
                    channel_id=ch,
                    log_time=_ns(t),
                    publish_time=_ns(t),
                    data=json.dumps({"theta_hat": th, "psi": psi}).encode(),
                )
                n += 1
        seg = channel("/calibration/segments", _SEG)
        for s in ds.segments:
            w.add_message(
                channel_id=seg,
                log_time=_ns(s.start),
                publish_time=_ns(s.start),
                data=json.dumps(
                    {"static_module": s.static_module, "start": s.start, "end": s.end}
                ).encode(),
            )
            n += 1
        w.finish()  # type: ignore[no-untyped-call]  # mcap: untyped
    return n
