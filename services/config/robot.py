"""Robot configuration: what the service needs to calibrate one robot.

YAML (every key documented in ``deploy/robot.example.yaml``)::

    robot: swpc                      # robot id (pose key mocap/<robot>/pose)
    nominal: {modules: [...]}        # or a path: nominal kinematics (kinematic-file schema)
    base_link: {x: 0, y: 0, yaw: 0}  # or centroid; unset: base_link = R (docs/ros2.md)
    drives: {kind: swpc, modules: {1: 1, 2: 2, 3: 3, 4: 4}}  # drive kind, CAN nodes
    limits: {...}                    # motion limits (SI)
    protocol: {...}                  # calibration protocol (angles in degrees for humans)
    tolerances: {...}                # max std devs for a result to be installed

Overrides in ``POST /calibrations`` are validated against the same model and may only
tighten the robot config's safety limits (:meth:`RobotConfig.for_run`); everything about
a run that can be checked before motion is checked by :meth:`RobotConfig.run_problems`
(422 on error, before any CAN frame).
"""

from __future__ import annotations

import itertools
import math
from pathlib import Path
from typing import Any, Literal, Optional

import yaml
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from swpc_hw.drives.bus import DEFAULT_WATCHDOG_MS
from swpc_hw.drives.registry import DrivesConfig, parse_drives
from swpc_hw.drives.swpc.config import SwpcDrives
from swpc_hw.errors import SwpcError
from swpc_hw.files.kinematic_file import kinematics_document, load_robot, parse_kinematics
from swpc_hw.protocol import DEFAULT_PROTOCOL as _DEFAULT
from swpc_hw.robot.frames import BaseLink
from swpc_hw.robot.model import KIND_OF, PARAM_NAMES, RobotParams
from swpc_hw.robot.paper_robot import PAPER_NOMINAL
from swpc_hw.sensors.mocap import pose_key


class RobotConfigError(SwpcError, ValueError):
    """The robot configuration is invalid."""


class OverrideError(SwpcError, ValueError):
    """Per-run overrides that would loosen a safety limit, or a run that cannot succeed;
    ``problems`` lists every reason (one line each, naming the key)."""

    def __init__(self, problems: list[str]) -> None:
        super().__init__("; ".join(problems))
        self.problems = problems


STRICT = ConfigDict(extra="forbid", allow_inf_nan=False)
"""Unknown keys and non-finite numbers are errors (NaN passes every ``gt``/``le`` test
otherwise, and Infinity every ``gt``)."""


class MotionLimits(BaseModel):
    """Everything that bounds motion during calibration (SI units).

    Every limit is tighter when smaller; a run's overrides may only tighten them
    (:data:`RUN_FIXED_LIMITS`: not per run at all).
    """

    model_config = STRICT

    spin_torque: float = Field(0.6, gt=0, description="wheel torque of the dynamic modules, N.m")
    max_wheel_torque: float = Field(2.0, gt=0, description="controller torque limit, N.m")
    max_wheel_velocity: float = Field(20.0, gt=0, description="controller wheel speed limit, rad/s")
    max_steer_velocity: float = Field(3.0, gt=0, description="controller steering speed limit")
    max_yaw_rate: float = Field(1.2, gt=0, description="spin aborted above this yaw rate, rad/s")
    rest_yaw_rate: float = Field(
        0.02, gt=0, description="at rest (wheels braked, before locking) below this, rad/s"
    )
    rest_speed: float = Field(
        0.01, gt=0, description="at rest (wheels braked, before locking) below this, m/s"
    )
    step_timeout: float = Field(60.0, gt=0, description="any single step longer than this fails, s")
    watchdog_ms: int = Field(
        DEFAULT_WATCHDOG_MS, ge=20, le=60000, description="controller command timeout, ms"
    )
    drive_torque: float = Field(
        0.6, gt=0, description="wheel torque of every wheel in the straight drive, N.m"
    )
    max_drive_speed: float = Field(
        0.5,
        gt=0,
        description="the straight drive fails above this speed (wheel encoders, nominal r), m/s",
    )

    @model_validator(mode="after")
    def _torque_within_limit(self) -> MotionLimits:
        if self.spin_torque > self.max_wheel_torque:
            raise ValueError("spin_torque must not exceed max_wheel_torque")
        if self.drive_torque > self.max_wheel_torque:
            raise ValueError("drive_torque must not exceed max_wheel_torque")
        return self


