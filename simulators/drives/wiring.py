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
from collections.abc import Mapping
from dataclasses import dataclass, field

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
