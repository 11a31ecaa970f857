"""Plan a calibration: the protocol that reaches target std devs in the least robot time.

A calibration's std devs are set by its *design* (the steering angles of the locked
module, the yaw swept per spin, the spin torque and so the yaw rate, the metrology's
noise); its robot time by the same design plus the pauses between spins.  The planner
(docs/plan.md) searches a grid of designs for the fastest whose *predicted* covariance
meets the requirement (:func:`plan`).  Everything here is pure; the prediction itself (a
simulated dataset of the candidate, solved by the joint solver, whose sandwich covariance
is the inverse Fisher information ``H^-1 M H^-1``, ``H = J^T J`` of the weighted
residuals) is passed in as a function, because the simulator lives a layer above
(``services.plan.predict``).

**Robot time** of a candidate on ``N`` modules (:func:`robot_time`; the constants of
:class:`TimeModel` are measured on the in-process simulator, docs/plan.md)::

    T = t_start + N t_probe + N align + (N - 1) t_lock
        + N sum_m (settle + sweep / omega + stop)                   (every spin)
        + N sum_{m>0} (|a_m - a_m-1| / steer_rate + 0.2 resteer)     (every re-steer)
    omega = k tau

(``N t_probe``: with motion capture, the fast part before the first spin, docs/commissioning.md)

and without motion capture (``metrology: imu``: rests of ``rest_time`` before every
spin, after the last, around the straight drive of ``drive_length``)::

    T_imu = T + (N sum_m 1 + 3) rest + drive_length / v_drive + t_drive

with ``v_drive`` the drive's cruise speed and ``t_drive`` the STEER for it and its ramp
and coast (without a drive, one rest at the end and no ``t_drive``).  The operator's
floor mark and tape reading (MARK, MEASURE) are not robot motion: the robot waits
braked, and the in-process simulator's time stands still; they are not counted.  Then
``omega`` is the robot's yaw rate while spinning, ``tau`` the candidate's spin torque
(the wheel torque of the dynamic modules) and ``k`` the robot's yaw rate per unit spin
torque (its damping is viscous: the steady rate is proportional to the torque),
``steer_rate`` the steering's speed limit and ``0.2 resteer`` the hold after a re-steer
(``services.runs.protocol``).  The spin torques a plan may choose: :func:`spin_torques`.

**What a plan must reach** (:class:`Requirement`), both on the predicted covariance
``Sigma`` (5N, 5N) of the candidate:

* **per-parameter targets** per kind (``position``: ``x_s``, ``y_s``, ``b``; ``beta``;
  ``radius``: ``r``): ``worst = max_i,k sd_i,k / target_k <= 1`` (:func:`worst_ratio`);
  by default the robot config's ``tolerances`` (a result within them is installed);
* **the square path** of ``swpc validate`` (docs/odometry.md): with the file ``p + dp``
  driving a robot whose truth is ``p`` (commands and odometry both from the file, so the
  odometry reports the commanded square exactly), the true end pose of an idealised
  square (legs of ``side`` along the body's x at ``speed``, turns in place of 90 deg at
  ``turn_rate``, every twist constant, :func:`square_path_end`) moves by ``e = S dp`` to
  first order, ``S`` by central differences (:func:`square_path_sensitivity`).  The end
  error's covariance is ``S Sigma S^T``.  The end error that 90 % of calibrations stay
  within (:data:`SQUARE_SHARE`; position ``|(x, y)|`` and heading ``|yaw|``, the
  larger of the CW and CCW squares, both within at once: :func:`square_path_quantile`)
  must be within the budget ``(B_p, B_h)``: by default what the calibrated file reaches
  on the square path (docs/figures.md: 0.50 mm, 0.016 deg, against the nominal design's
  68.6 mm, 2.21 deg), so the calibration's own uncertainty keeps the 99.3 % reduction
  the project reports in nine runs of ten.

The square path is judged on the whole covariance, not through per-kind targets derived
from it: the parameters' errors are correlated (docs/plan.md says by how much it matters).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from swpc_hw.calibration.parameters import BETA, N_PARAMS, PARAM_NAMES
from swpc_hw.calibration.parameters import B as B_COL
from swpc_hw.calibration.parameters import R as R_COL
from swpc_hw.calibration.plan.square_error import (
    SQUARE_BUDGET,
    SQUARE_SHARE,
    square_path_quantile,
)
from swpc_hw.errors import CalibrationError
from swpc_hw.protocol import DEFAULT_PROTOCOL, PRECHECK_TIME, has_fast_part
from swpc_hw.robot.model import (
    KIND_OF,
    PARAM_KINDS,
)

FloatArray = NDArray[np.float64]
class PlanError(CalibrationError):
    """No candidate reaches the targets (or the request cannot be planned): the reason."""


@dataclass(frozen=True)
class Targets:
    """Target std devs per parameter kind (SI): ``position`` for ``x_s``, ``y_s``, ``b``;
    ``beta``; ``radius`` for ``r``."""

    position: float
    beta: float
    radius: float

    def __post_init__(self) -> None:
        for k in PARAM_KINDS:
            v = getattr(self, k)
            if not (math.isfinite(v) and v > 0):
                raise PlanError(f"target {k} must be a positive finite std dev (got {v})")

    def per_parameter(self) -> FloatArray:
        """(5,) in the order ``x_s, y_s, beta, b, r``."""
        return np.array([getattr(self, KIND_OF[k]) for k in PARAM_NAMES], dtype=float)

    def document(self) -> dict[str, float]:
        """Display units: mm, deg."""
        return {
            "position_mm": self.position * 1e3,
            "beta_deg": math.degrees(self.beta),
            "radius_mm": self.radius * 1e3,
        }


@dataclass(frozen=True)
class MocapNoise:
    """The motion capture's noise as the planner assumes it (SI)."""

    sigma_xy: float = 0.5e-3
    sigma_yaw: float = math.radians(0.05)
    rate: float = 100.0
    rho: float = 0.0
    """AR(1) coefficient of the noise from frame to frame (0: white)."""


