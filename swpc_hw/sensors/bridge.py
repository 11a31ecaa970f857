"""A lab's motion capture into swpc's pose messages: its axes, units and frame numbers.

A motion-capture system reports a rigid body as a position ``p_M`` and a rotation matrix
``R_M`` (body axes in its frame M), in its own units and its own axis convention, with a
frame number and often its own capture time.  swpc's world frame W is z-up, in metres
(docs/model-and-frames.md).  The conversion, per frame:

    p_W = s C p_M              (s: metres per unit, 1e-3 for millimetres)
    R_W = C R_M C^T            (the body's axes were set in M's convention too)

with ``C`` the rotation from M to W: the identity for a z-up system, and for a y-up one
(OptiTrack Motive's default, Vicon or QTM set to y-up) the turn of +90 deg about x that
takes M's y (up) to W's z and M's z to W's -y:

        [1  0  0]
    C = [0  0 -1]
        [0  1  0]

The yaw of R in W is then ``atan2(R_W[1, 0], R_W[0, 0])``, and the pose sent is planar
(:meth:`swpc_hw.sensors.mocap.PoseSample.planar` keeps x, y and yaw; z and the small tilts
of a body on a floor are not used by the solver).  A body the system does not see this
frame comes as NaN (QTM) or is absent: no pose is sent, and the frame counts as *not seen*.

:class:`FrameCount` counts what arrived: frames, the frame numbers skipped (frames the
system made that never reached the bridge: *dropped*), the frames without the body, and
the rate over the last window.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from typing import Literal

from swpc_hw.sensors.mocap import PoseSample

Up = Literal["z", "y"]
UNITS: dict[str, float] = {"m": 1.0, "mm": 1e-3}
"""Metres per unit of the system's positions."""

Vec3 = tuple[float, float, float]
Mat3 = tuple[Vec3, Vec3, Vec3]
"""Rows of a 3x3 matrix."""


@dataclass(frozen=True)
class BodyFrame:
    """One rigid body in one frame of a motion-capture system, as the system says it.

    ``rotation`` by rows (``rotation[i][j]`` = R_M[i, j]); ``capture_time`` in s on the
    system's own clock (None: it gives none, the bridge's receipt time stands in)."""

    name: str
    frame: int
    position: Vec3
    rotation: Mat3
    capture_time: float | None = None

    @property
    def seen(self) -> bool:
        return all(math.isfinite(v) for v in self.position) and all(
            math.isfinite(v) for row in self.rotation for v in row
        )


def rows_from_column_major(m: tuple[float, ...] | list[float]) -> Mat3:
    """A 3x3 matrix from its 9 elements in column-major order (QTM's 6D rotation:
    r00 r10 r20 r01 r11 r21 r02 r12 r22)."""
    if len(m) != 9:
        raise ValueError(f"a rotation matrix has 9 elements, not {len(m)}")
    return (
        (float(m[0]), float(m[3]), float(m[6])),
        (float(m[1]), float(m[4]), float(m[7])),
        (float(m[2]), float(m[5]), float(m[8])),
    )


def rotation_rows(w: float, x: float, y: float, z: float) -> Mat3:
    """The rotation matrix (rows) of the unit quaternion ``w + x i + y j + z k``; NaN rows
    for a quaternion that is not one (a body the library has lost)."""
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if not math.isfinite(n) or n < 1e-9:
        nan = (math.nan, math.nan, math.nan)
        return nan, nan, nan
    w, x, y, z = w / n, x / n, y / n, z / n
    return (
        (1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)),
        (2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)),
        (2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)),
    )


def to_world(position: Vec3, rotation: Mat3, up: Up, scale: float) -> tuple[Vec3, Mat3]:
    """``(p_W, R_W)`` of the module docstring."""
    if up == "z":
        p, r = position, rotation
        return (scale * p[0], scale * p[1], scale * p[2]), r
    if up != "y":
        raise ValueError(f"up must be 'z' or 'y', not {up!r}")
    x, y, z = position
    # C p = (x, -z, y);  C R C^T: rows and columns both mapped by C
    (a, b, c), (d, e, f), (g, h, i) = rotation
    r_w = ((a, -c, b), (-g, i, -h), (d, -f, e))
    return (scale * x, -scale * z, scale * y), r_w


def planar_pose(body: BodyFrame, up: Up, scale: float, t: float, seq: int) -> PoseSample:
    """The body's planar pose in W (x, y, yaw; module docstring) at time ``t``."""
    p, r = to_world(body.position, body.rotation, up, scale)
    yaw = math.atan2(r[1][0], r[0][0])
    return PoseSample.planar(t, p[0], p[1], yaw, seq)


@dataclass
class FrameCount:
    """What a bridge received (module docstring).  ``window``: s of the rate."""

    window: float = 2.0
    frames: int = 0
    dropped: int = 0
    not_seen: int = 0
    sent: int = 0
    last_frame: int | None = None
    _times: deque[float] = field(default_factory=deque, init=False, repr=False)

    def frame(self, number: int, t: float, seen: bool) -> None:
        """A frame numbered ``number`` received at ``t`` (the bridge's clock, s)."""
        if self.last_frame is not None and number > self.last_frame + 1:
            self.dropped += number - self.last_frame - 1
        if self.last_frame is None or number > self.last_frame:
            self.last_frame = number
        self.frames += 1
        self.not_seen += not seen
        self._times.append(t)
        while self._times and self._times[0] < t - self.window:
            self._times.popleft()

    def rate(self) -> float:
        """Frames per second over the last window (0 before two frames)."""
        if len(self._times) < 2 or self._times[-1] <= self._times[0]:
            return 0.0
        return (len(self._times) - 1) / (self._times[-1] - self._times[0])

    def line(self) -> str:
        return (
            f"{self.frames} frames, {self.rate():.1f} Hz, {self.dropped} dropped, "
            f"{self.not_seen} without the body, {self.sent} poses sent"
        )
