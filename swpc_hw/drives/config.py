"""The ``drives:`` section of a robot config: which drive kind, and where each axis is.

YAML (``deploy/robot.example.yaml`` documents every key)::

    drives: swpc                   # short for {kind: swpc}: nodes numbered 1, 2, ...
    drives:
      kind: swpc                   # swpc's own firmware: one dual-axis controller a module
      modules: {1: 1, 2: 2, 3: 3, 4: 4}   # module id -> its controller's node (1..8)
    drives:
      kind: cia402                 # CiA 402 over CANopen: one single-axis drive an axis
      modules:                     # module id -> its steer and wheel axes (docs/drives.md)
        1: {steer: {node: 1, homing: 19}, wheel: {node: 2}}
    drives:
      kind: odrive                 # ODrive over CAN Simple: an axis a node
      firmware: "0.5"              # 0.5.x (v3.6) or 0.6.x (S1, Pro)
      modules:
        1: {steer: {node: 0, gear_ratio: 8.0}, wheel: {node: 1}}

A kind's model lists what that protocol needs (a CiA 402 drive's object dictionary, an
ODrive's firmware line, ...); :data:`DrivesConfig` is the union of the kinds, told apart by
``kind``.  Module ids must be exactly the robot's (checked by the robot config, which
knows them: :meth:`DrivesBase.check_modules`).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from firmware_protocol import cia402
from firmware_protocol.codec import MAX_NODE
from firmware_protocol.odrive.can_simple import FIRMWARE_LINES
from firmware_protocol.odrive.can_simple import MAX_NODE as ODRIVE_MAX_NODE

STRICT = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)

DEFAULT_KIND = "swpc"


class DrivesBase(BaseModel):
    """What every kind's model has: its ``kind`` and the module ids it maps."""

    model_config = STRICT

    kind: str

    def module_ids(self) -> list[int] | None:
        """The module ids the config maps (None: not given, numbered by default)."""
        raise NotImplementedError

    def check_modules(self, ids: list[int]) -> list[str]:
        """Why this config does not fit a robot with module ids ``ids`` (empty when it
        does)."""
        mine = self.module_ids()
        if mine is not None and sorted(mine) != sorted(ids):
            return [f"drives.modules must map exactly the module ids {ids}, not {sorted(mine)}"]
        return []

    def for_modules(self, ids: list[int]) -> DrivesBase:
        """This config with its default module map filled in for ``ids``."""
        return self

    def nodes(self) -> list[int]:
        """Every CAN node id the drives use (for a listing; each kind numbers its own)."""
        raise NotImplementedError


class SwpcDrives(DrivesBase):
    """swpc's own firmware (``firmware_protocol/swpc.dbc``): one dual-axis controller per
    module, both axes on its node; positions, velocities and torques are at the output in
    SI on the wire (the firmware applies the gear and the encoder counts)."""

    kind: Literal["swpc"] = "swpc"
    modules: dict[int, int] | None = Field(
        None, description="module id -> CAN node id of its controller (1..8); default 1, 2, ..."
    )

    @model_validator(mode="after")
    def _nodes_valid(self) -> SwpcDrives:
        if self.modules is not None:
            vals = list(self.modules.values())
            if len(set(vals)) != len(vals) or any(not 1 <= v <= MAX_NODE for v in vals):
                raise ValueError(
                    f"drives.modules: node ids must be unique and within 1..{MAX_NODE}"
                )
        return self

    def module_ids(self) -> list[int] | None:
        return None if self.modules is None else list(self.modules)

    def for_modules(self, ids: list[int]) -> SwpcDrives:
        if self.modules is not None:
            return self
        return self.model_copy(update={"modules": {m: i + 1 for i, m in enumerate(ids)}})

    def nodes(self) -> list[int]:
        return list((self.modules or {}).values())

    def node_map(self) -> dict[int, int]:
        """Module id -> node (the default numbering must have been filled in)."""
        assert self.modules is not None, "for_modules() first"
        return dict(self.modules)


