"""The paper's literal procedure (Kim, Park, Park 2023, section 3) — the benchmark baseline.

Per module: the fixed point of each of its two steering angles (a circle fit to the robot
origin's trajectory, brought into R with the measured heading), then eq. (1) ``b``,
eq. (2)-(3) ``P_s``, ``beta`` from the direction ``P_s -> P1``; for each dynamic module j
of those segments, ``D = sqrt(|P_s,j - C|^2 - b_j^2)`` (right angle at the settled wheel)
and eq. (4) ``r = D |dyaw| / |dpsi|`` over the whole segment; ``r_j`` is the median of its
2(N-1) values (the paper's "robust average").

With the data given, as the paper would do it: of more than two angles the **widest
pair** (largest chord factor ``|sin(da / 2)|``, the best-conditioned eq. 1); a given
clock offset shifts the encoder times (the procedure has no way to estimate one); a
segment used must turn at least :data:`MIN_PAPER_ROTATION` (the circle fit of a short arc
is wild, and the procedure has no uncertainty to show it).  The plausibility gates of
the joint solver apply too.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from swpc_hw.calibration import geometry as geo
from swpc_hw.calibration import plausibility
from swpc_hw.calibration.fixed_point import fit_fixed_point
from swpc_hw.calibration.prepare import (
    SegmentData,
    distinct_angles,
    encoders_in_window,
    prepare_segments,
)
from swpc_hw.calibration.result import CalibrationResult, SegmentQuality
from swpc_hw.errors import CalibrationError, ImplausibleDataError
from swpc_hw.files.dataset import Dataset
from swpc_hw.robot.model import RobotParams, rot

FloatArray = NDArray[np.float64]

MIN_PAPER_ROTATION = math.radians(90.0)
"""A segment the paper's procedure uses must turn at least this much (rad)."""


def paper_fixed_point(poses: FloatArray) -> FloatArray:
    """Centre of the origin's circle (Kasa fit) in W, expressed in R for every pose, averaged.

    ``C_R = mean_i R(yaw_i)^T (C_W - p_i)``.  ``poses``: (..., K, 3) (x, y, yaw).
    """
    C_W, _ = geo.circle_fit_kasa(poses[..., :2])
    R = rot(poses[..., 2])
    d = C_W[..., None, :] - poses[..., :2]
    return np.asarray(np.einsum("...kji,...kj->...ki", R, d).mean(axis=-2), dtype=float)


def paper_fixed_point_rms(poses: FloatArray) -> float:
    """RMS length of ``p_i + R_i C_R - C_W`` about the paper's fixed point (m)."""
    C_W, _ = geo.circle_fit_kasa(poses[:, :2])
    e = geo.fixed_point_residuals(poses, paper_fixed_point(poses), C_W)
    return float(np.sqrt(np.mean(np.sum(e**2, axis=-1))))


def widest_pair(angles: list[float]) -> tuple[float, float]:
    """The two angles with the largest chord factor ``|sin((a2 - a1) / 2)|``."""
    best = max(
        ((a1, a2) for i, a1 in enumerate(angles) for a2 in angles[i + 1 :]),
        key=lambda p: abs(math.sin(0.5 * (p[1] - p[0]))),
    )
    return best


def _pair_segments(mine: list[SegmentData]) -> tuple[SegmentData, SegmentData]:
    a1, a2 = widest_pair(distinct_angles([s.angle for s in mine]))
    s1 = next(s for s in mine if abs(s.angle - a1) < np.deg2rad(1.0))
    s2 = next(s for s in mine if abs(s.angle - a2) < np.deg2rad(1.0))
    return s1, s2


def _xy(v: FloatArray) -> tuple[float, float]:
    return float(v[0]), float(v[1])


def solve_paper(
    ds: Dataset, time_offset: float = 0.0, source: str = "dataset"
) -> CalibrationResult:
    """Calibrate with the paper's literal two-angle geometry (module docstring)."""
    if not math.isfinite(time_offset):
        raise CalibrationError(f"time offset must be a finite number of seconds ({time_offset})")
    if not ds.has_poses:
        raise CalibrationError(f"{source}: no poses: the paper's procedure needs poses.csv")
    plausibility.check_dataset(ds, source)
    segs = prepare_segments(ds, time_offset, source)
    plausibility.check_fixed_points(
        ds, segs, [fit_fixed_point(sd.poses) for sd in segs], source
    )
    ids = ds.robot.ids
    n = len(ids)
    P_s = np.zeros((n, 2))
    beta = np.zeros(n)
    b = np.zeros(n)
    C_of: dict[int, FloatArray] = {}
    for i in range(n):
        s1, s2 = _pair_segments([s for s in segs if s.static == i])
        for s in (s1, s2):
            turned = abs(float(s.poses[-1, 3] - s.poses[0, 3]))
            if turned < MIN_PAPER_ROTATION:
                raise ImplausibleDataError(
                    f"{source}: segment {s.row + 1} (module {ids[i]}) turned "
                    f"{math.degrees(turned):.1f} deg: the paper's circle fit needs >= "
                    f"{math.degrees(MIN_PAPER_ROTATION):.0f} deg (the joint solver, --method "
                    "joint, reports what such a segment is worth)"
                )
        P1 = paper_fixed_point(s1.poses[:, 1:])
        P2 = paper_fixed_point(s2.poses[:, 1:])
        dtheta = s2.angle - s1.angle
        b[i] = geo.offset_from_chord(P1, P2, dtheta)
        P_s[i] = geo.steering_axis_from_chord(P1, P2, b[i], dtheta)
        beta[i] = geo.homing_error(P1, P_s[i], s1.angle)
        C_of[s1.row], C_of[s2.row] = P1, P2
    radii: list[list[float]] = [[] for _ in range(n)]
    for sd in segs:
        if sd.row not in C_of:
            continue
        C = C_of[sd.row]
        t0, t1 = sd.poses[0, 0], sd.poses[-1, 0]
        dyaw = sd.poses[-1, 3] - sd.poses[0, 3]
        for j, mid in enumerate(ids):
            if j == sd.static:
                continue
            enc = encoders_in_window(ds, mid, t0, t1, time_offset)
            if enc.shape[0] < 2:
                continue
            psi = np.interp([t0, t1], enc[:, 0], enc[:, 2])
            D = geo.rolling_distance_perpendicular(P_s[j], b[j], C)
            radii[j].append(float(geo.radius_from_rotation(D, psi[1] - psi[0], dyaw)))
    r = np.array([float(np.median(v)) if v else np.nan for v in radii])
    X = np.column_stack([P_s, beta, b, r])
    plausibility.check_result(X, ds.robot)
    params = RobotParams.from_matrix(ids, X, robot=ds.robot.robot, frame=ds.robot.frame)
    quality = [
        SegmentQuality(
            row=s.row,
            static_module=ids[s.static],
            angle=s.angle,
            poses_used=s.poses.shape[0],
            poses_rejected=0,
            fixed_point_rms=paper_fixed_point_rms(s.poses[:, 1:]),
            fixed_point=_xy(C_of[s.row] if s.row in C_of else paper_fixed_point(s.poses[:, 1:])),
        )
        for s in segs
    ]
    return CalibrationResult(
        params=params,
        nominal=ds.robot,
        segments=quality,
        time_offset=time_offset,
        time_offset_std=None,
        time_offset_mode="given",
        poses_used=int(sum(s.poses.shape[0] for s in segs)),
        poses_rejected=0,
        increments_used=0,
        increments_rejected=0,
        reduced_chi2=None,
        method="paper",
    )
