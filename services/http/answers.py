"""The operator's answers to a run that waits for them (``GET /calibrations/{id}``'s
``waits_for``; with the IMU metrology: docs/imu-operation.md).

* ``POST /calibrations/{id}/continue``: the operator has marked the floor under the
  first module's steering axis (the run waits in MARK); the robot then drives.
* ``POST /calibrations/{id}/references``: the operator's tape measurements (the run waits
  in MEASURE): the straight drive's length, and any further reference.

A run that does not wait for the answer (another state, or a metrology that needs none)
answers 409 and is not changed.

The references' schema (:class:`ReferenceIn`) is also what ``POST /calibrations`` takes
with ``"metrology": "imu"`` (docs/dataset-format.md's ``references.yaml``; a
``straight_drive`` carries no times here: the run knows when it drove).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Literal

from fastapi import APIRouter, HTTPException
from fastapi.exceptions import RequestValidationError
from pydantic import BaseModel, ConfigDict, Field

from services.http.deps import AUTH, GUARDED, Rt, not_running, problems
from services.runs.protocol import CalibrationRun
from services.runs.state import RunStatus
from swpc_hw.errors import DatasetError

router = APIRouter()
RESPONSES = {**GUARDED, **problems(404, _409="the run does not wait for this")}


class ReferenceIn(BaseModel):
    """A known quantity with its std dev (SI), as an entry of ``references.yaml``."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    kind: Literal["axis_distance", "wheel_radius", "straight_drive"]
    value: float = Field(description="m: the distance or radius measured")
    stddev: float = Field(description="m: the measurement's std dev")
    modules: list[int] | None = Field(
        None, description="axis_distance: the two modules whose steering axes were measured"
    )
    module: int | None = Field(None, description="wheel_radius: the module")
    start: float | None = Field(None, description="not given: the run's drive sets it")
    end: float | None = Field(None, description="not given: the run's drive sets it")

    def entry(self) -> dict[str, Any]:
        return self.model_dump(exclude_none=True)


class ReferencesRequest(BaseModel):
    model_config = ConfigDict(extra="forbid")

    references: list[ReferenceIn] = Field(min_length=1)


def entries(refs: Sequence[ReferenceIn]) -> list[dict[str, Any]]:
    return [r.entry() for r in refs]


def refused(where: str, exc: Exception) -> RequestValidationError:
    """A 422 in the shape of FastAPI's own (one schema for 422)."""
    return RequestValidationError(
        [{"loc": ["body", where], "msg": str(exc), "type": "value_error"}]
    )


def _running(rt: Rt, run_id: str) -> CalibrationRun:
    run = rt.runs.get(run_id)
    if run is None:
        raise not_running(rt, run_id)
    return run


@router.post(
    "/calibrations/{run_id}/continue",
    response_model=RunStatus,
    dependencies=AUTH,
    responses=RESPONSES,
)
def continue_run(run_id: str, rt: Rt) -> dict[str, Any]:
    """The floor is marked under the first module's steering axis (MARK): drive."""
    run = _running(rt, run_id)
    try:
        run.answer("continue")
    except ValueError as exc:
        raise HTTPException(409, str(exc)) from exc
    return run.status.to_dict()


@router.post(
    "/calibrations/{run_id}/references",
    response_model=RunStatus,
    dependencies=AUTH,
    responses=RESPONSES,
)
def add_references(run_id: str, body: ReferencesRequest, rt: Rt) -> dict[str, Any]:
    """The tape measurements (MEASURE): the straight drive's length with its std dev
    (``{"kind": "straight_drive", "value": 4.0012, "stddev": 0.0005}``), and any
    further axis_distance or wheel_radius."""
    run = _running(rt, run_id)
    try:
        run.answer("references", entries(body.references))
    except DatasetError as exc:
        raise refused("references", exc) from exc
    except ValueError as exc:
        raise HTTPException(409, str(exc)) from exc
    return run.status.to_dict()
