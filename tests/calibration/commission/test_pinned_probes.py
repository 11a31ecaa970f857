"""A lock fought by its driver (swpc_hw.calibration.commission.probes): a pivot probe is
pinned only when its fixed point is where its driver was steered to turn about; the next
point to steer about converges on the lock's contact point; the analysis judges on the
pinned probes only.  The whole path on a drive that holds by position control (the CiA
402 simulator): tests/services/whole_runs/test_commission.py."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from swpc_hw.calibration.commission.analysis import MOCAP_TURNS, analyse
from swpc_hw.calibration.commission.probes import PINNED_TOL, PivotProbe, is_pinned, next_pivot
from tests.calibration.commission.test_analysis import NOMINAL, Wiring, probes


def fought(T: np.ndarray, alpha: float, P: np.ndarray) -> np.ndarray:
    """The fixed point of a lock at ``T`` fought by a driver steered about ``P``."""
    return T + alpha * (P - T)


def test_the_next_pivot_reaches_a_fought_locks_contact_point_in_two_rolls() -> None:
    T = np.array([0.2165, -0.1247])  # module 2's contact point (crossed: sought about 1's)
    for alpha in (0.3, 0.6, 0.9):
        P = np.array([0.215, 0.145])
        start = float(np.hypot(*(P - T)))
        history: list[tuple[tuple[float, float], tuple[float, float]]] = []
        misses = []
        for _ in range(3):
            X = fought(T, alpha, P)
            history.append(((float(P[0]), float(P[1])), (float(X[0]), float(X[1]))))
            P = np.array(next_pivot(history))
            misses.append(float(np.hypot(*(P - T))))
        # one roll: the fixed point itself (alpha of the way); two: the secant, exact
        assert abs(misses[0] - alpha * start) < 1e-12
        assert misses[1] < 1e-9 and misses[2] < 1e-9, (alpha, misses)


def test_an_iteration_that_leaves_the_model_takes_the_point_seen() -> None:
    # the fixed point jumped further than the steered point moved (alpha > 0.95)
    history = [((0.0, 0.0), (0.1, 0.0)), ((0.1, 0.0), (0.3, 0.0))]
    assert next_pivot(history) == (0.3, 0.0)


def test_a_probe_is_pinned_where_it_was_steered_to_turn_even_seen_by_a_turned_body() -> None:
    pivot = (0.2, 0.1)
    at = PivotProbe(1, 0.0, 3, 2.0, 1.0, 0.17, (0.2 + 0.8 * PINNED_TOL, 0.1), 5e-4)
    off = replace(at, fixed_point=(0.2 + 1.2 * PINNED_TOL, 0.1))
    assert is_pinned(at, pivot, [0.0]) and not is_pinned(off, pivot, [0.0])
    # a body turned 90 deg from R reports R(-90 deg) C
    turned = replace(at, fixed_point=(0.1, -0.2))
    assert not is_pinned(turned, pivot, [0.0]) and is_pinned(turned, pivot, MOCAP_TURNS)
    noisy = replace(off, fixed_point_std=PINNED_TOL / 2)  # 4 std devs cover it
    assert is_pinned(noisy, pivot, [0.0])


def test_the_analysis_judges_on_the_pinned_probes_only() -> None:
    right = probes(Wiring())
    # each lock's first roll fought by its driver: the fixed point 100 mm off, the turn
    # half what the roll asks
    bad = [
        replace(p, fixed_point=(p.fixed_point[0] + 0.1, p.fixed_point[1] - 0.05),
                turn=p.turn / 2, pinned=False)
        for p in right if p.fixed_point is not None
    ]  # fmt: skip
    c = analyse(NOMINAL, [], bad + right)
    assert c.right and not c.unknown, (c.findings, c.unknown)
    # the same rolls taken as pinned: the locks and the wheels are misjudged
    c = analyse(NOMINAL, [], [replace(p, pinned=True) for p in bad] + right)
    assert not c.right