RUN_FIXED_LIMITS = frozenset({"watchdog_ms"})
"""Limits set for the service in the robot config only: the controllers' command watchdog
is sent at activation and the driver's refresh period and the timing budget
(:mod:`services.config.timing`) are derived from it."""

MAX_ANGLE_DEG = 360.0
MAX_DRIVE_LENGTH = 20.0
"""m: the longest straight drive a run may ask for (the floor space it needs)."""
MIN_REST_TIME = 1.0
"""s: the shortest rest the IMU solver finds (0.5 s still, trimmed 0.1 s at both
ends, swpc_hw.calibration.gyro.bias) with a margin."""
MIN_ANGLE_SEPARATION_DEG = 10.0


def _circular_gap(a: float, b: float) -> float:
    """Smallest difference of two angles in degrees, modulo 360 (0..180)."""
    d = (a - b) % 360.0
    return min(d, 360.0 - d)


class ProtocolConfig(BaseModel):
    """The calibration protocol (angles in degrees, times in seconds); its defaults are
    :data:`swpc_hw.protocol.DEFAULT_PROTOCOL`."""

    model_config = STRICT

    angles_deg: list[float] = Field(
        default_factory=lambda: list(_DEFAULT.angles_deg), min_length=1, max_length=12
    )
    """A calibration needs two or more (:meth:`RobotConfig.run_problems`); a check, one."""
    sweep_deg: float = Field(
        _DEFAULT.sweep_deg, gt=10, le=3600, description="mocap-measured sweep per spin"
    )
    settle_time: float = Field(
        _DEFAULT.settle_time, ge=0, description="spin time before the window opens, s"
    )
    stop_time: float = Field(_DEFAULT.stop_time, ge=0, description="time allowed to spin down, s")
    align_time: float = Field(
        _DEFAULT.align_time, ge=0, description="time to align the dynamic modules, s"
    )
    resteer_time: float = Field(
        _DEFAULT.resteer_time, gt=0, description="time to re-steer the locked module, s"
    )
    modules: list[int] | None = Field(None, description="modules to lock (default all)")
    rest_time: float = Field(
        _DEFAULT.rest_time,
        ge=0,
        description="without motion capture: the robot held still before every spin, "
        "around the straight drive and at the end (the gyro's bias), s",
    )
    drive_length: float = Field(
        _DEFAULT.drive_length,
        ge=0,
        le=MAX_DRIVE_LENGTH,
        description="without motion capture: the straight drive at the end, m (0: none; "
        "a wheel_radius reference is then needed)",
    )
    drive_heading_deg: float = Field(
        0.0,
        ge=-360,
        le=360,
        description="without motion capture: the straight drive's direction in R, deg "
        "(0: along x)",
    )
    operator_timeout: float = Field(
        900.0,
        gt=0,
        le=86400,
        description="without motion capture: how long a run waits for the operator's floor "
        "mark and tape measurement of the drive, s",
    )
    precheck: bool = Field(
        True,
        description="with motion capture: before the first spin, every module locked at the "
        "first angle and turned a few degrees about (docs/commissioning.md): a robot "
        "that does not match its config is refused there, the axis named",
    )

    @field_validator("angles_deg")
    @classmethod
    def _distinct(cls, v: list[float]) -> list[float]:
        if any(not math.isfinite(a) for a in v):
            raise ValueError("angles must be finite")
        if any(abs(a) > MAX_ANGLE_DEG for a in v):
            raise ValueError(f"steering angles must be within +-{MAX_ANGLE_DEG:g} deg")
        # the steering is a circle: 0 and 360 deg are the same angle
        for a, b in itertools.combinations(v, 2):
            if _circular_gap(a, b) < MIN_ANGLE_SEPARATION_DEG:
                raise ValueError(
                    f"steering angles must differ by at least {MIN_ANGLE_SEPARATION_DEG:g} "
                    f"deg modulo 360 ({a:g} and {b:g} are {_circular_gap(a, b):g} deg apart)"
                )
        return v


