"""A spin's wheels against the robot's turn (issue 43, item 5): on a robot whose config is
wrong (a wheel drive mounted the other way round), the drives' own encoders agree with
every command while the robot does otherwise.  Motion capture (or the gyro) says how the
robot turns; each trailing wheel's encoder how it rolls; the steering encoders where each
wheel points.  In a spin the robot turns about the locked module's contact point ``C``
(its wheel braked), so a trailing wheel at ``P_w`` with heading ``u(theta)`` rolls

    r dpsi = dyaw ((C_y - P_wy) cos(theta) + (P_wx - C_x) sin(theta)) = k dyaw

(:func:`roll_per_turn`, nominal geometry, the measured steering), whichever way the robot
turns and however the casters point.  From the moment the robot has turned
:data:`MIN_TURN`, each :data:`WINDOW` of turning is compared with each wheel's roll in it,
and a wheel that rolled the other way stops the run naming its module, before the spin
goes on.  Judged on the first spin about each module; every wheel trails in the first spin
of another module.  Before that, wheels that roll :data:`ROLL_WITHOUT_TURN` while the
sensor sees the robot turn less than :data:`MIN_TURN` stop it too: the sensor does not
see the robot (a motion-capture body not the robot's, a Y-up system), or the robot does
not turn (against an obstacle, its wheels slipping).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from services.runs.metrology.base import RunSteps
from services.runs.state import RunFailedError
from swpc_hw.robot.model import RobotParams

MIN_TURN = math.radians(2.0)
"""How far the robot turns (either way) before its wheels are judged."""
WINDOW = 0.1
"""s: each judgement compares the turn and the rolls over the last this long."""
MIN_WINDOW_TURN = math.radians(0.3)
"""A window in which the robot turned less is not judged (it barely moves)."""
MIN_ROLL = math.radians(1.0)
"""A wheel that should roll less in a window is not judged (it points across its path)."""
ROLL_WITHOUT_TURN = math.radians(90.0)
"""A trailing wheel that rolled this far while the robot turned less than
:data:`MIN_TURN` is rolling while the sensor sees no turn (a right robot rolls its wheels
about 5-10 deg per degree it turns)."""
AGAINST_FRACTION = 0.5
"""A wheel that rolled against what the turn asks by this fraction of it turns the other
way (a caster slipping or swivelling still rolls the right way, if less)."""


def roll_per_turn(
    nominal: RobotParams, steering: Mapping[int, float], locked: int
) -> dict[int, float]:
    """``k_j``: wheel ``j``'s roll (rad) per radian the robot turns about the locked
    module's contact point (module docstring), from the steering encoders ``steering``
    (the host's angles: the true ones less the homing errors) and the nominal geometry."""
    A = nominal.arrays()
    ids = nominal.ids
    theta = {m: steering[m] + float(A.beta[ids.index(m)]) for m in steering}

    def contact(m: int) -> tuple[float, float]:
        i = ids.index(m)
        return (
            float(A.P_s[i, 0] + A.b[i] * math.cos(theta[m])),
            float(A.P_s[i, 1] + A.b[i] * math.sin(theta[m])),
        )

    cx, cy = contact(locked)
    out = {}
    for m in steering:
        if m == locked:
            continue
        px, py = contact(m)
        th = theta[m]
        out[m] = ((cy - py) * math.cos(th) + (px - cx) * math.sin(th)) / float(A.r[ids.index(m)])
    return out


def direction_problems(
    dyaw: float, dpsi: Mapping[int, float], k: Mapping[int, float]
) -> list[str]:
    """The wheels that rolled against the robot's turn ``dyaw`` in one window: module ``j``
    when ``e_j = k_j dyaw`` is at least :data:`MIN_ROLL`, ``dpsi_j e_j < 0`` and ``|dpsi_j| >
    AGAINST_FRACTION |e_j|``."""
    turn = "counter-clockwise" if dyaw > 0 else "clockwise"
    out = []
    for j, d in sorted(dpsi.items()):
        e = k[j] * dyaw
        if abs(e) >= MIN_ROLL and d * e < 0 and abs(d) > AGAINST_FRACTION * abs(e):
            way = "forward" if d > 0 else "backward"
            out.append(
                f"module {j}'s wheel rolled {math.degrees(abs(d)):.1f} deg {way} while the "
                f"robot turned {math.degrees(abs(dyaw)):.1f} deg {turn}, which rolls it about "
                f"{math.degrees(abs(e)):.0f} deg the other way: its wheel drive turns the "
                "other way round (its polarity), or its node is another module's"
            )
    return out


class DirectionWatch:
    """:func:`direction_problems` during one spin about ``locked``, from its start (the
    sensor's sample at time ``t0``, the robot's yaw then ``yaw0``), every :data:`WINDOW`.
    Times are the samples' (the sensor's, mapped to the clock): the wheels' encoder rows
    are taken up to each sample's time, so late poses are compared with the wheels as they
    were; a sample not newer than the last tells nothing (a sensor gone silent is the
    run's stale check's)."""

    def __init__(self, run: RunSteps, locked: int, t0: float, yaw0: float) -> None:
        self.run, self.locked, self.t0, self.yaw0 = run, locked, t0, yaw0
        self.started = run.clock.now()
        self.history: list[tuple[float, float]] = [(t0, yaw0)]
        self.decided = False
        self.judged = 0

    def _rows(self, module: int, since: float, until: float) -> Any:
        rows = self.run.robot.encoders(module, since)
        return rows[rows[:, 0] <= until] if len(rows) else rows

    def _stop(self, text: str) -> None:
        elapsed_ms = 1000.0 * (self.run.clock.now() - self.started)
        self.run.event(logging.ERROR, "run.direction", ok=False, after_ms=round(elapsed_ms))
        raise RunFailedError(f"stopped {elapsed_ms:.0f} ms into the spin: {text}")

    def _rolled_without_turn(self, t: float, yaw: float) -> None:
        """Stop when a trailing wheel rolled :data:`ROLL_WITHOUT_TURN` since the spin began
        while the robot turned less than :data:`MIN_TURN`."""
        rolled = {}
        for m in self.run.config.nominal.ids:
            if m != self.locked:
                rows = self._rows(m, self.t0, t)
                if len(rows) >= 2:
                    rolled[m] = abs(float(rows[-1, 2] - rows[0, 2]))
        if not rolled or max(rolled.values()) < ROLL_WITHOUT_TURN:
            return
        m = max(rolled, key=lambda k: rolled[k])
        self._stop(
            f"module {m}'s wheel rolled {math.degrees(rolled[m]):.0f} deg while the robot "
            f"turned {math.degrees(abs(yaw - self.yaw0)):.1f} deg as its sensor sees it: the "
            "sensor does not see the robot turn (a motion-capture body that is not the "
            "robot's, or a Y-up motion capture), or the robot does not turn (an obstacle, "
            "wheels slipping)"
        )

    def update(self, yaw: float, t: float) -> None:
        """The robot's yaw in the sample at time ``t``: the run fails on a wheel rolling
        the other way, or rolling while the robot does not turn."""
        if self.decided:
            return
        t_last, last = self.history[-1]
        if t <= t_last:
            return  # nothing new
        yaw = last + math.remainder(yaw - last, 2 * math.pi)  # unwrapped
        self.history.append((t, yaw))
        if abs(yaw - self.yaw0) < MIN_TURN:
            self._rolled_without_turn(t, yaw)
            return
        then = [h for h in self.history if h[0] <= t - WINDOW]
        if not then:
            return
        t1, yaw1 = then[-1]
        self.history = self.history[len(then) - 1 :]
        dyaw = yaw - yaw1
        if abs(dyaw) < MIN_WINDOW_TURN:
            return
        rows = {m: self._rows(m, t1, t) for m in self.run.config.nominal.ids}
        if any(len(r) < 2 for r in rows.values()):
            return
        steering = {m: float(np.mean(r[:, 1])) for m, r in rows.items()}
        dpsi = {m: float(r[-1, 2] - r[0, 2]) for m, r in rows.items() if m != self.locked}
        k = roll_per_turn(self.run.config.nominal, steering, self.locked)
        problems = direction_problems(dyaw, dpsi, k)
        if problems:
            self._stop("; ".join(problems))
        self.judged += 1
        if self.judged >= 3:  # three windows agreed: the spin goes on unwatched
            self.decided = True
            elapsed_ms = 1000.0 * (self.run.clock.now() - self.started)
            self.run.event(logging.INFO, "run.direction", ok=True, after_ms=round(elapsed_ms))
