"""The calibration experiment played on the tyre physics (issue 44: data from other physics).

:func:`generate_experiment` plays docs/model-and-frames.md's experiment on a hidden *truth*
robot simulated by :mod:`simulators.physics.tyres` (forces, tyre compliance and friction,
casters with inertia and friction, wheels driven by torque: no no-slip constraint) and
returns the same :class:`~swpc_hw.files.dataset.Dataset` as
:func:`simulators.offline.datagen.generate_experiment` (its ``robot`` the *nominal* robot,
never the truth), plus what the physics knows for tests and benchmarks.

Timeline (one clock from 0; R at the origin, every module at ``theta_hat = 0``, tyres
undeflected; a rest of ``rest_time`` with every wheel braked).  For each module k in id
order (or ``options.modules``) and each angle ``a_m`` of ``options.angles``:

1. **align** (``align_time``): every wheel braked at its angle; k's steering drive moves
   to ``theta_hat = a_m``, every other module's to the common direction ``u_c = -sign(w)
   z x (G - C) / |G - C|`` of the *nominal* robot (``G`` the steering axes' centroid, ``C =
   P_s,k + b_k u(a_m)``; the drive knows only the nominal), along a raised cosine over
   the first 80 % of the phase.  Steering a braked wheel scrubs its tyre: the tread sticks
   or slides as the tyre law says.  Then a **rest** (``rest_time``), still held.
2. **spin**: k's wheel stays braked and its steering held; every other module's steering
   is free and its wheel driven by the torque ``-sign(w) tau`` (raised-cosine ramp over
   ``ramp_time``).  ``tau`` is ``spin_torque`` or, by default, the torque that holds the
   *nominal* robot's no-slip spin at ``yaw_rate`` against the wheels' losses (power
   balance, ``D_j = |P_w,j - C|`` of the settled casters)::

       tau = c_w |w| sum (D_j / r_j)^2 / sum (D_j / r_j) + c_rr N r

   After ``settle_time`` of spinning (after the ramp) the segment window opens; it closes
   once the true yaw has turned ``sweep`` (the default protocol's 360 deg) further.
3. **stop** (``stop_time``): the driven wheels' drives hold zero velocity (``tau = -k_v
   psi_dot``, within their torque limit), k still locked; then every wheel is braked.

Sampling: the state every ``1 / encoder_rate`` (an integer number of steps): encoders
``theta_hat = theta - beta`` wrapped to ``(-pi, pi]`` and ``psi``, both quantised to
``counts_per_rev``; poses of R at ``pose_rate`` with datagen's noise (Gaussian, AR(1)
with ``pose_noise_rho``), by default 0.5 mm and 0.05 deg, yaw wrapped.  One shared clock
(no offset).  Everything random is seeded by ``options.seed``; the physics is
deterministic.  Cost: ~20 us of Python per step, ~7 s per default run (0.5 ms steps).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from simulators.offline.datagen import ar1_noise, experiment_modules, quantize
from simulators.physics.tyres import (
    ModuleCommand,
    Plant,
    State,
    TyreOptions,
    plant,
    rest_state,
    step,
    tread_points,
)
from swpc_hw.files.dataset import Dataset, Segment
from swpc_hw.protocol import DEFAULT_PROTOCOL
from swpc_hw.robot.model import RobotParams, wrap_angle

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class TyreExperimentOptions:
    """Settings of an experiment on the tyre physics (SI; the protocol's defaults are
    :data:`~swpc_hw.protocol.DEFAULT_PROTOCOL`'s, the noise the benchmarks' mocap)."""

    angles: tuple[float, ...] = tuple(math.radians(a) for a in DEFAULT_PROTOCOL.angles_deg)
    yaw_rate: float = 0.5  # rad/s the default spin torque aims at (> 0: counter-clockwise)
    spin_torque: float | None = None  # N m; None: from the nominal robot for yaw_rate
    sweep: float = math.radians(DEFAULT_PROTOCOL.sweep_deg)  # rad recorded per spin
    settle_time: float = DEFAULT_PROTOCOL.settle_time  # s spun after the ramp, before the window
    ramp_time: float = 1.0  # s, the spin torque's ramp
    align_time: float = DEFAULT_PROTOCOL.align_time
    rest_time: float = 0.5  # s still before each spin and at the start
    stop_time: float = DEFAULT_PROTOCOL.stop_time
    stop_gain: float = 0.5  # N m s/rad, the velocity loop that stops the driven wheels
    max_spin: float = 120.0  # s, give up (ValueError) if a window takes longer
    pose_rate: float = 100.0  # Hz
    encoder_rate: float = 200.0  # Hz
    counts_per_rev: int | None = 2**17  # encoder quantisation (both axes); None: off
    pose_sigma_xy: float = 0.5e-3  # m
    pose_sigma_yaw: float = math.radians(0.05)  # rad
    pose_noise_rho: float = 0.0  # AR(1) coefficient of the pose noise per frame
    modules: tuple[int, ...] | None = None  # ids locked, in order (None: all)
    physics: TyreOptions = field(default_factory=TyreOptions)
    seed: int = 0


@dataclass(frozen=True)
class SpinTruth:
    """What the physics did in one spin's window."""

    static_module: int
    theta_hat: float  # the locked module's held reported angle (the command)
    start: float
    end: float
    torque: float  # N m on each driven wheel
    yaw_rate: float  # mean over the window
    tread_drift: float  # m, largest distance of k's tread point from its place at start
    fixed_point: FloatArray  # (2,) in R: the model's P_s + b u(theta) at the window's theta