class Tolerances(BaseModel):
    """A result whose std devs exceed these is reported but not installed (SI).  Tighter
    when smaller; a run's overrides may only tighten them."""

    model_config = STRICT

    position: float = Field(0.5e-3, gt=0, description="x_s, y_s, b std dev, m")
    beta: float = Field(math.radians(0.2), gt=0, description="beta std dev, rad")
    radius: float = Field(0.2e-3, gt=0, description="r std dev, m")


TOLERANCE_OF = KIND_OF
"""The :class:`Tolerances` (and :class:`Repeatability`) field of each parameter."""


class Repeatability(BaseModel):
    """How much an unchanged robot's parameters differ between two days beyond the
    measurements' noise (the floor's and the tyres' state, temperature): a std dev per
    parameter kind added to the change's covariance of a check (docs/check.md), SI."""

    model_config = STRICT

    position: float = Field(0.05e-3, ge=0, description="x_s, y_s and b, m")
    beta: float = Field(math.radians(0.02), ge=0, description="beta, rad")
    radius: float = Field(0.02e-3, ge=0, description="r, m")

    def per_parameter(self) -> list[float]:
        """In the order ``x_s, y_s, beta, b, r``."""
        return [float(getattr(self, TOLERANCE_OF[k])) for k in PARAM_NAMES]


class CheckConfig(BaseModel):
    """The check (docs/check.md): the calibration protocol with these settings in place of
    its own, every module locked once per angle, and its test of the file in force."""

    model_config = STRICT

    angles_deg: list[float] = Field(
        default_factory=lambda: [45.0], min_length=1, max_length=12,
        description="steering angles of the locked module, deg (one is enough)",
    )  # fmt: skip
    sweep_deg: float = Field(60.0, gt=10, le=3600, description="yaw swept per spin, deg")
    settle_time: float = Field(1.5, ge=0, description="spin time before the window opens, s")
    stop_time: float = Field(1.0, ge=0, description="time allowed to spin down, s")
    align_time: float = Field(0.5, ge=0, description="time to align the dynamic modules, s")
    rest_time: float = Field(
        MIN_REST_TIME, ge=0,
        description="without motion capture: the robot held still before every spin and "
        "at the end (the gyro's bias), s",
    )  # fmt: skip
    false_alarm: float = Field(
        0.05, gt=0, lt=0.5,
        description="probability that an unchanged robot is found drifted (Sidak over the "
        "modules)",
    )  # fmt: skip
    whole_robot: float = Field(
        0.5, gt=0, le=1,
        description="from this fraction of the modules drifted on, the verdict is "
        "'recalibrate the whole robot'",
    )  # fmt: skip
    repeatability: Repeatability = Repeatability()

    def protocol(self) -> dict[str, Any]:
        """The protocol settings it replaces (a deep-merge document): its own, and no
        straight drive (a check has no references to measure)."""
        return {**self.model_dump(include=set(CHECK_PROTOCOL_KEYS)), "drive_length": 0.0}


CHECK_PROTOCOL_KEYS = frozenset(
    {"angles_deg", "sweep_deg", "settle_time", "stop_time", "align_time", "rest_time"}
)
"""The settings of :class:`CheckConfig` that replace the protocol's for a check."""

RunKind = Literal["calibration", "check", "commission"]


class Polarity(BaseModel):
    """Which way an axis turns against what its drive reports: -1 for a motor mounted the
    other way round (or its encoder counting the other way), applied by swpc to what a run
    commands and reads (docs/commissioning.md)."""

    model_config = STRICT

    steer: Literal[1, -1] = 1
    wheel: Literal[1, -1] = 1


