"""The ``swpc`` kind's part of a robot config's ``drives:``: which node each module's
controller is on."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from firmware_protocol.codec import MAX_NODE
from swpc_hw.drives.registry import KindConfig


class SwpcDrives(KindConfig):
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

    def axis_nodes(self) -> dict[int, tuple[int, int]]:
        """Both axes of a module on its controller's node."""
        return {m: (n, n) for m, n in self.node_map().items()}
