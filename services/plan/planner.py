"""A calibration planned from the information it yields (docs/plan.md).

:func:`plan_for` gives the planner (:func:`swpc_hw.calibration.plan.plan.plan`) what the robot
config says: the modules, the pauses the check uses (``check.settle_time``,
``stop_time``, ``align_time``: shorter than a calibration's and validated through the
service, docs/check.md) with the protocol's re-steer time, the spin torques within the
limits (:func:`swpc_hw.calibration.plan.plan.spin_torques`: the config's ``spin_torque`` and the
fastest under ``max_wheel_torque`` and ``max_yaw_rate``), the steering's speed limit, the
step timeout, and by default the ``tolerances`` as the per-parameter targets; the
prediction is :func:`services.plan.predict.predicted_covariance` on the nominal robot,
kept (:data:`_PREDICTED`); the plan's sequential stopping takes its spins from the
prediction's solve of the first seed, which it is (:func:`stopping_for`).
``swpc plan`` prints its answer; ``POST /calibrations {"plan": "auto"}`` runs it (the plan's
:meth:`~swpc_hw.calibration.plan.plan.Candidate.overrides`, its protocol and spin torque, as the
run's).

A plan takes seconds to a minute of CPU (a solve per candidate predicted): the service
makes it in the background, one at a time, and keeps it (:class:`Planner`), so that no
request waits for it.
"""

from __future__ import annotations

import functools
import math
import threading
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Generic, TypeVar

from services.config.robot import MAX_DRIVE_LENGTH, MIN_REST_TIME, RobotConfig
from services.plan.predict import (
    mean_covariance,
    predicted_imu_covariance,
    predicted_solution,
    predicted_spins,
    spins_of_solution,
)
from swpc_hw.calibration.gyro.solver import COARSE_INTERVAL
from swpc_hw.calibration.mocap.solver import JointSolution
from swpc_hw.calibration.plan.forecast import SpinInformation, Stopping
from swpc_hw.calibration.plan.plan import (
    Candidate,
    FloatArray,
    MocapNoise,
    Plan,
    PlanError,
    Requirement,
    Targets,
    TimeModel,
    plan,
    spin_torques,
)
from swpc_hw.calibration.plan.square_error import SQUARE_BUDGET, square_path_sensitivity
from swpc_hw.robot.model import RobotParams
from swpc_hw.sensors.gyro import GyroOptions

PLANNED_KEYS = frozenset(
    f"{group}.{name}"
    for group, names in Candidate((), 0.0, 0.0, 0.0, 0.0, 0.0, 1.0).overrides().items()
    for name in names
)
"""The robot config settings a plan chooses, ``group.name`` (a request may not set them
too): those of :meth:`Candidate.overrides`."""
IMU_PLANNED_KEYS = PLANNED_KEYS | {"protocol.rest_time", "protocol.drive_length"}
"""Those a plan without motion capture chooses: the rests and the drive too."""

REST_TIMES = (MIN_REST_TIME, 2.0 * MIN_REST_TIME)
"""s: the rests a plan without motion capture tries (the shortest the solver takes, and
the protocol's default)."""
MIN_IMU_WINDOW = 1.25 * COARSE_INTERVAL
"""s: the shortest window a plan without motion capture spins: the IMU solver's first,
coarse solve needs a wheel increment per spin (one per ``COARSE_INTERVAL``; a 30 deg
window of 0.52 s at 1.01 rad/s failed the run), with a margin."""
DRIVE_LENGTHS = (1.0, 2.0, 4.0)
"""m: the straight drives a plan without motion capture tries (within
``MAX_DRIVE_LENGTH`` and the step timeout at ``limits.max_drive_speed``)."""


def default_budget(metrology: str) -> tuple[float, float] | None:
    """The square path's budget a plan for ``metrology`` requires by default: with motion
    capture :data:`SQUARE_BUDGET`; without it none (docs/plan.md: in ``design-fit`` the
    square's error is that of the layout's length scale, which only the tape fixes: 8.5
    times the budget whatever the robot does)."""
    return None if metrology == "imu" else SQUARE_BUDGET


def planned_keys(metrology: str) -> frozenset[str]:
    """The settings a plan for ``metrology`` chooses."""
    return IMU_PLANNED_KEYS if metrology == "imu" else PLANNED_KEYS