class RobotConfig(BaseModel):
    model_config = STRICT

    robot: str = "swpc"
    nominal: RobotParams = PAPER_NOMINAL
    base_link: BaseLink | None = Field(
        None,
        description="base_link's pose in R {x, y, yaw} (m, rad) or 'centroid' (of the "
        "calibrated steering axes, x along R's); unset: base_link = R. Every export is in "
        "base_link (docs/ros2.md)",
    )
    drives: DrivesConfig = Field(
        SwpcDrives(), description="the drive kind and each module's CAN nodes (swpc_hw.drives)"
    )
    limits: MotionLimits = MotionLimits()
    protocol: ProtocolConfig = ProtocolConfig()
    tolerances: Tolerances = Tolerances()
    check: CheckConfig = CheckConfig()
    polarity: dict[int, Polarity] = Field(
        default_factory=dict,
        description="module id -> {steer, wheel}: -1 for an axis that turns the other way "
        "round from what its drive reports (commissioning finds it); unset: 1",
    )

    def axis_signs(self) -> dict[int, tuple[int, int]]:
        """``polarity`` as the drives' layer takes it (``swpc_hw.drives.types.AxisSigns``):
        module id -> (steer, wheel)."""
        return {m: (p.steer, p.wheel) for m, p in self.polarity.items()}

    @field_validator("nominal", mode="before")
    @classmethod
    def _nominal(cls, v: Any) -> Any:
        if isinstance(v, str | Path):
            return load_robot(v)
        if isinstance(v, dict) and "modules" in v and "format" not in v:
            doc = dict(v)
            doc.setdefault("format", "swpc-kinematics/1")
            doc.setdefault("robot", "swpc")
            doc.setdefault("frame", "R")
            return parse_kinematics(doc, "nominal").params
        return v

    @model_validator(mode="before")
    @classmethod
    def _old_spellings(cls, data: Any) -> Any:
        return old_spellings(data)

    @model_validator(mode="after")
    def _check_modules(self) -> RobotConfig:
        ids = self.nominal.ids
        problems = self.drives.check_modules(ids)
        if problems:
            raise ValueError("; ".join(problems))
        self.drives = self.drives.for_modules(ids)
        if self.protocol.modules is not None and not set(self.protocol.modules) <= set(ids):
            raise ValueError("protocol.modules must be module ids of the robot")
        if not set(self.polarity) <= set(ids):
            extra = sorted(set(self.polarity) - set(ids))
            raise ValueError(f"polarity: {extra} are not module ids")
        try:  # the check's protocol is valid as a protocol (its angles' spacing)
            ProtocolConfig.model_validate({**self.protocol.model_dump(), **self.check.protocol()})
        except ValueError as exc:
            raise ValueError(f"check: {exc}") from None
        return self

    @property
    def pose_key(self) -> str:
        return pose_key(self.robot)

    @property
    def imu_key(self) -> str:
        """The robot's gyro: ``sensor_msgs/msg/Imu`` (CDR) on ``imu/<robot>/data``."""
        return f"imu/{self.robot}/data"

    def to_document(self) -> dict[str, Any]:
        doc = self.model_dump(mode="json", exclude={"nominal"})
        doc["nominal"] = {"modules": kinematics_document(self.nominal)["modules"]}
        return doc

    def with_overrides(self, overrides: dict[str, Any]) -> RobotConfig:
        """A new config with ``overrides`` deep-merged (validated like the file)."""
        return RobotConfig.model_validate(_deep_merge(self.to_document(), overrides))

    def check_config(self) -> RobotConfig:
        """The config of a check: the protocol with the check's settings in place
        (:class:`CheckConfig`)."""
        return self.with_overrides({"protocol": self.check.protocol()})

    def for_run(
        self, overrides: dict[str, Any], metrology: str = "mocap", kind: RunKind = "calibration"
    ) -> RobotConfig:
        """The config of one run of ``kind``: ``overrides`` deep-merged (into
        :meth:`check_config` for a check), then checked against this (the service's)
        config.  Raises :class:`OverrideError` listing every problem:

        * a limit or tolerance above this config's (an override may tighten, never loosen
          or remove, them), or a limit that is not per run (:data:`RUN_FIXED_LIMITS`);
        * another robot id, drives or set of module ids (the service's drives and
          motion-capture subscription are this config's);
        * anything :meth:`run_problems` finds for ``metrology``.

        Pydantic's ``ValidationError`` (a ``ValueError``) for an invalid merged config.
        """
        overrides = old_spellings(overrides)
        base = self.check_config() if kind == "check" else self
        run = base.with_overrides(overrides)
        problems: list[str] = []
        for group in ("limits", "tolerances"):
            mine, theirs = getattr(self, group), getattr(run, group)
            for name in type(mine).model_fields:
                base, new = getattr(mine, name), getattr(theirs, name)
                if group == "limits" and name in RUN_FIXED_LIMITS and new != base:
                    problems.append(
                        f"{group}.{name}: set for the service in the robot config ({base:g}), "
                        "not per run"
                    )
                elif new > base:
                    problems.append(
                        f"{group}.{name}: {new:g} would loosen the robot config's {base:g} "
                        "(an override may only tighten it)"
                    )
        if run.robot != self.robot:
            problems.append(
                f"robot: {run.robot!r} is not this service's robot {self.robot!r} (its motion "
                "capture subscription is mocap/<robot>/pose)"
            )
        if run.drives != self.drives:
            problems.append(
                f"drives: the drive kind and CAN node map are the service's "
                f"({self.drives.model_dump(mode='json')}), not per run"
            )
        if run.nominal.ids != self.nominal.ids:
            problems.append(
                f"nominal: module ids {run.nominal.ids} are not the robot's {self.nominal.ids}"
            )
        problems += run.run_problems(metrology, kind)
        if problems:
            raise OverrideError(problems)
        return run

    def run_problems(self, metrology: str = "mocap", kind: RunKind = "calibration") -> list[str]:
        """Why a run of ``kind`` with this config could not succeed, found before any
        motion (empty when none): for a calibration every module locked (the solver needs
        spins about each) at two angles or more (a check starts from the file in force:
        one angle is enough, and some modules may be left out if the solver still
        determines every parameter, else its SOLVE says so), and every step of the
        protocol possible within ``limits.step_timeout``; without motion capture
        (``metrology="imu"``) rests long enough for the solver and a straight drive that
        fits the step timeout and the speed limit; a check does not drive."""
        p, lim = self.protocol, self.limits
        problems: list[str] = []
        if kind == "commission":  # its probes are its own, not the protocol's
            if metrology != "mocap":
                problems.append(
                    "metrology: commissioning needs motion capture (where a lock pins the "
                    "robot is the poses' fixed point); the gyro alone cannot tell it"
                )
            return problems
        if metrology == "imu":
            problems += self._imu_problems()
        if kind == "check" and p.drive_length > 0:
            problems.append(
                f"protocol.drive_length: {p.drive_length:g} m; a check does not drive (it "
                "has no references to measure): 0"
            )
        if kind == "calibration" and len(p.angles_deg) < 2:
            problems.append(
                f"protocol.angles_deg: {len(p.angles_deg)} angle; a calibration needs two or "
                "more (the steering axis of a module is the circle through its fixed points)"
            )
        ids = self.nominal.ids
        if p.modules is not None and kind == "calibration":
            missing = [m for m in ids if m not in p.modules]
            if missing:
                problems.append(
                    f"protocol.modules: modules {missing} are never locked; the solver needs "
                    "spins about every module"
                )
        for name in ("settle_time", "stop_time", "align_time", "resteer_time"):
            value = getattr(p, name)
            if value >= lim.step_timeout:
                problems.append(
                    f"protocol.{name}: {value:g} s is not shorter than limits.step_timeout "
                    f"{lim.step_timeout:g} s (the step would time out)"
                )
        shortest = p.settle_time + math.radians(p.sweep_deg) / lim.max_yaw_rate
        if shortest >= lim.step_timeout:
            problems.append(
                f"protocol.sweep_deg: {p.sweep_deg:g} deg after settle_time {p.settle_time:g} s "
                f"takes at least {shortest:.1f} s at limits.max_yaw_rate {lim.max_yaw_rate:g} "
                f"rad/s, not shorter than limits.step_timeout {lim.step_timeout:g} s"
            )
        return problems


    def _imu_problems(self) -> list[str]:
        p, lim = self.protocol, self.limits
        out = []
        if p.rest_time < MIN_REST_TIME:
            out.append(
                f"protocol.rest_time: {p.rest_time:g} s is shorter than {MIN_REST_TIME:g} s: "
                "the solver needs the robot still that long to measure the gyro's bias"
            )
        if p.rest_time >= lim.step_timeout:
            out.append(
                f"protocol.rest_time: {p.rest_time:g} s is not shorter than "
                f"limits.step_timeout {lim.step_timeout:g} s (the step would time out)"
            )
        drive = 2 * p.rest_time + p.drive_length / lim.max_drive_speed
        if p.drive_length > 0 and drive >= lim.step_timeout:
            out.append(
                f"protocol.drive_length: {p.drive_length:g} m between two rests of "
                f"{p.rest_time:g} s takes at least {drive:.1f} s at limits.max_drive_speed "
                f"{lim.max_drive_speed:g} m/s, not shorter than limits.step_timeout "
                f"{lim.step_timeout:g} s"
            )
        return out


