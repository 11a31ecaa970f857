"""A parameter over a robot's life: its linear trend and when it leaves its tolerance.

Every calibration and check of a robot measures each parameter ``y_i`` with a std dev
``s_i`` at a time ``t_i`` (the history, :mod:`services.runtime.history`).  The trend is
the weighted least-squares line (times centred on their weighted mean ``t_bar``)::

    y(t) = a + b (t - t_bar),   minimising  sum_i ((y_i - a - b (t_i - t_bar)) / s_i)^2

    b = sum_i w_i (t_i - t_bar) y_i / sum_i w_i (t_i - t_bar)^2,   a = sum_i w_i y_i / W,
    w_i = 1 / s_i^2,  W = sum_i w_i
    Var(a) = k / W,   Var(b) = k / sum_i w_i (t_i - t_bar)^2,   Cov(a, b) = 0

with ``k = max(1, chi2 / (n - 2))`` (Birge's ratio: a scatter of the points beyond their
std devs, wear that is not quite linear, widens the line's uncertainty rather than being
ignored; n = 2 points: k = 1).

**When it leaves its tolerance**: the parameter leaves the band
``|y - reference| <= tolerance`` around the file in force's value (the reference) at the
time the line reaches the band's edge in the direction of its slope::

    t_out = t_bar + (reference + sign(b) tolerance - a) / b

given only when the slope is significant, ``|b| > 2 sd(b)`` (otherwise the line's date
is noise); ``outside`` says the line is already out of the band now.

**Over a span that supports a slope**: no line unless the points span at least
:data:`MIN_SPAN` (a day).  Two calibrations minutes apart differ by their noise, which a
slope per week multiplies by thousands (+1192 mm/week +- 1113 from two points 10 min
apart): a number that reads as drift and is none.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

MIN_SPAN = 86400.0
"""s: the least span of a trend's points (module docstring)."""
SIGNIFICANT = 2.0
"""A slope is significant beyond this many of its std devs."""


@dataclass(frozen=True)
class Trend:
    """A parameter's line over time (module docstring); times in s (the caller's epoch),
    values in the caller's unit."""

    points: int
    t_bar: float
    value: float
    """``a``: the line at ``t_bar``."""
    slope: float
    """``b`` per second."""
    value_std: float
    slope_std: float
    birge: float
    """``k``: the points' scatter over their std devs (variance ratio, at least 1)."""
    significant: bool
    leaves_at: float | None
    """``t_out`` (s), None when the slope is not significant or zero."""
    outside: bool
    """The line is out of the band at ``now``."""

    def at(self, t: float) -> float:
        return self.value + self.slope * (t - self.t_bar)


def linear_trend(
    t: ArrayLike,
    y: ArrayLike,
    sd: ArrayLike,
    *,
    reference: float,
    tolerance: float,
    now: float,
) -> Trend | None:
    """The weighted line through ``(t_i, y_i)`` with std devs ``sd_i`` and when it leaves
    ``reference +- tolerance`` (module docstring).  None with fewer than two points or
    points spanning less than :data:`MIN_SPAN` (no line); a point without a finite
    positive std dev is left out."""
    t_a, y_a, s_a = (np.asarray(v, dtype=float).reshape(-1) for v in (t, y, sd))
    ok = np.isfinite(t_a) & np.isfinite(y_a) & np.isfinite(s_a) & (s_a > 0)
    t_a, y_a, s_a = t_a[ok], y_a[ok], s_a[ok]
    n = int(t_a.size)
    if n < 2 or float(np.ptp(t_a)) < MIN_SPAN:
        return None
    w = 1.0 / s_a**2
    W = float(w.sum())
    t_bar = float(w @ t_a) / W
    dt = t_a - t_bar
    Stt = float(w @ dt**2)
    a = float(w @ y_a) / W
    b = float(w @ (dt * y_a)) / Stt
    chi2 = float(w @ (y_a - a - b * dt) ** 2)
    k = max(1.0, chi2 / (n - 2)) if n > 2 else 1.0
    sa, sb = math.sqrt(k / W), math.sqrt(k / Stt)
    significant = b != 0.0 and abs(b) > SIGNIFICANT * sb
    leaves = None
    if significant:
        edge = reference + math.copysign(tolerance, b)
        leaves = t_bar + (edge - a) / b
    outside = abs(a + b * (now - t_bar) - reference) > tolerance
    return Trend(n, t_bar, a, b, sa, sb, k, significant, leaves, outside)