@dataclass
class TyreExperiment:
    """A simulated run: the dataset (nominal robot), the hidden truth and the physics."""

    dataset: Dataset
    truth: RobotParams
    true_poses: FloatArray  # (P, 4) t, x, y, yaw (not wrapped), noiseless
    spins: list[SpinTruth]
    duration: float
    generation_seconds: float
    physics: TyreOptions


def spin_torque(nominal: RobotParams, k: int, angle: float, opt: TyreOptions, w: float) -> float:
    """The torque that holds the nominal robot's no-slip spin about module index ``k`` at
    ``angle`` at yaw rate ``w`` (module docstring's power balance)."""
    a = nominal.arrays()
    C = a.P_s[k] + a.b[k] * np.array([math.cos(angle), math.sin(angle)])
    j = np.arange(a.n) != k
    D = np.sqrt(np.maximum(np.sum((a.P_s[j] - C) ** 2, axis=1) - a.b[j] ** 2, 0.0))
    q = D / a.r[j]
    load = opt.mass * opt.gravity / a.n
    return float(
        opt.wheel_viscous * abs(w) * np.sum(q**2) / np.sum(q)
        + opt.rolling_resistance * load * float(np.mean(a.r[j]))
    )


def _raised(x: float) -> float:
    """0 -> 1 along a raised cosine for ``x`` in [0, 1], clipped outside."""
    x = min(max(x, 0.0), 1.0)
    return 0.5 - 0.5 * math.cos(math.pi * x)


