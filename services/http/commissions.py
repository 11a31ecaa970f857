"""Commissioning over HTTP: what the robot's drives really move, and the robot config
corrected to say it (docs/commissioning.md).

* ``POST /commissions`` (token): start a commissioning: the probes (a few degrees of
  motion per axis, under the watchdog, limits, step timeout and abort of every run) with
  motion capture; 202 with its status and ``Location``.  409 while a run goes or while
  ``GET /health`` fails on the robot or its sensors; 422 without motion capture.
* ``GET /commissions``, ``GET /commissions/{id}``: every commissioning, one (its status;
  once DONE its ``result``: the findings, each naming the axis and its fix, the probes,
  the corrected robot config and its ``diff`` against the one in force, what the config
  cannot hold).
* ``POST /commissions/{id}/abort`` (no token needed): every axis stopped at once.
* ``POST /commissions/{id}/accept`` (token): write the corrected robot config over the
  service's (``SWPC_ROBOT_CONFIG``; the one in force kept beside it as
  ``<name>.<time>.bak``).  Nothing is written before this.  409 when the file changed
  since the commissioning started (commission again), while a run goes, when there is
  nothing to correct, or when the service runs on the embedded default (no file to
  write: the corrected document is in the result).  A correction of the drives (nodes,
  ratios) takes effect when the service restarts (``restart: true``); any other at once.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
from pathlib import Path
from typing import Any

import yaml
from fastapi import APIRouter, HTTPException, Request, Response
from pydantic import BaseModel, ConfigDict, Field

from services.config.commission import with_int_keys
from services.config.robot import RobotConfig, load_robot_config
from services.http.calibrations import abort_run, start_checked
from services.http.deps import AUTH, GUARDED, Rt, problems
from services.runs.state import RunStatus
from swpc_hw.files.kinematic_file import atomic_write_text

router = APIRouter()


class CommissionStatus(RunStatus):
    """A commissioning's status and, once DONE, its ``result``."""

    result: dict[str, Any] | None = Field(
        None,
        description="once DONE: right (bool), findings (module, axis, what, value, text), "
        "modules (what each configured module's drives move), steer_moves, pivot_probes, "
        "config (the corrected robot config document), diff, not_in_config, robot_time_s, "
        "largest_turn_deg, largest_move_mm, stop_latency_ms",
    )


class Accepted(BaseModel):
    model_config = ConfigDict(extra="forbid")

    written: str = Field(description="the robot config file written")
    backup: str | None = Field(description="the one in force before, kept")
    restart: bool = Field(
        description="the drives' part changed: it takes effect when the service restarts"
    )
    diff: str


def commission_status(rt: Rt, run_id: str) -> dict[str, Any]:
    st = rt.status(run_id, "commission")
    got = rt.result(run_id, "commission")
    if st is None or got is None:
        raise HTTPException(404, f"no commissioning {run_id}")
    return {**st, "result": got[1] if st["state"] == "DONE" else None}


@router.post(
    "/commissions",
    status_code=202,
    response_model=RunStatus,
    dependencies=AUTH,
    responses={
        **GUARDED,
        **problems(
            _409="a run goes, or GET /health fails on the robot or its sensors (named)",
            _503="the run store cannot be written",
            _507="no room on disk for a run",
        ),
    },
)
def start(rt: Rt, response: Response) -> dict[str, Any]:
    """Start a commissioning (module docstring)."""
    metrology = rt.settings.run_metrology
    problems_ = rt.config.run_problems(metrology, "commission")
    if problems_:
        raise HTTPException(422, "refused before any motion: " + "; ".join(problems_))
    run = start_checked(rt, rt.config, "never", metrology, [], "commission")
    response.headers["Location"] = f"/commissions/{run.id}"
    return run.status.to_dict()


@router.get("/commissions", response_model=list[RunStatus])
def list_commissions(rt: Rt) -> list[dict[str, Any]]:
    return rt.list_runs("commission")


@router.get("/commissions/{run_id}", response_model=CommissionStatus, responses=problems(404))
def get_commission(run_id: str, rt: Rt) -> dict[str, Any]:
    return commission_status(rt, run_id)


@router.post(
    "/commissions/{run_id}/abort",
    response_model=RunStatus,
    responses={**problems(413, 404, 409)},
)
async def abort(run_id: str, rt: Rt, request: Request) -> dict[str, Any]:
    """Stop the commissioning: no token needed."""
    return await abort_run(rt, run_id, "commission", request)


@router.post(
    "/commissions/{run_id}/accept",
    response_model=Accepted,
    dependencies=AUTH,
    responses={**GUARDED, **problems(404, 409)},
)
def accept(run_id: str, rt: Rt) -> dict[str, Any]:
    """Write the corrected robot config (module docstring)."""
    st = commission_status(rt, run_id)
    if st["state"] != "DONE" or st["result"] is None:
        raise HTTPException(409, f"commissioning {run_id} is {st['state']}: nothing to accept")
    res = st["result"]
    if not res["diff"]:
        raise HTTPException(409, f"commissioning {run_id} found nothing the config can correct")
    if res.get("config_error"):
        raise HTTPException(409, f"the corrected config does not load: {res['config_error']}")
    path = rt.settings.robot_config
    if path is None:
        raise HTTPException(
            409,
            "the service runs on the embedded default robot config: there is no file to "
            "write. Save the result's config as a file, set SWPC_ROBOT_CONFIG to it and "
            "restart the service",
        )
    if rt.running():
        raise HTTPException(409, "a run goes: accept once it has ended")
    path = Path(path)
    text = path.read_text(encoding="utf-8")
    if hashlib.sha256(text.encode()).hexdigest() != res["in_force_sha256"]:
        raise HTTPException(
            409,
            f"{path} changed since commissioning {run_id} started: commission again",
        )
    doc = with_int_keys(res["config"])
    new_text = yaml.safe_dump(doc, sort_keys=False, default_flow_style=False)
    new_config = RobotConfig.model_validate(doc)  # the result's: valid when it was made
    stamp = _dt.datetime.now(_dt.UTC).strftime("%Y%m%dT%H%M%SZ")
    backup = path.with_name(f"{path.name}.{stamp}.bak")
    atomic_write_text(backup, text)
    atomic_write_text(path, new_text)
    restart = new_config.drives != rt.config.drives
    if not restart:
        rt.config = load_robot_config(path)
    return {"written": str(path), "backup": str(backup), "restart": restart, "diff": res["diff"]}
