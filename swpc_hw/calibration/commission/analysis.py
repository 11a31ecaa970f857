"""What the commissioning probes say about the robot's wiring (pure functions).

Inputs are the probes of :mod:`swpc_hw.calibration.commission.probes` and the config's
nominal geometry; the output is, per configured module, what its drives really move
(:class:`AxisMap`) and the findings that name what disagrees with the config and its fix
(:class:`Finding`).  Every judgement below is in that order; from step 3 on, only the
pinned probes count (a probe whose fixed point was not where its driver was steered to
turn about: a fought lock, :mod:`~.probes`).

1. **A steering move that moved the robot** (pinned: it cannot) stopped the probes: the
   module's steering drive turns something that moves the robot.

2. **The sensor.**  Pivot probes whose driver rolled while the sensor saw the robot turn
   less than :data:`NO_TURN`: the sensor does not see the robot turn (a Y-up system read
   as Z-up, a body that is not the robot's).
3. **The motion-capture body's axes.**  A body turned by ``gamma`` from R reports every
   fixed point as ``R(-gamma) C``.  Of ``gamma`` in 0, 90, 180, 270 deg, the one that puts
   the most fixed points on their own module's caster circle (a tie: 0) is taken.
4. **Each module's steering.**  The fixed point ``F`` of a pivot probe is the braked
   wheel's contact point ``P_s,p + b_p u(phi)`` (the true steering angle ``phi``): the module
   ``p`` on whose circle of radius ``b_p`` about ``P_s,p`` it lies within :data:`ON_CIRCLE`
   is the module the configured one's drives move (crossed nodes when another), and
   ``phi = atan2(F - P_s,p)``.  Two probes at readings ``a_1, a_2`` give::

       phi = slope a + zero,   slope = wrap(phi_2 - phi_1) / (a_2 - a_1) = s / g

   the steering's polarity ``s`` (the sign), its ratio ``g`` (true over configured gear x
   resolution: ``1 / |slope|``) and ``zero``, the steering angle where it reads 0 (the
   homing error ``beta``: a quarter or half turn away when homing puts the zero there).
5. **Each wheel.**  In each probe it drove, the driver's true heading is its own steering
   map at its reading, its contact point ``c`` on its own physical module; (1) of
   :mod:`~.probes` (a pushed wheel: (1')) predicts the turn ``k dpsi`` of its roll
   reading.  The turns measured over those predicted (least squares over its probes) is
   ``f = 1 / (s g)``: the wheel's polarity and ratio; ``|f|`` under :data:`NOT_A_WHEEL`
   says its roll hardly turns the robot (its drive turns a steering).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from swpc_hw.calibration.commission.probes import PivotProbe, SteerMove
from swpc_hw.robot.model import RobotParams, contact_point

NO_TURN = math.radians(0.5)
"""rad: pivot probes that turned less than this saw no turn."""
ON_CIRCLE = 0.008
"""m: a fixed point this close to a caster's circle (or 4 std devs, whichever is more) is
that caster's contact point."""
RATIO_TOL = 0.2
"""An axis whose ratio is off by more than this share is said to be (a probe's ratio is
good to about 5 %: the fixed points' mm on a caster circle of radius ``b``)."""
ZERO_TOL = math.radians(30.0)
"""rad: a steering zero this far from the nominal ``beta`` is said to be off (a probe's
zero is good to a few degrees; the calibration measures ``beta`` to a tenth of one)."""
NOT_A_WHEEL = 0.3
"""A wheel whose roll turns the robot less than this share of what a wheel would is no
wheel's."""
MIN_COS = 0.7
"""A probe whose driver headed more than 45 deg off the circle's tangent does not judge
its wheel (the turn per roll goes with ``cos(delta)``, and a few degrees of error in the
heading are then tens of per cent in it)."""
MOCAP_TURNS = (0.0, 0.5 * math.pi, math.pi, 1.5 * math.pi)


def wrap(a: float) -> float:
    return math.remainder(a, 2 * math.pi)


