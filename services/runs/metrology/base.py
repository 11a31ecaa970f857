"""What measures the robot's motion during a run, and the steps that depend on it.

A calibration run (:class:`services.runs.protocol.CalibrationRun`) is one protocol; its
*metrology* is a part it holds, not a subclass: motion capture
(:class:`services.runs.metrology.mocap.MocapMetrology`) or the IMU's gyro with the wheel encoders
and a tape measure (:class:`services.runs.metrology.imu.ImuMetrology`).  The protocol asks its
metrology, at fixed points, what only the metrology knows:

* before any motion: what makes the run impossible (:meth:`Metrology.run_problems`);
* PRECHECK: is the sensor ready (:meth:`Metrology.precheck`); during motion, can it still
  be trusted (:meth:`Metrology.problem`, at every poll);
* REST: when is the robot still (:meth:`Metrology.come_to_rest`);
* before each SPIN (:meth:`Metrology.before_spin`: the gyro's STILL), the SPIN's sweep and
  its segment (:meth:`Metrology.spin`);
* after the last module (:meth:`Metrology.after_spins`: the gyro's straight drive and the
  operator's tape measurements) and just before SOLVE (:meth:`Metrology.before_solve`).

A metrology acts through :class:`RunSteps`, the run's step API (enter a state, check,
wait on robot time, record, log), and the run's robot; it keeps its own state (a gyro's
bias, the drive's times) for its one run.  A third metrology is a third class of this
shape, not a third subclass of a run.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, Protocol

from services.config.robot import RobotConfig
from services.runs.journal import RunJournal, SampleSource
from services.runs.state import RunStatus, State
from swpc_hw.clock import Clock
from swpc_hw.drives.robot_io import RobotIO
from swpc_hw.files.dataset import Dataset, Segment


class RunSteps(Protocol):
    """What a metrology may use of its run (:class:`services.runs.protocol.CalibrationRun`)."""

    @property
    def id(self) -> str: ...

    robot: RobotIO
    config: RobotConfig
    clock: Clock
    status: RunStatus
    journal: RunJournal
    poll: float
    """Robot seconds between two polls of a step."""

    def enter(self, state: State, step: str) -> None:
        """Enter ``state`` (along the protocol's transitions), its step text shown."""
        ...

    def check(self, motion: bool, deadline: float | None) -> None:
        """Abort, fault, sensor, step timeout: raises what ends the run."""
        ...

    def deadline(self) -> float:
        """Now plus the step timeout."""
        ...

    def wait_until(self, cond: Callable[[], bool], motion: bool) -> None:
        """Poll until ``cond()``, checking at every poll (step timeout)."""
        ...

    def set_status(self, **fields: Any) -> None:
        """Update the operator's view of the run (under its lock)."""
        ...

    def changed(self) -> None:
        """Save and publish the status now (a step text the operator must see)."""
        ...

    def event(self, level: int, name: str, **fields: Any) -> None:
        """A structured log line of the run (and a message in its MCAP)."""
        ...

    def record(self, force: bool = False) -> None:
        """The samples since the last batch to the run's recordings."""
        ...

    def add_segment(self, seg: Segment, sweep: float) -> None:
        """A finished spin's window (the solver's segment), logged and recorded."""
        ...

    def dataset(self) -> Dataset:
        """The run's dataset as recorded so far (its directory, as written)."""
        ...


class Metrology(Protocol):
    """What measures the robot's motion (module docstring)."""

    name: str
    """The API's ``metrology``: ``mocap`` or ``imu``."""
    sensor_name: str
    """The sensor as the operator reads of it (``mocap``, ``gyro``)."""
    samples_field: str
    """The :class:`~services.runs.state.RunStatus` field counting its recorded samples."""
    drive: tuple[float, float] | None
    """The straight drive's ``(start, end)`` on the run's clock, once driven (None: not
    driven, or a metrology that needs none)."""

    @property
    def sensor(self) -> SampleSource:
        """The ingest whose samples are recorded with the encoders."""
        ...

    def run_problems(self, config: RobotConfig) -> list[str]:
        """What makes a run with ``config`` impossible, found before any motion."""
        ...

    def start_fields(self) -> dict[str, Any]:
        """Its fields of the ``run.start`` log line."""
        ...

    def precheck(self) -> list[str]:
        """Why the sensor is not ready (PRECHECK); empty when it is."""
        ...

    def problem(self) -> str | None:
        """Why the sensor cannot be trusted now (checked at every poll during motion)."""
        ...

    def waits_for(self, state: State) -> str | None:
        """What the operator owes a run in ``state`` (``continue``, ``references``), if
        anything."""
        ...

    def answer(
        self, run_id: str, state: State, what: str, entries: Sequence[dict[str, Any]] = ()
    ) -> None:
        """The operator's answer ``what`` (with ``entries``) to run ``run_id`` in
        ``state``, from another thread; ValueError when the run does not wait for it,
        :class:`~swpc_hw.errors.DatasetError` for a bad entry."""
        ...

    def come_to_rest(self, run: RunSteps) -> None:
        """REST: every wheel braked until the robot is still."""
        ...

    def before_spin(self, run: RunSteps, k: int, dyn: list[int]) -> None:
        """Between the alignment (or re-steering) and a spin about module ``k``."""
        ...

    def spin(self, run: RunSteps, k: int) -> None:
        """SPIN about ``k`` until the sweep is reached; ends with
        :meth:`RunSteps.add_segment`."""
        ...

    def after_spins(self, run: RunSteps) -> None:
        """After the last module's RELEASE, before SOLVE."""
        ...

    def before_solve(self, run: RunSteps) -> None:
        """SOLVE's first step, before the dataset is closed and solved."""
        ...