def old_spellings(data: Any) -> Any:
    """``drives: <kind>`` short for ``{kind: <kind>}``; ``nodes:`` (module id -> node) is
    the old spelling of ``drives: {kind: swpc, modules: ...}``."""
    if not isinstance(data, dict):
        return data
    data = dict(data)
    if "drives" in data:
        data["drives"] = parse_drives(data["drives"])
    if "nodes" in data:
        nodes = data.pop("nodes")
        if "drives" in data:
            raise ValueError(
                "nodes and drives: give the node map once, in drives.modules (nodes is its "
                "old spelling)"
            )
        if nodes is not None:
            data["drives"] = {"kind": "swpc", "modules": nodes}
    return data


def _deep_merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _deep_merge(out[k], v)
        else:
            out[k] = v
    return out


def load_robot_config(path: str | Path | None) -> RobotConfig:
    """Load a robot config YAML (``None``: the default, the paper's robot)."""
    if path is None:
        return RobotConfig()
    p = Path(path)
    try:
        doc = yaml.safe_load(p.read_text(encoding="utf-8")) or {}
    except (OSError, yaml.YAMLError) as exc:
        raise RobotConfigError(f"{p}: cannot read robot config: {exc}") from exc
    if isinstance(doc.get("nominal"), str):
        doc["nominal"] = str((p.parent / doc["nominal"]).resolve())
    try:
        return RobotConfig.model_validate(doc)
    except ValueError as exc:
        first = str(exc).splitlines()
        raise RobotConfigError(f"{p}: {' '.join(first[:3])}") from exc


