"""Checks of the kinematic file in force over HTTP, and the robot's history (docs/check.md).

* ``POST /checks`` (token): start a check: a short run of the calibration protocol with
  the robot config's check settings (``check``), every safety limit of a calibration,
  that judges the file in force and installs nothing (202 with its status and
  ``Location``); ``metrology`` ``mocap`` or ``imu`` (the gyro: no references, the
  robot's shape judged).  ``overrides`` as for a calibration (limits and tolerances may only be
  tightened; ``protocol`` overrides the check's protocol).  422 for overrides that cannot
  succeed (before any motion); 409 while a run goes, while ``GET /health`` fails on the
  robot or its sensors, or without a kinematic file in force that loads; 507 without room
  on disk, 503 when the run store cannot be written.
* ``GET /checks``, ``GET /checks/{id}``: every check, one check (its status; once DONE
  with its ``result``: the verdict, per module the chi-square, per parameter the change,
  its std dev and z).
* ``POST /checks/{id}/abort`` (no token needed): every axis stopped at once, the check ends
  ABORTED.
* ``GET /history``: every calibration and check with its time and, per module and
  parameter, the time series with std devs and the trend with the date it leaves its
  tolerance (:mod:`services.runtime.history`); ``since`` (ISO 8601 UTC) keeps the newer.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from fastapi import APIRouter, HTTPException, Query, Request, Response
from fastapi.exceptions import RequestValidationError
from pydantic import BaseModel, ConfigDict, Field

from services.config.robot import ConfigOverrides, RunKind
from services.http.calibrations import abort_run, run_config, start_checked
from services.http.deps import AUTH, GUARDED, Rt, problems
from services.runs.state import RunStatus
from services.runtime.history import epoch, history_document

router = APIRouter()


class CheckRequest(BaseModel):
    """Start a check; ``overrides`` are deep-merged into the robot config's check protocol
    (limits and tolerances may only be tightened)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    overrides: ConfigOverrides = Field(default_factory=ConfigOverrides)
    metrology: Literal["mocap", "imu"] | None = Field(
        None,
        description="mocap (motion capture: every parameter in R) or imu (the gyro and the "
        "wheel encoders: the robot's shape, each module against the others); default the "
        "service's SWPC_METROLOGY",
    )


class CheckStatus(RunStatus):
    """A check's status and, once DONE, its ``result`` (docs/check.md)."""

    result: dict[str, Any] | None = Field(
        None,
        description="once DONE: verdict (consistent | drifted), action, summary, "
        "drifted_modules, modules (chi2 per module against chi2_threshold), table (per "
        "module and parameter: file, check, change, stddev, z, drifted; display units), "
        "file (the file judged), estimate (SI, with std devs)",
    )


def check_status(rt: Rt, run_id: str) -> dict[str, Any]:
    """A check's status with its result once DONE (404: no such check)."""
    st = rt.status(run_id, "check")
    got = rt.result(run_id, "check")
    if st is None or got is None:
        raise HTTPException(404, f"no check {run_id}")
    return {**st, "result": got[1] if st["state"] == "DONE" else None}


@router.post(
    "/checks",
    status_code=202,
    response_model=RunStatus,
    dependencies=AUTH,
    responses={
        **GUARDED,
        **problems(
            _409="a run goes, GET /health fails on the robot or its sensors, or no "
            "kinematic file in force loads (named)",
            _503="the run store cannot be written",
            _507="no room on disk for a run",
        ),
    },
)
def start(body: CheckRequest, rt: Rt, response: Response) -> dict[str, Any]:
    """Start a check (module docstring)."""
    metrology = body.metrology or rt.settings.run_metrology
    config = run_config(rt, body.overrides, metrology, "check")
    run = start_checked(rt, config, "never", metrology, [], "check")
    response.headers["Location"] = f"/checks/{run.id}"
    return run.status.to_dict()


@router.get("/checks", response_model=list[RunStatus])
def list_checks(rt: Rt) -> list[dict[str, Any]]:
    return rt.list_runs("check")


@router.get("/checks/{run_id}", response_model=CheckStatus, responses=problems(404))
def get_check(run_id: str, rt: Rt) -> dict[str, Any]:
    return check_status(rt, run_id)


@router.post(
    "/checks/{run_id}/abort",
    response_model=RunStatus,
    responses={**problems(413, 404, 409)},
)
async def abort(run_id: str, rt: Rt, request: Request) -> dict[str, Any]:
    """Stop the run: no token needed (stopping the robot is never refused for want of one;
    docs/operating.md)."""
    return await abort_run(rt, run_id, "check", request)


class HistoryPoint(BaseModel):
    time: str
    run: str
    kind: RunKind
    frame: str
    value: float | None
    stddev: float | None
    other_frame: bool = Field(
        description="of another frame than the reference's that cannot be re-expressed in it "
        "(a design-fit point where the file in force is in R): value and stddev null"
    )
    re_expressed: bool = Field(
        description="re-expressed in the reference's frame (a motion-capture point, frame R, "
        "where the file in force is in design-fit)"
    )


class TrendLinePoint(BaseModel):
    time: str
    value: float


class HistoryTrend(BaseModel):
    points: int = Field(description="points the line is fitted to")
    per_week: float = Field(description="slope, unit per week")
    per_week_std: float
    significant: bool = Field(description="|slope| > 2 of its std devs")
    value_now: float
    birge: float = Field(description="the points' scatter over their std devs (>= 1)")
    leaves_tolerance: str | None = Field(
        description="when the line leaves reference +- tolerance (None: not significant)"
    )
    outside: bool = Field(description="the line is out of the band now")
    line: list[TrendLinePoint]


class HistoryParameter(BaseModel):
    module: int
    param: str
    unit: str
    reference: float | None = Field(description="the file in force's value (else the newest "
                                    "calibration's)")
    tolerance: float
    points: list[HistoryPoint]
    trend: HistoryTrend | None


class HistoryRun(BaseModel):
    run: str
    kind: RunKind
    time: str
    frame: str
    installed: bool | None
    verdict: str | None


class History(BaseModel):
    robot: str
    now: str
    since: str | None
    file_in_force: dict[str, Any] | None
    tolerances: dict[str, float]
    runs: list[HistoryRun]
    last_check: dict[str, Any] | None
    parameters: list[HistoryParameter]


@router.get("/history", response_model=History)
def history(
    rt: Rt, since: Annotated[str | None, Query(description="ISO 8601 UTC time")] = None
) -> dict[str, Any]:
    """Every calibration and check with its time; per module and parameter the series,
    the reference, the trend and when it leaves its tolerance (module docstring)."""
    if since is not None:
        try:
            epoch(since)
        except (ValueError, OverflowError, OSError) as exc:  # FastAPI's own 422 shape
            raise RequestValidationError(
                [{"loc": ["query", "since"], "msg": f"not an ISO 8601 time: {exc}",
                  "type": "value_error"}]
            ) from exc  # fmt: skip
    return history_document(rt, since)