@dataclass(frozen=True)
class AxisMap:
    """What configured module ``module``'s drives move: ``physical`` (a module id; None
    unknown), its steering's ``steer_sign`` and ``steer_ratio`` (true over configured),
    ``zero`` (rad, the true steering angle where it reads 0), its wheel's ``wheel_sign``
    and ``wheel_ratio``; ``swapped``: its steering drive turns the wheel."""

    module: int
    physical: int | None = None
    steer_sign: int | None = None
    steer_ratio: float | None = None
    zero: float | None = None
    wheel_sign: int | None = None
    wheel_ratio: float | None = None
    swapped: bool = False

    def document(self) -> dict[str, Any]:
        return {
            "module": self.module,
            "physical": self.physical,
            "swapped": self.swapped,
            "steer_sign": self.steer_sign,
            "steer_ratio": None if self.steer_ratio is None else round(self.steer_ratio, 3),
            "zero_deg": None if self.zero is None else round(math.degrees(self.zero), 2),
            "wheel_sign": self.wheel_sign,
            "wheel_ratio": None if self.wheel_ratio is None else round(self.wheel_ratio, 3),
        }


@dataclass(frozen=True)
class Finding:
    """One disagreement between the robot and its config: ``module`` (the physical one,
    whose axes the fix is for; None for the sensor), ``axis`` (``steer``, ``wheel``,
    ``module`` or ``sensor``), ``what`` (``swapped``, ``crossed``, ``polarity``, ``ratio``,
    ``zero``, ``mocap_yaw``, ``not_seen``), ``value`` (the measured sign,
    ratio, angle in rad or module id) and ``text`` (it, and its fix, in words)."""

    module: int | None
    axis: str
    what: str
    value: float
    text: str

    def document(self) -> dict[str, Any]:
        return {
            "module": self.module,
            "axis": self.axis,
            "what": self.what,
            "value": round(self.value, 6),
            "text": self.text,
        }


@dataclass
class Commissioning:
    """The maps (per configured module), the findings, the motion-capture body's turn
    ``mocap_yaw`` (rad) and what could not be told (``unknown``: texts)."""

    maps: dict[int, AxisMap] = field(default_factory=dict)
    findings: list[Finding] = field(default_factory=list)
    unknown: list[str] = field(default_factory=list)
    """What the probes could not tell (a driver heading across its circle: commission
    again once the findings are fixed)."""
    mocap_yaw: float = 0.0

    @property
    def right(self) -> bool:
        """The robot agrees with its config on every axis, each one measured."""
        return not self.findings and not self.unknown

    def document(self) -> dict[str, Any]:
        return {
            "right": self.right,
            "mocap_yaw_deg": round(math.degrees(self.mocap_yaw), 1),
            "modules": [m.document() for m in self.maps.values()],
            "findings": [f.document() for f in self.findings],
            "unknown": self.unknown,
        }


def _rot(a: float, p: tuple[float, float]) -> tuple[float, float]:
    c, s = math.cos(a), math.sin(a)
    return (c * p[0] - s * p[1], s * p[0] + c * p[1])


def _on_circle(
    nominal: RobotParams, F: tuple[float, float], std: float
) -> tuple[int | None, float]:
    """The module whose caster circle ``F`` lies on (step 4), and its angle there."""
    A = nominal.arrays()
    tol = max(ON_CIRCLE, 4 * std)
    best, best_d = None, math.inf
    for i, m in enumerate(nominal.ids):
        d = abs(math.hypot(F[0] - A.P_s[i, 0], F[1] - A.P_s[i, 1]) - float(A.b[i]))
        if d < best_d:
            best, best_d = m, d
    if best is None or best_d > tol:
        return None, math.nan
    i = nominal.ids.index(best)
    return best, math.atan2(F[1] - A.P_s[i, 1], F[0] - A.P_s[i, 0])


