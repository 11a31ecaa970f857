"""What the commissioning probes say (swpc_hw.calibration.commission.analysis), on probes
made from the geometry of a known wiring: each miswiring named, with its module and axis,
and nothing else; a right robot nothing at all.  The probes' fixed points carry the
noise a 10 deg arc leaves (mm), so the tolerances are tried too."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
import pytest

from swpc_hw.calibration.commission.analysis import analyse, circle_centre, ratio_off
from swpc_hw.calibration.commission.probes import (
    PIVOT_ANGLES,
    PROBE_TURN,
    REFINE_ANGLES,
    PivotProbe,
    SteerMove,
    driver_of,
    pivot_plan,
)
from swpc_hw.robot.model import contact_point
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED as TRUTH
from swpc_hw.robot.paper_robot import PAPER_NOMINAL as NOMINAL

IDS = NOMINAL.ids


@dataclass
class Wiring:
    """Configured module -> what its drives move: the physical module, the steering's
    sign and ratio (true over configured), the zero added to the truth's beta, the
    wheel's sign and ratio; the motion-capture body's turn."""

    physical: dict[int, int] = field(default_factory=lambda: {m: m for m in IDS})
    steer: dict[int, tuple[int, float]] = field(default_factory=dict)
    zero: dict[int, float] = field(default_factory=dict)
    wheel: dict[int, tuple[int, float]] = field(default_factory=dict)
    gamma: float = 0.0


def probes(
    w: Wiring,
    noise: float = 0.0,
    seed: int = 0,
    pushed: bool = False,
    angles: tuple[float, ...] = PIVOT_ANGLES,
) -> list[PivotProbe]:
    """The pivot probes a robot wired as ``w`` gives (the truth's geometry): the fixed
    point is the pinned caster's contact point, the turn (1) of probes.py for the roll
    (``pushed``: (1'), a wheel pushed by torque)."""
    rng = np.random.default_rng(seed)
    T = TRUTH.arrays()
    out = []

    def true_angle(m: int, reading: float) -> float:
        p = w.physical[m]
        s, g = w.steer.get(p, (1, 1.0))
        return float(T.beta[IDS.index(p)]) + math.radians(w.zero.get(p, 0.0)) + reading / (s * g)

    for m in IDS:
        j = driver_of(IDS, m)
        for a in angles:
            plan = pivot_plan(NOMINAL, m, a, j)
            p = IDS.index(w.physical[m])
            C = contact_point(T.P_s[p], np.array(T.b[p]), true_angle(m, a))
            q = IDS.index(w.physical[j])
            phi = true_angle(j, plan.driver_steering)
            c = contact_point(T.P_s[q], np.array(T.b[q]), phi)
            rel = c - C
            D = float(np.hypot(*rel))
            cos_delta = (math.cos(phi) * -rel[1] + math.sin(phi) * rel[0]) / D
            s_w, g_w = w.wheel.get(w.physical[j], (1, 1.0))
            turn = PROBE_TURN
            physical_roll = (
                turn * D * cos_delta / float(T.r[q])
                if pushed
                else turn * D / (float(T.r[q]) * cos_delta)
            )
            F = C + rng.normal(0.0, noise, 2)
            c_g, s_g = math.cos(-w.gamma), math.sin(-w.gamma)
            seen = (c_g * F[0] - s_g * F[1], s_g * F[0] + c_g * F[1])
            out.append(PivotProbe(
                module=m, steering=a, driver=j, driver_steering=plan.driver_steering,
                roll=physical_roll * s_w * g_w, turn=turn, fixed_point=seen,
                fixed_point_std=max(noise, 1e-4), pushed=pushed,
            ))  # fmt: skip
    return out


def found(w: Wiring, noise: float = 0.0, seed: int = 0) -> set[tuple[str, int | None, str]]:
    c = analyse(NOMINAL, [], probes(w, noise, seed))
    return {(f.what, f.module, f.axis) for f in c.findings}


@pytest.mark.parametrize(
    ("wiring", "expected"),
    [
        (Wiring(), set()),
        (Wiring(physical={1: 2, 2: 1, 3: 3, 4: 4}),
         {("crossed", 1, "module"), ("crossed", 2, "module")}),
        (Wiring(wheel={2: (-1, 1.0)}), {("polarity", 2, "wheel")}),
        (Wiring(steer={3: (-1, 1.0)}), {("polarity", 3, "steer")}),
        (Wiring(steer={1: (1, 1.5)}), {("ratio", 1, "steer")}),
        (Wiring(wheel={4: (1, 2.0)}), {("ratio", 4, "wheel")}),
        (Wiring(zero={2: 90.0}), {("zero", 2, "steer")}),
        (Wiring(zero={4: 180.0}), {("zero", 4, "steer")}),
        (Wiring(gamma=math.pi / 2), {("mocap_yaw", None, "sensor")}),
        (Wiring(physical={1: 3, 3: 1, 2: 2, 4: 4}, wheel={2: (-1, 1.0)}, zero={4: 180.0}),
         {("crossed", 1, "module"), ("crossed", 3, "module"), ("polarity", 2, "wheel"),
          ("zero", 4, "steer")}),
    ],
    ids=["right", "crossed", "wheel-inverted", "steer-inverted", "steer-ratio", "wheel-ratio",
         "zero-90", "zero-180", "mocap-90", "combination"],
)  # fmt: skip
def test_each_miswiring_is_named_and_nothing_else(
    wiring: Wiring, expected: set[tuple[str, int | None, str]]
) -> None:
    assert found(wiring) == expected
    for seed in range(5):  # with the fixed points' noise of a 10 deg arc (1 mm)
        assert found(wiring, noise=0.001, seed=seed) == expected, seed


@pytest.mark.parametrize("pushed", [False, True], ids=["velocity", "pushed"])
def test_a_wheel_is_judged_by_how_it_was_driven(pushed: bool) -> None:
    """A driver heading 30-45 deg off the turn (its module crossed: steered for another's
    place): a pushed wheel turns the robot 1 / cos^2(delta) times what a velocity-driven
    one does for the same roll, up to twice; judged by the other's formula, its ratio is
    said off."""
    w = Wiring(physical={1: 2, 2: 1, 3: 3, 4: 4})
    expected = {("crossed", 1, "module"), ("crossed", 2, "module")}
    got = probes(w, pushed=pushed)
    assert found_in(got) == expected
    flipped = [replace(p, pushed=not p.pushed) for p in got]
    assert ("ratio", 1, "wheel") in found_in(flipped) or ("ratio", 2, "wheel") in found_in(
        flipped
    )


def found_in(ps: list[PivotProbe]) -> set[tuple[str, int | None, str]]:
    return {(f.what, f.module, f.axis) for f in analyse(NOMINAL, [], ps).findings}


@pytest.mark.parametrize("ratio", [1.5, 1.3])
def test_a_steering_ratio_off_is_measured_again_over_a_whole_turn(ratio: float) -> None:
    """A steering that turns less than commanded covers a third of its circle at the
    three pivot angles: its ratio then spreads over tens of per cent (0.5 mm fixed points);
    with :data:`REFINE_ANGLES`, which the commissioning adds once those say the ratio is
    off, within 4 % in 40 seeds (what the calibration on the corrected config needs)."""
    w = Wiring(steer={1: (1, ratio)})
    assert ratio_off(NOMINAL, 1, probes(w)) and not ratio_off(NOMINAL, 1, probes(Wiring()))
    worst = {}
    for angles in (PIVOT_ANGLES, PIVOT_ANGLES + REFINE_ANGLES):
        got = [analyse(NOMINAL, [], probes(w, 0.0005, seed, angles=angles)).maps[1].steer_ratio
               for seed in range(40)]  # fmt: skip
        worst[len(angles)] = max(abs(g / ratio - 1.0) for g in got if g is not None)
    assert worst[5] < 0.04 and worst[5] < worst[3], worst


def test_the_measured_ratios_and_zero() -> None:
    c = analyse(NOMINAL, [], probes(Wiring(steer={1: (1, 1.5)}, wheel={4: (1, 2.0)},
                                           zero={2: 90.0})))  # fmt: skip
    # against the nominal offsets, radii and axes (the truth's are 1-2 % and mm off)
    assert c.maps[1].steer_ratio == pytest.approx(1.5, rel=0.03)
    assert c.maps[4].wheel_ratio == pytest.approx(2.0, rel=0.03)
    beta2 = TRUTH.modules[1].beta + math.radians(90.0)
    assert c.maps[2].zero == pytest.approx(beta2, abs=math.radians(0.5))


def test_a_steering_move_that_moved_the_pinned_robot_is_a_wheel() -> None:
    moved = SteerMove(3, math.radians(90), 0.03, math.radians(2), 0.01, True)
    c = analyse(NOMINAL, [moved], [])
    assert [(f.what, f.module) for f in c.findings[:1]] == [("swapped", 3)]
    assert "turns a wheel" in c.findings[0].text


def test_rolls_the_sensor_does_not_see_say_so() -> None:
    blind = [
        PivotProbe(m, 0.0, driver_of(IDS, m), 0.0, math.radians(90), 0.0, None, math.inf)
        for m in IDS
    ]
    c = analyse(NOMINAL, [], blind)
    assert [(f.what, f.axis) for f in c.findings] == [("not_seen", "sensor")]
    assert "Y-up" in c.findings[0].text


def test_circle_centre_from_three_points() -> None:
    pts = [(0.1 + 0.02 * math.cos(a), -0.2 + 0.02 * math.sin(a)) for a in (0.3, 1.9, 3.4)]
    assert circle_centre(pts, 0.02, (0.11, -0.19)) == pytest.approx((0.1, -0.2), abs=1e-9)
