"""Cut a dataset into the per-segment arrays the solvers consume, and check it.

Without motion capture (no poses) a segment's rotation is the gyro's and its poses are
empty.  All checks raise :class:`~swpc_hw.errors.DatasetError` with a one-line message naming
the file and the problem: a module never locked, fewer than two steering angles for a
module, a segment with no rotation, too few samples.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from swpc_hw.calibration.slip import mad_sigma
from swpc_hw.errors import DatasetError
from swpc_hw.files.dataset import Dataset, Segment
from swpc_hw.robot.model import wrap_angle

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

MIN_POSES = 10
MIN_ROTATION = np.deg2rad(10.0)
ANGLE_CLUSTER_TOL = np.deg2rad(1.0)
LOCK_TOL = np.deg2rad(2.0)


@dataclass
class SegmentData:
    """One spin about a locked module, with everything inside its window.

    ``poses``: (K, 3) rows (t, x, y, yaw) on the pose clock, yaw unwrapped.
    ``angle``: the static module's reported steering (median in the window, rad).
    """

    row: int
    segment: Segment
    static: int  # index of the static module in robot order
    angle: float
    poses: FloatArray
    inliers: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, dtype=bool))


def _encoders_in(enc: FloatArray, start: float, end: float, offset: float) -> FloatArray:
    """Encoder rows (t, steer, wheel) whose pose-clock time ``t - offset`` is in [start, end].

    Returned times are on the pose clock.
    """
    t = enc[:, 0] - offset
    sel = (t >= start) & (t <= end)
    out = enc[sel].copy()
    out[:, 0] = t[sel]
    return out


def encoders_in_window(
    ds: Dataset, module_id: int, start: float, end: float, offset: float = 0.0
) -> FloatArray:
    """Encoder rows of ``module_id`` in a pose-clock window (times shifted to the pose clock).

    ``offset`` follows the dataset convention: encoder clock minus pose clock.
    """
    return _encoders_in(ds.encoders[module_id], start, end, offset)


def prepare_segments(
    ds: Dataset, offset: float = 0.0, source: str = "dataset", calibration: bool = True
) -> list[SegmentData]:
    """Validate the dataset and return one :class:`SegmentData` per segment.

    ``calibration``: every module locked at two angles or more (a calibration starts from
    the fixed points' closed form); False for a check, which starts from the file in
    force and may lock some modules at one angle (:mod:`swpc_hw.calibration.check.verdict`)."""
    seg_file = f"{source}/segments.csv"
    ids = ds.robot.ids
    if not ds.segments:
        raise DatasetError(f"{seg_file}: no segments")
    locked = {s.static_module for s in ds.segments}
    for mid in ids:
        if calibration and mid not in locked:
            raise DatasetError(f"{seg_file}: module {mid} is never locked (no segment for it)")
    out: list[SegmentData] = []
    t_all = ds.poses[:, 0]
    for row, seg in enumerate(ds.segments):
        where = (
            f"{seg_file}: segment {row + 1} "
            f"(module {seg.static_module}, {seg.start:g}-{seg.end:g} s)"
        )
        if ds.has_poses:
            sel = (t_all >= seg.start) & (t_all <= seg.end)
            poses = ds.poses[sel].copy()
            if poses.shape[0] < MIN_POSES:
                raise DatasetError(
                    f"{where}: too few pose samples "
                    f"({poses.shape[0]} in poses.csv, need >= {MIN_POSES})"
                )
            poses[:, 3] = np.unwrap(poses[:, 3])
            rotation = abs(poses[-1, 3] - poses[0, 3])
        else:  # no motion capture: the gyro's turn (bias and scale errors are small)
            poses = np.zeros((0, 4))
            rotation = gyro_rotation(ds, seg, where)
        if rotation < MIN_ROTATION:
            raise DatasetError(
                f"{where}: no rotation (robot turned {np.rad2deg(rotation):.2f} deg, "
                f"need >= {np.rad2deg(MIN_ROTATION):.0f})"
            )
        enc = encoders_in_window(ds, seg.static_module, seg.start, seg.end, offset)
        if enc.shape[0] < 1:
            raise DatasetError(
                f"{where}: too few encoder samples of the static module in encoders.csv (0)"
            )
        steer = enc[:, 1]
        angle = float(np.median(steer))
        spread = float(np.max(np.abs(steer - angle)))
        if spread > LOCK_TOL:
            raise DatasetError(
                f"{where}: the static module is not locked (its steering moved "
                f"{np.rad2deg(spread):.1f} deg in encoders.csv)"
            )
        for mid in ids:
            if (
                mid != seg.static_module
                and encoders_in_window(ds, mid, seg.start, seg.end, offset).shape[0] < 2
            ):
                raise DatasetError(
                    f"{where}: too few encoder samples of module {mid} in encoders.csv"
                )
        out.append(SegmentData(row, seg, ids.index(seg.static_module), angle, poses))
    for mid in ids if calibration else ():
        angles = distinct_angles([s.angle for s in out if s.segment.static_module == mid])
        if len(angles) < 2:
            raise DatasetError(
                f"{seg_file}: module {mid} has {len(angles)} distinct steering angle(s) "
                f"({', '.join(f'{np.rad2deg(a):.1f}' for a in angles)} deg); need >= 2"
            )
    return out


def gyro_rotation(ds: Dataset, seg: Segment, where: str) -> float:
    """``|int wz dt|`` over a segment's window (rad): how far the gyro says it turned."""
    imu = ds.imu if ds.imu is not None else np.zeros((0, 2))
    sel = (imu[:, 0] >= seg.start) & (imu[:, 0] <= seg.end)
    if int(sel.sum()) < MIN_POSES:
        raise DatasetError(
            f"{where}: too few gyro samples ({int(sel.sum())} in imu.csv, need >= {MIN_POSES})"
        )
    t, w = imu[sel, 0], imu[sel, 1]
    return abs(float(np.sum(0.5 * (w[1:] + w[:-1]) * np.diff(t))))


def distinct_angles(angles: list[float], tol: float = float(ANGLE_CLUSTER_TOL)) -> list[float]:
    """Cluster angles (rad) closer than ``tol``; returns one representative per cluster."""
    reps: list[float] = []
    for a in sorted(angles):
        if not reps or abs(a - reps[-1]) > tol:
            reps.append(a)
    return reps


def settled_steering(
    ds: Dataset, segs: list[SegmentData], offset: float, floor: float
) -> tuple[IntArray, IntArray, FloatArray, FloatArray]:
    """Settled reported steering of every (segment, dynamic module): median and its spread.

    The median is taken on angles unwrapped around the first sample (a caster settled
    near +-pi reports both signs).  Returns ``(seg, mod, theta, sigma_theta)``.
    """
    seg, mod, theta, sig = [], [], [], []
    for si, sd in enumerate(segs):
        for j, mid in enumerate(ds.robot.ids):
            if j == sd.static:
                continue
            th = encoders_in_window(ds, mid, sd.segment.start, sd.segment.end, offset)[:, 1]
            th = th[0] + wrap_angle(th - th[0])
            seg.append(si)
            mod.append(j)
            theta.append(float(np.median(th)))
            sig.append(max(mad_sigma(th), floor))
    return (
        np.array(seg, dtype=np.int64),
        np.array(mod, dtype=np.int64),
        np.array(theta),
        np.array(sig),
    )
