"""Wheel slip in the rolling series: short bursts and slow drifts.

The rolling residual of one increment (node l -> l+1) is ``d_l = r dpsi - dG``
(:func:`swpc_hw.calibration.rolling.rolling_increments`): yaw noise of the two nodes plus,
when the wheel slips, the extra wheel rotation.

* **Bursts** (a wheel spinning freely for a fraction of a second): increments beyond
  ``slip_sigmas`` robust sigmas of their series (median absolute deviation), and one
  increment either side.
* **Drifts** (a wheel slipping a fraction of a per cent for seconds): invisible in one
  increment, but a slope of the cumulative residual ``e = r psi - G`` against the rolled
  distance ``G``.  Tested for a whole series against the model (a slope beyond what the
  lever's uncertainty allows), and within a series for windows of 1, 2 and 4 chunks of
  ``chunk`` seconds against the series' own slope::

      k_hat = sum (G - G_bar)(e - e_bar) / sum (G - G_bar)^2,
      std(k_hat) = sigma_node sqrt(tau / sum (G - G_bar)^2)

  with ``sigma_node^2 = MAD(d)^2 / (2 (1 - rho))`` (robust, unaffected by the drift
  itself) and ``tau = (1 + rho) / (1 - rho)`` for the lag-1 correlation ``rho`` of the
  nodes' noise (from the increments' lag-1 correlation ``-(1 - rho) / 2``).  A window
  with ``|k_hat| > drift_sigmas std`` slips: 0.4 % over 2 s is ~4-6 std devs with 0.05 deg
  mocap yaw noise (the lever sets the scale), over 4 s three times that.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

BURST_DILATION = 1
"""Increments either side of a burst's that go with it (its edges slip partly)."""
MIN_SLIP_INCREMENTS = 8
"""Series with fewer wheel increments are not screened for slip (too little statistics)."""


def mad_sigma(x: FloatArray) -> float:
    """Robust std dev ``1.4826 median |x - median x|`` (0 for no data)."""
    if x.size == 0:
        return 0.0
    return 1.4826 * float(np.median(np.abs(x - np.median(x))))


def series_median(values: FloatArray, ser: IntArray) -> FloatArray:
    """Median of ``values`` within each series, broadcast back to the elements."""
    out = np.zeros_like(values)
    for k in np.unique(ser):
        sel = ser == k
        out[sel] = np.median(values[sel])
    return out


def increment_sigma(
    inc_res: FloatArray, ser: IntArray, floor: float | FloatArray = 1e-12
) -> FloatArray:
    """Robust std dev of every increment's series, floored by half the pooled one.

    The floor keeps a short series (few increments) from a tiny, over-rejecting scale;
    ``floor`` (m) is the encoders' own resolution (quantized increments of exact data are
    mostly equal: their MAD is 0), one for all or one per increment (a series takes the
    largest of its increments').
    """
    out = np.zeros(inc_res.size)
    dev = inc_res - series_median(inc_res, ser)
    pooled = 0.5 * mad_sigma(dev) if dev.size else 0.0
    floors = np.broadcast_to(np.asarray(floor, dtype=float), inc_res.shape)
    for k in np.unique(ser):
        sel = ser == k
        out[sel] = max(mad_sigma(inc_res[sel]), pooled, float(floors[sel].max()))
    return out


def burst_slip(
    inc_res: FloatArray, ser: IntArray, slip_sigmas: float, floor: float | FloatArray = 1e-12
) -> BoolArray:
    """Increments of a slip burst: beyond ``slip_sigmas`` robust sigmas, dilated by one.

    ``inc_res``: residual of every increment, ``ser``: its series.  Series with fewer
    than :data:`MIN_SLIP_INCREMENTS` increments are not screened; ``floor``: least
    increment std dev (m, the encoders' resolution).
    """
    sig = increment_sigma(inc_res, ser, floor)
    dev = inc_res - series_median(inc_res, ser)
    counts = np.bincount(ser) if ser.size else np.zeros(0, np.int64)
    enough = counts[ser] >= MIN_SLIP_INCREMENTS if ser.size else np.zeros(0, bool)
    bad = enough & (np.abs(dev) > slip_sigmas * sig)
    slip = bad.copy()
    for k in range(1, BURST_DILATION + 1):  # the burst's partial edges
        same = np.zeros_like(bad)
        same[k:] = ser[k:] == ser[:-k]
        slip[k:] |= bad[:-k] & same[k:]
        slip[:-k] |= bad[k:] & same[k:]
    return np.asarray(slip, dtype=bool)