@dataclass(frozen=True)
class Candidate:
    """One protocol design: what the robot config's ``protocol`` section holds, and the
    spin torque (its ``limits.spin_torque``)."""

    angles_deg: tuple[float, ...]
    sweep_deg: float
    settle_time: float
    stop_time: float
    align_time: float
    resteer_time: float
    spin_torque: float
    """N.m: the wheel torque of the dynamic modules while spinning."""
    rest_time: float | None = None
    """s: without motion capture, the rest before every spin, around the drive and at the
    end (the gyro's bias); None: with motion capture (no rests)."""
    drive_length: float | None = None
    """m: without motion capture, the straight drive; None: with motion capture."""

    @property
    def imu(self) -> bool:
        """A run without motion capture (``metrology: imu``): rests and a drive."""
        return self.rest_time is not None

    def protocol(self) -> dict[str, Any]:
        """The robot config's ``protocol`` overrides that run it."""
        out: dict[str, Any] = {
            "angles_deg": list(self.angles_deg),
            "sweep_deg": self.sweep_deg,
            "settle_time": self.settle_time,
            "stop_time": self.stop_time,
            "align_time": self.align_time,
            "resteer_time": self.resteer_time,
        }
        if self.imu:
            out |= {"rest_time": self.rest_time, "drive_length": self.drive_length}
        return out

    def overrides(self) -> dict[str, Any]:
        """The robot config overrides that run it: its ``protocol`` and its
        ``limits.spin_torque``."""
        return {"protocol": self.protocol(), "limits": {"spin_torque": self.spin_torque}}

    def label(self) -> str:
        angles = ", ".join(f"{a:g}" for a in self.angles_deg)
        out = f"angles {angles} deg, {self.sweep_deg:g} deg sweeps, {self.spin_torque:g} N.m"
        if self.imu:
            out += f", rests {self.rest_time:g} s, drive {self.drive_length:g} m"
        return out


