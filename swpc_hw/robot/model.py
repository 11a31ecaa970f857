"""Kinematic model of an SWPC robot (exactly the model of docs/model-and-frames.md).

Per module i: steering axis ``P_s = (x_s, y_s)`` in the robot frame R, homing error
``beta`` (true minus reported steering angle), caster offset ``b`` and wheel radius ``r``.

* true steering angle            ``theta = theta_hat + beta``
* rolling direction              ``u(theta) = (cos theta, sin theta)``
* contact point                  ``P_w = P_s + b u(theta)``
* no-slip constraint (twist (v, omega) in R, ``omega x p = omega (-p_y, p_x)``)::

      v + omega x P_w = r psi_dot u(theta) + b theta_dot n(theta),   n = (sin theta, -cos theta)

The functions here are pure and operate on numpy arrays; the typed parameter models
(:class:`ModuleParams`, :class:`RobotParams`) convert to arrays with
:meth:`RobotParams.arrays`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import AfterValidator, BaseModel, ConfigDict, Field, field_validator, model_validator

FloatArray = NDArray[np.float64]

PARAM_NAMES = ("x_s", "y_s", "beta", "b", "r")
"""One module's parameters, in the one order everything uses: a module's row of arrays
and covariances, the kinematic file's keys and its ``covariance.order``."""

PARAM_KINDS = ("position", "beta", "radius")
"""The kinds a tolerance, a plan's target and a check's repeatability are stated per."""
KIND_OF = {"x_s": "position", "y_s": "position", "b": "position", "beta": "beta", "r": "radius"}
"""The kind of each parameter (:data:`PARAM_KINDS`)."""


def _finite(value: float) -> float:
    if not math.isfinite(value):
        raise ValueError(f"must be finite (got {value!r})")
    return value


Finite = Annotated[float, AfterValidator(_finite)]
PositiveFinite = Annotated[float, AfterValidator(_finite), Field(gt=0.0)]
NonNegativeFinite = Annotated[float, AfterValidator(_finite), Field(ge=0.0)]


class ModuleStddev(BaseModel):
    """One standard deviation per parameter (SI units)."""

    model_config = ConfigDict(extra="ignore", frozen=True)

    x_s: NonNegativeFinite
    y_s: NonNegativeFinite
    beta: NonNegativeFinite
    b: NonNegativeFinite
    r: NonNegativeFinite

    def values(self) -> tuple[float, ...]:
        """The five std devs in the order of :data:`PARAM_NAMES`."""
        return tuple(float(getattr(self, k)) for k in PARAM_NAMES)

    @classmethod
    def of(cls, values: ArrayLike) -> ModuleStddev:
        """From five std devs in the order of :data:`PARAM_NAMES`."""
        v = np.asarray(values, dtype=float).reshape(-1)
        return cls(**{k: float(v[c]) for c, k in enumerate(PARAM_NAMES)})


class ModuleParams(BaseModel):
    """Kinematic parameters of one caster module (SI units, robot frame R)."""

    model_config = ConfigDict(extra="ignore", frozen=True)

    id: int = Field(ge=0)
    x_s: Finite
    y_s: Finite
    beta: Finite
    b: PositiveFinite
    r: PositiveFinite
    stddev: ModuleStddev | None = None

    def values(self) -> tuple[float, ...]:
        """The five parameters in the order of :data:`PARAM_NAMES`."""
        return tuple(float(getattr(self, k)) for k in PARAM_NAMES)


@dataclass(frozen=True)
class RobotArrays:
    """Array view of a robot's parameters, one row per module (in file order)."""

    ids: NDArray[np.int64]
    P_s: FloatArray  # (N, 2)
    beta: FloatArray  # (N,)
    b: FloatArray  # (N,)
    r: FloatArray  # (N,)

    @property
    def n(self) -> int:
        return int(self.ids.shape[0])

    def matrix(self) -> FloatArray:
        """(N, 5): one row per module, the columns in the order of :data:`PARAM_NAMES`."""
        return np.column_stack([self.P_s, self.beta, self.b, self.r])


