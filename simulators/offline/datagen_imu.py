"""Simulated IMU calibration run: the robot's gyro and tape-measure references.

:func:`generate_imu_experiment` runs :func:`simulators.offline.datagen.generate_experiment`
with rests and a straight drive (:data:`IMU_PROTOCOL`), then adds what a robot
without motion capture records (docs/dataset-format.md, "Without motion capture"):

* **a gyro fixed to R** (:func:`simulate_gyro`), sampled at ``rate`` on the encoders'
  clock::

      wz_i = (1 + scale_error) omega(t_i) + bias(t_i) + n_i,
      bias(t) = bias + bias_walk W(t),   n_i ~ N(0, noise_density^2 rate)

  ``omega`` the body's true yaw rate, ``W`` a standard Wiener process (a random walk of
  the bias: ``bias_walk`` in rad/s/sqrt(s)), ``n`` white noise of density
  ``noise_density`` (rad/s/sqrt(Hz): the integrated angle's std dev grows as
  ``noise_density sqrt(T)``).  The defaults: 200 Hz, 0.005 deg/s/sqrt(Hz), 0.1 deg/s,
  a 0.3 % scale error and a bias walk of 1e-4 deg/s/sqrt(s) (21.6 deg/h after an hour: a
  pessimistic MEMS gyro, slow thermal drift included; a good one walks ten times less).
* **references** drawn from the truth (:func:`draw_references`) with a given std dev
  (0.5 mm): the distances between the steering axes of the chosen module pairs (default:
  every pair, the 4 sides and 2 diagonals of a 4-module robot), optionally wheel radii,
  and the straight drive: the distance the steering axis of the first module travelled
  between the middles of the rests before and after the drive (a pure translation: every
  point travels the drive's length).

The dataset holds the poses too (motion capture of the same run, for comparing the
solvers); :meth:`ImuExperiment.save` writes it with or without ``poses.csv``.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from simulators.offline.datagen import Experiment, ExperimentOptions, generate_experiment
from simulators.physics.core import FloatArray
from swpc_hw.calibration.gyro.build import ImuRun, NoiseLevels, build_imu_problem
from swpc_hw.calibration.gyro.weights import initial_weights
from swpc_hw.calibration.options import SolverOptions
from swpc_hw.calibration.prepare import prepare_segments
from swpc_hw.files.dataset import Dataset, save_dataset
from swpc_hw.files.kinematic_file import save_kinematics
from swpc_hw.files.references import AxisDistance, Reference, StraightDrive, WheelRadius
from swpc_hw.protocol import DEFAULT_PROTOCOL
from swpc_hw.robot.frames import design_fit_transform, transform_parameters
from swpc_hw.robot.model import RobotParams, rot
from swpc_hw.sensors.gyro import GyroOptions

_DEG = math.pi / 180.0

IMU_PROTOCOL = ExperimentOptions(
    rest_time=DEFAULT_PROTOCOL.rest_time, drive_length=DEFAULT_PROTOCOL.drive_length
)
"""The default protocol without motion capture: the seed experiment with the default
protocol's rests (the gyro's bias) and straight drive at the end (the wheel radii)."""


@dataclass(frozen=True)
class ReferenceOptions:
    """Which references are measured and how well (m)."""

    stddev: float = 0.5e-3
    axis_pairs: tuple[tuple[int, int], ...] | None = None
    """Module id pairs with a measured axis distance; None: every pair."""
    wheel_radius_modules: tuple[int, ...] = ()
    straight_drive: bool = True


@dataclass
class ImuExperiment:
    """A simulated run with gyro and references; ``experiment.dataset`` has everything."""

    experiment: Experiment
    gyro: GyroOptions
    true_bias: FloatArray = field(default_factory=lambda: np.zeros(0))
    """The gyro's bias at its sample times (rad/s)."""

    @property
    def dataset(self) -> Dataset:
        """Poses, encoders, segments, gyro and references of the run."""
        return self.experiment.dataset

    @property
    def imu_dataset(self) -> Dataset:
        """The same run without motion capture (no poses)."""
        return dataclasses.replace(self.dataset, poses=np.zeros((0, 4)))

    @property
    def mocap_dataset(self) -> Dataset:
        """The same run as a motion-capture dataset (no gyro, no references)."""
        return dataclasses.replace(self.dataset, imu=None, references=[])

    @property
    def truth(self) -> RobotParams:
        return self.experiment.truth

    def save(self, directory: str | os.PathLike[str], poses: bool = False) -> None:
        """Write the dataset (without ``poses.csv`` unless ``poses``) and ``truth.yaml``."""
        d = Path(directory)
        save_dataset(d, self.dataset if poses else self.imu_dataset)
        save_kinematics(d / "truth.yaml", self.truth, extra={"note": "simulation ground truth"})