@dataclass(frozen=True)
class TimeModel:
    """Robot time of a protocol (module docstring).  Defaults: measured on the in-process
    simulator (paper's robot, docs/plan.md)."""

    rate_per_torque: float = 0.59 / 0.6
    """rad/s per N.m: ``k``, the robot's steady yaw rate while spinning over the spin
    torque (the simulator's: 0.59 rad/s at 0.6 N.m)."""
    steer_rate: float = 3.0
    """rad/s: the steering's speed in a re-steer (the limits' ``max_steer_velocity``)."""
    start: float = 1.0
    """s: CONNECT, PRECHECK, REST and the first LOCK, and the first spin's ramp."""
    lock: float = 0.6
    """s: RELEASE of a module and LOCK of the next."""
    probe: float = PRECHECK_TIME
    """s: the fast part's probe of one module."""
    drive_speed: float = 0.325
    """m/s: without motion capture, the straight drive's cruise speed (the simulator's at
    the limits' ``drive_torque`` of 0.6 N.m)."""
    drive_extra: float = 1.85
    """s: without motion capture, STEER for the drive and the drive's ramp up and coast
    down beyond ``drive_length / drive_speed``."""

    def __post_init__(self) -> None:
        if not (self.rate_per_torque > 0 and self.steer_rate > 0 and self.start >= 0
                and self.lock >= 0 and self.probe >= 0 and self.drive_speed > 0
                and self.drive_extra >= 0):  # fmt: skip
            raise PlanError(
                "time model: rate_per_torque, steer_rate and drive_speed > 0, start, lock "
                "and drive_extra >= 0"
            )

    def yaw_rate(self, spin_torque: float) -> float:
        """rad/s: ``omega = k tau``, the robot's yaw rate at ``spin_torque`` (N.m)."""
        return self.rate_per_torque * spin_torque

    def window(self, c: Candidate) -> float:
        """s: how long candidate ``c``'s window lasts, ``sweep / omega``."""
        return math.radians(c.sweep_deg) / self.yaw_rate(c.spin_torque)


YAW_RATE_MARGIN = 0.85
"""The largest share of ``limits.max_yaw_rate`` a plan's predicted yaw rate may take: the
run fails above the limit, and a real robot's yaw rate at a given spin torque varies
about the predicted one (its damping changes with the floor, the tyres, the battery)."""

TORQUE_STEP = 0.01
"""N.m: the fastest spin torque is rounded down to it (a torque people read)."""


def spin_torques(
    spin_torque: float, max_wheel_torque: float, max_yaw_rate: float, tm: TimeModel
) -> tuple[float, ...]:
    """The spin torques a plan tries, fastest first: the largest within the limits
    (``<= max_wheel_torque``, its yaw rate ``<= YAW_RATE_MARGIN max_yaw_rate``, rounded
    down to :data:`TORQUE_STEP`) and the config's ``spin_torque``, only the config's when
    it is already that fast.  Never slower than the config's: at a given robot time a
    slower spin sweeps less yaw in the same window (as many mocap samples, a shorter
    arc), so it never reaches more."""
    fastest = min(max_wheel_torque, YAW_RATE_MARGIN * max_yaw_rate / tm.rate_per_torque)
    fastest = math.floor(fastest / TORQUE_STEP + 1e-9) * TORQUE_STEP
    fastest = round(fastest, 6)
    return (fastest, spin_torque) if fastest > spin_torque else (spin_torque,)


def robot_time(c: Candidate, n_modules: int, tm: TimeModel) -> float:
    """Predicted robot time (s) of candidate ``c`` on ``n_modules`` (module docstring)."""
    m = len(c.angles_deg)
    spin = c.settle_time + tm.window(c) + c.stop_time
    resteer = sum(
        abs(math.radians(b - a)) / tm.steer_rate + 0.2 * c.resteer_time
        for a, b in zip(c.angles_deg[:-1], c.angles_deg[1:], strict=True)
    )
    per_module = c.align_time + m * spin + resteer
    t = tm.start + n_modules * per_module + (n_modules - 1) * tm.lock
    if has_fast_part(n_modules, "mocap" if c.rest_time is None else "imu"):
        t += n_modules * tm.probe  # the fast part first
    if c.rest_time is not None and c.drive_length is not None:  # without motion capture
        rests = n_modules * m + (3 if c.drive_length > 0 else 1)
        t += rests * c.rest_time
        if c.drive_length > 0:
            t += c.drive_length / tm.drive_speed + tm.drive_extra
    return t


