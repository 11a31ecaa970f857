"""Plausibility gates: data and results that cannot be right are refused, with the likely cause.

Before solving (:class:`~swpc_hw.errors.ImplausibleDataError`):

* **clocks**: pose and encoder times sorted, no timestamp carrying two different samples
  (a clock that jumped back; the loader also catches it in the file order);
* **units and magnitudes**: every segment's fixed point ``C_R`` against the contact point
  the nominal robot puts there, ``C_nom = P_s,k + b_k u(a)``.  Off by more than half the
  robot's size: the poses are not of the robot frame R, in other units, or robot.yaml is
  another robot.  The likely cause is named by trying the alternatives: positions in
  millimetres (``C_R / 1000`` fits the nominal robot), yaw in degrees (the fixed point
  refitted with ``yaw * pi / 180`` fits);
* **fixed-point RMS against the noise the poses imply**: pose noise shows as frame-to-
  frame jitter, ``sigma^2 = var(x_i+1 - 2 x_i + x_i-1) / 6`` (robust: median absolute
  deviation).  The fixed-point residual RMS expected from it is
  ``sqrt(2 sigma_xy^2 + |C_R|^2 sigma_yaw^2)``; a segment over
  :data:`RMS_OVER_JITTER` times that (and over :data:`RMS_FLOOR`), or over
  :data:`RMS_MAX_FRACTION` of the robot's size, or with over
  :data:`MAX_OUTLIER_FRACTION` of its poses rejected as outliers, did not turn about one
  point: a clock jump, the locked wheel slipping, a wrong window.  (Correlated noise
  is smoother than white: AR(1) noise with rho 0.8 reads ~2.6x the jitter.)

After solving (:class:`~swpc_hw.errors.ImplausibleResultError`): every value finite,
``b > 0``, ``r > 0``; ``P_s`` within half the robot's size of the nominal, ``r`` within a
factor :data:`RADIUS_FACTOR` and ``b`` within a factor :data:`OFFSET_FACTOR` of nominal.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from swpc_hw.calibration.fixed_point import FixedPointFit, robust_fixed_point
from swpc_hw.calibration.parameters import P_S, PARAM_NAMES, R
from swpc_hw.calibration.parameters import B as B_COL
from swpc_hw.calibration.prepare import SegmentData
from swpc_hw.errors import ImplausibleDataError, ImplausibleResultError
from swpc_hw.files.dataset import Dataset
from swpc_hw.robot.model import RobotParams, contact_point

FloatArray = NDArray[np.float64]

RMS_OVER_JITTER = 10.0
"""A segment's fixed-point RMS may be at most this many times what its jitter implies."""
RMS_FLOOR = 1e-3
"""... unless it is below this (m): noise-free data have no jitter to compare with."""
MAX_OUTLIER_FRACTION = 0.1
"""A segment with more of its poses rejected as outliers of its fixed point is refused."""
RMS_MAX_FRACTION = 0.05
"""A fixed-point RMS over this fraction of the robot's size is refused whatever the jitter
(interleaved samples of a jumped clock have a huge jitter too)."""
FIXED_POINT_TOLERANCE = 0.5
"""A fixed point may be this fraction of the robot's size from the nominal one."""
RADIUS_FACTOR = 2.0
OFFSET_FACTOR = 3.0
MM_RATIO = (300.0, 3000.0)
"""A length ratio in this range is read as millimetres given as metres."""


def robot_size(nominal: RobotParams) -> float:
    """``max_i |P_s,i| + max_i b_i`` of the nominal robot (m)."""
    a = nominal.arrays()
    return float(np.max(np.linalg.norm(a.P_s, axis=1)) + np.max(a.b))


def check_dataset(ds: Dataset, source: str = "dataset") -> None:
    """Clocks: sorted times, no timestamp with two different samples (poses, encoders and
    the gyro, those present)."""
    if ds.has_poses:
        _check_clock(ds.poses, f"{source}/poses.csv", "poses")
    if ds.imu is not None:
        _check_clock(ds.imu, f"{source}/imu.csv", "gyro samples")
    for mid, rows in ds.encoders.items():
        _check_clock(rows, f"{source}/encoders.csv", f"module {mid}'s encoders")


def _check_clock(rows: FloatArray, where: str, what: str) -> None:
    t = rows[:, 0]
    dt = np.diff(t)
    if np.any(dt < 0):
        i = int(np.argmax(dt < 0))
        raise ImplausibleDataError(
            f"{where}: {what} are not in time order ({t[i + 1]:.6f} s after {t[i]:.6f} s)"
        )
    dup = np.flatnonzero(dt == 0)
    conflict = [i for i in dup.tolist() if not np.array_equal(rows[i, 1:], rows[i + 1, 1:])]
    if conflict:
        raise ImplausibleDataError(
            f"{where}: {len(conflict)} timestamp(s) carry two different {what} (first at "
            f"{t[conflict[0]]:.6f} s): the clock jumped back or two streams were merged"
        )


