"""The robot's drives as the running service knows them: ``GET /drives`` (the console's
Drives view, and every ``live`` event of its stream).

For each module axis: the drive the robot config puts on it (kind, module, axis, node)
and what the driver knows of it now (:meth:`swpc_hw.drives.interface.Drives.axis_status`):
alive, the robot time since its last heartbeat, its NMT and power (or axis) state, its
mode, its error named, homed.  It reads what the driver has already heard and sends
nothing: no active scan while the driver owns the bus (a second SDO client on the bus
would take the driver's answers for its own, and the driver its).  What a drive is
(identity, software version, supported modes, heartbeat settings) is ``swpc drives
scan``'s, run with the service stopped (docs/drives.md, *Scanning the bus*).

A kind whose driver reports whole modules only (``axis_status`` None) is shown from its
modules' snapshots: ``axis_detail`` false, each axis' liveness and heartbeat its module's,
its error by number.
"""

from __future__ import annotations

import math
from typing import Literal

from fastapi import APIRouter
from pydantic import BaseModel, Field

from firmware_protocol.codec import Axis
from services.http.deps import Rt
from services.runtime.health import simulated_time_still
from services.runtime.runtime import Runtime
from swpc_hw.drives.interface import Drives
from swpc_hw.drives.types import AXIS_NAMES, AxisStatus, Lifecycle, axis_status_of_module

SCAN_NOTE = (
    "what each drive is (identity, software, supported modes, heartbeat settings) and the "
    "nodes on the bus the config does not name: swpc drives scan, with the service stopped"
)


class DriveAxis(BaseModel):
    """One module axis: the drive the robot config puts on it, and what the driver knows
    of it now (null: not known, e.g. no driver open)."""

    module: int
    axis: Literal["steer", "wheel"]
    node: int = Field(description="the CAN node id of its drive, from the robot config")
    alive: bool | None = Field(
        description="its heartbeat on time; null: unknown, no heartbeat is watched now (the "
        "in-process simulator between runs, whose time stands still; no driver open)"
    )
    heartbeat_age_s: float | None = Field(
        description="robot time since its last heartbeat, s (null: none yet)"
    )
    heartbeats: int | None = Field(description="heartbeats received since the service began")
    state: str | None = Field(
        description="its state in its kind's words: swpc's axis state, the CiA 402 power "
        "state, the ODrive's axis state"
    )
    nmt: str | None = Field(description="CANopen NMT state from its heartbeat (cia402 only)")
    mode: str | None = Field(
        description="the mode in force: the host's control mode (swpc, odrive), the modes "
        "display 0x6061 (cia402)"
    )
    error: int | None = Field(description="the kind's error word or code (0: none)")
    error_name: str | None = Field(description="the error named (none for 0)")
    fault: bool | None = Field(description="the drive is in fault by its kind's rule")
    homed: bool | None = Field(description="the steering is homed (null for a wheel)")


class DrivesView(BaseModel):
    """The robot's drives: the config's, and what the running driver knows of each axis."""

    kind: str = Field(description="the drive kind of the robot config (drives.kind)")
    bus: str = Field(description="the CAN bus the service drives, interface:channel")
    driver: str = Field(
        description="the driver's lifecycle state: unconfigured, inactive (watching), active "
        "(commands flow), finalized; 'not open' without a driver"
    )
    fault_cause: str | None = Field(description="the fault the driver last stopped on")
    watched: bool = Field(description="heartbeats are judged now (alive is known)")
    axis_detail: bool = Field(
        description="the kind's driver reports each axis; false: each axis' alive, heartbeat "
        "and homed are its module's, its error by number"
    )
    axes: list[DriveAxis]
    scan: str = Field(SCAN_NOTE, description="where the rest is")


router = APIRouter()


def _age(d: Drives, t: float | None) -> float | None:
    if t is None:
        return None
    age = max(0.0, d.clock.now() - t)
    return age if math.isfinite(age) else None


def _from_module(d: Drives, module: int, axis: Axis) -> AxisStatus:
    """One axis from its module's snapshot (a kind without ``axis_status``): its error by
    number, in fault when its state says so or it reports an error."""
    return axis_status_of_module(
        d.module_state(module), axis, lambda e: f"0x{e:04X}", fault_on_error=True
    )


def _configured(rt: Runtime) -> dict[int, tuple[int, int]]:
    """Module id -> (steering node, wheel node) as the robot config gives them."""
    drives = rt.config.drives.for_modules(rt.config.nominal.ids)
    try:
        return drives.axis_nodes()
    except NotImplementedError:  # a kind's config without it: the driver's nodes
        return {}


def drives_view(rt: Runtime) -> DrivesView:
    """The document of ``GET /drives`` (module docstring)."""
    d = rt.drives
    nodes = _configured(rt)
    open_ = d is not None and d.state in (Lifecycle.INACTIVE, Lifecycle.ACTIVE)
    watched = open_ and not simulated_time_still(rt)
    axes: list[DriveAxis] = []
    detail = True
    modules = d.modules() if d is not None else list(nodes)
    for m in modules:
        for axis in (Axis.STEER, Axis.WHEEL):
            name = AXIS_NAMES[axis]
            if d is None:
                node = nodes[m][axis]
                axes.append(DriveAxis(
                    module=m, axis=name, node=node, alive=None, heartbeat_age_s=None,
                    heartbeats=None, state=None, nmt=None, mode=None, error=None,
                    error_name=None, fault=None, homed=None,
                ))  # fmt: skip
                continue
            s = d.axis_status(m, axis)
            if s is None:
                detail = False
                s = _from_module(d, m, axis)
            axes.append(
                DriveAxis(
                    module=m,
                    axis=name,
                    node=nodes[m][axis] if m in nodes else s.node,
                    alive=s.alive if watched else None,
                    heartbeat_age_s=_age(d, s.t_heartbeat),
                    heartbeats=s.heartbeats,
                    state=s.state,
                    nmt=s.nmt,
                    mode=s.mode,
                    error=s.error,
                    error_name=s.error_name,
                    fault=s.fault,
                    homed=s.homed,
                )
            )
    return DrivesView(
        kind=rt.config.drives.kind,
        bus=f"{rt.can_interface}:{rt.can_channel}",
        driver="not open" if d is None else d.state.value,
        fault_cause=None if d is None else d.fault_cause,
        watched=watched,
        axis_detail=detail and d is not None,
        axes=axes,
    )


@router.get("/drives", response_model=DrivesView)
def drives(rt: Rt) -> DrivesView:
    """The robot's drives: for each module axis the node the robot config gives it, and
    what the running driver knows of it now (alive, heartbeat age, NMT and power state,
    mode, error named, homed).  Reads only: no frame is sent for it.  The full scan of the
    bus (identity, modes, nodes the config does not name) is ``swpc drives scan`` with
    the service stopped."""
    return drives_view(rt)