def _partial(model: type[BaseModel], name: str) -> type[BaseModel]:
    """A copy of ``model`` whose fields are all optional (default None), same constraints."""
    from pydantic import create_model
    from pydantic.fields import FieldInfo

    fields: dict[str, Any] = {}
    for fname, f in model.model_fields.items():
        info = FieldInfo.merge_field_infos(f, default=None)
        info.default_factory = None
        fields[fname] = (Optional[f.annotation], info)  # noqa: UP045 - runtime type
    return create_model(name, __config__=STRICT, **fields)


LimitsOverride = _partial(MotionLimits, "LimitsOverride")
ProtocolOverride = _partial(ProtocolConfig, "ProtocolOverride")
TolerancesOverride = _partial(Tolerances, "TolerancesOverride")


class ConfigOverrides(BaseModel):
    """Overrides of the robot config for one run (every key optional, deep-merged).  Limits
    and tolerances may only be tightened; ``robot``, ``drives`` and the module ids are the
    service's (:meth:`RobotConfig.for_run`; ``nodes`` is the old spelling of ``drives``)."""

    model_config = STRICT

    robot: str | None = None
    nominal: RobotParams | None = None
    drives: dict[str, Any] | str | None = None
    nodes: dict[int, int] | None = None
    limits: LimitsOverride | None = None  # type: ignore[valid-type]
    protocol: ProtocolOverride | None = None  # type: ignore[valid-type]
    tolerances: TolerancesOverride | None = None  # type: ignore[valid-type]

    def document(self) -> dict[str, Any]:
        """Only what the request set, as plain data (nominal in the file's schema)."""
        doc: dict[str, Any] = self.model_dump(mode="json", exclude_unset=True, exclude_none=True)
        if self.nominal is not None:
            doc["nominal"] = {"modules": kinematics_document(self.nominal)["modules"]}
        return doc