DRIFT_SCALES = (1, 2, 4)
"""Window lengths of the drift test, in chunks (smallest first)."""


def drift_slip(
    inc_res: FloatArray,
    dG: FloatArray,
    ser: IntArray,
    t: FloatArray,
    exclude: BoolArray,
    chunk: float,
    drift_sigmas: float,
    lever_rel_std: FloatArray,
    floor: float = 1e-12,
) -> BoolArray:
    """Increments of series or windows whose cumulative residual drifts (module docstring).

    ``inc_res``, ``dG``, ``ser``, ``t`` (time of the increment's first node): one entry per
    increment; ``exclude``: increments already known to slip (bursts), left out;
    ``lever_rel_std``: per series, the relative std dev of its lever that the fixed
    points' uncertainty allows (a whole series may lean by that much without slipping);
    ``floor``: least increment std dev (m).

    1. The whole series against the model: its slope, with the lever's uncertainty added
       to the slope's std dev.
    2. Within the series, its own slope removed (insensitive to the model): windows of 1,
       2 and 4 ``chunk`` lengths, half a chunk apart, smallest first; increments of the
       windows flagged at one length are left out of the larger ones, so a large window
       is cut only for a drift the small ones could not localise.
    """
    out = np.zeros(inc_res.size, dtype=bool)
    for k in np.unique(ser):
        idx = np.flatnonzero(ser == k)
        if idx.size < MIN_SLIP_INCREMENTS:
            continue
        d, g, ok = inc_res[idx], dG[idx], ~exclude[idx]
        if ok.sum() < MIN_SLIP_INCREMENTS:
            continue
        sig_inc = max(mad_sigma(d[ok]), floor)
        # node noise with lag-1 correlation rho_n gives increments with lag-1 correlation
        # -(1 - rho_n) / 2 and variance 2 sigma_n^2 (1 - rho_n)
        rho_n = min(max(2.0 * _lag1(np.where(ok, d - np.median(d[ok]), 0.0)) + 1.0, 0.0), 0.95)
        var_factor = (1.0 + rho_n) / (2.0 * (1.0 - rho_n) ** 2)  # sigma_n^2 tau / sig_inc^2
        slope, z = drift_slope(d, g, ok, sig_inc, var_factor, float(lever_rel_std[k]))
        if abs(z) > drift_sigmas:
            out[idx] = True
            continue
        d = d - slope * g  # the series' own lean is the model's business
        tr = t[idx] - t[idx[0]]
        flagged = np.zeros(idx.size, dtype=bool)
        for scale in DRIFT_SCALES:
            width = scale * chunk
            a = np.arange(0.0, max(float(tr[-1]) - 0.5 * width, 0.0) + 1e-9, 0.5 * chunk)
            i0 = np.searchsorted(tr, a, side="left")
            i1 = np.searchsorted(tr, a + width, side="left")
            usable = ok & ~flagged
            left_out = np.concatenate([[0], np.cumsum(~usable)])
            whole = left_out[i1] - left_out[i0] == 0
            zw = np.zeros(a.size)
            zw[whole] = window_z(d, g, i0[whole], i1[whole], sig_inc, var_factor)
            for w in np.flatnonzero(~whole).tolist():
                sel = usable.copy()
                sel[: i0[w]] = False
                sel[i1[w] :] = False
                zw[w] = drift_slope(d, g, sel, sig_inc, var_factor)[1]
            for w in np.flatnonzero(np.abs(zw) > drift_sigmas).tolist():
                flagged[i0[w] : i1[w]] = True
        out[idx] = flagged
    return out


