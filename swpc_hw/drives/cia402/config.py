"""The ``cia402`` kind's part of a robot config's ``drives:``: each axis' CiA 402 drive,
its units and homing, the object dictionary, the host's node (docs/drives.md)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, Field, model_validator

from firmware_protocol import cia402
from swpc_hw.drives.registry import STRICT, KindConfig

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
    rated_torque: float | None = Field(
        None,
        gt=0,
        description="N.m at the motor: the unit of the torque objects (thousandths of it) "
        "for a drive without 0x6076; the drive's 0x6076 wins when it has one",
    )
    object_dictionary: Path | None = Field(
        None,
        description="EDS or DCF of this axis' drive, when it is not the drives' "
        "object_dictionary (a robot whose steering and wheel drives differ)",
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


class Cia402Drives(KindConfig):
    """CiA 402 drives over CANopen: one single-axis drive per axis (a module's steering and
    wheel on two nodes), its object dictionary from an EDS/DCF, the host's heartbeat
    consumed by every drive (the drives' own dead-man).  Units come from each axis's gear
    ratio and encoder counts (checked against the drive's factor group when it has one)."""

    kind: Literal["cia402"] = "cia402"
    object_dictionary: Path = Field(
        cia402.EDS_PATH,
        description="EDS or DCF of the drives (every axis' that does not name its own)",
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

    def eds(self, axis: Cia402Axis) -> Path:
        """The object dictionary of ``axis``' drive: its own, else the drives'."""
        return axis.object_dictionary or self.object_dictionary

    def eds_files(self) -> list[Path]:
        """Every object dictionary the axes use, each once, in the axes' order."""
        axes = [a for m in (self.modules or {}).values() for a in (m.steer, m.wheel)]
        return list(dict.fromkeys([self.object_dictionary, *(self.eds(a) for a in axes)]))

    def axis_nodes(self) -> dict[int, tuple[int, int]]:
        return {m: (md.steer.node, md.wheel.node) for m, md in self.axes().items()}