def stddevs(covariance: FloatArray) -> FloatArray:
    """(N, 5) std devs from a (5N, 5N) covariance (modules in order, NaN stays NaN)."""
    d = np.diag(np.asarray(covariance, dtype=float))
    return np.asarray(np.sqrt(d).reshape(-1, N_PARAMS), dtype=float)


def worst_ratio(sd: FloatArray, targets: Targets, mask: NDArray[np.bool_] | None = None) -> float:
    """``max_i,k sd_i,k / target_k`` over an (N, 5) matrix of std devs (NaN: infinite),
    on the parameters of ``mask`` (N, 5) only when given."""
    r = np.asarray(sd, dtype=float) / targets.per_parameter()[None, :]
    if mask is not None:
        r = np.where(mask, r, 0.0)
    return math.inf if not np.all(np.isfinite(r)) else float(np.max(r))


def worst_per_kind(sd: FloatArray) -> dict[str, float]:
    """The largest std dev of each kind over the modules (SI)."""
    out: dict[str, float] = {}
    for c, k in enumerate(PARAM_NAMES):
        kind = KIND_OF[k]
        out[kind] = max(out.get(kind, 0.0), float(np.max(sd[:, c])))
    return out


# ------------------------------------------------------------------ the search


@dataclass(frozen=True)
class Requirement:
    """What a plan must reach (module docstring): per-kind ``targets`` and, when
    ``square`` (the :func:`square_path_sensitivity` of the robot) is given, the square
    path's end error within ``budget`` (m, rad) in ``share`` of runs."""

    targets: Targets
    square: FloatArray | None = None
    budget: tuple[float, float] = SQUARE_BUDGET
    share: float = SQUARE_SHARE

    def __post_init__(self) -> None:
        if not all(math.isfinite(v) and v > 0 for v in self.budget):
            raise PlanError(f"square-path budget must be positive and finite (got {self.budget})")
        if not 0.0 < self.share < 1.0:
            raise PlanError(f"square-path share must be within (0, 1) (got {self.share})")

    def square_bound(self, covariance: FloatArray) -> tuple[float, float, float] | None:
        """The square path's end error that ``share`` of runs stay within: ``(position,
        heading, ratio to the budget)`` (:func:`square_path_quantile`), None without
        ``square``."""
        if self.square is None:
            return None
        return square_path_quantile(self.square, covariance, self.budget, self.share)

    def ratio(self, covariance: FloatArray, mask: NDArray[np.bool_] | None = None) -> float:
        """The largest of ``sd / target`` (every parameter, or those of ``mask``) and the
        square path's ``quantile / budget``: at most 1 when the covariance meets the
        requirement."""
        r = worst_ratio(stddevs(covariance), self.targets, mask)
        sq = self.square_bound(covariance)
        if sq is not None:
            r = max(r, sq[2])
        return r

    def document(self) -> dict[str, Any]:
        """Display units: mm, deg, percent of runs."""
        return {
            **self.targets.document(),
            "square_position_mm": None if self.square is None else self.budget[0] * 1e3,
            "square_heading_deg": None if self.square is None else math.degrees(self.budget[1]),
            "square_share_percent": None if self.square is None else self.share * 100,
        }


ANGLE_SETS: tuple[tuple[float, ...], ...] = (
    DEFAULT_PROTOCOL.angles_deg, (45.0, 225.0), (45.0, 165.0, 285.0)
)
"""The steering angles tried (deg): the default pair, a pair 180 deg apart (the longest
chord), three 120 deg apart.  Every module gets the same set (the protocol's
``angles_deg``)."""

