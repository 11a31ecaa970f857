"""The HTTP routes of a calibration without motion capture, and the simulator's tape.

* ``POST /calibrations/{id}/continue``: the operator has marked the floor under the
  first module's steering axis (the run waits in MARK); the robot then drives.
* ``POST /calibrations/{id}/references``: the operator's tape measurements (the run waits
  in MEASURE): the straight drive's length, and any further reference.
* ``GET /simulator/tape-measure?run=<id>``: the in-process simulator plays the operator's
  tape: the distance the first module's steering axis truly travelled between the
  drive's start and end, plus a tape's error (``stddev``, default 0.5 mm).  The route
  exists only when the service runs its in-process simulator: never against a robot.

The references' schema (:class:`ReferenceIn`) is also what ``POST /calibrations`` takes
with ``"metrology": "imu"`` (docs/dataset-format.md's ``references.yaml``; a
``straight_drive`` carries no times here: the run knows when it drove).
"""

from __future__ import annotations

import math
from collections.abc import Awaitable, Callable, Sequence
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Depends, HTTPException, Query, Request
from fastapi.exceptions import RequestValidationError
from pydantic import BaseModel, ConfigDict, Field

from services.runs.protocol import CalibrationRun
from services.runs.state import RunStatus
from services.runtime.runtime import Runtime
from swpc_hw.errors import DatasetError

DEFAULT_TAPE_STDDEV = 0.5e-3


class Problem(BaseModel):
    detail: str


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


class TapeMeasure(BaseModel):
    """What the simulated operator's tape reads, as a reference to post."""

    run: str
    kind: Literal["straight_drive"] = "straight_drive"
    value: float
    stddev: float
    start: float
    end: float
    note: str = (
        "simulated: the in-process simulator's true travel of the first module's steering "
        "axis between the drive's start and end, plus the tape's error"
    )


def entries(refs: Sequence[ReferenceIn]) -> list[dict[str, Any]]:
    return [r.entry() for r in refs]


def refused(where: str, exc: Exception) -> RequestValidationError:
    """A 422 in the shape of FastAPI's own (one schema for 422)."""
    return RequestValidationError(
        [{"loc": ["body", where], "msg": str(exc), "type": "value_error"}]
    )


async def _runtime(request: Request) -> Runtime:
    rt: Runtime = request.app.state.runtime
    return rt


Rt = Annotated[Runtime, Depends(_runtime)]


def _running(rt: Runtime, run_id: str) -> CalibrationRun:
    run = rt.runs.get(run_id)
    if run is None:
        if rt.status(run_id) is None:
            raise HTTPException(404, f"no calibration {run_id}")
        raise HTTPException(409, f"calibration {run_id} is not running")
    return run


def imu_router(auth: Callable[..., Awaitable[None]], in_process: bool) -> APIRouter:
    """The routes above; ``auth`` is the bearer-token dependency; ``in_process``: the
    service runs its in-process simulator (the tape-measure route exists only then)."""
    router = APIRouter()
    guarded: dict[int | str, dict[str, Any]] = {
        401: {"model": Problem},
        404: {"model": Problem},
        409: {"model": Problem, "description": "the run does not wait for this"},
    }

    @router.post(
        "/calibrations/{run_id}/continue",
        response_model=RunStatus,
        dependencies=[Depends(auth)],
        responses=guarded,
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
        dependencies=[Depends(auth)],
        responses=guarded,
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

    if in_process:

        @router.get(
            "/simulator/tape-measure",
            response_model=TapeMeasure,
            responses={404: {"model": Problem}, 409: {"model": Problem}},
        )
        def tape_measure(
            rt: Rt,
            run: Annotated[str, Query(description="the run whose straight drive to measure")],
            stddev: Annotated[float, Query(gt=0, le=0.1)] = DEFAULT_TAPE_STDDEV,
            seed: int = 0,
        ) -> TapeMeasure:
            """In-process simulator only: the simulated operator's tape measurement of a
            run's straight drive (the true travel plus ``N(0, stddev^2)``, seeded)."""
            if rt.simulator is None:
                raise HTTPException(404, "no in-process simulator")
            got = rt.runs.get(run)
            if got is None:
                raise HTTPException(404, f"no calibration {run} in this service")
            drive = got.metrology.drive
            if drive is None:
                raise HTTPException(409, f"calibration {run} has not driven straight")
            try:
                value = rt.simulator.tape_measure(*drive, stddev=stddev, seed=seed)
            except ValueError as exc:
                raise HTTPException(409, str(exc)) from exc
            if not math.isfinite(value):
                raise HTTPException(409, "no finite tape reading")
            return TapeMeasure(run=run, value=value, stddev=stddev, start=drive[0], end=drive[1])

    return router