@dataclass(frozen=True)
class PlanRequest:
    """What may change a plan besides the robot config (SI; None: the default)."""

    targets: Targets | None = None
    """Per-kind targets; None: the config's ``tolerances``."""
    budget: tuple[float, float] | None = SQUARE_BUDGET
    """The square path's (position, heading) budget; None: not required."""
    noise: MocapNoise = field(default_factory=MocapNoise)
    yaw_rate: float | None = None
    """rad/s while spinning at the config's ``limits.spin_torque`` (a run's segments give
    it: the sweep over the window's length); None: the in-process simulator's
    (:attr:`TimeModel.rate_per_torque`).  Other torques' in proportion."""
    metrology: str = "mocap"
    """``mocap`` or ``imu`` (the gyro and the tape: rests and a straight drive too)."""
    gyro: GyroOptions = field(default_factory=GyroOptions)
    """Without motion capture: the gyro's noise the prediction assumes (the service's
    ``sim_gyro_*`` settings, by default :class:`GyroOptions`')."""


def time_model(config: RobotConfig, yaw_rate: float | None = None) -> TimeModel:
    """The robot's :class:`TimeModel` from its config (and a measured yaw rate at its spin
    torque)."""
    lim = config.limits
    tm = TimeModel(steer_rate=lim.max_steer_velocity)
    if yaw_rate is not None:
        if not (math.isfinite(yaw_rate) and yaw_rate > 0):
            raise PlanError(f"yaw rate must be positive and finite (got {yaw_rate})")
        tm = replace(tm, rate_per_torque=yaw_rate / lim.spin_torque)
    w = tm.yaw_rate(lim.spin_torque)
    if w > lim.max_yaw_rate:
        raise PlanError(
            f"yaw rate {w:g} rad/s at limits.spin_torque {lim.spin_torque:g} N.m exceeds "
            f"limits.max_yaw_rate {lim.max_yaw_rate:g} rad/s"
        )
    return tm


def pauses(config: RobotConfig) -> Candidate:
    """The pauses a plan uses (module docstring) at the config's spin torque; angles,
    sweep and spin torque are the planner's."""
    c, p = config.check, config.protocol
    return Candidate(
        (), 0.0, c.settle_time, c.stop_time, c.align_time, p.resteer_time,
        config.limits.spin_torque,
    )  # fmt: skip


def plan_for(config: RobotConfig, request: PlanRequest | None = None) -> Plan:
    """The plan of a calibration of ``config``'s robot with motion capture (module
    docstring).  :class:`~swpc_hw.calibration.plan.plan.PlanError` when no candidate meets the
    requirement, with the closest named."""
    req = request or PlanRequest()
    tol = config.tolerances
    targets = req.targets or Targets(tol.position, tol.beta, tol.radius)
    nominal = config.nominal
    if config.protocol.modules is not None and set(config.protocol.modules) != set(nominal.ids):
        raise PlanError("a plan locks every module (protocol.modules must be all or unset)")
    square = None if req.budget is None else square_path_sensitivity(nominal)
    requirement = Requirement(targets, square, req.budget or SQUARE_BUDGET)
    tm = time_model(config, req.yaw_rate)
    lim = config.limits
    torques = spin_torques(lim.spin_torque, lim.max_wheel_torque, lim.max_yaw_rate, tm)

    key = nominal.model_dump_json()
    if req.metrology == "imu":
        base = pauses(config)

        def predict_imu(c: Candidate) -> FloatArray:
            return _predicted_imu(key, c, req.gyro, tm)

        return plan(
            predict_imu, requirement, nominal.ids, base, tm, torques=torques,
            max_spin_time=lim.step_timeout, variants=imu_variants(config, base),
            min_window=MIN_IMU_WINDOW,
        )  # fmt: skip
    if req.metrology != "mocap":
        raise PlanError(f"no plan for metrology {req.metrology} (mocap or imu)")

    meeting: dict[Candidate, JointSolution] = {}  # the first seed's solve of those that meet
    robot = RobotParams.model_validate_json(key)

    def predict(c: Candidate) -> FloatArray:
        def solved() -> FloatArray:
            sols = [predicted_solution(robot, c, req.noise, tm, s) for s in SEEDS]
            cov = mean_covariance(c, sols)
            if requirement.ratio(cov) <= 1.0:  # the plan is one of them
                meeting[c] = sols[0]
            return cov

        return _PREDICTED.get((key, c, req.noise, tm), solved)

    p = plan(
        predict, requirement, nominal.ids, pauses(config), tm, torques=torques,
        max_spin_time=lim.step_timeout,
    )  # fmt: skip
    if p.candidate in meeting:  # its spins from the prediction's solve: not solved again
        sol = meeting[p.candidate]
        _SPINS.get((key, p.candidate, req.noise, tm),
                   lambda: tuple(spins_of_solution(p.candidate, sol)))  # fmt: skip
    return p