class RobotParams(BaseModel):
    """A robot: N >= 2 modules with unique ids, expressed in frame ``frame``."""

    model_config = ConfigDict(extra="ignore", frozen=True)

    robot: str = "swpc"
    frame: str = "R"
    modules: list[ModuleParams]

    @field_validator("modules")
    @classmethod
    def _at_least_two(cls, modules: list[ModuleParams]) -> list[ModuleParams]:
        if len(modules) < 2:
            raise ValueError(f"an SWPC robot needs N >= 2 modules (got {len(modules)})")
        return modules

    @model_validator(mode="after")
    def _unique_ids(self) -> RobotParams:
        seen: set[int] = set()
        for m in self.modules:
            if m.id in seen:
                raise ValueError(f"duplicate module id {m.id}")
            seen.add(m.id)
        return self

    @property
    def ids(self) -> list[int]:
        return [m.id for m in self.modules]

    def module(self, module_id: int) -> ModuleParams:
        for m in self.modules:
            if m.id == module_id:
                return m
        raise KeyError(f"no module with id {module_id}")

    def index(self, module_id: int) -> int:
        return self.ids.index(module_id)

    def arrays(self) -> RobotArrays:
        return RobotArrays(
            ids=np.array(self.ids, dtype=np.int64),
            P_s=np.array([[m.x_s, m.y_s] for m in self.modules], dtype=float),
            beta=np.array([m.beta for m in self.modules], dtype=float),
            b=np.array([m.b for m in self.modules], dtype=float),
            r=np.array([m.r for m in self.modules], dtype=float),
        )

    @classmethod
    def from_arrays(
        cls,
        ids: ArrayLike,
        P_s: ArrayLike,
        beta: ArrayLike,
        b: ArrayLike,
        r: ArrayLike,
        *,
        robot: str = "swpc",
        frame: str = "R",
        stddev: ArrayLike | None = None,
    ) -> RobotParams:
        """Build from arrays; ``stddev`` is (N, 5) in the order x_s, y_s, beta, b, r."""
        ids_a = np.asarray(ids, dtype=np.int64)
        P = np.asarray(P_s, dtype=float).reshape(-1, 2)
        be, bb, rr = (np.asarray(a, dtype=float).reshape(-1) for a in (beta, b, r))
        n_par = len(PARAM_NAMES)
        sd = None if stddev is None else np.asarray(stddev, dtype=float).reshape(-1, n_par)
        modules = []
        for i, mid in enumerate(ids_a):
            std = None
            if sd is not None:
                std = ModuleStddev.of(sd[i])
            modules.append(
                ModuleParams(
                    id=int(mid),
                    x_s=float(P[i, 0]),
                    y_s=float(P[i, 1]),
                    beta=float(be[i]),
                    b=float(bb[i]),
                    r=float(rr[i]),
                    stddev=std,
                )
            )
        return cls(robot=robot, frame=frame, modules=modules)

    @classmethod
    def from_matrix(
        cls,
        ids: ArrayLike,
        X: ArrayLike,
        *,
        robot: str = "swpc",
        frame: str = "R",
        stddev: ArrayLike | None = None,
    ) -> RobotParams:
        """Build from an (N, 5) matrix, columns in the order of :data:`PARAM_NAMES`
        (:meth:`RobotArrays.matrix`); ``stddev`` (N, 5) likewise."""
        M = np.asarray(X, dtype=float).reshape(-1, len(PARAM_NAMES))
        return cls.from_arrays(
            ids, M[:, 0:2], M[:, 2], M[:, 3], M[:, 4], robot=robot, frame=frame, stddev=stddev
        )


# --------------------------------------------------------------------------- geometry


def rot(angle: ArrayLike) -> FloatArray:
    """Planar rotation matrix ``R(a) = [[cos a, -sin a], [sin a, cos a]]``, shape (..., 2, 2)."""
    a = np.asarray(angle, dtype=float)
    c, s = np.cos(a), np.sin(a)
    return np.stack([np.stack([c, -s], axis=-1), np.stack([s, c], axis=-1)], axis=-2)


