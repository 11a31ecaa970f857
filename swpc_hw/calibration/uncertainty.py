"""Covariances that hold when the noise is not white: HAC (Newey-West) sandwiches.

A least-squares estimate ``x_hat`` with weighted residuals ``f`` and Jacobian ``J`` has,
for *any* noise covariance, the sandwich covariance::

    Cov(x_hat) = H^-1 M H^-1,        H = J^T J,        M = Var(J^T f)

White noise of the assumed size gives ``M = H`` and the textbook ``H^-1``.  Motion
capture noise is not white (a filtered stream: AR(1) from frame to frame), so ``M`` is
estimated from the data.  The scores ``s_t = J_t^T f_t`` are summed per time step ``t``
of a regular grid (a missing sample is a zero row), and ``M`` is their long-run
covariance: AR(1) prewhitening (Andrews & Monahan 1992, made exact for gaps), then
Bartlett weights (Newey & West 1987) on what is left::

    u_t = s_t - rho^m s_t-m   (t - m: the previous sample),    sum_t s_t = sum_u beta_u u_u,
    Omega = Gamma_0 + sum_{k=1..L} (1 - k / (L + 1)) (Gamma_k + Gamma_k^T),
    Gamma_k = sum_u v_u v_u+k^T,    v_u = beta_u u_u

``rho`` is the scores' lag-1 autocorrelation; the bandwidth ``L`` (grid steps) follows
from the correlation left in ``v`` (Sokal's automatic window, :func:`window_bandwidth`).
See ``docs/solver-uncertainty.md`` for the reasoning and the measured coverage.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

WINDOW_FACTOR = 6.0
"""Sokal's window: the lags summed span this many integrated autocorrelation times."""

SIGNIFICANT = 2.0
"""A column's correlation asks for lags only when its integrated autocorrelation over
Sokal's window exceeds 1 by this many of white noise's sampling std devs
(:func:`window_bandwidth`)."""

AR1_BLOCK_GROWTH = 1e100
""":func:`ar1_filter` works in blocks over which ``rho^-k`` grows at most this much."""


def ar1_filter(x: FloatArray, rho: float) -> FloatArray:
    """``y_t = x_t + rho y_t-1`` (``y_-1 = 0``, ``0 <= rho < 1``): scipy's
    ``lfilter([1], [1, -rho], x)`` in numpy (``scipy.signal`` costs every process that
    imports it 0.8 s, 20x that on a slow robot computer or in an emulated one).

    Over a block of ``B`` samples from ``s`` with the carry ``c = y_s-1``::

        y_s+k = rho^k (rho c + sum_{j <= k} x_s+j rho^-j)

    a cumulative sum, with ``B`` such that ``rho^-B <= AR1_BLOCK_GROWTH`` (no overflow;
    each ``y`` is still the weighted sum of its terms to rounding).
    """
    x = np.asarray(x, dtype=float)
    if rho == 0.0 or x.size == 0:
        return x.copy()
    if not 0.0 < rho < 1.0:
        raise ValueError(f"rho {rho} outside [0, 1)")
    block = max(1, int(math.log(AR1_BLOCK_GROWTH) / -math.log(rho)))
    y = np.empty_like(x)
    carry = 0.0
    for s in range(0, x.size, block):
        seg = x[s : s + block]
        k = np.arange(seg.size, dtype=float)
        grow = rho**-k
        y[s : s + seg.size] = (rho * carry + np.cumsum(seg * grow)) / grow
        carry = float(y[s + seg.size - 1])
    return y


def grid_index(t: FloatArray, dt: float) -> IntArray:
    """Index of every sample time on the regular grid ``t_0 + k dt``: ``round((t - t_0) / dt)``."""
    if t.size == 0:
        return np.zeros(0, dtype=np.int64)
    return np.asarray(np.rint((t - t[0]) / dt), dtype=np.int64)


def dense_rows(index: IntArray, rows: FloatArray) -> FloatArray:
    """Rows summed into a dense grid: ``S[k] = sum of rows with index k`` (zeros elsewhere)."""
    size = int(np.max(index)) + 1 if index.size else 0
    S = np.zeros((size, rows.shape[1]))
    np.add.at(S, index, rows)
    return S


def lag1_autocorrelation(e: FloatArray, present: BoolArray) -> float:
    """``rho_1 = sum_t e_t . e_t+1 / sqrt(sum |e_t|^2 sum |e_t+1|^2)`` over pairs both present.

    ``e``: (T, p) dense grid of residuals, ``present``: (T,) which rows are samples.
    0 when there are no such pairs.
    """
    both = present[:-1] & present[1:]
    if not both.any():
        return 0.0
    a, b = e[:-1][both], e[1:][both]
    den = math.sqrt(float(np.sum(a * a)) * float(np.sum(b * b)))
    return float(np.sum(a * b)) / den if den > 0 else 0.0


