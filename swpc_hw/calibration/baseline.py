"""The paper's literal procedure (Kim, Park, Park 2023, section 3) — the benchmark baseline.

Per module: the fixed point of each of its first two steering angles (a circle fit to
the robot origin's trajectory, brought into R with the measured heading), then
eq. (1) ``b``, eq. (2)-(3) ``P_s``, ``beta`` from the direction ``P_s -> P1``; for each
dynamic module j of each segment, ``D = sqrt(|P_s,j - C|^2 - b_j^2)`` (right angle at the
settled wheel) and eq. (4) ``r = D |dyaw| / |dpsi|`` over the whole segment; ``r_j`` is
the median of its 2(N-1) values (the paper's "robust average").
"""

from __future__ import annotations

import math

import numpy as np

from swpc_hw.calibration import geometry as geo
from swpc_hw.calibration.prepare import distinct_angles, encoders_in_window, prepare_segments
from swpc_hw.calibration.solver import CalibrationResult, SegmentQuality
from swpc_hw.dataset import Dataset
from swpc_hw.model import RobotParams, rot


def paper_fixed_point(poses: np.ndarray) -> np.ndarray:
    """Centre of the origin's circle (Kasa fit) in W, expressed in R for every pose, averaged.

    ``C_R = mean_i R(yaw_i)^T (C_W - p_i)``.  ``poses``: (..., K, 3) (x, y, yaw).
    """
    C_W, _ = geo.circle_fit_kasa(poses[..., :2])
    R = rot(poses[..., 2])
    d = C_W[..., None, :] - poses[..., :2]
    return np.asarray(np.einsum("...kji,...kj->...ki", R, d).mean(axis=-2), dtype=float)


def solve_paper(
    ds: Dataset, time_offset: float = 0.0, source: str = "dataset"
) -> CalibrationResult:
    """Calibrate with the paper's literal two-angle geometry."""
    segs = prepare_segments(ds, time_offset, source)
    ids = ds.robot.ids
    n = len(ids)
    P_s = np.zeros((n, 2))
    beta = np.zeros(n)
    b = np.zeros(n)
    C_of: dict[int, np.ndarray] = {}
    for i in range(n):
        mine = [s for s in segs if s.static == i]
        a1, a2 = distinct_angles([s.angle for s in mine])[:2]
        s1 = next(s for s in mine if abs(s.angle - a1) < np.deg2rad(1.0))
        s2 = next(s for s in mine if abs(s.angle - a2) < np.deg2rad(1.0))
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
    params = RobotParams.from_arrays(
        ids, P_s, beta, b, r, robot=ds.robot.robot, frame=ds.robot.frame
    )
    quality = [
        SegmentQuality(
            row=s.row,
            static_module=ids[s.static],
            angle=s.angle,
            poses_used=s.poses.shape[0],
            poses_rejected=0,
            fixed_point_rms=float("nan"),
            fixed_point=(float(C_of[s.row][0]), float(C_of[s.row][1]))
            if s.row in C_of
            else (math.nan, math.nan),
            fixed_point_std=float("nan"),
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
        reduced_chi2=float("nan"),
        method="paper",
    )