def jitter_sigma(t: FloatArray, v: FloatArray) -> float:
    """Noise std dev of a smooth signal from its second differences on uniform triples.

    ``sigma = 1.4826 MAD(v_i+1 - 2 v_i + v_i-1) / sqrt(6)`` over consecutive samples with
    equal spacing (within 10 %).  0 without such triples.
    """
    if t.size < 3:
        return 0.0
    d1, d2 = np.diff(t)[:-1], np.diff(t)[1:]
    ok = np.abs(d1 - d2) <= 0.1 * np.maximum(d1, d2)
    sec = (v[2:] - 2.0 * v[1:-1] + v[:-2])[ok]
    if sec.size == 0:
        return 0.0
    return 1.4826 * float(np.median(np.abs(sec - np.median(sec)))) / math.sqrt(6.0)


def implied_rms(poses_t: FloatArray, C_R: FloatArray) -> float:
    """Fixed-point residual RMS the poses' jitter implies: ``sqrt(2 s_xy^2 + |C_R|^2 s_yaw^2)``."""
    t = poses_t[:, 0]
    s_x, s_y = jitter_sigma(t, poses_t[:, 1]), jitter_sigma(t, poses_t[:, 2])
    s_xy = math.sqrt(0.5 * (s_x**2 + s_y**2))
    s_yaw = jitter_sigma(t, poses_t[:, 3])
    return math.sqrt(2.0 * s_xy**2 + float(C_R @ C_R) * s_yaw**2)


def check_fixed_points(
    ds: Dataset, segs: list[SegmentData], fits: list[FixedPointFit], source: str = "dataset"
) -> None:
    """Units, magnitudes and fixed-point RMS of every segment (module docstring)."""
    nominal = ds.robot.arrays()
    size = robot_size(ds.robot)
    tol = max(FIXED_POINT_TOLERANCE * size, 0.05)
    for sd, fit in zip(segs, fits, strict=True):
        k = sd.static
        C_nom = contact_point(nominal.P_s[k], nominal.b[k], sd.angle)
        off = float(np.linalg.norm(fit.C_R - C_nom))
        where = (
            f"{source}: segment {sd.row + 1} (module {sd.segment.static_module}, "
            f"{sd.segment.start:g}-{sd.segment.end:g} s)"
        )
        if off > tol:
            cause = _likely_cause(sd, fit, C_nom, tol)
            raise ImplausibleDataError(
                f"{where}: fixed point {np.linalg.norm(fit.C_R):.4g} m from the origin of R, "
                f"{off:.4g} m from where the nominal robot puts it: {cause}"
            )
        outliers = float(np.mean(~fit.inliers))
        if outliers > MAX_OUTLIER_FRACTION:
            raise ImplausibleDataError(
                f"{where}: {outliers:.0%} of its {fit.inliers.size} poses do not fit one fixed "
                "point: the robot did not turn about one point (a clock jump, the locked "
                "wheel slipping, a wrong window) or the motion capture lost the robot"
            )
        expect = implied_rms(sd.poses, fit.C_R)
        if fit.rms > RMS_MAX_FRACTION * size:
            raise ImplausibleDataError(
                f"{where}: fixed-point RMS {fit.rms * 1e3:.1f} mm on a robot of "
                f"{size:.3g} m: the robot did not turn about one point (a clock jump, the "
                "locked wheel slipping, a wrong window)"
            )
        if fit.rms > RMS_FLOOR and fit.rms > RMS_OVER_JITTER * expect:
            raise ImplausibleDataError(
                f"{where}: fixed-point RMS {fit.rms * 1e3:.1f} mm, but the poses' frame-to-"
                f"frame jitter implies {expect * 1e3:.2f} mm: the robot did not turn about one "
                "point (a clock jump, the locked wheel slipping, a wrong window)"
            )


def _likely_cause(sd: SegmentData, fit: FixedPointFit, C_nom: FloatArray, tol: float) -> str:
    ratio = float(np.linalg.norm(fit.C_R)) / max(float(np.linalg.norm(C_nom)), 1e-9)
    if MM_RATIO[0] < ratio < MM_RATIO[1] and np.linalg.norm(fit.C_R / 1e3 - C_nom) < tol:
        return "poses look like millimetres (poses.csv needs metres)"
    deg = sd.poses[:, 1:].copy()
    deg[:, 2] = np.unwrap(np.deg2rad(deg[:, 2]))
    C_deg, _, _, _ = robust_fixed_point(deg)
    if np.linalg.norm(C_deg - C_nom) < tol:
        return "yaw looks like degrees (poses.csv needs radians)"
    return (
        "the poses are not of the robot frame R, or robot.yaml describes another robot"
    )


