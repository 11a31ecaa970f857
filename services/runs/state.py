"""A calibration run's vocabulary: its states and their transitions, what an operator
sees of a run (:class:`RunStatus`) and the errors that end one.

The protocol that walks these states is :mod:`services.runs.protocol` (with motion
capture) and :mod:`services.runs.metrology.imu` (without: the states STILL, STEER, MARK, DRIVE and
MEASURE are its own).
"""

from __future__ import annotations

import datetime as _dt
from enum import StrEnum
from typing import Any, Literal

from pydantic import BaseModel, Field

from services.config.robot import RunKind


class State(StrEnum):
    PENDING = "PENDING"
    CONNECT = "CONNECT"
    PRECHECK = "PRECHECK"
    REST = "REST"
    PROBE = "PROBE"
    LOCK = "LOCK"
    ALIGN = "ALIGN"
    FREE = "FREE"
    SPIN = "SPIN"
    STOP = "STOP"
    RESTEER = "RESTEER"
    RELEASE = "RELEASE"
    STILL = "STILL"
    STEER = "STEER"
    MARK = "MARK"
    DRIVE = "DRIVE"
    MEASURE = "MEASURE"
    SOLVE = "SOLVE"
    WRITE = "WRITE"
    DONE = "DONE"
    FAILED = "FAILED"
    ABORTED = "ABORTED"


TERMINAL = frozenset({State.DONE, State.FAILED, State.ABORTED})
MOTION = frozenset(
    {
        State.REST,
        State.PROBE,
        State.ALIGN,
        State.FREE,
        State.SPIN,
        State.STOP,
        State.RESTEER,
        State.STILL,
        State.STEER,
        State.DRIVE,
    }
)
OPERATOR = frozenset({State.MARK, State.MEASURE})
"""States that wait for the operator (without motion capture: the floor marks of the
straight drive)."""

TRANSITIONS: dict[State, frozenset[State]] = {
    State.PENDING: frozenset({State.CONNECT}),
    State.CONNECT: frozenset({State.PRECHECK}),
    State.PRECHECK: frozenset({State.REST}),
    State.REST: frozenset({State.LOCK, State.PROBE}),
    State.PROBE: frozenset({State.PROBE, State.LOCK, State.SOLVE}),
    State.LOCK: frozenset({State.ALIGN}),
    State.ALIGN: frozenset({State.FREE}),
    State.FREE: frozenset({State.SPIN, State.STILL}),
    State.STILL: frozenset({State.SPIN, State.SOLVE, State.STEER}),
    State.SPIN: frozenset({State.STOP}),
    State.STOP: frozenset({State.RESTEER, State.RELEASE}),
    State.RESTEER: frozenset({State.SPIN, State.STILL}),
    State.RELEASE: frozenset({State.LOCK, State.SOLVE, State.STILL}),
    State.STEER: frozenset({State.MARK}),
    State.MARK: frozenset({State.DRIVE}),
    State.DRIVE: frozenset({State.MEASURE}),
    State.MEASURE: frozenset({State.SOLVE}),
    State.SOLVE: frozenset({State.WRITE}),
    State.WRITE: frozenset({State.DONE}),
}


class RunFailedError(Exception):
    """A fault: the run ends FAILED with this reason."""


class RunAbortedError(Exception):
    """The operator aborted: the run ends ABORTED."""


class PersistError(RunFailedError):
    """The run's state could not be saved (the run store): the run ends FAILED."""


class Forecast(BaseModel):
    """A planned run's std devs forecast from its data so far (sequential stopping,
    docs/plan.md): the worst per kind over the modules and the square path's end error
    that the requirement's share of runs stay within, against the plan's targets (mm,
    deg)."""

    position_mm: float | None = None
    beta_deg: float | None = None
    radius_mm: float | None = None
    square_position_mm: float | None = None
    square_heading_deg: float | None = None
    ratio: float | None = None
    """The spin in progress: the largest std dev over its target on what the spin informs
    (<= 1: met, the spin may end); before the first spin: the plan's on everything."""
    targets: dict[str, float | None] = Field(default_factory=dict)
    """The plan's requirement (``position_mm``, ``beta_deg``, ``radius_mm``,
    ``square_position_mm``, ``square_heading_deg``, ``square_share_percent``)."""


class RunStatus(BaseModel):
    """What an operator sees of a run (``GET /calibrations/{id}``)."""

    id: str
    created: str
    kind: RunKind = "calibration"
    """A calibration (``/calibrations``), a check of the file in force (``/checks``,
    docs/check.md) or a commissioning (``/commissions``, docs/commissioning.md): the same
    machinery."""
    state: State = State.PENDING
    metrology: str = "mocap"
    step: str = "waiting to start"
    module: int | None = None
    module_index: int = 0
    modules_total: int = 0
    angle_deg: float | None = None
    angle_index: int = 0
    angles_total: int = 0
    progress: float = 0.0
    sweep_deg: float = 0.0
    poses: int = 0
    gyro_samples: int = 0
    encoder_samples: int = 0
    segments: int = 0
    errors: list[str] = Field(default_factory=list)
    reason: str | None = None
    started: str | None = None
    finished: str | None = None
    installed: bool | None = None
    verdict: Literal["consistent", "drifted", "right", "miswired"] | None = None
    """A check once DONE: does the robot still match the file (consistent, drifted); a
    commissioning: does the robot match its config (right, miswired).  The result says
    more."""
    drive_m: float | None = None
    """Without motion capture: how far the straight drive has gone (m, nominal radii)."""
    notes: list[str] = Field(default_factory=list)
    """What the operator should know that does not stop the run (e.g. a straight drive
    steered by the nominal betas), each once, as the run's log says it too."""
    waits_for: Literal["continue", "references"] | None = None
    """What the run waits for from its operator now, if anything: ``continue`` (MARK:
    ``POST /calibrations/{id}/continue``) or ``references`` (MEASURE: ``POST
    /calibrations/{id}/references``); the step says it in words."""
    elapsed_s: float | None = None
    """Robot time since the run started (s)."""
    forecast: Forecast | None = None
    """A planned run (``plan: auto``): its std devs forecast from the data so far, updated
    during every spin; None otherwise."""
    remaining_s: float | None = None
    """Robot time the steps left of the protocol's plan should take (s), estimated
    (:meth:`services.runs.machine.RunMachine.remaining`); None when it cannot be: before
    the first spin has ended, past the plan (the operator's steps without motion
    capture), after the run."""

    def to_dict(self) -> dict[str, Any]:
        return self.model_dump(mode="json")


def now_iso() -> str:
    """The host's UTC time, ISO 8601 to the millisecond (a run's created/started/finished:
    for people, never judged)."""
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")