def steering_direction(theta: ArrayLike) -> FloatArray:
    """``u(theta) = (cos theta, sin theta)``: steering axis -> contact point, shape (..., 2)."""
    t = np.asarray(theta, dtype=float)
    return np.stack([np.cos(t), np.sin(t)], axis=-1)


def steering_normal(theta: ArrayLike) -> FloatArray:
    """``n(theta) = (sin theta, -cos theta)``: the direction multiplying ``b theta_dot``."""
    t = np.asarray(theta, dtype=float)
    return np.stack([np.sin(t), -np.cos(t)], axis=-1)


def true_steering_angle(theta_hat: ArrayLike, beta: ArrayLike) -> FloatArray:
    """``theta = theta_hat + beta``."""
    return np.asarray(np.asarray(theta_hat, dtype=float) + np.asarray(beta), dtype=float)


def contact_point(P_s: ArrayLike, b: ArrayLike, theta: ArrayLike) -> FloatArray:
    """``P_w = P_s + b u(theta)`` (true steering angle ``theta``)."""
    b_col = np.asarray(b, dtype=float)[..., None]
    return np.asarray(np.asarray(P_s, dtype=float) + b_col * steering_direction(theta))


def cross_z(omega: ArrayLike, p: ArrayLike) -> FloatArray:
    """``omega x p = omega (-p_y, p_x)`` for planar vectors ``p`` (..., 2)."""
    P = np.asarray(p, dtype=float)
    w = np.asarray(omega, dtype=float)[..., None]
    return np.asarray(w * np.stack([-P[..., 1], P[..., 0]], axis=-1), dtype=float)


def cross2(a: ArrayLike, b: ArrayLike) -> FloatArray:
    """Scalar 2-D cross product ``a_x b_y - a_y b_x``."""
    A = np.asarray(a, dtype=float)
    B = np.asarray(b, dtype=float)
    return np.asarray(A[..., 0] * B[..., 1] - A[..., 1] * B[..., 0], dtype=float)


# --------------------------------------------------------------------------- kinematics


def contact_velocity(v: ArrayLike, omega: ArrayLike, P_w: ArrayLike) -> FloatArray:
    """Velocity of the body point at ``P_w``, in R: ``v + omega x P_w``."""
    return np.asarray(v, dtype=float) + cross_z(omega, P_w)


def inverse_kinematics(
    arrays: RobotArrays, theta_hat: ArrayLike, v: ArrayLike, omega: float
) -> tuple[FloatArray, FloatArray]:
    """Wheel and steering rates that realise the twist ``(v, omega)`` at steering ``theta_hat``.

    Projecting the no-slip constraint on ``u`` and ``n``::

        r psi_dot     = (v + omega x P_w) . u(theta)
        b theta_dot   = (v + omega x P_w) . n(theta)

    Returns ``(theta_hat_dot, psi_dot)``, one value per module (``theta_hat_dot ==
    theta_dot`` since beta is constant).
    """
    theta = true_steering_angle(theta_hat, arrays.beta)
    P_w = contact_point(arrays.P_s, arrays.b, theta)
    vel = contact_velocity(np.asarray(v, dtype=float)[None, :], np.full(arrays.n, omega), P_w)
    psi_dot = np.einsum("ij,ij->i", vel, steering_direction(theta)) / arrays.r
    theta_dot = np.einsum("ij,ij->i", vel, steering_normal(theta)) / arrays.b
    return theta_dot, psi_dot


def module_jacobian(P_w: FloatArray) -> FloatArray:
    """Rows mapping the twist ``(v_x, v_y, omega)`` to contact-point velocities.

    For module i: ``[[1, 0, -P_w,y], [0, 1, P_w,x]]``; stacked to shape (2N, 3).
    """
    n = P_w.shape[0]
    J = np.zeros((2 * n, 3))
    J[0::2, 0] = 1.0
    J[1::2, 1] = 1.0
    J[0::2, 2] = -P_w[:, 1]
    J[1::2, 2] = P_w[:, 0]
    return J


