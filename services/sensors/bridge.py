"""``swpc mocap``: a lab's motion capture onto swpc's pose key (docs/mocap-bridge.md).

A bridge runs on the lab's motion-capture PC (or beside it), not on the robot.  It reads
one rigid body from a vendor's stream through a client library swpc did not write, turns
it into swpc's frame and units (:mod:`swpc_hw.sensors.bridge`) and publishes it on the
robot's key ``mocap/<robot>/pose`` in swpc's native encoding, through the same zenoh
session settings (and user-password authentication) as the rest of swpc's traffic.

Sources (``--source``):

* ``qtm://HOST[:PORT]``: Qualisys Track Manager's real-time protocol through Qualisys'
  ``qtm-rt`` (little-endian port, 22223 by default).  Each pose carries QTM's capture time
  (its data packets' time stamp, us): the service maps it to its clock with
  ``SWPC_MOCAP_CLOCK=source``; frame numbers give the frames dropped on the way.
* ``vicon://HOST``, ``optitrack://HOST``, ``vrpn://HOST``, ``qualisys://HOST``, ``mock://``:
  Bitcraze's ``motioncapture`` (libmotioncapture), which gives neither a capture time nor a
  frame number: the bridge's receipt time (this host's wall clock) stamps the pose and no
  drop is counted.  OptiTrack's NatNet default is multicast: configure Motive for unicast.

The bridge refuses to publish a body it has not seen and says which bodies the system
has; it prints its counts (:class:`swpc_hw.sensors.bridge.FrameCount`) every
``report_every`` seconds.
"""

from __future__ import annotations

import asyncio
import json
import math
import threading
import time
import xml.etree.ElementTree as ET
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any
from urllib.parse import urlsplit

from swpc_hw.errors import SwpcError
from swpc_hw.sensors.bridge import (
    UNITS,
    BodyFrame,
    FrameCount,
    Up,
    planar_pose,
    rotation_rows,
    rows_from_column_major,
)
from swpc_hw.sensors.mocap import NATIVE_ENCODING, PoseSample, encode_native

QTM_PORT = 22223
"""QTM's little-endian real-time port."""
LIBRARY_KINDS = ("vicon", "optitrack", "vrpn", "qualisys", "mock")
"""The ``motioncapture`` library's systems the bridge offers."""
STATUS_EVERY = 1.0
"""Wall seconds between two status documents of a bridge (on ``mocap/<robot>/source``)."""
NOT_SEEN_AFTER = 100
"""Frames in a row without the body before the bridge says so (1 s at 100 Hz)."""


class BridgeError(SwpcError):
    """The bridge cannot read the source (named) or the body is not in it."""


@dataclass(frozen=True)
class Source:
    """Where the poses come from: ``kind`` (``qtm`` or one of :data:`LIBRARY_KINDS`),
    ``host``, ``port`` (None: the kind's default)."""

    kind: str
    host: str
    port: int | None = None

    @classmethod
    def parse(cls, text: str) -> Source:
        """``qtm://127.0.0.1:22223``, ``vicon://10.0.0.5``, ``mock://``."""
        u = urlsplit(text)
        kind = u.scheme.lower()
        if kind != "qtm" and kind not in LIBRARY_KINDS:
            raise BridgeError(
                f"--source {text!r}: the kind must be one of qtm, {', '.join(LIBRARY_KINDS)} "
                "(e.g. qtm://192.0.2.10)"
            )
        if not u.hostname and kind != "mock":
            raise BridgeError(f"--source {text!r}: no host (e.g. {kind}://192.0.2.10)")
        try:
            port = u.port
        except ValueError as exc:
            raise BridgeError(f"--source {text!r}: {exc}") from None
        return cls(kind, u.hostname or "", port)


