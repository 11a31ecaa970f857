"""Spins whose wheels do not roll as the robot's geometry says: a whole-spin misfit test.

A burst of slip shows in a few wheel increments (:mod:`.slip`); a wheel that slips
steadily over a whole spin (a low-friction patch: 0.4 % for 12 s) does not, it only
changes that wheel's rolling ratio in that spin.  The spin's wheels still share one yaw,
so what the geometry fixes is the ratios of their levers: in one spin the wheel angles
roll as (:mod:`.problem`, ``spin``)::

    psi_jl = c_j + h_j Y_l,      h_j = g_j / r_j

with ``h`` from the calibration (the model) or, freely, any ``h`` (the spin alone: only
the ratios ``h_j / h_1`` count, ``Y`` absorbs a common scale).  With ``RSS_model`` and
``RSS_free`` the profiled residuals' sums of squares (:func:`.rolling_sets.profiled_rolling`)
and ``nu`` the free fit's degrees of freedom, a spin that fits leaves::

    chi2 = (RSS_model - RSS_free) / (RSS_free / nu)  ~  chi2(m - 1)

(``m`` wheels: ``m - 1`` ratios; a little less, since the spin's own data helped fix the
model).  A steady slip of ``k`` on one wheel moves its ratio by ``k``: with 2^17-count
encoders ``k = 0.4 %`` gives ``chi2`` of ~1e6.  The test is the ratio's misfit in std devs,
``z = sqrt(chi2)``; real wheels are not exact rigid rollers (tyre compliance, the floor),
so beside ``z`` the misfit must also exceed a relative size: the RMS of the ratios'
relative changes ``sqrt(mean_j (h_free,j / h_model,j / k_c - 1)^2)`` with the common
scale ``k_c`` removed (median of the ratios), :data:`MIN_RATIO_MISFIT`.

:func:`spin_misfit` computes both for one spin; the solver
(:func:`swpc_hw.calibration.gyro.solver.fit_imu`) cuts one spin whole (its wheel
readings; its settled casters stay; which one by trial,
:func:`swpc_hw.calibration.gyro.solver.trial_cut`) while any is beyond both, refuses the
dataset when more than :func:`max_cut` spins would go, and tests a straight drive's
wheels the same way against its arc (a drive is never cut).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from swpc_hw.calibration.gyro.rolling_sets import ProfileStructure, RollingSet, profiled_rolling

FloatArray = NDArray[np.float64]

MISFIT_SIGMAS = 8.0
"""A spin's ratio misfit beyond this many std devs (``z``) may be cut."""
MIN_RATIO_MISFIT = 3e-5
"""... and only when the wheels' ratios are off by more than this (relative RMS, 0.003 %):
in a clean run it is below 1e-6, while a fit bent by a 0.4 % slip elsewhere leaves
1e-4 in spins that do not slip."""
MAX_CUT_FRACTION = 0.25
"""More spins than this fraction (at least 2) not fitting: the dataset is refused."""


@dataclass(frozen=True)
class SpinMisfit:
    """One spin's misfit: ``z`` in std devs, ``ratio`` the relative RMS of its wheels'
    ratio changes, ``rss_model`` / ``rss_free`` (rad^2) and ``dof``."""

    z: float
    ratio: float
    rss_model: float
    rss_free: float
    dof: int

    @property
    def fits(self) -> bool:
        return not (self.z > MISFIT_SIGMAS and self.ratio > MIN_RATIO_MISFIT)


NO_TEST = SpinMisfit(0.0, 0.0, 0.0, 0.0, 0)
"""A spin that cannot be tested (fewer than two wheels, or no degrees of freedom)."""


def free_levers(rs: RollingSet, h0: FloatArray) -> tuple[FloatArray, float]:
    """The levers ``h`` (m,) that fit one rolling set's wheels best, and their RSS.

    ``h_1`` held at ``h0_1`` (a common scale of ``h`` is the yaw's), the others by
    Levenberg-Marquardt from ``h0``; wheels with no sample keep ``h0``.
    """
    from scipy.optimize import least_squares  # at first use: see swpc_hw.calibration

    st = ProfileStructure.of(rs.present, rs.run)
    used = np.flatnonzero(rs.present.any(axis=0))
    if used.size < 2:
        resid, _ = profiled_rolling(rs.psi, h0, rs.present, rs.run, st)
        return h0.copy(), float(np.sum(resid**2))
    free = used[1:]

    def h_of(q: FloatArray) -> FloatArray:
        h = h0.copy()
        h[free] = h0[free] * (1.0 + q)
        return h

    def fun(q: FloatArray) -> FloatArray:
        resid, _ = profiled_rolling(rs.psi, h_of(q), rs.present, rs.run, st)
        return np.asarray(resid[rs.present], dtype=float)

    sol = least_squares(fun, np.zeros(free.size), method="lm", xtol=1e-14, ftol=1e-14)
    return h_of(np.asarray(sol.x, dtype=float)), float(np.sum(sol.fun**2))


def spin_misfit(rs: RollingSet, h_model: FloatArray) -> SpinMisfit:
    """The misfit of one spin's wheels against the model's levers (module docstring)."""
    used = np.flatnonzero(rs.present.any(axis=0))
    if used.size < 2:
        return NO_TEST
    resid, _ = profiled_rolling(rs.psi, h_model, rs.present, rs.run)
    rss_model = float(np.sum(resid**2))
    h_free, rss_free = free_levers(rs, h_model)
    cnt = rs.present.sum(axis=1)
    n_run = np.unique(rs.run[rs.present]).size
    n_chunk = max(len(rs.chunks), 1)
    dof = int(np.sum(np.maximum(cnt - 1, 0))) - (n_run - n_chunk) - (used.size - 1)
    if dof <= 0:
        return NO_TEST
    var = max(rss_free / dof, 1e-300)
    z = math.sqrt(max(rss_model - rss_free, 0.0) / var)
    q = h_free[used] / h_model[used]
    q = q / float(np.median(q))
    dev = q - 1.0
    return SpinMisfit(
        z=z,
        ratio=float(np.sqrt(np.mean(dev**2))),
        rss_model=rss_model,
        rss_free=rss_free,
        dof=dof,
    )


def max_cut(n_spins: int) -> int:
    """How many spins may be cut whole before the dataset is refused."""
    return max(2, math.floor(MAX_CUT_FRACTION * n_spins))