def wheel_velocities(
    arrays: RobotArrays, theta: ArrayLike, theta_dot: ArrayLike, psi_dot: ArrayLike
) -> FloatArray:
    """Right-hand side of the constraint per module: ``r psi_dot u + b theta_dot n``, (N, 2)."""
    th = np.asarray(theta, dtype=float)
    roll = (arrays.r * np.asarray(psi_dot, dtype=float))[:, None] * steering_direction(th)
    steer = (arrays.b * np.asarray(theta_dot, dtype=float))[:, None] * steering_normal(th)
    return np.asarray(roll + steer, dtype=float)


def forward_kinematics(
    arrays: RobotArrays,
    theta_hat: ArrayLike,
    theta_hat_dot: ArrayLike,
    psi_dot: ArrayLike,
    weights: ArrayLike | None = None,
) -> tuple[FloatArray, FloatArray]:
    """Least-squares robot twist from all modules' steering angles and rates.

    Solves ``min_{v, omega} sum_i w_i |v + omega x P_w,i - (r psi_dot u + b theta_dot n)_i|^2``.

    Returns ``(twist, residuals)`` with ``twist = (v_x, v_y, omega)`` and the per-module
    residual vectors (N, 2) (contact-point velocity mismatch, m/s): a slip indicator.
    """
    theta = true_steering_angle(theta_hat, arrays.beta)
    P_w = contact_point(arrays.P_s, arrays.b, theta)
    J = module_jacobian(P_w)
    rhs = wheel_velocities(arrays, theta, theta_hat_dot, psi_dot).reshape(-1)
    if weights is None:
        twist, *_ = np.linalg.lstsq(J, rhs, rcond=None)
    else:
        sw = np.sqrt(np.repeat(np.asarray(weights, dtype=float), 2))
        twist, *_ = np.linalg.lstsq(J * sw[:, None], rhs * sw, rcond=None)
    residuals = (J @ twist - rhs).reshape(-1, 2)
    return np.asarray(twist, dtype=float), np.asarray(residuals, dtype=float)


def trailing_steering_angle(arrays: RobotArrays, v: ArrayLike, omega: float) -> FloatArray:
    """Reported steering angles ``theta_hat`` at which free casters trail the twist ``(v, omega)``.

    A trailing caster's wheel lies behind its steering axis: ``u`` points against the
    velocity of the contact point.  For the settled state (``theta_dot = 0``) the contact
    point velocity is parallel to ``u``; we solve ``(v + omega x (P_s + b u)) . n = 0`` by
    fixed-point iteration starting from the direction opposite to the steering axis's
    velocity (exact for pure translation).
    """
    # contact_point and contact_velocity by components: the same operations on the same
    # numbers (the same result) without their stacking, for the simulators and fake
    # robots that call this at every change of twist
    vv = np.asarray(v, dtype=float)
    vx, vy = vv[0], vv[1]
    w = float(omega)
    xs, ys, b = arrays.P_s[:, 0], arrays.P_s[:, 1], np.asarray(arrays.b, dtype=float)
    theta = np.arctan2(-(vy + w * xs), -(vx + w * -ys))  # opposite the axis' velocity
    for _ in range(50):
        # v + omega x P_w, P_w = P_s + b u(theta)
        new = np.arctan2(-(vy + w * (xs + b * np.cos(theta))),
                         -(vx + w * -(ys + b * np.sin(theta))))
        if np.all(np.abs(new - theta) <= 1e-15):  # np.allclose(atol=1e-15, rtol=0)
            theta = new
            break
        theta = new
    return wrap_angle(theta - arrays.beta)


def wrap_angle(a: ArrayLike) -> FloatArray:
    """Wrap angles to ``(-pi, pi]``."""
    x = np.asarray(a, dtype=float)
    return np.asarray(np.pi - np.mod(np.pi - x, 2.0 * np.pi), dtype=float)


def nearest_turn(current: ArrayLike, target: ArrayLike) -> FloatArray:
    """The angle equal to ``target`` modulo 2 pi that is closest to ``current``::

        theta_cmd = theta + wrap(target - theta)

    A steering setpoint for a multi-turn axis: the shortest move (at most half a turn) to
    the direction ``target`` from the axis' continuous position ``current``.
    """
    c = np.asarray(current, dtype=float)
    return np.asarray(c + wrap_angle(np.asarray(target, dtype=float) - c), dtype=float)
