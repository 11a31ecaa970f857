"""Calibration runs over HTTP: start, list, watch, read the result and the plot, abort.

* ``POST /calibrations`` (token): start a run (202 with its status and ``Location``);
  ``{"plan": "auto"}`` plans its protocol first (docs/plan.md; 422 with the reason when
  it cannot be planned).
  Overrides may only tighten the robot config's limits and tolerances, and everything
  that can be checked before motion is: 422 otherwise, before any CAN frame; 409 while a
  run goes, or while ``GET /health`` fails on the robot or its sensors (the run would
  fail at CONNECT or PRECHECK: the detail names why), 507 without room on disk, 503 when
  the run store cannot be written.
* ``GET /plan``: the plan ``{"plan": "auto"}`` runs, before Start (docs/plan.md); 202
  while it is being made.
* ``GET /calibrations``, ``GET /calibrations/{id}``: every run, one run.
* ``GET /calibrations/{id}/result``: a DONE run's result document (409 otherwise).
* ``POST /calibrations/{id}/abort`` (no token needed): every axis stopped at once, the run ends
  ABORTED and nothing is installed; 409 when it is too late: the run has finished, or
  has begun installing its result (then that stands).
* ``GET /calibrations/{id}/plot.png``: the run's plot, rendered once.
* ``GET /calibrations/{id}/export?to=urdf|ros2-params|kinematics``: a DONE run's result in
  the robot config's base_link, as ``swpc export`` writes it (docs/ros2.md), a download;
  404 for a run never seen, 409 without a result, 422 for a result the target cannot hold.
"""

from __future__ import annotations

import logging
import re
from dataclasses import replace
from pathlib import Path
from typing import Any, Literal

from fastapi import APIRouter, HTTPException, Request, Response
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, JSONResponse
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from services.config.robot import ConfigOverrides, OverrideError, RobotConfig, RunKind
from services.http.answers import ReferenceIn, entries, refused
from services.http.deps import AUTH, GUARDED, Rt, done_result, not_running, problems
from services.http.edge.control import ABORT, run_in
from services.http.edge.guard import has_token
from services.plan.planner import (
    PlannerBusyError,
    PlanRequest,
    default_budget,
    planned_keys,
    stopping_for,
)
from services.runs.metrology.imu import parse_references, reference_problems
from services.runs.protocol import CalibrationRun
from services.runs.state import RunStatus
from services.runtime.errors import (
    DiskSpaceError,
    NoFileError,
    NoResultError,
    RunConflictError,
    StoreError,
)
from services.runtime.health import start_problems
from services.store.logs import event
from swpc_hw.calibration.plan.forecast import Stopping
from swpc_hw.calibration.plan.plan import MocapNoise, PlanError, Targets
from swpc_hw.errors import DatasetError, KinematicFileError
from swpc_hw.files.kinematic_file import load_kinematics
from swpc_hw.files.references import Reference
from swpc_hw.onboard.export import TARGETS, file_name, make_export, render

log = logging.getLogger("swpc.service")
router = APIRouter()


