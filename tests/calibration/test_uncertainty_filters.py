"""The long-run covariance's filters in numpy against scipy.signal's (the peer: the
solver stopped importing it, 0.8 s of every service's start-up and 20x that in the VM)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.signal

from swpc_hw.calibration.uncertainty import ar1_filter, bartlett_smooth, bartlett_weights


@pytest.mark.parametrize("rho", [0.0, 1e-3, 0.5, 0.8, 0.97, 0.999])
def test_the_ar1_filter_is_lfilters_across_its_blocks(rho: float) -> None:
    """20,000 samples: at rho 0.5 more than 300 blocks of 332, at 0.97 three."""
    x = np.random.default_rng(3).normal(size=20_000)
    x[5000:5400] = 0.0  # a gap, as absent rows are
    want = scipy.signal.lfilter([1.0], [1.0, -rho], x)
    got = ar1_filter(x, rho)
    assert np.max(np.abs(got - want)) <= 1e-14 * np.max(np.abs(want))


def test_the_ar1_filter_refuses_a_rho_it_cannot_sum() -> None:
    with pytest.raises(ValueError, match=r"rho 1\.0 outside"):
        ar1_filter(np.ones(3), 1.0)


@pytest.mark.parametrize(("rows", "bandwidth"), [(1, 4), (5, 3), (100, 7), (5000, 40)])
def test_the_bartlett_smoothing_is_fftconvolves_same(rows: int, bandwidth: int) -> None:
    S = np.random.default_rng(rows).normal(size=(rows, 3))
    w = bartlett_weights(bandwidth)
    want = scipy.signal.fftconvolve(S, w[:, None], mode="same", axes=0)
    np.testing.assert_allclose(bartlett_smooth(S, bandwidth), want, rtol=0, atol=1e-12)
