"""The ``drives:`` section of a robot config: which drive kind, and where each axis is.

YAML (``deploy/robot.example.yaml`` documents every key)::

    drives: swpc                   # short for {kind: swpc}: nodes numbered 1, 2, ...
    drives:
      kind: swpc                   # swpc's own firmware: one dual-axis controller a module
      modules: {1: 1, 2: 2, 3: 3, 4: 4}   # module id -> its controller's node (1..8)

A kind's model lists what that protocol needs (a CiA 402 drive's object dictionary, an
ODrive's firmware line, ...); :data:`DrivesConfig` is the union of the kinds, told apart by
``kind``.  Module ids must be exactly the robot's (checked by the robot config, which
knows them: :meth:`DrivesBase.check_modules`).
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from firmware_protocol.codec import MAX_NODE

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


DrivesConfig = SwpcDrives
"""Every drive kind's config (a union told apart by ``kind`` once there are several)."""


def parse_drives(value: Any) -> Any:
    """The short form ``drives: <kind>`` as ``{kind: <kind>}``; anything else as it is."""
    if isinstance(value, str):
        return {"kind": value}
    return value