SWEEPS: tuple[float, ...] = (30.0, 45.0, 60.0, 75.0, 90.0, 105.0, 120.0, 135.0, 150.0, 165.0,
                             180.0, 210.0, 240.0, 270.0, 300.0, 360.0, 420.0, 480.0, 540.0,
                             600.0, 720.0)  # fmt: skip
"""The sweeps tried (deg of yaw per spin).  Beyond a turn: at the fastest spin torque a
window of 360 deg lasts 6.2 s, and the default protocol's own std devs need windows as
long as its own (10.6 s at 0.59 rad/s, docs/plan.md)."""


@dataclass
class Evaluated:
    """A candidate as the planner saw it."""

    candidate: Candidate
    robot_time: float
    covariance: FloatArray | None = None
    """(5N, 5N) predicted covariance; None: not predicted (a faster one met the
    requirement, or it was left out)."""
    ratio: float = math.nan
    """:meth:`Requirement.ratio` of the prediction."""
    failure: str = ""
    """Why the prediction failed (a :class:`PlanError`'s reason), if it did."""


@dataclass
class Plan:
    """The planner's answer: the fastest candidate predicted to meet the requirement."""

    candidate: Candidate
    robot_time: float
    covariance: FloatArray
    """(5N, 5N) predicted covariance, modules in the robot's order (SI)."""
    requirement: Requirement
    ids: list[int]
    time_model: TimeModel
    tried: list[Evaluated] = field(default_factory=list)

    @property
    def yaw_rate(self) -> float:
        """rad/s: the predicted yaw rate at the plan's spin torque."""
        return self.time_model.yaw_rate(self.candidate.spin_torque)

    @property
    def stddev(self) -> FloatArray:
        """(N, 5) predicted std devs."""
        return stddevs(self.covariance)

    @property
    def ratio(self) -> float:
        return self.requirement.ratio(self.covariance)

    def document(self) -> dict[str, Any]:
        """Plain data (display units: mm, deg), as ``swpc plan --json`` and the run's
        status give it."""
        sd = self.stddev
        sq = self.requirement.square_bound(self.covariance)
        return {
            "protocol": self.candidate.protocol(),
            "spin_torque_nm": self.candidate.spin_torque,
            "yaw_rate_rad_s": round(self.yaw_rate, 3),
            "robot_time_s": round(self.robot_time, 1),
            "requirement": self.requirement.document(),
            "ratio": self.ratio,
            "square_position_mm": None if sq is None else sq[0] * 1e3,
            "square_heading_deg": None if sq is None else math.degrees(sq[1]),
            "predicted": [
                {
                    "module": m,
                    "x_s_mm": float(sd[i, 0]) * 1e3,
                    "y_s_mm": float(sd[i, 1]) * 1e3,
                    "beta_deg": math.degrees(float(sd[i, BETA])),
                    "b_mm": float(sd[i, B_COL]) * 1e3,
                    "r_mm": float(sd[i, R_COL]) * 1e3,
                }
                for i, m in enumerate(self.ids)
            ],
            "tried": [
                {
                    "protocol": e.candidate.label(),
                    "robot_time_s": round(e.robot_time, 1),
                    "ratio": e.ratio,
                }
                for e in self.tried
                if e.covariance is not None
            ],
        }


def candidates(
    pauses: Candidate,
    angle_sets: Iterable[Sequence[float]] = ANGLE_SETS,
    sweeps: Iterable[float] = SWEEPS,
    torques: Iterable[float] | None = None,
) -> list[Candidate]:
    """Every design of the grid with ``pauses``' settle, stop, align and re-steer times,
    at each of ``torques`` (None: ``pauses``' spin torque)."""
    sweeps = list(sweeps)
    taus = [pauses.spin_torque] if torques is None else list(torques)
    return [
        replace(pauses, angles_deg=tuple(float(a) for a in angles), sweep_deg=float(s),
                spin_torque=float(t))
        for angles in angle_sets
        for t in taus
        for s in sweeps
    ]  # fmt: skip


