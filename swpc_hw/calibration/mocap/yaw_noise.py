"""The yaw noise of the pose nodes in the cumulative rolling residual (the clock offset's std dev).

A series' cumulative residual ``e_l = r psi_l - G_l`` (:mod:`swpc_hw.calibration.rolling`)
carries the yaw noise ``n_m`` of its nodes through
``G_l = sum_{m<l} gbar_m (yaw_m+1 - yaw_m)`` (``gbar_m`` the trapezoid lever of increment
m)::

    G_noise_l = sum_{m<l} gbar_m (n_m+1 - n_m)

With a constant lever that is ``g (n_l - n_0)``: each node's noise in its own residual,
white when the mocap's is.  But while the casters swing round at the start of a spin the
lever changes, and ``(gbar_m-1 - gbar_m) n_m`` is carried into every later residual of
the run: scores per node are then correlated over the whole run, and a Bartlett sum of
them read the clock offset's std dev 1.2-1.5 times too small.

So a score sum ``sum_l a_l e_l`` (``a`` with zero sum over every run, as the derivative of
a residual whose run intercept is profiled) is written over the noise itself::

    sum_l a_l e_l = -sum_m c_m n_m,   c_m = gbar_m-1 T_m - gbar_m T_m+1,   T_m = sum_{l>=m} a_l

(:func:`node_coefficients`, summed over the modules at each node: they see the same
pose), and its variance is ``c^T Cov(n) c`` with the yaw noise modelled as AR(1) from
node to node (white: rho 0; a filtered mocap stream: rho > 0).  Its variance and
coefficient are measured from the increments of the residuals (:func:`yaw_noise_ar1`),
which carry no accumulated noise: ``e_l - e_l-1 = -gbar_l-1 (n_l - n_l-1)``, so the
modules at one increment give ``n_l - n_l-1`` by least squares.  (In the joint solver's
rolling block the casters have settled: the lever is constant, and per-node scores with
a Bartlett sum are right there.)
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from swpc_hw.calibration.rolling import RollingSeries
from swpc_hw.calibration.uncertainty import ar1_quadratic_form, dense_rows

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

WELL_DETERMINED = 0.25
"""An increment's noise is estimated where the modules' ``sum gbar^2`` is at least this
fraction of its median (casters that all turn across the spin at once see no yaw)."""
MAX_RHO = 0.97


def _increment_levers(series: RollingSeries, levers: FloatArray) -> tuple[FloatArray, BoolArray]:
    """Per clean node l: ``gbar`` of the increment into it (0 at a run's first node) and
    whether l continues the run of the node before it."""
    clean = series.clean
    run, g = series.run[clean], levers[clean]
    after = np.zeros(run.size, dtype=bool)
    after[1:] = run[1:] == run[:-1]
    g_in = np.zeros(run.size)
    g_in[1:] = 0.5 * (g[1:] + g[:-1])
    g_in[~after] = 0.0
    return g_in, after


def node_coefficients(
    series: RollingSeries, levers: FloatArray, a: FloatArray
) -> list[tuple[FloatArray, BoolArray]]:
    """Per segment, ``c`` (coefficient of each node's yaw noise in ``-sum_l a_l e_l``,
    summed over the modules at the node) on the segment's node grid, and which grid rows
    are nodes.  ``levers``: ``g`` of every node of ``series``; ``a``: per clean node."""
    clean = series.clean
    run, bins, seg = series.run[clean], series.bin[clean], series.seg[clean]
    n = run.size
    g_in, after = _increment_levers(series, levers)
    last = np.ones(n, dtype=bool)
    last[:-1] = ~after[1:]
    g_out = np.zeros(n)
    g_out[:-1] = g_in[1:]
    g_out[last] = 0.0
    # T_l: sum of a from node l to the end of its run
    before = np.cumsum(a) - a
    run_start = np.zeros(int(np.max(run)) + 1 if n else 0)
    run_start[run[~after]] = before[~after]
    T = np.bincount(run, weights=a, minlength=run_start.size)[run] - (before - run_start[run])
    T_next = np.zeros(n)
    T_next[:-1] = T[1:]
    T_next[last] = 0.0
    c = g_in * T - g_out * T_next
    out = []
    for s in np.unique(seg):
        sel = seg == s
        k = bins[sel] - int(bins[sel].min())
        present = np.zeros(int(k.max()) + 1, dtype=bool)
        present[k] = True
        out.append((dense_rows(k, c[sel][:, None])[:, 0], present))
    return out


def yaw_noise_ar1(
    series: RollingSeries, levers: FloatArray, e_raw: FloatArray
) -> tuple[float, float]:
    """``(variance, rho)`` of the yaw noise per node step, AR(1), from the residuals.

    Per increment the modules give ``dn_l = n_l - n_l-1 = -sum gbar d / sum gbar^2``
    (``d`` the increments of ``e_raw``, the raw (m) cumulative residual of every clean
    node) where that is well determined (:data:`WELL_DETERMINED`).  AR(1) noise gives
    ``Var(dn) = 2 var (1 - rho)`` and a lag-1 autocorrelation of ``dn`` of
    ``-(1 - rho) / 2``.  ``(nan, 0)`` without such increments.
    """
    clean = series.clean
    bins, seg = series.bin[clean], series.seg[clean]
    g_in, after = _increment_levers(series, levers)
    d = np.zeros(e_raw.size)
    d[1:] = e_raw[1:] - e_raw[:-1]
    d[~after] = 0.0
    sq = cross = 0.0
    count = 0
    for s in np.unique(seg):
        sel = seg == s
        k = bins[sel] - int(bins[sel].min())
        num = dense_rows(k, (g_in[sel] * d[sel])[:, None])[:, 0]
        den = dense_rows(k, (g_in[sel] ** 2)[:, None])[:, 0]
        if not np.any(den > 0):
            continue
        ok = den >= WELL_DETERMINED * float(np.median(den[den > 0]))
        dn = np.where(ok, -num / np.where(ok, den, 1.0), 0.0)
        sq += float(dn @ dn)
        cross += float(dn[:-1] @ dn[1:])
        count += int(ok.sum())
    if count < 3 or sq <= 0:
        return math.nan, 0.0
    rho = min(max(1.0 + 2.0 * cross / sq, 0.0), MAX_RHO)
    return sq / count / (2.0 * (1.0 - rho)), rho


def score_variance(
    series: RollingSeries, levers: FloatArray, a: FloatArray, e_raw: FloatArray
) -> float:
    """``Var(sum_l a_l e_l)`` over the clean nodes of ``series`` (module docstring):
    ``var sum_seg c^T R(rho) c``; segments are independent."""
    var, rho = yaw_noise_ar1(series, levers, e_raw)
    if not math.isfinite(var):
        return math.inf
    return var * sum(
        ar1_quadratic_form(c, present, rho)
        for c, present in node_coefficients(series, levers, a)
    )
