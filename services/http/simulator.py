"""The in-process simulator's own route: it plays the operator's tape.

* ``GET /simulator/tape-measure?run=<id>``: the distance the first module's steering axis
  truly travelled between the run's straight drive's start and end, plus a tape's error
  (``stddev``, default 0.5 mm), as the reference to post to
  ``/calibrations/{id}/references``.
* ``GET /simulator/axis-distances``: the distances between the steering axes of every pair
  of modules, each read twice with the tape's error: the references a run without motion
  capture starts with (``axis_distance``).

The router is included only when the service runs its in-process simulator: never against
a robot.
"""

from __future__ import annotations

import math
from typing import Annotated, Literal

from fastapi import APIRouter, HTTPException, Query
from pydantic import BaseModel

from services.http.deps import Rt, problems
from simulators.offline.datagen_imu import ReferenceOptions

router = APIRouter()

Seed = Annotated[int, Query(ge=0, le=2**63 - 1, description="the tape's random seed")]
"""A simulated tape's seed: a non-negative integer numpy's generators take."""
DEFAULT_TAPE_STDDEV = ReferenceOptions.stddev
"""m: the simulated tape's error (1 sigma) unless the request says otherwise."""


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


@router.get("/simulator/tape-measure", response_model=TapeMeasure, responses=problems(404, 409))
def tape_measure(
    rt: Rt,
    run: Annotated[str, Query(description="the run whose straight drive to measure")],
    stddev: Annotated[float, Query(gt=0, le=0.1)] = DEFAULT_TAPE_STDDEV,
    seed: Seed = 0,
) -> TapeMeasure:
    """The simulated operator's tape measurement of a run's straight drive (the true
    travel plus ``N(0, stddev^2)``, seeded)."""
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


class AxisDistanceReading(BaseModel):
    """One pair of modules' steering axes, as the simulated tape reads it (m)."""

    kind: Literal["axis_distance"] = "axis_distance"
    modules: tuple[int, int]
    value: float
    stddev: float


class AxisDistances(BaseModel):
    """Every pair's readings, as references for ``POST /calibrations``."""

    references: list[AxisDistanceReading]
    note: str = (
        "simulated: the in-process simulator's true distance between the two steering axes, "
        "plus the tape's error, each pair read twice"
    )


@router.get("/simulator/axis-distances", response_model=AxisDistances, responses=problems(404))
def axis_distances(
    rt: Rt,
    stddev: Annotated[float, Query(gt=0, le=0.1)] = DEFAULT_TAPE_STDDEV,
    seed: Seed = 0,
) -> AxisDistances:
    """The simulated operator's tape between the steering axes (true distance plus
    ``N(0, stddev^2)``, seeded), each pair read twice."""
    if rt.simulator is None:
        raise HTTPException(404, "no in-process simulator")
    return AxisDistances(references=[
        AxisDistanceReading(modules=(a, b), value=v, stddev=stddev)
        for a, b, values in rt.simulator.axis_distances(stddev, seed)
        for v in values
    ])  # fmt: skip