class _Run:
    """The physics with its recorder: every step through :meth:`advance`."""

    def __init__(self, truth: RobotParams, opt: TyreExperimentOptions) -> None:
        self.opt, self.phys = opt, opt.physics
        self.plant: Plant = plant(truth, self.phys)
        self.state: State = rest_state(self.plant)
        self.n = len(self.plant.modules)
        dt = self.phys.dt
        self.stride = round(1.0 / (opt.encoder_rate * dt))
        self.pose_every = round(opt.encoder_rate / opt.pose_rate)
        if abs(self.stride * dt * opt.encoder_rate - 1.0) > 1e-9 or abs(
            self.pose_every * opt.pose_rate - opt.encoder_rate
        ) > 1e-9:
            raise ValueError("1 / encoder_rate must be whole steps and pose_rate divide it")
        self.i = 0  # steps taken
        self.rows: list[list[float]] = []  # t, x, y, yaw, theta..., psi...

    @property
    def t(self) -> float:
        return self.i * self.phys.dt

    def record(self) -> None:
        s = self.state
        self.rows.append([self.t, *s.pose(self.plant), *(m.theta for m in s.modules),
                          *(m.psi for m in s.modules)])  # fmt: skip

    def advance(self, cmds: list[ModuleCommand]) -> None:
        if self.i % self.stride == 0:
            self.record()
        self.state = step(self.state, cmds, self.plant, self.phys)
        self.i += 1

    def held(self) -> list[ModuleCommand]:
        """Every steering held where it is, every wheel braked where it is."""
        return [ModuleCommand(True, m.theta, True, m.psi, 0.0) for m in self.state.modules]

    def align(self, targets: list[float]) -> None:
        """Steer every module (true angles ``targets``, nearest turn) with the wheels
        braked, then rest."""
        opt = self.opt
        start = [m.theta for m in self.state.modules]
        goal = [a + float(wrap_angle(g - a)) for a, g in zip(start, targets, strict=True)]
        base = self.held()
        t0 = self.t
        while self.t < t0 + opt.align_time + opt.rest_time - 1e-9:
            f = _raised((self.t - t0) / (0.8 * opt.align_time))
            self.advance([c._replace(steer_target=a + f * (g - a))
                          for c, a, g in zip(base, start, goal, strict=True)])  # fmt: skip

    def spin(self, k: int, torque: float) -> tuple[float, float, float, float]:
        """Spin about module index ``k`` (module docstring, 2 and 3): the window's start,
        end, mean yaw rate and the locked tread point's largest drift in it."""
        opt, p = self.opt, self.plant
        sign = 1.0 if opt.yaw_rate > 0 else -1.0
        lock = self.held()[k]
        t0 = self.t
        t_open = t0 + opt.ramp_time + opt.settle_time
        yaw0 = start = math.nan
        drift, tread0 = 0.0, (0.0, 0.0)
        while True:
            tau = -sign * torque * _raised((self.t - t0) / opt.ramp_time)
            cmds = [lock if j == k else ModuleCommand(False, 0.0, False, 0.0, tau)
                    for j in range(self.n)]  # fmt: skip
            if self.i % self.stride == 0 and self.t >= t_open - 1e-9:
                tp = tread_points(self.state, p)[k]
                if math.isnan(start):
                    start, yaw0, tread0 = self.t, self.state.yaw, tp
                drift = max(drift, math.hypot(tp[0] - tread0[0], tp[1] - tread0[1]))
                if abs(self.state.yaw - yaw0) >= opt.sweep:
                    break
            if self.t > t_open + opt.max_spin:
                sweep = math.degrees(opt.sweep)
                raise ValueError(
                    f"the spin about module index {k} did not sweep {sweep:g} deg in "
                    f"{opt.max_spin:g} s"
                )
            self.advance(cmds)
        end = self.t
        rate = abs(self.state.yaw - yaw0) / (end - start)
        t1 = self.t
        while self.t < t1 + opt.stop_time - 1e-9:
            g = self.phys.brake_gains.limit
            self.advance([
                lock if j == k else ModuleCommand(
                    False, 0.0, False, 0.0, max(-g, min(g, -opt.stop_gain * m.psi_dot)))
                for j, m in enumerate(self.state.modules)
            ])  # fmt: skip
        return start, end, rate, drift

    def rest(self) -> None:
        base, t0 = self.held(), self.t
        while self.t < t0 + self.opt.rest_time - 1e-9:
            self.advance(base)