def check_result(X: FloatArray, nominal: RobotParams) -> None:
    """Refuse a solution no robot can have or far from the nominal robot, naming every value."""
    ids = nominal.ids
    bad = []
    for mid, row in zip(ids, X, strict=True):
        bad += [
            f"module {mid} {name} = {v}"
            for name, v in zip(PARAM_NAMES, row, strict=True)
            if not math.isfinite(v)
        ]
        b, r = float(row[B_COL]), float(row[R])
        if math.isfinite(b) and math.isfinite(r) and (b <= 0 or r <= 0):
            bad.append(f"module {mid} b = {b:.6g} m, r = {r:.6g} m")
    if bad:
        raise ImplausibleResultError(
            "the solver did not converge to a physical solution: " + "; ".join(bad)
        )
    a = nominal.arrays()
    tol = max(FIXED_POINT_TOLERANCE * robot_size(nominal), 0.05)
    far = []
    for i, mid in enumerate(ids):
        dp = float(np.linalg.norm(X[i, P_S] - a.P_s[i]))
        if dp > tol:
            far.append(f"module {mid} P_s {dp:.4g} m from nominal")
        for name, col, nom, f in (
            ("r", R, a.r[i], RADIUS_FACTOR),
            ("b", B_COL, a.b[i], OFFSET_FACTOR),
        ):
            v = float(X[i, col])
            if not nom / f <= v <= nom * f:
                far.append(f"module {mid} {name} = {v:.6g} m against {nom:.6g} m nominal")
    if far:
        ratio = float(np.max(X[:, R] / a.r))
        cause = (
            "poses look like millimetres"
            if MM_RATIO[0] < ratio < MM_RATIO[1]
            else "the data do not fit robot.yaml's robot"
        )
        raise ImplausibleResultError(
            "implausible result, far from the nominal robot: " + "; ".join(far) + f" ({cause})"
        )



# ------------------------------------------------------------------ without motion capture

GYRO_RATIO = (0.5, 2.0)
"""The gyro's turn over the wheels' (nominal robot) must lie in this range."""
MAX_GYRO_SCALE_ERROR = 0.05
"""A calibrated gyro scale error beyond this is refused."""


def check_gyro_ratio(ratio: float, source: str = "dataset") -> None:
    """Units and axis of the gyro: its turn over each segment against the wheels'.

    ``ratio``: the median over the segments of the gyro's yaw (bias removed) over the
    yaw the wheels imply with the starting geometry; 1 when ``imu.csv`` is the yaw rate
    of R in rad/s.  57 (= 180 / pi): degrees per second; negative: the gyro's z axis
    points down (or clockwise is positive).
    """
    where = f"{source}/imu.csv"
    deg = 180.0 / math.pi
    if ratio < 0:
        raise ImplausibleDataError(
            f"{where}: wz turns the other way than the wheels (ratio {ratio:.3g}): the gyro's "
            "z axis points down, or clockwise is positive; wz must be counter-clockwise "
            "positive about R's z (up)"
        )
    if GYRO_RATIO[0] * deg < ratio < GYRO_RATIO[1] * deg:
        raise ImplausibleDataError(
            f"{where}: wz looks like deg/s (it reads {ratio:.3g} times the yaw rate the "
            "wheels show; imu.csv needs rad/s)"
        )
    if not GYRO_RATIO[0] < ratio < GYRO_RATIO[1]:
        raise ImplausibleDataError(
            f"{where}: wz reads {ratio:.3g} times the yaw rate the wheels show: not the yaw "
            "rate of R in rad/s (another axis or sensor, or robot.yaml is another robot)"
        )


def check_gyro_scale(eps: float) -> None:
    """Refuse a calibrated gyro scale error ``eps`` beyond :data:`MAX_GYRO_SCALE_ERROR`."""
    if not math.isfinite(eps) or abs(eps) > MAX_GYRO_SCALE_ERROR:
        raise ImplausibleResultError(
            f"implausible result: the gyro's scale is off by {eps * 100:.3g} % "
            f"(more than {MAX_GYRO_SCALE_ERROR * 100:g} %): a wrong unit or sample time in "
            "imu.csv, or references that contradict the encoders"
        )
