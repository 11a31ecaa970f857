"""The long-run covariance on a short series of centred residuals (issue 44): what a 3 s
spin's rolling block gives the solver (30 nodes; ``python -m benchmarks honesty_blocks``
measures the same on whole solves)."""

from __future__ import annotations

import numpy as np
import pytest

from swpc_hw.calibration.uncertainty import long_run_covariance


def scores(rng: np.random.Generator, T: int, rho: float) -> np.ndarray:
    """(T, 2) scores of a cumulative rolling series: residuals centred over the run (its
    unknown start angle) times the Jacobian of such residuals (centred too), which grows
    with the wheel's travel (column 0: a radius) or bends with it (column 1), the noise
    AR(1) with ``rho``."""
    e = np.empty(T)
    e[0] = rng.normal()
    for t in range(1, T):
        e[t] = rho * e[t - 1] + np.sqrt(1 - rho**2) * rng.normal()
    f = e - e.mean()
    k = np.arange(T, dtype=float)
    bend = (k - k.mean()) ** 2
    J = np.column_stack([k - k.mean(), bend - bend.mean()])
    return np.asarray(J * f[:, None])


@pytest.mark.parametrize("T", [30, 20])
def test_short_centred_white_series_are_read_at_their_variance(T: int) -> None:
    """Over 3000 draws the mean estimate of ``Var(sum s)`` against the variance of the sums
    themselves: never below.  Sokal's window gave white noise 6 lags, whose sample
    autocovariances the centring biases negative: 0.83 of the variance before.  The
    window now asks for lags only for a correlation the estimate's noise does not explain
    (``SIGNIFICANT``); what remains above 1 (1.19-1.21) is the AR(1) prewhitening, whose
    lag-1 estimate is positive half the time on white noise and recolours upward: on the
    safe side.  (AR(1) noise of 0.5 on 30 nodes is still read at 0.86: the lag-1
    estimate's own bias on a short series, docs/solver-uncertainty.md.)"""
    rho = 0.0
    rng = np.random.default_rng(44)
    present = np.ones(T, dtype=bool)
    sums, est = [], []
    for _ in range(3000):
        S = scores(rng, T, rho)
        sums.append(S.sum(axis=0))
        est.append(long_run_covariance(S, present)[0])
    true = np.var(np.array(sums), axis=0)
    mean = np.mean(np.array(est), axis=0).diagonal()
    ratio = mean / true
    print(f"\nT {T}, rho {rho}: estimate / variance {np.round(ratio, 3)}")
    assert np.all((ratio > 0.97) & (ratio < 1.25)), ratio