class TargetsIn(BaseModel):
    """Target std devs of a planned calibration, SI (as the robot config's tolerances)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    position: float | None = Field(None, gt=0, description="x_s, y_s, b std dev, m")
    beta: float | None = Field(None, gt=0, description="beta std dev, rad")
    radius: float | None = Field(None, gt=0, description="r std dev, m")


class StartRequest(BaseModel):
    """Start a calibration; ``overrides`` are deep-merged into the robot config (limits and
    tolerances may only be tightened).  ``metrology``: ``mocap`` (motion capture) or
    ``imu`` (none: the robot's gyro, with ``references`` measured by tape; the straight
    drive's comes during the run); default ``imu`` when the service is set up without
    motion capture (``SWPC_METROLOGY=imu``), else ``mocap``."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    overrides: ConfigOverrides = Field(default_factory=ConfigOverrides)
    install: Literal["if-within-tolerance", "always", "never"] = "if-within-tolerance"
    metrology: Literal["mocap", "imu"] | None = None
    references: list[ReferenceIn] = Field(default_factory=list)
    plan: Literal["auto"] | None = None
    """``auto``: the protocol is planned (docs/plan.md): the angles, sweep, pauses and spin
    torque that reach ``targets`` and keep the square path within its budget in the least
    robot time (without motion capture the rests and the drive too; the request's
    ``overrides`` may not set them)."""
    targets: TargetsIn | None = None
    """With ``plan``: per-kind target std devs (default: the robot config's tolerances)."""


def refused_before_motion(where: str, problems: list[str]) -> RequestValidationError:
    """A 422 in the shape of FastAPI's own (one schema for 422), one entry per problem."""
    msg = "refused before any motion: {}"
    return RequestValidationError(
        [{"loc": ["body", where], "msg": msg.format(p), "type": "value_error"} for p in problems]
    )


def start_references(
    config: RobotConfig, metrology: str, given: list[ReferenceIn]
) -> list[Reference]:
    """The references of a run to start, checked before any motion (422 otherwise)."""
    if metrology != "imu":
        if given:
            raise refused("references", ValueError("references are for metrology imu"))
        return []
    try:
        refs = parse_references(entries(given), config.nominal.ids)
    except DatasetError as exc:
        raise refused("references", ValueError(f"refused before any motion: {exc}")) from exc
    problems = reference_problems(config, refs)
    if problems:
        raise refused_before_motion("references", problems)
    return refs


def run_config(
    rt: Rt,
    overrides: ConfigOverrides,
    metrology: str,
    kind: RunKind = "calibration",
    *,
    spin_torque: float | None = None,
) -> RobotConfig:
    """The run's robot config: the service's (a check's: :meth:`RobotConfig.check_config`)
    with the request's overrides (422 when they loosen a limit or cannot succeed).
    ``spin_torque``: a plan's (:func:`planned_config`): the overrides are checked against
    the service's config with it as ``limits.spin_torque`` (a plan may spin faster than the
    robot config; its other limits bound the plan's choice and stay limits)."""
    base = rt.config
    if spin_torque is not None:
        base = base.with_overrides({"limits": {"spin_torque": spin_torque}})
    try:
        return base.for_run(overrides.document(), metrology, kind)
    except OverrideError as exc:
        raise refused_before_motion("overrides", exc.problems) from exc
    except (ValidationError, ValueError, TypeError) as exc:
        raise RequestValidationError(
            [
                {
                    "loc": ["body", "overrides"],
                    "msg": f"invalid robot config override: {exc}",
                    "type": "value_error",
                }
            ]
        ) from exc


@router.post(
    "/calibrations",
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
def start(body: StartRequest, rt: Rt, response: Response) -> dict[str, Any]:
    """Start a run (module docstring)."""
    metrology = body.metrology or rt.settings.run_metrology
    config = run_config(rt, body.overrides, metrology)
    stopping = None
    if body.plan == "auto":
        config, stopping = planned_config(rt, body, metrology, config)
    elif body.targets is not None:
        raise refused("targets", ValueError("targets are for a planned run (plan: auto)"))
    refs = start_references(config, metrology, body.references)
    run = start_checked(rt, config, body.install, metrology, refs, stopping=stopping)
    response.headers["Location"] = f"/calibrations/{run.id}"
    return run.status.to_dict()


def planned_config(
    rt: Rt, body: StartRequest, metrology: str, config: RobotConfig
) -> tuple[RobotConfig, Stopping | None]:
    """The run's config with the plan's overrides (its protocol and spin torque; without
    motion capture its rests and drive too) in the request's, and its sequential stopping
    (motion capture only: a run without it sweeps its planned sweep; 422 with the reason
    when it cannot be planned: settings the plan chooses, no candidate that reaches the
    targets).  The plan's spin torque may be above the robot config's
    ``limits.spin_torque``: the plan chose it within the run's ``max_wheel_torque`` and
    ``max_yaw_rate`` (docs/plan.md), which stay limits."""
    cur = rt.current
    if rt.running() and cur is not None:  # not after seconds of planning
        raise HTTPException(409, f"{cur.status.kind} {cur.id} is still running")
    doc = body.overrides.document()
    given = {f"{g}.{k}" for g, v in doc.items() if isinstance(v, dict) for k in v}
    taken = sorted(planned_keys(metrology) & given)
    if taken:
        raise refused(
            "plan",
            ValueError(f"plan auto chooses {', '.join(taken)}: leave them out of the "
                       "overrides, or leave out the plan"),
        )  # fmt: skip
    tol, t = config.tolerances, body.targets or TargetsIn()
    try:
        targets = Targets(t.position or tol.position, t.beta or tol.beta, t.radius or tol.radius)
        request = plan_request(rt, metrology, targets)
        p = rt.planner.get(config, request)
        stopping = (
            stopping_for(config, p, request) if p is not None and metrology == "mocap" else None
        )
    except PlannerBusyError as exc:
        raise HTTPException(409, f"not started: {exc}") from exc
    except PlanError as exc:
        raise refused("plan", ValueError(f"refused before any motion: {exc}")) from exc
    if p is None:
        raise HTTPException(
            409, "not started: the plan is being made (seconds to a minute): send the same "
            "request again then (GET /plan shows the robot config's)",
        )  # fmt: skip
    for group, settings in p.candidate.overrides().items():
        doc.setdefault(group, {}).update(settings)
    config = run_config(rt, ConfigOverrides.model_validate(doc), metrology,
                        spin_torque=p.candidate.spin_torque)  # fmt: skip
    return config, stopping


def plan_request(rt: Rt, metrology: str, targets: Targets | None = None) -> PlanRequest:
    """The plan request of a run with ``metrology``: the square path's default budget of
    that metrology; with motion capture the frame rate it streams at now (to the nearest
    Hz; 100 Hz, the planner's default, while no pose comes), without it the service's gyro
    (``sim_gyro_*``).  A faster motion capture gives more poses per spin: shorter spins
    meet the same requirement (docs/plan.md)."""
    rate = rt.mocap.frame_rate() if metrology == "mocap" else None
    noise = MocapNoise() if rate is None else replace(MocapNoise(), rate=float(round(rate)))
    return PlanRequest(
        targets=targets, budget=default_budget(metrology), metrology=metrology,
        gyro=rt.settings.sim_gyro, noise=noise,
    )  # fmt: skip


def start_checked(
    rt: Rt,
    config: RobotConfig,
    install: str,
    metrology: str,
    refs: list[Reference],
    kind: RunKind = "calibration",
    stopping: Stopping | None = None,
) -> CalibrationRun:
    """Start a run once ``GET /health`` passes (409 naming why not; 409 while one runs,
    507 without room, 503 when the store cannot be written; a check without a file in
    force, 409)."""
    failing = [] if rt.running() else start_problems(rt)
    if failing:
        raise HTTPException(409, "not started: GET /health is failing: " + "; ".join(failing))
    try:
        return rt.start_run(config, install, metrology, refs, kind, stopping)
    except (RunConflictError, NoFileError) as exc:
        raise HTTPException(409, str(exc)) from exc
    except DiskSpaceError as exc:
        raise HTTPException(507, str(exc)) from exc
    except StoreError as exc:
        raise HTTPException(503, str(exc)) from exc


@router.get(
    "/plan",
    responses=problems(
        _202="the plan is being made (ask again in a few seconds)",
        _409="the robot config cannot be planned (why), or another plan is being made",
    ),
)
def get_plan(rt: Rt, metrology: Literal["mocap", "imu"] | None = None) -> Any:
    """The plan of a calibration of the robot config (docs/plan.md): what
    ``POST /calibrations {"plan": "auto"}`` without overrides runs (``metrology``: as the
    request's, default the service's), with its predicted
    robot time, std devs and the requirement (mm, deg).  The first call starts making it
    (202 until it is made: seconds to a minute), then it is kept; 409 naming why when no
    candidate meets the requirement, or while a run goes and it is not made yet (a plan
    takes CPU a run needs)."""
    try:  # the config of a run without overrides: the plan it runs; none started in a run
        m = metrology or rt.settings.run_metrology
        request = plan_request(rt, m)
        p = rt.planner.get(rt.config.for_run({}, m), request, start=not rt.running())
    except OverrideError as exc:
        raise HTTPException(409, f"no plan: the robot config cannot run: {exc}") from exc
    except PlanError as exc:
        raise HTTPException(409, f"no plan: {exc}") from exc
    if p is None:
        return JSONResponse({"detail": "the plan is being made"}, status_code=202)
    doc = p.document()
    if m == "mocap":  # the rate the plan assumed: the motion capture's, as it streams now
        doc["mocap_rate_hz"] = request.noise.rate
    return doc


@router.get("/calibrations", response_model=list[RunStatus])
def list_runs(rt: Rt) -> list[dict[str, Any]]:
    return rt.list_runs("calibration")


@router.get("/calibrations/{run_id}", response_model=RunStatus, responses=problems(404))
def get_run(run_id: str, rt: Rt) -> dict[str, Any]:
    st = rt.status(run_id, "calibration")
    if st is None:
        raise HTTPException(404, f"no calibration {run_id}")
    return st


@router.get("/calibrations/{run_id}/result", responses=problems(404, 409))
def get_result(run_id: str, rt: Rt) -> dict[str, Any]:
    doc = done_result(rt, run_id)
    return doc


@router.post(
    "/calibrations/{run_id}/abort",
    response_model=RunStatus,
    responses={**problems(413, 404, 409)},
)
async def abort(run_id: str, rt: Rt, request: Request) -> dict[str, Any]:
    """Stop the run: no token needed (stopping the robot is never refused for want of one;
    docs/operating.md)."""
    return await abort_run(rt, run_id, "calibration", request)


async def abort_run(rt: Rt, run_id: str, kind: RunKind, request: Request) -> dict[str, Any]:
    """Abort run ``run_id`` of ``kind`` (404 unknown, 409 too late); who asked is logged
    (an abort needs no token)."""
    # async: runs on the event loop itself, so stop_all() is not queued behind a
    # threadpool hand-off; only the wait for the run's thread goes to a thread of its own
    run = rt.runs.get(run_id)
    if run is None or run.status.kind != kind:
        raise not_running(rt, run_id, kind)
    stopping = run.abort()
    client = request.client.host if request.client else "?"
    token = has_token(request.scope, str(request.app.state.token))
    event(log, logging.WARNING, "run.abort_request", run=run_id, client=client,
          token="yes" if token else "no", stopped="yes" if stopping else "no")  # fmt: skip
    if not stopping:
        st = run.status.state
        why = "it has finished" if run.finished else "it is installing its result, which stands"
        raise HTTPException(409, f"{kind} {run_id} is {st}: too late to abort ({why})")
    await run_in(ABORT, run.join, 10.0)
    return run.status.to_dict()


@router.get(
    "/calibrations/{run_id}/plot.png",
    responses={200: {"content": {"image/png": {}}}, **problems(404, 409)},
    response_class=Response,
)
def plot(run_id: str, rt: Rt) -> Response:
    """The run's plot: rendered once, then served from the run's directory."""
    try:
        path = rt.plot(run_id)
    except NoResultError as exc:
        raise HTTPException(409, str(exc)) from exc
    if path is None:
        raise HTTPException(404, f"no calibration {run_id}")
    return FileResponse(path, media_type="image/png")


ExportTarget = Literal["urdf", "ros2-params", "kinematics"]


@router.get(
    "/calibrations/{run_id}/export",
    responses={
        200: {"content": {"application/xml": {}, "application/yaml": {}}},
        **problems(404, 409),
    },
    response_class=Response,
)
def export(run_id: str, rt: Rt, to: ExportTarget) -> Response:
    """A DONE run's result file in the robot config's ``base_link``: a URDF, a ROS 2
    parameter file or the kinematic file (``to``), as ``swpc export`` writes it."""
    done_result(rt, run_id)
    path = Path(rt.settings.data_dir) / "runs" / run_id / "kinematics.yaml"
    try:
        kf = load_kinematics(path)
    except KinematicFileError as exc:
        raise HTTPException(409, f"calibration {run_id}: its result file: {exc}") from exc
    try:
        text = render(
            make_export(kf, rt.config.base_link, f"run {run_id}", rt.config.axis_signs()), to
        )
    except ValueError as exc:  # the shape of FastAPI's own 422 (one schema for 422)
        raise RequestValidationError(
            [{"loc": ["query", "to"], "msg": f"calibration {run_id}: {exc}", "type": "value_error"}]
        ) from exc
    name = file_name(re.sub(r"[^A-Za-z0-9._-]", "_", f"{kf.params.robot}-{run_id}"), to)
    return Response(
        text,
        media_type=TARGETS[to][1],
        headers={"Content-Disposition": f'attachment; filename="{name}"'},
    )
