"""Odometry over recorded logs: :class:`swpc_hw.onboard.odometry.Odometry` run over synchronous
readings, and asynchronous per-module encoder rows brought onto common times."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from swpc_hw.onboard.odometry import Odometry, OdometryError, OdometryOptions
from swpc_hw.robot.model import RobotParams

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class OdometryTrack:
    """Result of integrating a log: one row per reading (row 0 = initial pose, zero twist)."""

    t: FloatArray  # (T,)
    poses: FloatArray  # (T, 3) x, y, yaw
    twists: FloatArray  # (T, 3) v_x, v_y, omega of the step ending at t
    residuals: FloatArray  # (T, N) m/s, per step
    weights: FloatArray  # (T, N)


def integrate_log(
    params: RobotParams,
    t: ArrayLike,
    theta_hat: ArrayLike,
    psi: ArrayLike,
    *,
    pose: tuple[float, float, float] = (0.0, 0.0, 0.0),
    options: OdometryOptions | None = None,
) -> OdometryTrack:
    """Run :class:`Odometry` over synchronous readings ``t`` (T,), ``theta_hat``/``psi`` (T, N)."""
    tt = np.asarray(t, dtype=float).reshape(-1)
    TH = np.asarray(theta_hat, dtype=float)
    PS = np.asarray(psi, dtype=float)
    n = len(params.modules)
    if TH.shape != (tt.size, n) or PS.shape != (tt.size, n):
        raise OdometryError(
            f"odometry: readings must be ({tt.size}, {n}) (got {TH.shape} and {PS.shape})"
        )
    odo = Odometry(params, pose=pose, options=options)
    poses = np.zeros((tt.size, 3))
    twists = np.zeros((tt.size, 3))
    residuals = np.zeros((tt.size, n))
    weights = np.ones((tt.size, n))
    th_rows = TH.tolist()
    ps_rows = PS.tolist()
    for k in range(tt.size):
        poses[k] = odo.update(float(tt[k]), th_rows[k], ps_rows[k])
        if k > 0 and odo._last is not None:
            sol = odo._last[2]
            twists[k] = sol.twist
            residuals[k] = sol.residuals
            weights[k] = sol.weights
    return OdometryTrack(t=tt, poses=poses, twists=twists, residuals=residuals, weights=weights)


def synchronize_encoders(
    encoders: Mapping[int, ArrayLike], ids: Sequence[int], t: ArrayLike | None = None
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Resample per-module encoder logs onto common timestamps.

    ``encoders[id]`` is (K, 3) rows ``t, steer, wheel`` (as in
    :class:`swpc_hw.files.dataset.Dataset`).
    ``t`` defaults to the timestamps of the first module inside the common time span.
    Steering is unwrapped before linear interpolation.  Returns ``(t, theta_hat, psi)`` with
    (T, N) arrays in ``ids`` order.
    """
    tables: list[FloatArray] = []
    for mid in ids:
        if mid not in encoders:
            raise OdometryError(f"odometry: no encoder readings for module {mid}")
        e = np.asarray(encoders[mid], dtype=float)
        if e.ndim != 2 or e.shape[1] != 3 or e.shape[0] < 2:
            raise OdometryError(f"odometry: module {mid}: need (K >= 2, 3) rows t, steer, wheel")
        tables.append(e[np.argsort(e[:, 0], kind="stable")])
    lo = max(float(e[0, 0]) for e in tables)
    hi = min(float(e[-1, 0]) for e in tables)
    if t is None:
        t0 = tables[0][:, 0]
        tt = t0[(t0 >= lo) & (t0 <= hi)]
    else:
        tt = np.asarray(t, dtype=float).reshape(-1)
        if tt.size and (np.min(tt) < lo or np.max(tt) > hi):
            raise OdometryError(f"odometry: requested times outside the common span [{lo}, {hi}]")
    TH = np.column_stack([np.interp(tt, e[:, 0], np.unwrap(e[:, 1])) for e in tables])
    PS = np.column_stack([np.interp(tt, e[:, 0], e[:, 2]) for e in tables])
    return tt, TH, PS


__all__ = ["OdometryTrack", "integrate_log", "synchronize_encoders"]