ABSOLUTE = "absolute"
"""``homing: absolute``: the steering's encoder is absolute and set to the homing
reference at commissioning; the axis is homed from power-up, no homing runs."""

DEFAULT_GEAR_RATIO = 32.0
DEFAULT_COUNTS_PER_TURN = 4096
DEFAULT_HOMING_METHOD = 19
"""CiA 402 homing method 19: on the positive home switch (the steering's homing sensor)."""


class Cia402Axis(BaseModel):
    """One axis of a module: a single-axis CiA 402 drive on its own CANopen node."""

    model_config = STRICT

    node: int = Field(ge=1, le=cia402.MAX_NODE, description="CANopen node id (1..127)")
    gear_ratio: float = Field(
        DEFAULT_GEAR_RATIO, gt=0, description="motor turns per turn of the module's axis"
    )
    counts_per_turn: int = Field(
        DEFAULT_COUNTS_PER_TURN, ge=1, description="encoder counts per motor turn"
    )

    def counts_per_rad(self) -> float:
        """Position units (encoder counts) per radian at the module's output."""
        return self.counts_per_turn * self.gear_ratio / (2.0 * math.pi)


class Cia402Steer(Cia402Axis):
    homing: int | Literal["absolute"] = Field(
        DEFAULT_HOMING_METHOD,
        description="the 402 homing method (0x6098) the drive runs, or 'absolute' (an "
        "absolute encoder set at commissioning: no homing)",
    )

    @model_validator(mode="after")
    def _method(self) -> Cia402Steer:
        if self.homing != ABSOLUTE and not -128 <= int(self.homing) <= 127:
            raise ValueError(f"homing: method {self.homing} is not a 402 method (-128..127)")
        return self


class Cia402Module(BaseModel):
    model_config = STRICT

    steer: Cia402Steer
    wheel: Cia402Axis


class Cia402Drives(DrivesBase):
    """CiA 402 drives over CANopen: one single-axis drive per axis (a module's steering and
    wheel on two nodes), its object dictionary from an EDS/DCF, the host's heartbeat
    consumed by every drive (the drives' own dead-man).  Units come from each axis's gear
    ratio and encoder counts (checked against the drive's factor group when it has one)."""

    kind: Literal["cia402"] = "cia402"
    object_dictionary: Path = Field(
        cia402.EDS_PATH, description="EDS or DCF of the drives (one for all axes)"
    )
    host_node: int = Field(
        cia402.MAX_NODE,
        ge=1,
        le=cia402.MAX_NODE,
        description="the host's node id: its heartbeat is 0x700 + host_node",
    )
    quick_stop_option: int = Field(
        2, ge=0, le=8, description="0x605A written to every drive (2: quick-stop ramp, then off)"
    )
    modules: dict[int, Cia402Module] | None = Field(
        None,
        description="module id -> its axes; default: module i (i-th in order) steer on "
        "node 2i-1, wheel on node 2i, the default gear, counts and homing",
    )

    @model_validator(mode="after")
    def _nodes_valid(self) -> Cia402Drives:
        nodes = self.nodes()
        if len(set(nodes)) != len(nodes):
            raise ValueError(f"drives.modules: node ids must be unique, got {nodes}")
        if self.host_node in nodes:
            raise ValueError(f"drives.host_node {self.host_node} is also a drive's node")
        return self

    def module_ids(self) -> list[int] | None:
        return None if self.modules is None else list(self.modules)

    def for_modules(self, ids: list[int]) -> Cia402Drives:
        if self.modules is not None:
            return self
        mods = {
            m: Cia402Module(steer=Cia402Steer(node=2 * i + 1), wheel=Cia402Axis(node=2 * i + 2))
            for i, m in enumerate(ids)
        }
        return self.model_copy(update={"modules": mods})

    def nodes(self) -> list[int]:
        return [n for m in (self.modules or {}).values() for n in (m.steer.node, m.wheel.node)]

    def axes(self) -> dict[int, Cia402Module]:
        """Module id -> its axes (the default numbering must have been filled in)."""
        assert self.modules is not None, "for_modules() first"
        return dict(self.modules)


