"""Controller helper: steering and wheel rates that realise a commanded robot twist.

Inverse kinematics of the no-slip model (docs/model-and-frames.md), per module at the current
reported steering ``theta_hat`` (true ``theta = theta_hat + beta``)::

    r psi_dot   = (v + omega x P_w) . u(theta)
    b theta_dot = (v + omega x P_w) . n(theta)          (P_w = P_s + b u(theta))

Both rates are linear in the twist at fixed steering, so a twist that would exceed a rate
limit is scaled down uniformly (``k = min(1, max_wheel_rate / max|psi_dot|,
max_steer_rate / max|theta_dot|)``): the instantaneous centre of rotation and the path are
kept, only the speed drops.

Commanding these rates at every control step realises the twist at any steering angle (a
powered caster needs no pre-steering); under a constant twist the casters converge to the
trailing configuration of :func:`settled_steering`.  Like the odometry, this module does not
import FastAPI, zenoh or scipy.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from swpc_hw.errors import SwpcError
from swpc_hw.robot.model import (
    RobotArrays,
    RobotParams,
    contact_point,
    contact_velocity,
    inverse_kinematics,
    steering_direction,
    trailing_steering_angle,
    true_steering_angle,
)

FloatArray = NDArray[np.float64]


class ControllerError(SwpcError, ValueError):
    """A command cannot be computed (wrong number of readings, non-finite input, bad limit)."""


@dataclass(frozen=True)
class CasterCommand:
    """Rates for every module (module order), and the applied twist (after saturation).

    ``theta_hat_dot``: steering rates (rad/s); ``psi_dot``: wheel rates (rad/s);
    ``twist``: (v_x, v_y, omega) actually commanded; ``scale``: factor applied (1 = none).
    """

    theta_hat_dot: FloatArray
    psi_dot: FloatArray
    twist: tuple[float, float, float]
    scale: float


def twist_rates(
    arrays: RobotArrays, theta_hat: ArrayLike, twist: ArrayLike
) -> tuple[FloatArray, FloatArray]:
    """``(theta_hat_dot, psi_dot)`` realising ``twist = (v_x, v_y, omega)`` at ``theta_hat``."""
    tw = np.asarray(twist, dtype=float).reshape(3)
    return inverse_kinematics(arrays, np.asarray(theta_hat, dtype=float), tw[:2], float(tw[2]))


def saturation_scale(
    theta_hat_dot: FloatArray,
    psi_dot: FloatArray,
    max_wheel_rate: float | None = None,
    max_steer_rate: float | None = None,
) -> float:
    """``k = min(1, max_wheel_rate / max|psi_dot|, max_steer_rate / max|theta_hat_dot|)``."""
    k = 1.0
    if max_wheel_rate is not None:
        peak = float(np.max(np.abs(psi_dot)))
        if peak > max_wheel_rate:
            k = min(k, max_wheel_rate / peak)
    if max_steer_rate is not None:
        peak = float(np.max(np.abs(theta_hat_dot)))
        if peak > max_steer_rate:
            k = min(k, max_steer_rate / peak)
    return k


def settled_steering(arrays: RobotArrays, twist: ArrayLike) -> FloatArray:
    """Reported steering angles at which every caster trails the twist with ``theta_dot = 0``.

    Solves ``(v + omega x P_w) . n(theta) = 0`` with ``u`` against the contact velocity
    (:func:`swpc_hw.robot.model.trailing_steering_angle`).
    """
    tw = np.asarray(twist, dtype=float).reshape(3)
    return trailing_steering_angle(arrays, tw[:2], float(tw[2]))


def settled_wheel_rates(arrays: RobotArrays, twist: ArrayLike) -> FloatArray:
    """Wheel rates at the settled steering: ``psi_dot = (v + omega x P_w) . u / r``."""
    tw = np.asarray(twist, dtype=float).reshape(3)
    theta = true_steering_angle(settled_steering(arrays, tw), arrays.beta)
    P_w = contact_point(arrays.P_s, arrays.b, theta)
    vel = contact_velocity(tw[None, :2], np.full(arrays.n, tw[2]), P_w)
    return np.asarray(np.einsum("ij,ij->i", vel, steering_direction(theta)) / arrays.r)


class TwistController:
    """Velocity-level controller: commanded twist -> per-module steering and wheel rates.

    Uses its own copy of the kinematic parameters (those under test in a validation drive);
    :meth:`set_params` swaps them (same module ids).  Optional rate limits scale the twist.
    """

    def __init__(
        self,
        params: RobotParams,
        *,
        max_wheel_rate: float | None = None,
        max_steer_rate: float | None = None,
    ) -> None:
        for name, lim in (("max_wheel_rate", max_wheel_rate), ("max_steer_rate", max_steer_rate)):
            if lim is not None and not (np.isfinite(lim) and lim > 0.0):
                raise ControllerError(f"controller: {name} must be > 0 (got {lim!r})")
        self._params = params
        self._arrays = params.arrays()
        self.max_wheel_rate = max_wheel_rate
        self.max_steer_rate = max_steer_rate

    @property
    def params(self) -> RobotParams:
        return self._params

    def set_params(self, params: RobotParams) -> None:
        if params.ids != self._params.ids:
            raise ControllerError(
                f"controller: new parameters have module ids {params.ids}, "
                f"running robot has {self._params.ids}"
            )
        self._params, self._arrays = params, params.arrays()

    def command(self, theta_hat: ArrayLike, twist: ArrayLike) -> CasterCommand:
        """Rates realising ``twist`` (scaled down to the limits) at the current ``theta_hat``."""
        th = np.asarray(theta_hat, dtype=float).reshape(-1)
        tw = np.asarray(twist, dtype=float).reshape(-1)
        if th.size != self._arrays.n or tw.size != 3:
            raise ControllerError(
                f"controller: need {self._arrays.n} steering readings and a 3-vector twist "
                f"(got {th.size}, {tw.size})"
            )
        if not (np.all(np.isfinite(th)) and np.all(np.isfinite(tw))):
            raise ControllerError("controller: non-finite steering reading or twist")
        theta_dot, psi_dot = twist_rates(self._arrays, th, tw)
        k = saturation_scale(theta_dot, psi_dot, self.max_wheel_rate, self.max_steer_rate)
        return CasterCommand(
            theta_hat_dot=theta_dot * k,
            psi_dot=psi_dot * k,
            twist=(float(tw[0] * k), float(tw[1] * k), float(tw[2] * k)),
            scale=k,
        )