def _mocap_turn(nominal: RobotParams, probes: Sequence[PivotProbe]) -> float:
    """Step 3: the body's turn that puts the most fixed points on their own circle."""
    best, best_n = 0.0, -1
    for g in MOCAP_TURNS:
        n = 0
        for p in probes:
            if p.fixed_point is not None:
                m, _ = _on_circle(nominal, _rot(g, p.fixed_point), p.fixed_point_std)
                n += 2 if m == p.module else (1 if m is not None else 0)
        if n > best_n:
            best, best_n = g, n
    return best


def circle_centre(
    points: Sequence[tuple[float, float]], radius: float, start: tuple[float, float]
) -> tuple[float, float]:
    """The centre ``c`` of the circle of ``radius`` nearest ``points`` (two or more):
    least squares of ``|F_k - c| - radius`` by Gauss-Newton from ``start``.  The radius
    is the nominal offset ``b``: three points over a third of a turn with mm of noise do
    not tell a circle's radius, and a free one moves its centre by mm (degrees)."""
    c = np.array(start, dtype=float)
    P = np.asarray(points, dtype=float)
    for _ in range(20):
        d = P - c
        rho = np.hypot(d[:, 0], d[:, 1])
        J = -d / rho[:, None]  # d|F - c| / dc
        step = np.linalg.lstsq(J, -(rho - radius), rcond=None)[0]
        c = c + step
        if float(np.hypot(*step)) < 1e-7:
            break
    return float(c[0]), float(c[1])


def _steering(
    nominal: RobotParams, module: int, probes: Sequence[PivotProbe], gamma: float
) -> tuple[int | None, float | None, float | None]:
    """Step 4 for one configured module: (physical module, slope, zero).  With three
    points or more the circle's centre is fitted (:func:`circle_centre`: the nominal axis
    may be mm off, which on a circle of 20 mm is degrees).  The readings are multi-turn: the
    angles are unwrapped in the readings' order, and ``phi = slope a + zero`` holds for a
    reading ``a`` as read, whole turns and all (a steering whose ratio is off turns another
    angle for each whole turn it reads).  A slope within :data:`RATIO_TOL` of +-1 is taken
    as +-1; the zero is the mean over the probes."""
    A = nominal.arrays()
    seen = []
    for p in probes:
        if p.module == module and p.fixed_point is not None:
            F = _rot(gamma, p.fixed_point)
            m, _ = _on_circle(nominal, F, p.fixed_point_std)
            if m is not None:
                seen.append((m, p.steering, F))
    if not seen:
        return None, None, None
    physical = max({m for m, _, _ in seen}, key=lambda m: sum(s[0] == m for s in seen))
    i = nominal.ids.index(physical)
    base = seen[0][1] - wrap(seen[0][1])  # the first reading's whole turns
    pts = sorted((a - base, F) for m, a, F in seen if m == physical)
    centre = (float(A.P_s[i, 0]), float(A.P_s[i, 1]))
    if len(pts) >= 3:
        b = float(A.b[i])
        cx, cy = circle_centre([F for _, F in pts], b, centre)
        if math.hypot(cx - centre[0], cy - centre[1]) < 0.5 * b:
            centre = (cx, cy)  # else the nominal axis (points too close together to tell)
    a_k = [a for a, _ in pts]
    phi = np.unwrap([math.atan2(F[1] - centre[1], F[0] - centre[0]) for _, F in pts])
    if len(pts) < 2 or a_k[-1] - a_k[0] < math.radians(10):
        return physical, None, wrap(float(phi[0]) - (a_k[0] + base))
    am = float(np.mean(a_k))
    slope = float(np.polyfit(np.array(a_k) - am, phi, 1)[0])
    if abs(abs(slope) - 1.0) <= RATIO_TOL:
        slope = math.copysign(1.0, slope)
    zero = math.atan2(
        sum(math.sin(f - slope * a) for a, f in zip(a_k, phi, strict=True)),
        sum(math.cos(f - slope * a) for a, f in zip(a_k, phi, strict=True)),
    )
    return physical, slope, wrap(zero - slope * base)  # phi = slope a + zero, a as read


