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

:class:`WiredAxes` does it every tick of the virtual robot
(:class:`simulators.virtual_robot.VirtualRobot`): the drives' commands into the physics'
drives, the encoders back into the drives.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from firmware_protocol.codec import Axis
from simulators.drives.base import VirtualDrive, module_drive, quantize
from simulators.physics.robot import ModuleDrive, RobotPhysics, SteerDrive, WheelDrive


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


class WiredAxes:
    """The physical modules' axes of ``robot`` and the drive channels of ``drives`` they
    hang on through ``wiring`` (module docstring): what the drives command becomes the
    physics' drives, what the encoders read goes back into the drives.  When the wiring is
    the identity (:attr:`Wiring.identity`), module ``i`` is on drive ``i`` as the config
    says; else every tick goes through the wiring (:attr:`wired`)."""

    def __init__(
        self,
        wiring: Wiring,
        robot: RobotPhysics,
        drives: Sequence[VirtualDrive],
        counts: tuple[int, int],
    ) -> None:
        self.wiring = wiring
        self.robot = robot
        self.drives = drives
        self.wired = not wiring.identity  # miswired: every tick through the wiring
        self.quanta = {
            axis: 2.0 * math.pi / c if c > 0 else 0.0
            for axis, c in zip((Axis.STEER, Axis.WHEEL), counts, strict=True)
        }
        """One count of each axis' encoder (rad; ``counts`` per turn, 0: none)."""
        self._rest: dict[tuple[int, Axis], float] = {}

    def rest_offset(self, i: int, axis: Axis) -> float:
        """Where within its encoder count physical module ``i``'s ``axis`` comes to rest
        under position control, from the setpoint (rad, within +-half a count).

        A drive's position loop closes on its encoder: it holds the reading at the
        setpoint, and the shaft stops wherever within that count the approach leaves it
        (friction), not on the count's edge; so the reading is off the true angle by
        up to half a count, uniformly (std dev ``q / sqrt(12)``, what the solvers take a
        held steering's reading error to be).  Drawn anew at every physics step the loop
        is still more than a count from its aim, from the position and the rate there
        (reproducible, and different from run to run); an ideal loop that ended on the
        setpoint itself read its held steering exactly, and the gyro solver's covariance
        came out twice too wide where that reading counts (issue 44, NEES 0.60).
        """
        return self._rest.get((i, axis), 0.0)

    def _aimed(self, i: int, axis: Axis, position: float, kind: str, v: float,
               dt: float, position_tau: float) -> None:  # fmt: skip
        """After a drive's command for the next ``dt``: a new :meth:`rest_offset` while the
        loop still moves by more than a count per its time constant."""
        q = self.quanta[axis]
        if q > 0.0 and kind == "rate" and abs(v) * max(position_tau, dt) > q:
            u = (hash((position, v)) & 0xFFFFFFFF) / 2.0**32
            self._rest[(i, axis)] = (u - 0.5) * q

    def _drive(self, i: int, axis: Axis, d: VirtualDrive, channel: Axis, position: float,
               dt: float, position_tau: float) -> tuple[str, float]:  # fmt: skip
        """``d.drive`` of physical module ``i``'s ``axis`` (on ``d``'s ``channel``) from
        ``position`` (the drive's units) less its :meth:`rest_offset`."""
        kind, v = d.drive(channel, position - self.rest_offset(i, axis), dt, position_tau)
        self._aimed(i, axis, position, kind, v, dt, position_tau)
        return kind, v

    def steer_reported(self, i: int) -> float:
        """Physical module ``i``'s steering as its encoder counts it before the wiring's
        gain: ``theta - beta`` once its drive has homed, ``+ sensor_position`` before."""
        d = self.drives[self.wiring.channel(i, Axis.STEER)[0]]
        off = 0.0 if d.homed else d.sensor_position
        return float(self.robot.theta[i] - self.robot.arrays.beta[i] + off)

    def physical(self, i: int, axis: Axis) -> tuple[float, float]:
        """Physical module ``i``'s ``axis``: (angle as its encoder counts it before the
        wiring's gain, rate)."""
        r = self.robot
        if axis == Axis.STEER:
            return self.steer_reported(i), float(r.theta_dot[i])
        return float(r.psi_encoder[i]), float(r.psi_dot[i])

    def module_drives(self, dt: float, position_tau: float) -> list[ModuleDrive]:
        """What every physical module's axes do over the next ``dt``: each drive channel's
        :meth:`~simulators.drives.base.VirtualDrive.drive` from where its axis is now."""
        r = self.robot
        drives = []
        if not self.wired:
            for i, d in enumerate(self.drives):
                s = self._drive(i, Axis.STEER, d, Axis.STEER, self.steer_reported(i), dt,
                                position_tau)  # fmt: skip
                w = self._drive(i, Axis.WHEEL, d, Axis.WHEEL, float(r.psi_encoder[i]), dt,
                                position_tau)  # fmt: skip
                drives.append(module_drive(s, w))
        else:
            drives = [self.wired_drive(i, dt, position_tau) for i in range(len(self.drives))]
        return drives

    def wired_drive(self, i: int, dt: float, position_tau: float) -> ModuleDrive:
        """Physical module ``i``'s drive through the wiring: each axis commanded by the
        drive channel it hangs on, scaled by its gain."""
        w = self.wiring
        out: list[tuple[str, float]] = []
        for axis in (Axis.STEER, Axis.WHEEL):
            k, channel = w.channel(i, axis)
            g = w.gain(i, axis)
            position, _ = self.physical(i, axis)
            kind, v = self._drive(i, axis, self.drives[k], channel, g * position, dt, position_tau)
            if kind == "rate":
                v = v / g
            elif kind == "torque":
                v = v * g
                if axis == Axis.STEER:
                    kind, v = "passive", 0.0  # a steering's torque is not modelled
            elif kind == "brake" and axis == Axis.STEER:
                kind, v = "rate", 0.0
            out.append((kind, v))
        return module_drive(out[0], out[1])

    def write_encoders(
        self, drives: Sequence[ModuleDrive] | None, steer_counts: int, wheel_counts: int
    ) -> None:
        """The encoders after a tick into the drives, quantised to ``steer_counts`` /
        ``wheel_counts`` per turn (``drives``: what each module's axes did in it; None at
        the start: nothing applied yet)."""
        r = self.robot
        if self.wired:
            self._write_wired_encoders(drives, steer_counts, wheel_counts)
            return
        for i, d in enumerate(self.drives):
            steer_torque: float | None = 0.0
            wheel_torque: float | None = 0.0
            if drives is not None:
                md = drives[i]
                steer_torque = None if md.steer is SteerDrive.RATE else 0.0
                if md.wheel is WheelDrive.TORQUE:
                    wheel_torque = md.wheel_value
                elif md.wheel is WheelDrive.RATE:
                    wheel_torque = None
            d.sense(
                Axis.STEER,
                quantize(self.steer_reported(i), steer_counts),
                float(r.theta_dot[i]),
                steer_torque,
            )
            d.sense(
                Axis.WHEEL,
                quantize(float(r.psi_encoder[i]), wheel_counts),
                float(r.psi_dot[i]),
                wheel_torque,
            )

    def _write_wired_encoders(
        self, drives: Sequence[ModuleDrive] | None, steer_counts: int, wheel_counts: int
    ) -> None:
        """:meth:`write_encoders` through the wiring: each physical axis's encoder into
        the drive channel it hangs on, scaled by its gain."""
        w = self.wiring
        for i in range(len(self.drives)):
            md = None if drives is None else drives[i]
            for axis in (Axis.STEER, Axis.WHEEL):
                k, channel = w.channel(i, axis)
                g = w.gain(i, axis)
                position, rate = self.physical(i, axis)
                torque: float | None = 0.0
                if md is not None and axis == Axis.STEER and md.steer is SteerDrive.RATE:
                    torque = None
                if md is not None and axis == Axis.WHEEL:
                    if md.wheel is WheelDrive.TORQUE:
                        torque = md.wheel_value / g
                    elif md.wheel is WheelDrive.RATE:
                        torque = None
                counts = steer_counts if channel == Axis.STEER else wheel_counts
                self.drives[k].sense(channel, quantize(g * position, counts), g * rate, torque)
