"""How the drives are really wired to the robot: the simulator's hidden truth beside the
robot config, which says what swpc believes (issue 43: a real robot's config is wrong
until someone commissions it).

A :class:`Wiring` maps each physical module's axis to the drive channel its motor and
encoder hang on, and scales what passes between them:

* ``drive_of``: physical module ``i`` (in the truth's order) is wired to the drives the
  config gives module ``drive_of[i]`` (crossed node ids: a permutation);
* ``swapped``: physical modules whose steering motor is on the drive's wheel channel and
  the wheel motor on its steering channel;
* ``scale[(i, axis)]``: drive units per physical radian relative to the config, ``s x g``:
  the sign ``s`` -1 for a motor mounted the other way round (or its encoder counting the
  other way), ``g`` the true gear x resolution over the configured one (a wrong ratio).

What a drive commands becomes physics as: a rate ``v`` (drive rad/s) drives its physical
axis at ``v / (s g)``, a torque ``tau`` (N.m at the configured output) at ``s g tau`` (the
motor's torque through the true gear); its encoder reads ``s g`` times the physical angle.
A steering wired to a wheel channel in torque is left passive (the steering's torque is
not modelled), a braked one held.  The steering's zero a quarter or half turn off is the
truth's own homing error (``beta``), and a rotated motion-capture body the sensor's
(:attr:`Wiring.mocap_yaw`, :attr:`Wiring.mocap_y_up`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from firmware_protocol.codec import Axis


@dataclass(frozen=True)
class Wiring:
    """The drives' real wiring (module docstring); the default is what the config says."""

    drive_of: tuple[int, ...] | None = None
    swapped: frozenset[int] = frozenset()
    scale: Mapping[tuple[int, Axis], float] = field(default_factory=dict)
    mocap_yaw: float = 0.0
    """rad: the motion-capture body's x axis is R's turned by this."""
    mocap_y_up: bool = False
    """The motion capture's vertical is its y (a Y-up system) and swpc takes its x and y:
    it sees x and the body's height, and no turn about its z."""

    def check(self, n: int) -> None:
        """ValueError unless it fits a robot of ``n`` modules."""
        if self.drive_of is not None and sorted(self.drive_of) != list(range(n)):
            raise ValueError(f"wiring.drive_of {self.drive_of} is not a permutation of 0..{n - 1}")
        for i in self.swapped:
            if not 0 <= i < n:
                raise ValueError(f"wiring.swapped: no module index {i}")
        for (i, _axis), g in self.scale.items():
            if not 0 <= i < n or not math.isfinite(g) or g == 0.0:
                raise ValueError(f"wiring.scale[{i}]: {g} (a non-zero factor on a module)")

    def channel(self, i: int, axis: Axis) -> tuple[int, Axis]:
        """The drive (its module index in the config's order) and the drive's axis that
        physical module ``i``'s ``axis`` hangs on."""
        k = i if self.drive_of is None else self.drive_of[i]
        if i in self.swapped:
            axis = Axis.WHEEL if axis == Axis.STEER else Axis.STEER
        return k, axis

    def gain(self, i: int, axis: Axis) -> float:
        """``s x g``: drive units per physical radian, relative to the config."""
        return float(self.scale.get((i, axis), 1.0))

    @property
    def identity(self) -> bool:
        return (
            (self.drive_of is None or list(self.drive_of) == sorted(self.drive_of))
            and not self.swapped
            and all(g == 1.0 for g in self.scale.values())
            and self.mocap_yaw == 0.0
            and not self.mocap_y_up
        )

    def mocap_pose(self, x: float, y: float, yaw: float) -> tuple[float, float, float]:
        """The pose the motion capture reports of R's pose ``(x, y, yaw)``: the body's
        frame turned by :attr:`mocap_yaw`, its origin at R's; with :attr:`mocap_y_up`, x,
        the height (:data:`BODY_HEIGHT`) and no yaw."""
        if self.mocap_y_up:
            return x, BODY_HEIGHT, 0.0
        return x, y, yaw + self.mocap_yaw


BODY_HEIGHT = 0.3
"""m: the motion-capture body's height above the floor (what a Y-up system's y is)."""
WIRED_AS_CONFIGURED = Wiring()


AXES = {"steer": Axis.STEER, "wheel": Axis.WHEEL}
WIRING_KEYS = ("crossed", "swapped", "inverted", "ratio", "mocap_yaw_deg", "mocap_y_up")


def wiring_from_document(doc: Any, ids: Sequence[int]) -> Wiring:
    """A :class:`Wiring` from its YAML document, module ids as in the robot config::

        crossed: {1: 2, 2: 1}          # module 1 is on module 2's drives, and 2 on 1's
        swapped: [3]                   # module 3's steering and wheel motors exchanged
        inverted: [{module: 2, axis: wheel}]
        ratio: [{module: 4, axis: steer, factor: 2.0}]
        mocap_yaw_deg: 90              # the motion-capture body turned
        mocap_y_up: false              # a Y-up motion capture

    :class:`ValueError` names the key that is wrong."""
    if not isinstance(doc, dict):
        raise ValueError("wiring: a mapping of " + ", ".join(WIRING_KEYS))
    unknown = sorted(set(doc) - set(WIRING_KEYS))
    if unknown:
        raise ValueError(f"wiring: unknown key(s) {unknown}; known: {', '.join(WIRING_KEYS)}")
    index = {m: i for i, m in enumerate(ids)}

    def module(key: str, m: Any) -> int:
        if m not in index:
            raise ValueError(f"wiring.{key}: no module {m!r} (modules {list(ids)})")
        return index[m]

    def axis(key: str, a: Any) -> Axis:
        if a not in AXES:
            raise ValueError(f"wiring.{key}: axis {a!r} is not steer or wheel")
        return AXES[a]

    drive_of = None
    crossed = doc.get("crossed") or {}
    if crossed:
        perm = list(range(len(ids)))
        for m, on in dict(crossed).items():
            perm[module("crossed", m)] = module("crossed", on)
        drive_of = tuple(perm)
    swapped = frozenset(module("swapped", m) for m in doc.get("swapped") or [])
    scale: dict[tuple[int, Axis], float] = {}
    for e in doc.get("inverted") or []:
        key = (module("inverted", e.get("module")), axis("inverted", e.get("axis")))
        scale[key] = -scale.get(key, 1.0)
    for e in doc.get("ratio") or []:
        key = (module("ratio", e.get("module")), axis("ratio", e.get("axis")))
        factor = e.get("factor")
        if not isinstance(factor, (int, float)) or not factor > 0:
            raise ValueError(f"wiring.ratio: factor {factor!r} (true over configured, > 0)")
        scale[key] = scale.get(key, 1.0) * float(factor)
    w = Wiring(
        drive_of=drive_of,
        swapped=swapped,
        scale=scale,
        mocap_yaw=math.radians(float(doc.get("mocap_yaw_deg") or 0.0)),
        mocap_y_up=bool(doc.get("mocap_y_up", False)),
    )
    w.check(len(ids))
    return w


def load_wiring(path: Path, ids: Sequence[int]) -> Wiring:
    """:func:`wiring_from_document` of a YAML file (its errors name the file)."""
    try:
        return wiring_from_document(yaml.safe_load(path.read_text()), ids)
    except (OSError, yaml.YAMLError, ValueError) as exc:
        raise ValueError(f"{path}: {exc}") from exc