def bartlett_weights(bandwidth: int) -> FloatArray:
    """``w_k = 1 - |k| / (L + 1)`` for ``k = -L..L``."""
    k = np.arange(-bandwidth, bandwidth + 1, dtype=float)
    return np.asarray(1.0 - np.abs(k) / (bandwidth + 1.0), dtype=float)


def bartlett_smooth(S: FloatArray, bandwidth: int) -> FloatArray:
    """``sum_{|k| <= L} w_k s_t+k`` for every t (zero beyond the ends), (T, p)."""
    if bandwidth <= 0 or S.shape[0] == 0:
        return S.copy()
    w = bartlett_weights(bandwidth)
    T = S.shape[0]
    n = 1 << math.ceil(math.log2(T + 2 * bandwidth))  # no wrap-around: a linear convolution
    full = np.fft.irfft(np.fft.rfft(S, n, axis=0) * np.fft.rfft(w, n)[:, None], n, axis=0)
    return np.asarray(full[bandwidth : bandwidth + T], dtype=float)


def bartlett_covariance(S: FloatArray, bandwidth: int) -> FloatArray:
    """``Gamma_0 + sum_{k=1..L} (1 - k / (L + 1)) (Gamma_k + Gamma_k^T)`` of ``S`` (T, p).

    ``= sum_t s_t (sum_{|k| <= L} w_k s_t+k)^T`` (:func:`bartlett_smooth`, by FFT).
    Positive semi-definite by construction (the Bartlett window has a non-negative
    spectrum).
    """
    L = min(bandwidth, max(S.shape[0] - 1, 0))
    omega = S.T @ bartlett_smooth(S, L)
    return np.asarray(0.5 * (omega + omega.T), dtype=float)


def ar1_innovations(S: FloatArray, present: BoolArray, rho: float) -> FloatArray:
    """``u_t = s_t - rho^m s_t-m`` with ``t - m`` the previous present sample (``u = s`` for
    the first); zero rows where absent.  Independent for AR(1) scores, gaps or not."""
    U = np.zeros_like(S)
    idx = np.flatnonzero(present)
    if idx.size == 0:
        return U
    U[idx[0]] = S[idx[0]]
    gap = np.diff(idx).astype(float)
    U[idx[1:]] = S[idx[1:]] - (rho**gap)[:, None] * S[idx[:-1]]
    return U


def ar1_recolouring(present: BoolArray, rho: float) -> FloatArray:
    """``beta_u = sum_{t >= u, present} rho^(t - u)``: the weight of innovation u in ``sum_t s_t``.

    From ``s_t = u_t + rho^m s_t-m``: ``sum_t s_t = sum_u beta_u u_u`` (backward recursion
    ``beta_t = p_t + rho beta_t+1``; ``1 / (1 - rho)`` away from the end without gaps).
    """
    p = present.astype(float)
    return ar1_filter(p[::-1], rho)[::-1]


def long_run_covariance(S: FloatArray, present: BoolArray) -> tuple[FloatArray, float, int]:
    """Long-run covariance ``Var(sum_t s_t)`` of a score sequence with gaps, AR(1)-prewhitened.

    ``S``: (T, p) scores on a regular grid, a missing sample a zero row; ``present``: (T,)
    which rows are samples.  With the scores' lag-1 autocorrelation ``rho`` (pairs of
    present samples, clipped to ``[0, 0.97]``) the innovations ``u`` of
    :func:`ar1_innovations` are near white, and ``sum_t s_t = sum_u beta_u u_u``
    (:func:`ar1_recolouring`; Andrews & Monahan's prewhitening, made exact for gaps), so

        Omega = Bartlett(beta_u u_u)

    at the bandwidth of :func:`window_bandwidth` for what correlation ``v`` has left:
    exact for AR(1) noise, measured rather than modelled for any other.  Returns
    ``(Omega, rho, L)``.
    """
    rho = min(max(lag1_autocorrelation(S, present), 0.0), 0.97)
    V = ar1_innovations(S, present, rho) * ar1_recolouring(present, rho)[:, None]
    L = window_bandwidth(V, int(present.sum()))
    return bartlett_covariance(V, L), rho, L


def ar1_quadratic_form(c: FloatArray, present: BoolArray, rho: float) -> float:
    """``c^T R c`` with ``R_tu = rho^|t - u|`` between the present rows of a grid.

    ``sum_t c_t sum_k rho^|k| c_t+k`` by a forward and a backward AR(1) filter (absent rows
    count as zero; the correlation spans them as the grid distance says).
    """
    x = np.where(present, c, 0.0)
    fwd = ar1_filter(x, rho)
    bwd = ar1_filter(x[::-1], rho)[::-1]
    return float(x @ (fwd + bwd - x))