def ratio_off(nominal: RobotParams, module: int, probes: Sequence[PivotProbe]) -> bool:
    """Whether ``module``'s pinned probes so far put its steering's ratio beyond
    :data:`RATIO_TOL` (step 4, the sensor's axes taken as R's): the commissioning then
    locks it at :data:`~.probes.REFINE_ANGLES` too."""
    _, slope, _ = _steering(nominal, module, [p for p in probes if p.pinned], 0.0)
    if slope is None or abs(slope) < NOT_A_WHEEL:
        return False
    return abs(1.0 / abs(slope) - 1.0) > RATIO_TOL


def analyse(
    nominal: RobotParams,
    steer_moves: Sequence[SteerMove],
    pivot_probes: Sequence[PivotProbe],
) -> Commissioning:
    """The wiring the probes show (module docstring), against ``nominal`` (the config's
    geometry: where each module's steering axis is, its offset and radius)."""
    A = nominal.arrays()
    ids = nominal.ids
    out = Commissioning()
    maps: dict[int, dict[str, Any]] = {m: {"module": m} for m in ids}
    # 1. swapped
    for sp in steer_moves:
        if sp.stopped:
            maps[sp.module]["swapped"] = True
            out.findings.append(Finding(
                sp.module, "module", "swapped", 1.0,
                f"module {sp.module}'s steering drive moved its steering axis "
                f"{1000 * sp.moved:.0f} mm for a {math.degrees(abs(sp.step)):.0f} deg "
                f"steering move with the robot pinned (at most {1000 * sp.budget:.0f} mm): it "
                "turns a wheel (stopped there). "
                "Fix: exchange its steering and wheel motors' connectors (each drive is set "
                "up for its own motor), then commission again",
            ))  # fmt: skip
    # 2. the sensor
    rolled = [p for p in pivot_probes if abs(p.roll) > math.radians(20)]
    if rolled and all(abs(p.turn) < NO_TURN for p in rolled):
        out.findings.append(Finding(
            None, "sensor", "not_seen", max(abs(p.turn) for p in rolled),
            f"the wheels rolled up to {math.degrees(max(abs(p.roll) for p in rolled)):.0f} "
            "deg and the sensor saw the robot turn less than "
            f"{math.degrees(NO_TURN):.1f} deg: it does not see the robot turn (a Y-up motion "
            "capture read as Z-up: swpc mocap --up y; a body that is not the robot's). Fix "
            "the sensor, then commission again",
        ))  # fmt: skip
        out.maps = {m: AxisMap(**d) for m, d in maps.items()}
        return out
    # 3.-5. on the pinned probes only: an unpinned one's fixed point is not the lock's
    pivot_probes = [p for p in pivot_probes if p.pinned]
    # 3. the body's axes
    gamma = _mocap_turn(nominal, pivot_probes)
    out.mocap_yaw = gamma
    if gamma != 0.0:
        out.findings.append(Finding(
            None, "sensor", "mocap_yaw", gamma,
            f"the motion-capture body's x axis is turned {math.degrees(gamma):.0f} deg from "
            f"R's: every fixed point fits its module only turned by that. Fix: define the "
            f"rigid body with its x axis along R's x (the robot's forward), then commission "
            "again",
        ))  # fmt: skip
    # 4. steering
    for m in ids:
        physical, slope, zero = _steering(nominal, m, pivot_probes, gamma)
        d = maps[m]
        d["physical"] = physical
        if physical is None:
            if not d.get("swapped"):
                out.unknown.append(
                    f"module {m}: no fixed point of its pivot probes lies on a caster's "
                    "circle: where its drives lock the robot is not known"
                )
            continue
        if physical != m:
            out.findings.append(Finding(
                physical, "module", "crossed", float(m),
                f"module {m}'s drives move module {physical}: its lock pinned the robot on "
                f"module {physical}'s caster. Fix: module {physical}'s nodes are those the "
                f"config gives module {m}",
            ))  # fmt: skip
        if slope is not None and abs(slope) < NOT_A_WHEEL:
            d["swapped"] = True
            out.findings.append(Finding(
                physical, "module", "swapped", slope,
                f"module {physical}'s caster turned {abs(slope):.2f} of what its steering "
                "drive was commanded (its lock pinned the robot at the same point at both "
                "angles): that drive turns the wheel. Fix: exchange its steering and wheel "
                "motors' connectors (each drive is set up for its own motor)",
            ))  # fmt: skip
        elif slope is not None:
            sign = 1 if slope > 0 else -1
            ratio = 1.0 / abs(slope)
            d["steer_sign"], d["steer_ratio"] = sign, ratio
            if sign < 0:
                out.findings.append(Finding(
                    physical, "steer", "polarity", -1.0,
                    f"module {physical}'s steering turns clockwise when commanded "
                    "counter-clockwise (its caster's contact point went the other way round "
                    "its circle). Fix: its steering's polarity -1",
                ))  # fmt: skip
            if abs(ratio - 1.0) > RATIO_TOL:
                out.findings.append(Finding(
                    physical, "steer", "ratio", ratio,
                    f"module {physical}'s steering turned {1 / ratio:.2f} times what it was "
                    f"commanded: its gear x encoder resolution is {ratio:.2f} times the "
                    "config's. Fix: its steering's ratio times that",
                ))  # fmt: skip
        if zero is not None and not d.get("swapped"):
            d["zero"] = zero
            beta = float(A.beta[ids.index(physical)])
            if abs(wrap(zero - beta)) > ZERO_TOL:
                out.findings.append(Finding(
                    physical, "steer", "zero", zero,
                    f"module {physical}'s steering reads 0 at {math.degrees(zero):.0f} deg, "
                    f"the config's beta is {math.degrees(beta):.1f} deg: its zero is "
                    f"{math.degrees(wrap(zero - beta)):.0f} deg away. Fix: beta "
                    f"{math.degrees(zero):.0f} deg in the config's nominal geometry (the "
                    "calibration then measures it), or the drive's homing offset",
                ))  # fmt: skip
    # 5. wheels
    for j in ids:
        d = maps[j]
        q = d.get("physical")
        if q is None:
            continue
        qi = ids.index(q)
        slope = d.get("steer_sign", 1) / d.get("steer_ratio", 1.0)
        zero = d.get("zero", float(A.beta[qi]))
        num = den = 0.0
        for p in pivot_probes:
            if p.driver != j or p.fixed_point is None:
                continue
            C = _rot(gamma, p.fixed_point)
            # the reading as it is, whole turns and all: a steering whose ratio is off
            # turns another angle for each whole turn read
            phi = slope * p.driver_steering + zero
            c = contact_point(A.P_s[qi], np.array(A.b[qi]), phi)
            rel = (float(c[0] - C[0]), float(c[1] - C[1]))
            D = math.hypot(*rel)
            t = (-rel[1] / D, rel[0] / D)
            cos_delta = math.cos(phi) * t[0] + math.sin(phi) * t[1]
            if abs(cos_delta) < MIN_COS:
                continue  # its heading across the circle: its roll barely turns the robot
            r_q = float(A.r[qi])
            predicted = r_q * p.roll / (D * cos_delta) if p.pushed else r_q * cos_delta * p.roll / D
            num += p.turn * predicted
            den += predicted * predicted
        if den < math.radians(1.0) ** 2:
            out.unknown.append(
                f"module {q}'s wheel: no pinned probe it drove headed along the turn (within "
                f"{math.degrees(math.acos(MIN_COS)):.0f} deg): its direction and ratio are not "
                "known; commission again once the findings are fixed"
            )
            continue
        f = num / den
        if abs(abs(f) - 1.0) <= RATIO_TOL * abs(f):
            f = math.copysign(1.0, f)
        if abs(f) < NOT_A_WHEEL:
            d["swapped"] = True
            if any(x.what == "swapped" and x.module == q for x in out.findings):
                continue
            out.findings.append(Finding(
                q, "module", "swapped", f,
                f"module {q}'s wheel drive rolled and the robot turned {abs(f):.2f} of "
                "what a wheel turns it: that drive turns the steering. Fix: exchange its "
                "steering and wheel motors' connectors (each drive is set up for its own "
                "motor), then commission again",
            ))  # fmt: skip
            continue
        sign = 1 if f > 0 else -1
        ratio = 1.0 / abs(f)
        d["wheel_sign"], d["wheel_ratio"] = sign, ratio
        if sign < 0:
            out.findings.append(Finding(
                q, "wheel", "polarity", -1.0,
                f"module {q}'s wheel rolls backwards when commanded forwards (the robot "
                "turned against its roll). Fix: its wheel's polarity -1",
            ))  # fmt: skip
        if abs(ratio - 1.0) > RATIO_TOL:
            out.findings.append(Finding(
                q, "wheel", "ratio", ratio,
                f"module {q}'s wheel rolled {1 / ratio:.2f} times what its encoder says: "
                f"its gear x encoder resolution is {ratio:.2f} times the config's. Fix: its "
                "wheel's ratio times that",
            ))  # fmt: skip
    out.maps = {m: AxisMap(**d) for m, d in maps.items()}
    return out