def imu_variants(config: RobotConfig, base: Candidate) -> list[Candidate]:
    """``base`` with every rest of :data:`REST_TIMES` and drive of :data:`DRIVE_LENGTHS`
    the limits allow (a drive between two rests within ``limits.step_timeout`` at
    ``limits.max_drive_speed``, as the run checks), the shortest first."""
    lim = config.limits
    out = [
        replace(base, rest_time=r, drive_length=d)
        for r in REST_TIMES
        for d in DRIVE_LENGTHS
        if d <= MAX_DRIVE_LENGTH and 2 * r + d / lim.max_drive_speed < lim.step_timeout
        and r < lim.step_timeout
    ]  # fmt: skip
    if not out:
        raise PlanError("no rest and straight drive fits limits.step_timeout")
    return out


def stopping_for(config: RobotConfig, p: Plan, request: PlanRequest | None = None) -> Stopping:
    """The sequential stopping of a run of plan ``p`` (docs/plan.md): the plan's spins
    from a simulated run of it (kept, like the prediction) and its requirement."""
    req = request or PlanRequest()
    tm = time_model(config, req.yaw_rate)
    spins = _spins(config.nominal.model_dump_json(), p.candidate, req.noise, tm)
    return Stopping(spins, p.requirement)


class PlannerBusyError(PlanError):
    """Another plan is being made (the service makes one at a time)."""


class Planner:
    """Plans made in the background, one at a time, the newest ``keep`` kept (with the
    error of one that could not be made).

    :meth:`get` answers at once: the plan, or None while it is being made (it starts it
    when nothing else is being made), or raises the :class:`PlanError` it ended with, or
    :class:`PlannerBusyError` while another is being made."""

    def __init__(self, keep: int = 16) -> None:
        self._lock = threading.Lock()
        self._done: OrderedDict[tuple[str, PlanRequest], Plan | PlanError] = OrderedDict()
        self._making: tuple[str, PlanRequest] | None = None
        self._keep = keep

    def get(
        self, config: RobotConfig, request: PlanRequest | None = None, *, start: bool = True
    ) -> Plan | None:
        """``start=False``: a plan not made yet is not started either
        (:class:`PlannerBusyError`): no plan takes CPU from a run."""
        req = request or PlanRequest()
        if req.targets is None:  # the same plan as with the tolerances given
            tol = config.tolerances
            req = replace(req, targets=Targets(tol.position, tol.beta, tol.radius))
        key = (config.model_dump_json(), req)
        with self._lock:
            if key in self._done:
                out = self._done[key]
                if isinstance(out, PlanError):
                    raise out
                return out
            if self._making == key:
                return None
            if self._making is not None:
                raise PlannerBusyError("another plan is being made: ask again in a minute")
            if not start:
                raise PlannerBusyError("plans are made between runs: ask again after this one")
            self._making = key
        threading.Thread(
            target=self._make, args=(key, config, req), name="swpc-plan", daemon=True
        ).start()
        return None

    def _make(self, key: tuple[str, PlanRequest], config: RobotConfig, req: PlanRequest) -> None:
        out: Plan | PlanError
        try:
            out = plan_for(config, req)
            if req.metrology == "mocap":  # sequential stopping is motion capture's
                stopping_for(config, out, req)  # kept: a run of it starts at once
        except PlanError as exc:
            out = exc
        except Exception as exc:  # a bug: its reason, not a planner stuck for ever
            out = PlanError(f"the plan could not be made: {type(exc).__name__}: {exc}")
        with self._lock:
            self._done[key] = out
            while len(self._done) > self._keep:
                self._done.popitem(last=False)
            self._making = None


K = TypeVar("K")
V = TypeVar("V")


class Kept(Generic[K, V]):
    """The newest ``size`` values made, by key (thread-safe; a value that raises is not
    kept): the planner's predictions, kept because a plan of the same robot is the same
    plan (the prediction's seeds are fixed) and the service plans every ``plan: auto``
    run."""

    def __init__(self, size: int) -> None:
        self._lock = threading.Lock()
        self._done: OrderedDict[K, V] = OrderedDict()
        self._size = size

    def get(self, key: K, make: Callable[[], V]) -> V:
        """The value kept for ``key``, else ``make()``'s (then kept)."""
        with self._lock:
            if key in self._done:
                self._done.move_to_end(key)
                return self._done[key]
        value = make()
        with self._lock:
            self._done[key] = value
            while len(self._done) > self._size:
                self._done.popitem(last=False)
        return value