def yaw_rate(exp: Experiment, t: FloatArray, h: float = 1e-5) -> FloatArray:
    """The body's true yaw rate (rad/s) at pose-clock times ``t``: central difference of
    the exact yaw, ``(yaw(t + h) - yaw(t - h)) / 2h`` (the motion profiles are smooth:
    error ~1e-10 rad/s)."""
    tt = np.asarray(t, dtype=float)
    lo = np.clip(tt - h, 0.0, exp.duration)
    hi = np.clip(tt + h, 0.0, exp.duration)
    up, down = exp.poses_at(hi)[:, 2], exp.poses_at(lo)[:, 2]
    return np.asarray((up - down) / np.maximum(hi - lo, 1e-12), dtype=float)


def simulate_gyro(
    exp: Experiment, opt: GyroOptions, rng: np.random.Generator, clock_offset: float = 0.0
) -> tuple[FloatArray, FloatArray]:
    """Gyro rows (K, 2) ``t, wz`` and the true bias at each (module docstring).

    Stamped on the encoders' clock (``clock_offset``: encoder clock minus pose clock), at
    ``i / rate`` within the run.
    """
    dt = 1.0 / opt.rate
    i0 = math.ceil(clock_offset * opt.rate - 1e-9)
    i1 = math.floor((exp.duration + clock_offset) * opt.rate + 1e-9)
    stamps = np.arange(i0, i1 + 1) * dt
    omega = yaw_rate(exp, np.clip(stamps - clock_offset, 0.0, exp.duration))
    walk = np.cumsum(rng.normal(0.0, opt.bias_walk * math.sqrt(dt), stamps.size))
    bias = opt.bias + walk - walk[0]
    noise = rng.normal(0.0, opt.noise_density * math.sqrt(opt.rate), stamps.size)
    wz = (1.0 + opt.scale_error) * omega + bias + noise
    return np.column_stack([stamps, wz]), np.asarray(bias, dtype=float)


def draw_references(
    exp: Experiment, opt: ReferenceOptions, rng: np.random.Generator, clock_offset: float = 0.0
) -> list[Reference]:
    """References measured on the truth with errors ``N(0, stddev^2)`` (module docstring);
    the straight drive's times on the encoders' clock."""
    a = exp.truth.arrays()
    ids = exp.truth.ids
    refs: list[Reference] = []
    pairs = opt.axis_pairs
    if pairs is None:
        pairs = tuple(itertools.combinations(ids, 2))
    for i, j in pairs:
        d = float(np.linalg.norm(a.P_s[ids.index(i)] - a.P_s[ids.index(j)]))
        refs.append(AxisDistance((i, j), d + float(rng.normal(0.0, opt.stddev)), opt.stddev))
    for m in opt.wheel_radius_modules:
        r = float(a.r[ids.index(m)])
        refs.append(WheelRadius(m, r + float(rng.normal(0.0, opt.stddev)), opt.stddev))
    if opt.straight_drive:
        if exp.drive is None:
            raise ValueError("a straight_drive reference needs a run with drive_length > 0")
        before = max(w for w in exp.rests if w[1] <= exp.drive[0] + 1e-9)
        after = min(w for w in exp.rests if w[0] >= exp.drive[1] - 1e-9)
        t0, t1 = 0.5 * (before[0] + before[1]), 0.5 * (after[0] + after[1])
        P = exp.poses_at(np.array([t0, t1]))
        q = [P[k, :2] + rot(P[k, 2]) @ a.P_s[0] for k in range(2)]
        travelled = float(np.linalg.norm(q[1] - q[0]))
        refs.append(
            StraightDrive(
                round(t0 + clock_offset, 6), round(t1 + clock_offset, 6),
                travelled + float(rng.normal(0.0, opt.stddev)), opt.stddev,
            )
        )
    return refs


