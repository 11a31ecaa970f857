"""The ``odrive`` kind's part of a robot config's ``drives:``: the firmware line, each
axis' node, gear ratio and torque constant, the homing (docs/drives.md)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, Field, model_validator

from firmware_protocol.odrive.can_simple import FIRMWARE_LINES
from firmware_protocol.odrive.can_simple import MAX_NODE as ODRIVE_MAX_NODE
from swpc_hw.drives.registry import STRICT, KindConfig


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


class ODriveDrives(KindConfig):
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

    def axis_nodes(self) -> dict[int, tuple[int, int]]:
        return {m: (md.steer.node, md.wheel.node) for m, md in self.module_map().items()}