PRECHECK_ANGLE = math.radians(45.0)
"""rad: a pre-check whose locked caster points this far from where its steering says (or
farther) disagrees: a quarter or half turn off, a steering the other way round at the
first angle (45 deg: 90 deg apart); the nominal geometry and a short arc's fixed point
are a few mm off on a circle of ``b`` (20 mm on the paper's robot), a few degrees."""


def precheck_problems(
    nominal: RobotParams, probes: Sequence[PivotProbe], mocap: bool = True
) -> list[str]:
    """The fast part of every calibration and check (docs/commissioning.md): one pivot
    probe per module at the protocol's first angle ``a``, judged against the config alone:

    * a roll that stopped (the robot turned the wrong way, or not at all);
    * a fixed point nearer another module's steering axis than the locked one's (crossed
      nodes; the modules are a robot's size apart, the nominal geometry mm to cm off);
    * a fixed point on the locked module's caster circle (within ``b / 2``: a nominal
      geometry cm off leaves the angle unjudged, as the calibration still takes it) at an
      angle :data:`PRECHECK_ANGLE` or more from ``a + beta``; not without motion capture
      (``mocap`` false: the gyro's fixed point, from the free wheels and the nominal
      geometry, is up to 26 mm off on robots whose nominal radii are 2 % and steering
      axes 5 % off: the caster's whole circle.  The driver's roll judges its steering
      there: a steering the other way round or a zero off heads its wheel off the turn).

    Each says the axis; ``swpc commission`` finds the fix."""
    A = nominal.arrays()
    ids = nominal.ids
    out = []
    for p in probes:
        i = ids.index(p.module)
        if p.stopped is not None:
            out.append(f"locked module {p.module}, module {p.driver} rolling: {p.stopped}")
            continue
        if p.fixed_point is None:
            out.append(
                f"locked module {p.module}, module {p.driver} rolling: the robot did not turn "
                "as the sensor sees it"
            )
            continue
        F = p.fixed_point
        dist = [math.hypot(F[0] - A.P_s[k, 0], F[1] - A.P_s[k, 1]) for k in range(len(ids))]
        nearest = ids[int(np.argmin(dist))]
        if nearest != p.module:
            out.append(
                f"module {p.module}'s lock pinned the robot nearest module {nearest}'s steering "
                f"axis ({1000 * min(dist):.0f} mm from it): its nodes are module {nearest}'s "
                "(crossed)" + (", or the motion-capture body is not along R" if mocap else "")
            )
            continue
        b = float(A.b[i])
        if not mocap or abs(dist[i] - b) > 0.5 * b:
            continue  # the nominal axis too far off to judge the angle
        seen = math.atan2(F[1] - A.P_s[i, 1], F[0] - A.P_s[i, 0])
        off = wrap(seen - p.steering - float(A.beta[i]))
        if abs(off) >= PRECHECK_ANGLE:
            out.append(
                f"module {p.module}'s caster points {math.degrees(off):+.0f} deg from where "
                f"its steering says ({math.degrees(p.steering):.0f} deg): its steering turns "
                "another way, by another ratio or from another zero"
            )
    return out