@dataclass
class Bridge:
    """One body of one source onto one publisher.

    ``publish(payload)`` sends a native pose (the caller's zenoh publisher);
    ``clock()`` is this host's wall clock (the receipt time of a source without its own
    capture time); ``say(line)`` reports (stdout in the CLI)."""

    source: Source
    body: str
    publish: Callable[[bytes], None]
    up: Up = "z"
    units: str = "mm"
    clock: Callable[[], float] = time.time
    say: Callable[[str], None] = print
    report_every: float = 5.0
    status: Callable[[bytes], None] | None = None
    """Publishes :meth:`status_document` as JSON every :data:`STATUS_EVERY` s and when
    the body appears or goes (the service shows it and refuses to start without it)."""
    count: FrameCount = field(default_factory=FrameCount)
    bodies: list[str] = field(default_factory=list)
    _stop: threading.Event = field(default_factory=threading.Event, init=False, repr=False)
    _seq: int = field(default=0, init=False, repr=False)
    _unseen_run: int = field(default=0, init=False, repr=False)
    _said: float = field(default=0.0, init=False, repr=False)
    _status_at: float = field(default=-math.inf, init=False, repr=False)
    _seen: bool | None = field(default=None, init=False, repr=False)

    def __post_init__(self) -> None:
        if self.units not in UNITS:
            raise BridgeError(f"units {self.units!r}: one of {', '.join(UNITS)}")

    # ------------------------------------------------------------------ per frame
    def on_frame(self, frame: BodyFrame | None, number: int | None = None) -> PoseSample | None:
        """One frame of the source: ``frame`` the body (None: absent from this frame);
        the pose sent, or None."""
        now = self.clock()
        seen = frame is not None and frame.seen
        n = number if number is not None else (frame.frame if frame is not None else 0)
        self.count.frame(n, now, seen)
        self._send_status(now, seen)
        if not seen or frame is None:
            self._unseen_run += 1
            if self._unseen_run == NOT_SEEN_AFTER:
                self.say(
                    f"body {self.body!r} not seen for {NOT_SEEN_AFTER} frames (the system "
                    f"has: {', '.join(self.bodies) or 'no bodies'})"
                )
            self._report(now)
            return None
        self._unseen_run = 0
        t = frame.capture_time if frame.capture_time is not None else now
        pose = planar_pose(frame, self.up, UNITS[self.units], t, self._seq)
        self._seq += 1
        self.publish(encode_native(pose))
        self.count.sent += 1
        self._report(now)
        return pose

    def status_document(self) -> dict[str, Any]:
        """What the bridge says of itself: its source, body and conversion, the frame rate
        it receives, its counts, whether the last frame had the body, the bodies the system
        has."""
        c = self.count
        port = "" if self.source.port is None else f":{self.source.port}"
        return {
            "source": f"{self.source.kind}://{self.source.host}{port}",
            "body": self.body, "up": self.up, "units": self.units,
            "rate_hz": round(c.rate(), 1), "frames": c.frames, "dropped": c.dropped,
            "not_seen": c.not_seen, "sent": c.sent, "seen": bool(self._seen),
            "bodies": list(self.bodies),
        }  # fmt: skip

    def _send_status(self, now: float, seen: bool) -> None:
        if self.status is None:
            return
        changed = self._seen is None or seen != self._seen
        self._seen = seen
        if changed or now - self._status_at >= STATUS_EVERY:
            self._status_at = now
            self.status(json.dumps(self.status_document()).encode())

    def _report(self, now: float) -> None:
        if self.report_every > 0 and now - self._said >= self.report_every:
            self._said = now
            self.say(f"{self.source.kind} {self.body!r}: {self.count.line()}")

    def stop(self) -> None:
        self._stop.set()

    @property
    def stopping(self) -> bool:
        """:meth:`stop` was called."""
        return self._stop.is_set()

    # ------------------------------------------------------------------ sources
    def run(self, duration: float = 0.0) -> None:
        """Bridge until :meth:`stop` (or ``duration`` s, 0: no end)."""
        if duration > 0:
            threading.Timer(duration, self.stop).start()
        if self.source.kind == "qtm":
            asyncio.run(self._run_qtm())
        else:
            self._run_library()

    async def _run_qtm(self) -> None:
        import qtm_rt

        port = self.source.port or QTM_PORT
        where = f"QTM at {self.source.host}:{port}"
        conn = await qtm_rt.connect(self.source.host, port=port, timeout=5)
        if conn is None:
            raise BridgeError(f"{where}: no connection (is QTM running, its RT port {port}?)")
        try:
            xml = await conn.get_parameters(parameters=["6d"])
            self.bodies = [
                (n.text or "").strip() for n in ET.fromstring(xml).findall("*/Body/Name")
            ]
            if self.body not in self.bodies:
                raise BridgeError(
                    f"{where}: no 6DOF body {self.body!r} (its bodies: "
                    f"{', '.join(self.bodies) or 'none'})"
                )
            index = self.bodies.index(self.body)

            def on_packet(packet: Any) -> None:
                got = packet.get_6d()
                frame = None
                if got is not None and index < len(got[1]):
                    position, rotation = got[1][index]
                    frame = BodyFrame(
                        self.body, int(packet.framenumber),
                        (position.x, position.y, position.z),
                        rows_from_column_major(rotation.matrix),
                        capture_time=packet.timestamp * 1e-6,
                    )  # fmt: skip
                self.on_frame(frame, int(packet.framenumber))

            await conn.stream_frames(components=["6d"], on_packet=on_packet)
            while not self._stop.is_set() and conn.has_transport():
                await asyncio.sleep(0.05)
            if conn.has_transport():
                await conn.stream_frames_stop()
            elif not self._stop.is_set():
                raise BridgeError(f"{where}: the connection was closed")
        finally:
            if conn.has_transport():
                conn.disconnect()

    def _run_library(self) -> None:
        import motioncapture

        cfg = {"hostname": self.source.host} if self.source.host else {}
        if self.source.port is not None:
            cfg["port"] = str(self.source.port)
        try:
            mc = motioncapture.connect(self.source.kind, cfg)
        except RuntimeError as exc:
            raise BridgeError(f"{self.source.kind} at {self.source.host}: {exc}") from None
        n = 0
        while not self._stop.is_set():
            mc.waitForNextFrame()
            n += 1
            bodies = mc.rigidBodies
            self.bodies = sorted(bodies)
            b = bodies.get(self.body)
            frame = None
            if b is not None:
                q = b.rotation  # unit quaternion (w, x, y, z)
                frame = BodyFrame(
                    self.body,
                    n,
                    tuple(float(v) for v in b.position),  # type: ignore[arg-type]
                    rotation_rows(q.w, q.x, q.y, q.z),
                )
            self.on_frame(frame, n)


def zenoh_publisher(
    session: Any, key: str, encoding: str = NATIVE_ENCODING
) -> Callable[[bytes], None]:
    """``publish(payload)`` on ``key`` (the native pose encoding unless told)."""
    pub = session.declare_publisher(key, encoding=encoding)
    return lambda payload: pub.put(payload)