def autocorrelation(V: FloatArray, max_lag: int) -> FloatArray:
    """Autocorrelation of every column, ``r_k = sum_t v_t v_t+k / sum_t v_t^2``: (K + 1, p)."""
    T = V.shape[0]
    n = 1 << math.ceil(math.log2(max(2 * T, 2)))
    F = np.fft.rfft(V, n, axis=0)
    acov = np.fft.irfft(F * np.conj(F), n, axis=0)[: max_lag + 1]
    var = acov[0]
    return np.asarray(
        np.where(var > 0, acov / np.where(var > 0, var, 1.0), 0.0), dtype=float
    )


def window_bandwidth(V: FloatArray, n: int, c: float = WINDOW_FACTOR) -> int:
    """Bartlett bandwidth from the correlation left in ``V`` (Sokal's automatic window).

    Per column, ``tau(M) = 1 + 2 sum_{k=1..M} r_k`` and ``M`` is the smallest window with
    ``M >= c tau(M)`` (the correlation has died out within it); ``L = 2 max M`` (the
    Bartlett weights halve the lags' weight on average), at most ``n // 3``.  Unlike a
    rule on the lag-1 autocorrelation alone this sees a slow component under a fast one
    (white noise plus AR(1) noise: the lag-1 correlation is small, the tail long), and
    per column it sees a correlated component of small variance.

    A column that is all zeros (a parameter the segment does not touch) or whose lag-1
    autocorrelation is not positive asks for no lag (``L = 0`` when none does): Sokal's
    rule gives white noise a window of ``c``, harmless on a long series, but on a short
    one of centred residuals the sample autocovariances within it are biased negative
    (the centring's ``-sigma^2 / T`` per pair, summed over lags whose compensating far
    part the window leaves out), and the estimate under-read the scores' true variance
    by 19-29 % over 3 s spins (30 nodes; ``python -m benchmarks honesty_blocks``).
    """
    K = max(1, min(n // 3, V.shape[0] - 1))
    live = np.any(V != 0.0, axis=0)
    if not live.any():
        return 0
    r = autocorrelation(V[:, live], K)
    tau = 1.0 + 2.0 * np.cumsum(r[1:], axis=0)
    M = np.arange(1, K + 1)[:, None]
    done = c * tau <= M
    m = np.where(done.any(axis=0), np.argmax(done, axis=0) + 1, K)
    m = np.where(r[1] > 0.0, m, 0)  # white or anti-correlated: no lag to add
    # a correlation the noise of the estimate explains asks for no lag either: white
    # noise's sample tau(M) - 1 has a std dev of 2 sqrt(M / n)
    tau_m = np.take_along_axis(tau, np.maximum(m - 1, 0)[None, :], axis=0)[0]
    m = np.where(tau_m - 1.0 > SIGNIFICANT * 2.0 * np.sqrt(m / max(n, 1)), m, 0)
    return int(min(2 * int(m.max()), max(1, n // 3)))


def sandwich_covariance(J: FloatArray, M: FloatArray) -> FloatArray:
    """``H^-1 M H^-1`` with ``H = J^T J``, computed stably; NaN where undetermined.

    The columns of ``J`` are first scaled to unit norm (parameters in metres and radians
    with weights spanning many decades make ``J^T J`` numerically singular otherwise),
    then ``H`` is inverted by SVD.  If the data do not determine every parameter (a zero
    column or a singular value below ``1e-12`` of the largest) the whole matrix is NaN:
    unknown, never 0.
    """
    p = J.shape[1]
    out = np.full((p, p), np.nan)
    norms = np.linalg.norm(J, axis=0)
    if not np.all(norms > 0) or not np.all(np.isfinite(J)):
        return out
    Js = J / norms
    _, sv, Vt = np.linalg.svd(Js, full_matrices=False)
    if sv.size < p or sv[-1] <= sv[0] * 1e-12:
        return out
    H_inv = (Vt.T / sv**2) @ Vt
    scale = np.outer(norms, norms)
    cov = (H_inv @ (M / scale) @ H_inv) / scale
    return np.asarray(0.5 * (cov + cov.T), dtype=float)


def stddev_of(cov: FloatArray) -> FloatArray:
    """``sqrt(diag(cov))``; NaN where the variance is not finite and positive."""
    var = np.diag(cov).copy()
    good = np.isfinite(var) & (var > 0)
    out = np.full(var.shape, np.nan)
    out[good] = np.sqrt(var[good])
    return out