SEEDS = (0, 1)
"""The noise draws a prediction averages (:func:`services.plan.predict.predicted_covariance`);
sequential stopping's spins are the first's (:func:`stopping_for`)."""

PredictionKey = tuple[str, Candidate, MocapNoise, TimeModel]
"""The nominal robot (its JSON), the candidate, the noise, the time model."""
_PREDICTED: Kept[PredictionKey, FloatArray] = Kept(256)
""":func:`services.plan.predict.predicted_covariance` of the nominal robot over
:data:`SEEDS`, kept."""
_SPINS: Kept[PredictionKey, tuple[SpinInformation, ...]] = Kept(16)
""":func:`services.plan.predict.predicted_spins` of seed 0, kept: :func:`plan_for`
keeps those of its plan from the prediction's solve."""


@functools.lru_cache(maxsize=256)
def _predicted_imu(nominal: str, c: Candidate, gyro: GyroOptions, tm: TimeModel) -> FloatArray:
    """:func:`predicted_imu_covariance` (the tape as the operator reads it), kept."""
    robot = RobotParams.model_validate_json(nominal)
    return predicted_imu_covariance(robot, c, gyro, tm)


def _spins(
    nominal: str, c: Candidate, noise: MocapNoise, tm: TimeModel
) -> tuple[SpinInformation, ...]:
    """:func:`predicted_spins`, kept (:data:`_SPINS`)."""

    def make() -> tuple[SpinInformation, ...]:
        robot = RobotParams.model_validate_json(nominal)
        return tuple(predicted_spins(robot, c, noise, tm, SEEDS[0]))

    return _SPINS.get((nominal, c, noise, tm), make)


def plan_text(p: Plan) -> str:
    """The plan for people: the protocol, its robot time, the requirement and, per module,
    the predicted std devs (mm, deg)."""
    c, doc = p.candidate, p.document()
    req = doc["requirement"]
    lines = [
        f"plan: steering angles {', '.join(f'{a:g}' for a in c.angles_deg)} deg, "
        f"{c.sweep_deg:g} deg sweeps; settle {c.settle_time:g} s, stop {c.stop_time:g} s, "
        f"align {c.align_time:g} s, re-steer {c.resteer_time:g} s",
        *(
            [
                f"without motion capture: rests {c.rest_time:g} s, straight drive "
                f"{c.drive_length:g} m"
            ]
            if c.imu
            else []
        ),
        f"spin torque: {c.spin_torque:g} N.m (yaw rate {p.yaw_rate:.2f} rad/s, predicted)",
        f"robot time: {p.robot_time:.1f} s (predicted)",
        f"targets: position {req['position_mm']:.4g} mm, beta {req['beta_deg']:.4g} deg, "
        f"radius {req['radius_mm']:.4g} mm"
        + (
            ""
            if req["square_position_mm"] is None
            else f"; square path within {req['square_position_mm']:.3g} mm, "
            f"{req['square_heading_deg']:.3g} deg in {req['square_share_percent']:.0f} % of runs"
        ),
    ]
    if doc["square_position_mm"] is not None:
        lines.append(
            f"square path (predicted, {req['square_share_percent']:.0f} % of runs within): "
            f"{doc['square_position_mm']:.3f} mm, {doc['square_heading_deg']:.4f} deg"
        )
    lines.append(f"{'module':>6} {'x_s mm':>9} {'y_s mm':>9} {'beta deg':>9} {'b mm':>9} "
                 f"{'r mm':>9}")  # fmt: skip
    for row in doc["predicted"]:
        lines.append(
            f"{row['module']:>6} {row['x_s_mm']:9.4f} {row['y_s_mm']:9.4f} "
            f"{row['beta_deg']:9.5f} {row['b_mm']:9.4f} {row['r_mm']:9.5f}"
        )
    lines.append("candidates predicted (robot time, share of the requirement; <= 1 meets it):")
    for t in doc["tried"]:
        ratio = "inf" if not math.isfinite(t["ratio"]) else f"{t['ratio']:.2f}"
        lines.append(f"  {t['protocol']:<54} {t['robot_time_s']:6.1f} s  {ratio}")
    return "\n".join(lines)