class ODriveAxis(BaseModel):
    """One ODrive axis (its own CAN node): an S1 or a Pro, or one axis of a v3.6."""

    model_config = STRICT

    node: int = Field(ge=0, le=ODRIVE_MAX_NODE, description="the axis' CAN node id (can.node_id)")
    gear_ratio: float = Field(
        1.0, gt=0, le=1000, description="axis (encoder) turns per turn of the module's output"
    )
    torque_constant: float = Field(
        8.27 / 270,
        gt=0,
        le=10,
        description="motor torque per amp, N.m/A (8.27 / KV): turns swpc's torque limit into "
        "the axis' current limit",
    )


class ODriveModule(BaseModel):
    """A module's two axes: on one v3.6 (axis0, axis1: two nodes) or one S1 / Pro each."""

    model_config = STRICT

    steer: ODriveAxis
    wheel: ODriveAxis


ODRIVE_HOMING = ("index", "absolute", "none")
"""How the steering finds its reference: an encoder index search (the axis turns until
the index), an absolute encoder (referenced at power-up), none (the power-up position is
the reference: a calibration holds only until the next power-up)."""


class ODriveDrives(DrivesBase):
    """ODrive axes over CAN Simple (``firmware_protocol/odrive/``, :mod:`swpc_hw.drives.odrive`).

    Positions are turns of the axis on the wire, converted with each axis' gear ratio;
    torques N.m at the motor.  The ODrive keeps its own settings: the CAN node ids, the
    heartbeat (100 ms), the encoder estimates' rate and the axis watchdog are set on it
    (docs/drives.md); swpc checks them when it activates the drives."""

    kind: Literal["odrive"] = "odrive"
    firmware: Literal["0.5", "0.6"] = Field(
        "0.6",
        description="firmware line: 0.5 (ODrive v3.6, 0.5.x) or 0.6 (S1, Pro, 0.6.x); the "
        "frames and error bits differ",
    )
    encoder_rate_hz: int | None = Field(
        None,
        ge=1,
        le=500,
        description="the rate of the axes' cyclic Get_Encoder_Estimates (1000 / "
        "encoder_msg_rate_ms); default: the service's feedback rate",
    )
    homing: Literal["index", "absolute", "none"] = Field(
        "index", description="steering reference: index search, absolute encoder or none"
    )
    modules: dict[int, ODriveModule] | None = Field(
        None,
        description="module id -> its steering and wheel axes; default a v3.6 per module, "
        "nodes 0, 1 for the first module, 2, 3 for the second, ...",
    )

    @model_validator(mode="after")
    def _nodes_valid(self) -> ODriveDrives:
        assert self.firmware in FIRMWARE_LINES
        if self.modules is not None:
            nodes = self.nodes()
            if len(set(nodes)) != len(nodes):
                raise ValueError(f"drives.modules: every axis needs its own node id, got {nodes}")
        return self

    def module_ids(self) -> list[int] | None:
        return None if self.modules is None else list(self.modules)

    def for_modules(self, ids: list[int]) -> ODriveDrives:
        if self.modules is not None:
            return self
        default = {
            m: ODriveModule(steer=ODriveAxis(node=2 * i), wheel=ODriveAxis(node=2 * i + 1))
            for i, m in enumerate(ids)
        }
        return self.model_copy(update={"modules": default})

    def nodes(self) -> list[int]:
        return [n for md in (self.modules or {}).values() for n in (md.steer.node, md.wheel.node)]

    def module_map(self) -> dict[int, ODriveModule]:
        """Module id -> its axes (the default numbering must have been filled in)."""
        assert self.modules is not None, "for_modules() first"
        return dict(self.modules)


DrivesConfig = Annotated[
    SwpcDrives | Cia402Drives | ODriveDrives, Field(discriminator="kind")
]
"""Every drive kind's config: a union told apart by ``kind``."""


def parse_drives(value: Any) -> Any:
    """The short form ``drives: <kind>`` as ``{kind: <kind>}``; anything else as it is."""
    if isinstance(value, str):
        return {"kind": value}
    return value
