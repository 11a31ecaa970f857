"""Simulated calibration experiment (docs/model-and-frames.md, "The calibration experiment").

:func:`generate_experiment` plays the whole seed method on a hidden *truth* robot and
returns a :class:`~swpc_hw.files.dataset.Dataset` (whose ``robot`` is the *nominal* robot, never
the truth) plus ground-truth extras for tests.

Timeline (time starts at 0, one continuous clock; the body starts at pose (0, 0, 0); every
module starts at ``theta_hat = 0``, ``psi = 0``).  For each module k in id order (or the order of
``options.modules``, which may lock only some: a check, docs/check.md) and each angle
``a_m`` of ``options.angles`` (one is enough for a check; a calibration needs two):

1. ``m > 0`` only: **re-steer** k from ``a_{m-1}`` to ``a_m`` (``resteer_time``): its wheel
   is pinned in the fixing tool and its fork keeps its world orientation, so the body
   rotates about ``P_s,k`` by ``-(a_m - a_{m-1})`` (raised-cosine profile) while the free
   casters trail (exact integration, :func:`simulators.physics.core.trailing_about_pivot`).
2. **align** (``align_time``, body still, wheels do not turn, steering scrubs): k steers to
   ``theta_hat = a_m``; every other module steers to the common true direction
   ``u_c = -sign(omega) z x (G - C) / |G - C|`` (``G`` centroid of the steering axes,
   ``C = P_s,k + b_k u(a_m + beta_k)``): the trailing direction of the point ``G``.
3. **spin** about ``C``: yaw rate ramps (raised cosine, ``ramp_time``) to ``yaw_rate``,
   holds, ramps down.  The steady part lasts ``settle + spin_duration`` where ``settle``
   is at least ``settle_time`` and long enough that every free caster is within
   ``settle_tol`` of its settled angle (computed from the exact solution); the segment
   window is ``[start, start + spin_duration]`` after the settle (pose clock).

With ``rest_time > 0`` the robot also rests (body, wheels and steering still) for that
long at the start and between each alignment and its spin; with ``drive_length > 0`` the
run ends with a **straight drive**: every wheel steered to the true angle
``drive_direction``, a rest, a pure translation along ``-u(drive_direction)`` of
``drive_length`` metres (speed ramps of ``ramp_time``, cruise ``drive_speed``) and a rest
(without a drive, a final rest).  The rests are where a gyro's bias is seen
(:mod:`simulators.offline.datagen_imu`).

Integration: every motion above is a rotation about a body point fixed in the world, for
which the free-caster dynamics have the closed-form solution of
:func:`simulators.physics.core.trailing_about_pivot`; it is evaluated at every sample time, so
there is no step error and no Python loop over time steps (a default run takes ~0.03 s).
:func:`simulators.physics.rk4_step` integrates the same dynamics numerically and the tests
check both agree.  ``integration_dt`` is the time grid on which the settle is searched.

Mocap noise: Gaussian, white by default; ``pose_noise_rho > 0`` makes it AR(1) from frame
to frame (``n_k = rho n_k-1 + sqrt(1 - rho^2) w_k``, as a filtered mocap stream is) with
the same marginal std devs.  Slip: random short bursts (``slip_burst_rate``) and/or
explicit slow slips over part of a segment (``partial_slips``).

Outputs: poses (t, x, y, yaw) at ``pose_rate`` with **yaw wrapped to (-pi, pi]**;
encoders at ``encoder_rate`` for every module with reported steering
``theta_hat = theta - beta`` **wrapped to (-pi, pi]** (the static module reports its held
angle) and cumulative wheel angle ``psi`` (not wrapped).  Trailing wheels turn backwards
(``psi`` decreasing) in the sign convention of docs/model-and-frames.md.

Clock offset convention (dataset): ``time_offset = encoder clock - pose clock``; an
encoder row stamped ``t_e`` was sampled at pose-clock time ``t_e - clock_offset``.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from simulators.offline.phases import Phase, evaluate_phases
from simulators.physics.core import (
    FloatArray,
    settled_trailing,
    trailing_about_pivot,
)
from swpc_hw.files.dataset import Dataset, Segment, save_dataset
from swpc_hw.files.kinematic_file import save_kinematics
from swpc_hw.protocol import DEFAULT_PROTOCOL
from swpc_hw.robot.model import RobotParams, contact_point, rot, wrap_angle
from swpc_hw.robot.paper_robot import PAPER_NOMINAL

_DEG = math.pi / 180.0


@dataclass(frozen=True)
class PartialSlip:
    """Slow slip of one wheel over part of one segment's window.

    Between ``start`` and ``end`` (fractions of the window of segment number ``segment``,
    0-based in time order) the wheel encoder of module ``module`` (id) turns ``factor``
    times its rolling rotation more than rolling without slip would turn it (0.004: a
    0.4 % slip).
    """

    module: int
    segment: int
    start: float = 0.0
    end: float = 1.0
    factor: float = 0.004


@dataclass(frozen=True)
class ExperimentOptions:
    """Settings of a simulated experiment (SI units; everything random is seeded by ``seed``).
    The protocol's defaults are :data:`swpc_hw.protocol.DEFAULT_PROTOCOL`'s but for two
    pauses, ``settle_time`` and ``resteer_time``, shorter (their docstrings)."""

    angles: tuple[float, ...] = tuple(a * _DEG for a in DEFAULT_PROTOCOL.angles_deg)
    yaw_rate: float = 0.5  # rad/s, > 0 counter-clockwise
    spin_duration: float = 12.0  # s of steady spin recorded per segment
    settle_time: float = 2.0
    """s, least steady spin before the window: the generator's own, below DEFAULT_PROTOCOL's
    (the window opens only once the casters settled, which a robot cannot see)."""
    settle_tol: float = 1e-10  # rad, max caster error at window start (noiseless physics)
    max_settle: float = 120.0  # s, give up (ValueError) if casters settle slower
    ramp_time: float = 1.0  # s, yaw-rate ramp up / down
    align_time: float = DEFAULT_PROTOCOL.align_time  # s, steering alignment before each spin
    resteer_time: float = 2.0
    """s, re-steering the locked module: the generator's own, below DEFAULT_PROTOCOL's (its
    runs' timelines, and the tests and figures measured on them, are these)."""
    pose_rate: float = 100.0  # Hz
    encoder_rate: float = 200.0  # Hz
    counts_per_rev: int | None = 2**17  # encoder quantization (both axes); None = off
    pose_sigma_xy: float = 0.0  # m
    pose_sigma_yaw: float = 0.0  # rad
    pose_noise_rho: float = 0.0  # AR(1) coefficient of the pose noise per frame (0: white)
    dropout_fraction: float = 0.0  # fraction of pose rows removed
    outlier_fraction: float = 0.0  # fraction of (kept) pose rows made outliers
    outlier_magnitude: float = 0.05  # m jump (random direction); yaw jumps magnitude/0.25 rad
    slip_burst_rate: float = 0.0  # bursts per second per dynamic wheel
    slip_duration: tuple[float, float] = (0.2, 0.5)  # s, uniform
    slip_factor: tuple[float, float] = (0.3, 1.0)  # extra wheel rotation / rolling rotation
    partial_slips: tuple[PartialSlip, ...] = ()  # slow slips over part of a segment
    clock_offset: float = 0.0  # s, encoder clock - pose clock
    integration_dt: float = 1e-3  # s, time grid of the settle search
    rest_time: float = 0.0  # s of stillness at the start, before each spin and around the drive
    drive_length: float = 0.0  # m, straight drive at the end (0: none)
    drive_speed: float = 0.4  # m/s, cruise speed of the straight drive
    drive_direction: float = math.pi  # rad, true steering of every wheel while driving
    modules: tuple[int, ...] | None = None  # ids of the modules locked, in order (None: all)
    seed: int = 0


@dataclass(frozen=True)
class SegmentTruth:
    """Ground truth of one spin: the window, its fixed point and the settled casters."""

    static_module: int
    angle_index: int
    theta_hat: float  # held reported angle of the static module
    start: float
    end: float
    fixed_point: FloatArray  # (2,) C in R
    fixed_point_world: FloatArray  # (2,) C in W
    settled_theta: FloatArray  # (N,) true steering of every module in the window
    settled_theta_hat: FloatArray  # (N,) reported (wrapped), static = held angle
    D: FloatArray  # (N,) |P_w,j - C| (0 for the static module)
    yaw_rate: float


@dataclass(frozen=True)
class SlipBurst:
    """Encoder over-rotation of one wheel: extra ``factor`` x rolling rotation in [start, end]."""

    module: int
    start: float
    end: float
    factor: float


@dataclass
class Experiment:
    """A simulated run: the dataset (nominal robot) and the hidden truth."""

    dataset: Dataset
    truth: RobotParams
    true_poses: FloatArray  # (P, 4) t, x, y, yaw (wrapped), noiseless, every pose time
    encoder_stamps: FloatArray  # (E,) encoder clock
    true_theta: FloatArray  # (E, N) true steering (wrapped) at the encoder sample times
    true_psi: FloatArray  # (E, N) rolling wheel angle without slip or quantization
    segments: list[SegmentTruth]
    slip_bursts: list[SlipBurst] = field(default_factory=list)
    dropped_times: FloatArray = field(default_factory=lambda: np.zeros(0))
    outlier_times: FloatArray = field(default_factory=lambda: np.zeros(0))
    duration: float = 0.0
    generation_seconds: float = 0.0
    rests: list[tuple[float, float]] = field(default_factory=list)
    """Windows (s, pose clock) in which body, wheels and steering are still."""
    drive: tuple[float, float] | None = None
    """The straight drive's motion (s, pose clock), None without one."""
    phases: list[Phase] = field(default_factory=list, repr=False)

    def poses_at(self, t: FloatArray) -> FloatArray:
        """True poses (K, 3) ``x, y, yaw`` (yaw not wrapped) at pose-clock times ``t``."""
        a = self.truth.arrays()
        return evaluate_phases(self.phases, np.asarray(t, dtype=float), a.P_s, a.b, a.r)[0]

    def save(self, directory: str | os.PathLike[str]) -> None:
        """Write the dataset directory plus ``truth.yaml`` (kinematic file of the truth)."""
        d = Path(directory)
        save_dataset(d, self.dataset)
        save_kinematics(d / "truth.yaml", self.truth, extra={"note": "simulation ground truth"})


# --------------------------------------------------------------------------- generator


def ar1_noise(white: FloatArray, rho: float) -> FloatArray:
    """AR(1) noise along axis 0 with the marginal std dev of ``white``::

        n_0 = w_0,   n_k = rho n_k-1 + sqrt(1 - rho^2) w_k

    ``rho = 0`` returns ``white`` itself (the same draws: white-noise runs keep their seeds).
    """
    if not 0.0 <= rho < 1.0:
        raise ValueError(f"pose_noise_rho must be in [0, 1) (got {rho})")
    if rho == 0.0:
        return white
    c = math.sqrt(1.0 - rho * rho)
    zi = ((1.0 - c) * white[0])[None, ...]  # n_0 = c w_0 + zi = w_0: stationary start
    from scipy.signal import lfilter  # on first use: it costs 0.8 s to import

    out, _ = lfilter([c], [1.0, -rho], white, axis=0, zi=zi)
    return np.asarray(out, dtype=float)


def default_nominal(truth: RobotParams) -> RobotParams:
    """The nominal robot of a run: PAPER_NOMINAL for the paper's ids, else the truth rounded.

    Rounded: ``beta = 0``, ``x_s, y_s`` to 5 mm, ``b, r`` to 1 mm.
    """
    if truth.ids == PAPER_NOMINAL.ids:
        return PAPER_NOMINAL
    a = truth.arrays()
    return RobotParams.from_arrays(
        a.ids,
        np.round(a.P_s / 0.005) * 0.005,
        np.zeros(a.n),
        np.maximum(np.round(a.b, 3), 0.001),
        np.maximum(np.round(a.r, 3), 0.001),
        robot=truth.robot,
        frame=truth.frame,
    )


def quantize(x: FloatArray, counts: int | None) -> FloatArray:
    """Angles ``x`` (rad) rounded to an encoder of ``counts`` per turn (None: as they are)."""
    if counts is None:
        return x
    q = 2.0 * np.pi / counts
    return np.asarray(np.round(x / q) * q, dtype=float)


def _settle_time(
    theta0: FloatArray,
    P_s: FloatArray,
    b: FloatArray,
    r: FloatArray,
    C: FloatArray,
    opt: ExperimentOptions,
    free: NDArray[np.bool_],
) -> float:
    """Steady time after the ramp until every free caster is within ``settle_tol``."""
    idx = np.flatnonzero(free)
    w = opt.yaw_rate
    target, _ = settled_trailing(P_s[idx], b[idx], C, np.sign(w))
    dt = opt.integration_dt
    chunk = 4096
    start = 0
    n_max = math.ceil(opt.max_settle / dt)
    while start <= n_max:
        i = np.arange(start, min(start + chunk, n_max + 1))
        phi = w * (0.5 * opt.ramp_time + i * dt)
        th, _ = trailing_about_pivot(P_s[idx], b[idx], r[idx], C, theta0[idx], phi[:, None])
        err = np.abs(wrap_angle(th - target)).max(axis=1)
        ok = err < opt.settle_tol
        # convergence is monotonic: first index from which all later ones are ok
        bad = np.flatnonzero(~ok)
        first_ok = 0 if bad.size == 0 else int(bad[-1]) + 1
        if first_ok < i.size:
            t_conv = float(i[first_ok]) * dt
            return max(opt.settle_time, t_conv)
        start += chunk
    raise ValueError(
        f"casters did not settle to {opt.settle_tol:g} rad within {opt.max_settle:g} s of spin"
    )


class _Timeline:
    """The experiment's motion as phases, built step by step (module docstring's timeline):
    each step starts where the previous one ended."""

    def __init__(self, truth: RobotParams, opt: ExperimentOptions) -> None:
        A = truth.arrays()
        self.opt = opt
        self.P_s, self.beta, self.b, self.r = A.P_s, A.beta, A.b, A.r
        self.t = 0.0
        self.pose = np.zeros(3)
        self.theta = self.beta.copy()  # theta_hat = 0 everywhere
        self.psi = np.zeros(A.n)
        self.phases: list[Phase] = []
        self.seg_info: list[tuple[int, int, float, float, float, FloatArray, FloatArray]] = []
        self.rests: list[tuple[float, float]] = []
        self.drive: tuple[float, float] | None = None

    def close(self, ph: Phase) -> None:
        """Append a phase; the next starts at its end state."""
        self.phases.append(ph)
        pe, te, se = ph.evaluate(np.array([ph.t1]), self.P_s, self.b, self.r)
        self.t, self.pose, self.theta, self.psi = ph.t1, pe[0], te[0], se[0]

    def until(self, duration: float) -> float:
        return round(self.t + duration, 9)

    def rest(self) -> None:
        if self.opt.rest_time > 0:
            self.rests.append((self.t, self.until(self.opt.rest_time)))
            self.close(
                Phase(self.t, self.rests[-1][1], self.pose, self.theta, self.psi, "align",
                       theta1=self.theta)
            )  # fmt: skip

    def align(self, theta1: FloatArray) -> None:
        opt = self.opt
        self.close(
            Phase(self.t, self.until(opt.align_time), self.pose, self.theta, self.psi, "align",
                   theta1=theta1)
        )  # fmt: skip

    def module(self, k: int) -> None:
        """Every angle of static module ``k``: re-steer, align, rest, spin."""
        opt, P_s, b, beta, w = self.opt, self.P_s, self.b, self.beta, self.opt.yaw_rate
        n = len(beta)
        dyn = np.ones(n, dtype=bool)
        dyn[k] = False
        G = P_s.mean(axis=0)
        for m, a in enumerate(opt.angles):
            if m > 0:
                d = a - opt.angles[m - 1]
                self.close(
                    Phase(
                        self.t, self.until(opt.resteer_time), self.pose, self.theta, self.psi,
                        "rotate", pivot=P_s[k].copy(), free=dyn, fork=k,
                        profile=("resteer", -d, opt.resteer_time, 0.0),
                    )
                )  # fmt: skip
            C = contact_point(P_s[k], b[k], a + beta[k])
            gc = G - C
            uc = -np.sign(w) * np.array([-gc[1], gc[0]])
            target = np.full(n, math.atan2(uc[1], uc[0]))
            target[k] = a + beta[k]
            self.align(self.theta + wrap_angle(target - self.theta))
            self.rest()
            settle = _settle_time(self.theta, P_s, b, self.r, C, opt, dyn)
            settle = math.ceil(settle / opt.integration_dt - 1e-9) * opt.integration_dt
            steady = settle + opt.spin_duration
            t0, pose0 = self.t, self.pose.copy()
            self.close(
                Phase(
                    self.t, self.until(2.0 * opt.ramp_time + steady), self.pose, self.theta,
                    self.psi, "rotate", pivot=C, free=dyn,
                    profile=("spin", w, opt.ramp_time, steady),
                )
            )  # fmt: skip
            w0 = t0 + opt.ramp_time + settle
            C_W = pose0[:2] + rot(pose0[2]) @ C
            self.seg_info.append((k, m, float(a), w0, w0 + opt.spin_duration, C, C_W))

    def straight_drive(self) -> None:
        opt = self.opt
        self.align(self.theta + wrap_angle(opt.drive_direction - self.theta))
        self.rest()
        steady = opt.drive_length / opt.drive_speed - opt.ramp_time
        if steady < 0:
            raise ValueError("drive_length too short for drive_speed and ramp_time")
        direction = -np.array([math.cos(opt.drive_direction), math.sin(opt.drive_direction)])
        self.drive = (self.t, self.until(2.0 * opt.ramp_time + steady))
        self.close(
            Phase(
                self.t, self.drive[1], self.pose, self.theta, self.psi, "translate",
                pivot=direction, profile=("spin", opt.drive_speed, opt.ramp_time, steady),
            )
        )  # fmt: skip


def _slipped(
    tl: _Timeline, ids: list[int], t_enc: FloatArray, psi_e: FloatArray, rng: np.random.Generator
) -> tuple[FloatArray, list[SlipBurst]]:
    """The wheel encoders with slip: random bursts on rolling wheels (extra rotation factor
    x rolling rotation), then the options' partial slips of one segment's window."""
    opt, t_end = tl.opt, tl.t
    bursts: list[SlipBurst] = []
    psi_meas = psi_e.copy()

    def slip(j: int, ts: float, te: float, f: float) -> None:
        """Encoder j turns ``f`` x its rolling rotation extra in [ts, te] (kept after)."""
        _, _, ps = evaluate_phases(tl.phases, np.array([ts, te]), tl.P_s, tl.b, tl.r)
        if abs(ps[1, j] - ps[0, j]) < 1e-12:
            return  # wheel not rolling (static or still): nothing to slip
        inside = (t_enc > ts) & (t_enc < te)
        after = t_enc >= te
        psi_meas[inside, j] += f * (psi_e[inside, j] - ps[0, j])
        psi_meas[after, j] += f * (ps[1, j] - ps[0, j])
        bursts.append(SlipBurst(ids[j], float(ts), float(te), float(f)))

    if opt.slip_burst_rate > 0.0:
        for j in range(len(ids)):
            n_b = rng.poisson(opt.slip_burst_rate * t_end)
            starts = np.sort(rng.uniform(0.0, t_end, n_b))
            durs = rng.uniform(*opt.slip_duration, n_b)
            facs = rng.uniform(*opt.slip_factor, n_b)
            for ts, du, f in zip(starts, durs, facs, strict=True):
                slip(j, float(ts), float(min(ts + du, t_end)), float(f))
    for ps_ in opt.partial_slips:
        if ps_.module not in ids:
            raise ValueError(f"partial slip: no module {ps_.module}")
        if not 0 <= ps_.segment < len(tl.seg_info):
            raise ValueError(
                f"partial slip: no segment {ps_.segment} (run has {len(tl.seg_info)})"
            )
        if not 0.0 <= ps_.start < ps_.end <= 1.0:
            raise ValueError("partial slip: need 0 <= start < end <= 1 (fractions of the window)")
        s0, s1 = tl.seg_info[ps_.segment][3], tl.seg_info[ps_.segment][4]
        slip(ids.index(ps_.module), s0 + ps_.start * (s1 - s0), s0 + ps_.end * (s1 - s0),
             ps_.factor)  # fmt: skip
    return psi_meas, bursts


def _measured_poses(
    poses_true: FloatArray, opt: ExperimentOptions, rng: np.random.Generator
) -> tuple[FloatArray, NDArray[np.bool_], NDArray[np.intp]]:
    """The poses as the mocap gives them: noise (AR(1) over frames), dropouts, outliers.
    Returns the measured poses, the kept mask and the outliers' indices."""
    n_p = int(poses_true.shape[0])
    meas = poses_true.copy()
    if opt.pose_sigma_xy > 0:
        meas[:, :2] += ar1_noise(rng.normal(0.0, opt.pose_sigma_xy, (n_p, 2)), opt.pose_noise_rho)
    if opt.pose_sigma_yaw > 0:
        meas[:, 2] += ar1_noise(rng.normal(0.0, opt.pose_sigma_yaw, n_p), opt.pose_noise_rho)
    keep = np.ones(n_p, dtype=bool)
    if opt.dropout_fraction > 0:
        drop = rng.choice(n_p, round(opt.dropout_fraction * n_p), replace=False)
        keep[drop] = False
    kept = np.flatnonzero(keep)
    out_idx = np.zeros(0, dtype=np.intp)
    if opt.outlier_fraction > 0:
        n_out = round(opt.outlier_fraction * kept.size)
        out_idx = np.sort(rng.choice(kept, n_out, replace=False))
        ang = rng.uniform(-np.pi, np.pi, n_out)
        meas[out_idx, 0] += opt.outlier_magnitude * np.cos(ang)
        meas[out_idx, 1] += opt.outlier_magnitude * np.sin(ang)
        meas[out_idx, 2] += rng.choice([-1.0, 1.0], n_out) * opt.outlier_magnitude / 0.25
    meas[:, 2] = wrap_angle(meas[:, 2])
    return meas, keep, out_idx


def _segments(tl: _Timeline, ids: list[int]) -> tuple[list[Segment], list[SegmentTruth]]:
    """Every spin's segment window and its truth."""
    w = tl.opt.yaw_rate
    segments: list[Segment] = []
    seg_truth: list[SegmentTruth] = []
    for k, m, a, s0, s1, C, C_W in tl.seg_info:
        _, th_s, _ = evaluate_phases(tl.phases, np.array([0.5 * (s0 + s1)]), tl.P_s, tl.b, tl.r)
        th_set = np.asarray(wrap_angle(th_s[0]), dtype=float)
        _, D = settled_trailing(tl.P_s, tl.b, C, np.sign(w))
        D[k] = 0.0
        th_hat = np.asarray(wrap_angle(th_set - tl.beta), dtype=float)
        th_hat[k] = a
        segments.append(Segment(ids[k], round(s0, 6), round(s1, 6)))
        seg_truth.append(
            SegmentTruth(ids[k], m, a, s0, s1, C.copy(), np.asarray(C_W), th_set, th_hat, D, w)
        )
    return segments, seg_truth


def experiment_modules(
    truth: RobotParams, nominal: RobotParams | None, modules: Sequence[int] | None
) -> tuple[RobotParams, list[int], list[int]]:
    """An experiment's nominal robot (default :func:`default_nominal`), its module ids and
    the modules it locks (``modules``, default all, in that order), checked against
    ``truth``."""
    nom = nominal if nominal is not None else default_nominal(truth)
    if nom.ids != truth.ids:
        raise ValueError(f"nominal ids {nom.ids} differ from truth ids {truth.ids}")
    ids = [int(m) for m in truth.ids]
    locked = ids if modules is None else [int(m) for m in modules]
    if not set(locked) <= set(ids):
        raise ValueError(f"modules {locked} are not all module ids of the robot {ids}")
    return nom, ids, locked


def generate_experiment(
    truth: RobotParams, options: ExperimentOptions | None = None, nominal: RobotParams | None = None
) -> Experiment:
    """Simulate the calibration experiment on ``truth``; see the module docstring."""
    t_start = time.perf_counter()
    opt = options or ExperimentOptions()
    if not opt.angles:
        raise ValueError("the experiment needs at least one steering angle per module")
    if opt.yaw_rate == 0.0:
        raise ValueError("yaw_rate must be non-zero")
    nom, ids, locked = experiment_modules(truth, nominal, opt.modules)

    # ---------------------------------------------------------------- the motion
    tl = _Timeline(truth, opt)
    tl.rest()
    for m in locked:
        tl.module(ids.index(m))
    if opt.drive_length > 0:
        tl.straight_drive()
    tl.rest()
    t_end = tl.t

    # ---------------------------------------------------------------- sampling
    rng = np.random.default_rng(opt.seed)
    n_p = math.floor(t_end * opt.pose_rate + 1e-9) + 1
    t_pose = np.arange(n_p) / opt.pose_rate
    i0 = math.ceil(opt.clock_offset * opt.encoder_rate - 1e-9)
    i1 = math.floor((t_end + opt.clock_offset) * opt.encoder_rate + 1e-9)
    stamps = np.arange(i0, i1 + 1) / opt.encoder_rate
    t_enc = np.clip(stamps - opt.clock_offset, 0.0, t_end)
    poses_true, _, _ = evaluate_phases(tl.phases, t_pose, tl.P_s, tl.b, tl.r)
    _, theta_e, psi_e = evaluate_phases(tl.phases, t_enc, tl.P_s, tl.b, tl.r)
    theta_e = np.asarray(wrap_angle(theta_e), dtype=float)
    psi_meas, bursts = _slipped(tl, ids, t_enc, psi_e, rng)

    # encoders: reported steering (held angle for the static module) and wheel
    steer = quantize(np.asarray(wrap_angle(theta_e - tl.beta), dtype=float), opt.counts_per_rev)
    wheel = quantize(psi_meas, opt.counts_per_rev)
    encoders = {m: np.column_stack([stamps, steer[:, j], wheel[:, j]]) for j, m in enumerate(ids)}

    meas, keep, out_idx = _measured_poses(poses_true, opt, rng)
    poses_out = np.column_stack([t_pose, meas])[keep]
    true_rows = np.column_stack([t_pose, poses_true[:, :2], wrap_angle(poses_true[:, 2])])
    segments, seg_truth = _segments(tl, ids)
    return Experiment(
        dataset=Dataset(robot=nom, poses=poses_out, encoders=encoders, segments=segments),
        truth=truth,
        true_poses=true_rows,
        encoder_stamps=stamps,
        true_theta=theta_e,
        true_psi=psi_e,
        segments=seg_truth,
        slip_bursts=bursts,
        dropped_times=t_pose[~keep],
        outlier_times=t_pose[out_idx],
        duration=t_end,
        generation_seconds=time.perf_counter() - t_start,
        rests=tl.rests,
        drive=tl.drive,
        phases=tl.phases,
    )