def _targets(nominal: RobotParams, truth: RobotParams, k: int, a: float, w: float) -> list[float]:
    """True steering targets of the alignment before a spin about index ``k`` at ``a``:
    the drives hold reported angles (``theta_hat`` from the nominal), the true angle is
    ``theta_hat + beta``."""
    nom, tru = nominal.arrays(), truth.arrays()
    C = nom.P_s[k] + nom.b[k] * np.array([math.cos(a), math.sin(a)])
    gc = nom.P_s.mean(axis=0) - C
    uc = -math.copysign(1.0, w) * np.array([-gc[1], gc[0]])
    hat = np.full(nom.n, math.atan2(uc[1], uc[0]))
    hat[k] = a
    return [float(v) for v in hat + tru.beta]



def generate_experiment(
    truth: RobotParams,
    options: TyreExperimentOptions | None = None,
    nominal: RobotParams | None = None,
) -> TyreExperiment:
    """Play the calibration experiment on the tyre physics of ``truth``; see the module
    docstring.  ``nominal``: the dataset's robot (default
    :func:`~simulators.offline.datagen.default_nominal`)."""
    t_wall = time.perf_counter()
    opt = options or TyreExperimentOptions()
    if len(opt.angles) < 1 or opt.yaw_rate == 0.0:
        raise ValueError("the experiment needs a steering angle and a non-zero yaw_rate")
    nom, ids, locked = experiment_modules(truth, nominal, opt.modules)
    run = _Run(truth, opt)
    run.rest()
    spins: list[SpinTruth] = []
    for m in locked:
        k = ids.index(m)
        for a in opt.angles:
            run.align(_targets(nom, truth, k, a, opt.yaw_rate))
            tau = opt.spin_torque
            if tau is None:
                tau = spin_torque(nom, k, a, opt.physics, opt.yaw_rate)
            theta_k = run.state.modules[k].theta
            start, end, rate, drift = run.spin(k, tau)
            mk = run.plant.modules[k]
            P_w = np.array([mk.lx + run.plant.com[0] + mk.b * math.cos(theta_k),
                            mk.ly + run.plant.com[1] + mk.b * math.sin(theta_k)])  # fmt: skip
            spins.append(SpinTruth(m, a, start, end, tau, rate, drift, P_w))
    run.rest()
    run.record()
    rows = np.array(run.rows)
    n = run.n
    t = rows[:, 0]
    beta = np.array([mc.beta for mc in run.plant.modules])
    steer = quantize(np.asarray(wrap_angle(rows[:, 4 : 4 + n] - beta), dtype=float),
                      opt.counts_per_rev)  # fmt: skip
    wheel = quantize(rows[:, 4 + n : 4 + 2 * n], opt.counts_per_rev)
    encoders = {mid: np.column_stack([t, steer[:, j], wheel[:, j]]) for j, mid in enumerate(ids)}
    true_poses = rows[:: run.pose_every, :4]
    rng = np.random.default_rng(opt.seed)
    meas = true_poses[:, 1:].copy()
    if opt.pose_sigma_xy > 0:
        meas[:, :2] += ar1_noise(rng.normal(0.0, opt.pose_sigma_xy, (len(meas), 2)),
                                 opt.pose_noise_rho)  # fmt: skip
    if opt.pose_sigma_yaw > 0:
        meas[:, 2] += ar1_noise(rng.normal(0.0, opt.pose_sigma_yaw, len(meas)),
                                opt.pose_noise_rho)  # fmt: skip
    meas[:, 2] = wrap_angle(meas[:, 2])
    poses = np.column_stack([true_poses[:, 0], meas])
    segments = [Segment(s.static_module, round(s.start, 6), round(s.end, 6)) for s in spins]
    return TyreExperiment(
        dataset=Dataset(robot=nom, poses=poses, encoders=encoders, segments=segments),
        truth=truth,
        true_poses=true_poses,
        spins=spins,
        duration=float(t[-1]),
        generation_seconds=time.perf_counter() - t_wall,
        physics=opt.physics,
    )