def plan(
    predict: Callable[[Candidate], FloatArray],
    requirement: Requirement,
    ids: list[int],
    pauses: Candidate,
    time_model: TimeModel,
    *,
    angle_sets: Iterable[Sequence[float]] = ANGLE_SETS,
    sweeps: Iterable[float] = SWEEPS,
    torques: Iterable[float] | None = None,
    max_spin_time: float | None = None,
    variants: Sequence[Candidate] | None = None,
    min_window: float = 0.0,
) -> Plan:
    """The fastest candidate whose predicted covariance meets ``requirement``.

    ``predict(c)`` returns the (5N, 5N) covariance of candidate ``c`` (modules in ``ids``
    order).  Candidates: every set of ``angle_sets`` at every spin torque of ``torques``
    (None: ``pauses``' spin torque; :func:`spin_torques`) and every sweep.  At a given set
    of angles and torque the std devs shrink as the sweep grows, and the robot time grows:
    per (set, torque), the fastest torque first, among the sweeps faster than the best
    plan so far, the largest is predicted first (when it falls short, so does the pair),
    then bisection finds the smallest with ``requirement.ratio(predict(c)) <= 1``; the
    plan is the fastest of these.  Left out: a candidate whose spin (settle and sweep)
    would last ``max_spin_time`` (s, the step timeout) or more, or whose window would be
    shorter than ``min_window`` (s).  ``variants``: other
    pauses than ``pauses`` to try, each with every set, torque and sweep (without motion
    capture: the rests and the drive, the shortest first).  A candidate whose
    prediction raises :class:`PlanError` falls short.  None meets the requirement:
    :class:`PlanError` naming the closest (or the first failure, none predicted)."""
    n = len(ids)
    sweeps = sorted(float(s) for s in sweeps)
    taus = sorted((pauses.spin_torque,) if torques is None else torques, reverse=True)
    tried: list[Evaluated] = []
    best: Evaluated | None = None
    groups = [(a, t, v) for a in angle_sets for t in taus for v in (variants or [pauses])]
    for angles, tau, var in groups:
        pool = [
            Evaluated(c, robot_time(c, n, time_model))
            for c in candidates(var, [angles], sweeps, [tau])
            if (max_spin_time is None or c.settle_time + time_model.window(c) < max_spin_time)
            and time_model.window(c) >= min_window
        ]
        if best is not None:
            pool = [e for e in pool if e.robot_time < best.robot_time]
        tried += pool

        def meets(e: Evaluated) -> bool:
            try:
                e.covariance = np.asarray(predict(e.candidate), dtype=float)
            except PlanError as exc:  # a design the prediction cannot solve
                e.failure, e.ratio = str(exc), math.inf
                return False
            e.ratio = requirement.ratio(e.covariance)
            return e.ratio <= 1.0

        if not pool or not meets(pool[-1]):  # not even the largest sweep: none of the pair
            continue
        best = pool[-1]
        lo, hi = 0, len(pool) - 2
        while lo <= hi:
            mid = (lo + hi) // 2
            if meets(pool[mid]):
                best, hi = pool[mid], mid - 1
            else:
                lo = mid + 1
    tried.sort(key=lambda e: e.robot_time)
    if best is not None:
        assert best.covariance is not None
        return Plan(
            best.candidate, best.robot_time, best.covariance, requirement, list(ids),
            time_model, tried,
        )  # fmt: skip
    seen = [e for e in tried if e.covariance is not None]
    if not seen:
        failed = [e.failure for e in tried if e.failure]
        raise PlanError(
            failed[0] if failed else
            "no candidate protocol fits the limits (a spin within the step timeout)"
        )  # fmt: skip
    closest = min(seen, key=lambda e: e.ratio)
    raise PlanError(
        f"no candidate protocol reaches the requirement: the closest "
        f"({closest.candidate.label()}, {closest.robot_time:.0f} s of robot time) is "
        f"{closest.ratio:.2f} times it"
    )
