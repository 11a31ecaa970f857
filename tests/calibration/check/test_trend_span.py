"""A trend only over points that span a day (swpc_hw.calibration.check.trend.MIN_SPAN):
two calibrations minutes apart gave Drift "+1192 mm/week +- 1113" (issue 45 item 4)."""

from __future__ import annotations

import numpy as np
import pytest

from swpc_hw.calibration.check.trend import MIN_SPAN, linear_trend


def test_no_slope_from_points_minutes_apart_and_one_from_a_day() -> None:
    y, sd = [55.0, 55.02], [0.01, 0.01]  # mm: two calibrations 0.02 mm apart (2 std devs)
    assert linear_trend([0.0, 600.0], y, sd, reference=55.0, tolerance=0.2, now=600.0) is None
    assert linear_trend([0.0, MIN_SPAN - 1], y, sd, reference=55.0, tolerance=0.2,
                        now=MIN_SPAN) is None  # fmt: skip
    tr = linear_trend([0.0, MIN_SPAN], y, sd, reference=55.0, tolerance=0.2, now=MIN_SPAN)
    assert tr is not None and tr.slope * 7 * MIN_SPAN == pytest.approx(0.14)
    assert np.isfinite(tr.slope_std) and not tr.significant  # 2 std devs in a day: noise
