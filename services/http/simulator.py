"""The in-process simulator's own route: it plays the operator's tape.

* ``GET /simulator/tape-measure?run=<id>``: the distance the first module's steering axis
  truly travelled between the run's straight drive's start and end, plus a tape's error
  (``stddev``, default 0.5 mm), as the reference to post to
  ``/calibrations/{id}/references``.
* ``GET /simulator/axis-distances``: the distances between the steering axes of every pair
  of modules, each read twice with the tape's error: the references a run without motion
  capture starts with (``axis_distance``).
* ``GET /simulator/reached?run=<id>``: a DONE calibration against the simulator's hidden
  truth, weighed by the run's own covariance: what it reached where its forecast said
  (:func:`swpc_hw.calibration.plan.square_error.against_truth`; the console shows it
  under the result).

The router is included only when the service runs its in-process simulator: never against
a robot.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from fastapi import APIRouter, HTTPException, Query
from pydantic import BaseModel

from services.http.deps import Rt, done_result, problems
from services.plan.planner import default_budget
from simulators.offline.datagen_imu import ReferenceOptions
from swpc_hw.calibration.plan.square_error import (
    SQUARE_SHARE,
    against_truth,
    square_path_quantile,
    square_path_sensitivity,
    square_path_within,
)
from swpc_hw.errors import KinematicFileError
from swpc_hw.files.kinematic_file import load_kinematics
from swpc_hw.robot.frames import DESIGN_FIT, params_in_design_fit

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


class KindReached(BaseModel):
    """One kind of parameter against the truth (mm, deg)."""

    kind: str
    largest: float
    unit: str
    rms_z: float


class Reached(BaseModel):
    """A calibration against the simulator's truth (:func:`reached`)."""

    run: str
    frame: str
    kinds: list[KindReached]
    nees: float
    dof: int
    square_position_mm: float
    square_heading_deg: float
    forecast_position_mm: float
    forecast_heading_deg: float
    budget_position_mm: float | None
    budget_heading_deg: float | None
    bound_position_mm: float | None
    """The end position error ``share_percent`` of runs stay within by the result's own
    covariance (None without a budget)."""
    bound_heading_deg: float | None
    share_percent: float | None
    within_budget: bool | None
    """The square path's end position and heading both within the budget."""
    note: str = (
        "simulated: the run's result against the in-process simulator's hidden truth. nees "
        "is e' C^+ e / dof over the run's whole covariance (about 1 when it is honest); "
        "rms_z per kind; the square path's end error the result makes beside its forecast "
        "from the same covariance (a std dev), the bound share_percent of runs stay "
        "within by that covariance, the budget a plan keeps them within, and whether "
        "this run is within it"
    )


@router.get("/simulator/reached", response_model=Reached, responses=problems(404, 409))
def reached(
    rt: Rt, run: Annotated[str, Query(description="a DONE calibration of this service")]
) -> Reached:
    """A DONE calibration's result against the simulator's hidden truth (in the result's
    frame: the truth re-expressed in design-fit for a run without motion capture)."""
    if rt.simulator is None:
        raise HTTPException(404, "no in-process simulator")
    done_result(rt, run)
    try:
        kf = load_kinematics(Path(rt.settings.data_dir) / "runs" / run / "kinematics.yaml")
    except KinematicFileError as exc:
        raise HTTPException(409, f"calibration {run}: its result file: {exc}") from exc
    if kf.covariance is None:
        raise HTTPException(409, f"calibration {run}: its result has no covariance")
    nominal, truth = rt.config.nominal, rt.simulator.truth
    if kf.params.frame == DESIGN_FIT:
        truth = params_in_design_fit(truth, nominal)[0]
    C = np.asarray(kf.covariance, dtype=float)
    S = square_path_sensitivity(nominal)
    try:
        a = against_truth(kf.params, C, truth, nominal, S)
    except ValueError as exc:
        raise HTTPException(409, f"calibration {run}: {exc}") from exc
    show = {"position": (1e3, "mm"), "beta": (math.degrees(1.0), "deg"), "radius": (1e3, "mm")}
    budget = default_budget("imu" if kf.params.frame == DESIGN_FIT else "mocap")
    bound = None if budget is None else square_path_quantile(S, C, budget)
    return Reached(
        run=run,
        frame=kf.params.frame,
        kinds=[
            KindReached(kind=k, largest=v * show[k][0], unit=show[k][1], rms_z=a.rms_z[k])
            for k, v in a.largest.items()
        ],
        nees=a.nees,
        dof=a.dof,
        square_position_mm=a.square[0] * 1e3,
        square_heading_deg=math.degrees(a.square[1]),
        forecast_position_mm=a.square_forecast[0] * 1e3,
        forecast_heading_deg=math.degrees(a.square_forecast[1]),
        budget_position_mm=None if budget is None else budget[0] * 1e3,
        budget_heading_deg=None if budget is None else math.degrees(budget[1]),
        bound_position_mm=None if bound is None else bound[0] * 1e3,
        bound_heading_deg=None if bound is None else math.degrees(bound[1]),
        share_percent=None if bound is None else SQUARE_SHARE * 100,
        within_budget=None if budget is None else square_path_within(a.square, budget),
    )