def window_z(
    d: FloatArray, g: FloatArray, i0: IntArray, i1: IntArray, sig_inc: float, var_factor: float
) -> FloatArray:
    """:func:`drift_slope`'s z of many windows ``[i0, i1)`` of consecutive increments at once.

    With prefix sums ``P_d[k] = sum_{l<k} d_l`` (likewise ``P_g``) the window's cumulative
    values are ``P[k] - P[i0]``, ``k = i0+1..i1``, plus the window's first node (0, 0);
    the regression sums follow from prefix sums of ``P_g``, ``P_d``, ``P_g^2``,
    ``P_g P_d``.  Windows of fewer than 4 increments get 0.
    """
    Pd = np.concatenate([[0.0], np.cumsum(d)])
    Pg = np.concatenate([[0.0], np.cumsum(g)])

    def span(v: FloatArray) -> FloatArray:  # sum of v[k] for k = i0+1 .. i1
        c = np.concatenate([[0.0], np.cumsum(v)])
        return np.asarray(c[i1 + 1] - c[i0 + 1], dtype=float)

    n = (i1 - i0).astype(float)
    g0, d0 = Pg[i0], Pd[i0]
    sg, sd = span(Pg) - n * g0, span(Pd) - n * d0
    sgg = span(Pg * Pg) - 2.0 * g0 * span(Pg) + n * g0 * g0
    sgd = span(Pg * Pd) - d0 * span(Pg) - g0 * span(Pd) + n * g0 * d0
    m = n + 1.0
    sxx = sgg - sg * sg / m
    sxy = sgd - sg * sd / m
    ok = (n >= 4) & (sxx > 0)
    z = np.zeros(n.size)
    slope = sxy[ok] / sxx[ok]
    z[ok] = slope / np.sqrt(sig_inc**2 * var_factor / sxx[ok])
    return z


def drift_slope(
    d: FloatArray,
    g: FloatArray,
    sel: BoolArray,
    sig_inc: float,
    var_factor: float,
    model_std: float = 0.0,
) -> tuple[float, float]:
    """Slope of the cumulative residual against the rolled distance, and it in std devs.

    Over the selected increments ``sel`` of one series, split into runs of consecutive
    ones (a left-out increment breaks the cumulative sums: its node noise no longer
    telescopes): per run ``e_m = sum_{l<m} d_l``, ``G_m = sum_{l<m} dG_l``, centred in
    the run; pooled ``k_hat = sum (G - G_bar)(e - e_bar) / S_GG``,
    ``std^2 = sig_inc^2 var_factor / S_GG + model_std^2``.  ``(0, 0)`` for fewer than 4
    increments.
    """
    idx = np.flatnonzero(sel)
    if idx.size < 4:
        return 0.0, 0.0
    breaks = np.flatnonzero(np.diff(idx) > 1) + 1
    sxy = sxx = 0.0
    for run in np.split(idx, breaks) if breaks.size else (idx,):
        e = np.cumsum(d[run])
        G = np.cumsum(g[run])
        # with the run's first node (0, 0) prepended: n + 1 points
        m = run.size + 1
        Gm, em = G.sum() / m, e.sum() / m
        sxx += float(G @ G) - m * Gm * Gm
        sxy += float(G @ e) - m * Gm * em
    if sxx <= 0:
        return 0.0, 0.0
    slope = sxy / sxx
    return slope, slope / math.sqrt(sig_inc**2 * var_factor / sxx + model_std**2)


def _lag1(x: FloatArray) -> float:
    den = float(x @ x)
    return float(x[:-1] @ x[1:]) / den if den > 0 else 0.0


def detect_slip(
    inc_res: FloatArray,
    dG: FloatArray,
    ser: IntArray,
    t: FloatArray,
    slip_sigmas: float,
    chunk: float,
    drift_sigmas: float,
    lever_rel_std: FloatArray,
    floor: float | FloatArray = 1e-12,
) -> BoolArray:
    """Slipping increments: bursts (:func:`burst_slip`) and drifts (:func:`drift_slip`).

    ``floor``: least increment std dev (m), the wheel encoders' resolution; per increment,
    the bursts' (the drifts take the least).
    """
    burst = burst_slip(inc_res, ser, slip_sigmas, floor)
    if math.isinf(drift_sigmas):
        return burst
    least = float(np.min(floor)) if np.size(floor) else 1e-12
    return burst | drift_slip(
        inc_res, dG, ser, t, burst, chunk, drift_sigmas, lever_rel_std, least
    )