def generate_imu_experiment(
    truth: RobotParams,
    options: ExperimentOptions | None = None,
    gyro: GyroOptions | None = None,
    references: ReferenceOptions | None = None,
    nominal: RobotParams | None = None,
) -> ImuExperiment:
    """Simulate the IMU protocol on ``truth`` (module docstring).

    ``options`` default to :data:`IMU_PROTOCOL`; its ``seed`` seeds the gyro and
    the references too (other streams than the run's own noise).
    """
    opt = options or IMU_PROTOCOL
    g = gyro or GyroOptions()
    ref = references or ReferenceOptions()
    exp = generate_experiment(truth, opt, nominal)
    rng = np.random.default_rng([opt.seed, 20])
    imu, bias = simulate_gyro(exp, g, rng, opt.clock_offset)
    refs = draw_references(exp, ref, rng, opt.clock_offset)
    exp.dataset = dataclasses.replace(exp.dataset, imu=imu, references=refs)
    return ImuExperiment(exp, g, bias)


def fisher_setup(
    truth: RobotParams,
    options: ExperimentOptions | None = None,
    gyro: GyroOptions | None = None,
    references: ReferenceOptions | None = None,
    nominal: RobotParams | None = None,
) -> tuple[ImuRun, FloatArray]:
    """The IMU problem of an experiment at its truth, weighted for its noise.

    The run of ``options`` (default :data:`IMU_PROTOCOL`) without noise
    (encoders unquantized, gyro without noise or walk, exact references), built with the
    noise levels of the sensors as simulated (encoders of ``counts_per_rev`` counts, the
    ``gyro``'s white noise and walk, the references' std dev): the Jacobian at the truth,
    in the design-fit frame, is the experiment's (:mod:`swpc_hw.calibration.plan.identifiability`).
    Returns the built problem (weights set) and the true unknowns.
    """
    opt = options or IMU_PROTOCOL
    g = gyro or GyroOptions()
    ref = references or ReferenceOptions()
    exact = dataclasses.replace(opt, counts_per_rev=None)
    mf = generate_imu_experiment(
        truth, exact, dataclasses.replace(g, noise_density=0.0, bias_walk=0.0),
        dataclasses.replace(ref, stddev=1e-12), nominal,
    )
    ds = mf.imu_dataset
    ds.references = [dataclasses.replace(r, stddev=ref.stddev) for r in ds.references]
    q = 2.0 * math.pi / (opt.counts_per_rev or 2**40)
    noise = NoiseLevels(
        steer=q / math.sqrt(12.0),
        wheel=q / math.sqrt(12.0),
        gyro_var=g.noise_density**2 * g.rate,
        gyro_dt=1.0 / g.rate,
        walk_q2=g.bias_walk**2,
    )
    segs = prepare_segments(ds)
    run = build_imu_problem(ds, segs, SolverOptions(), noise=noise)
    prob = run.problem
    a = truth.arrays()
    X = np.column_stack([a.P_s, a.beta, a.b, a.r])
    phi, t = design_fit_transform(a.P_s, ds.robot.arrays().P_s)
    x = np.zeros(prob.layout.size)
    x[: X.size] = transform_parameters(X, phi, t).ravel()
    x[prob.layout.scale] = 1.0 + g.scale_error
    x[prob.layout.knots] = g.bias
    initial_weights(run, x)
    return run, x
