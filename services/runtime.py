"""What the service holds while it runs: clock, bus, driver, zenoh session, mocap, runs.

Opened in the FastAPI lifespan (or by tests) and injected into the app, so tests run
the real app against the in-process simulator.  With no CAN interface configured
(``SWPC_CAN_INTERFACE`` unset) it runs on the *in-process simulator*: the virtual robot in
this process on a python-can ``virtual`` bus and zenoh on a loopback endpoint, in
simulated time (one :class:`swpc_hw.clock.SimClock` shared by the simulator, the driver,
the mocap ingest and the calibration runs).  Otherwise the clock is the host's, scaled by
``time_scale`` for an external simulator (:mod:`services.timing`).
"""

from __future__ import annotations

import contextlib
import sys
import threading
import time
import uuid
from pathlib import Path
from typing import Any

from services.calibration_run import TERMINAL, CalibrationRun, State
from services.in_process_simulator import in_process_simulator
from services.mocap_ingest import MocapIngest
from services.robot_config import RobotConfig, load_robot_config
from services.robot_io import DriverRobotIO
from services.settings import ServiceSettings
from services.store import RunStore
from services.timing import TimingBudget, driver_config, timing_budget
from simulators.virtual_robot import Simulator
from swpc_hw.can.driver import CanDriver
from swpc_hw.clock import Clock, SimClock, SystemClock
from swpc_hw.zenoh_session import free_tcp_endpoint, open_session

SWITCH_INTERVAL_S = 0.001


class RunConflictError(RuntimeError):
    """A calibration is already running."""


class Runtime:
    """Owns every long-lived resource of the service; :meth:`close` is idempotent."""

    def __init__(self, settings: ServiceSettings, config: RobotConfig | None = None) -> None:
        self.settings = settings
        self.config = config or load_robot_config(settings.robot_config)
        self.data_dir = Path(settings.data_dir)
        self.data_dir.mkdir(parents=True, exist_ok=True)
        self.store = RunStore(self.data_dir / "runs.sqlite")
        self.interrupted = self.store.mark_interrupted()
        self.runs: dict[str, CalibrationRun] = {}
        self.current: CalibrationRun | None = None
        self._lock = threading.Lock()
        self.simulator: Simulator | None = None
        self.can_channel = settings.can_channel
        self.can_interface = settings.can_interface or "virtual"
        self.session: Any = None
        self.driver: CanDriver | None = None
        self.timing: TimingBudget = timing_budget(settings, self.config)
        self.clock: Clock = (
            SimClock(max_speed=settings.sim_speed)
            if settings.in_process
            else SystemClock(rate=settings.external_time_scale)
        )
        self.mocap = MocapIngest(
            clock=self.clock,
            encoding=settings.pose_encoding,
            stale_after=self.timing.mocap_stale,
            # the in-process simulator stamps its simulated wall time: exact
            clock_mode="wall" if settings.in_process else settings.mocap_clock,
        )
        self.started = time.time()
        self._closed = False

    # ---------------------------------------------------------------- lifecycle
    def open(self) -> Runtime:
        # An optimisation, not a correctness condition: safety paths (abort, driver
        # faults) hand off between threads sooner than the default 5 ms switch interval.
        sys.setswitchinterval(SWITCH_INTERVAL_S)
        s = self.settings
        listen, connect = list(s.zenoh_listen), list(s.zenoh_connect)
        channel = s.can_channel
        interface = s.can_interface or "virtual"
        if s.in_process:
            channel = f"swpc-sim-{uuid.uuid4().hex[:8]}"
            if not listen and not connect:
                listen = [free_tcp_endpoint()]
        self.can_channel, self.can_interface = channel, interface
        self.session = open_session(
            mode=s.zenoh_mode, listen=listen, connect=connect, config_file=s.zenoh_config_file
        )
        self.mocap.subscribe(self.session, self.config.pose_key)
        self.driver = CanDriver(
            driver_config(
                s,
                self.config,
                interface=interface,
                channel=channel,
                log_path=self.data_dir / f"can-{time.strftime('%Y%m%dT%H%M%S')}.log",
            ),
            clock=self.clock,
        )
        self.driver.configure()
        if s.in_process:
            assert isinstance(self.clock, SimClock)
            self.simulator = in_process_simulator(
                config=self.config,
                channel=channel,
                zenoh_endpoints=listen or connect,
                clock=self.clock,
                seed=s.sim_seed,
                physics_dt=s.sim_physics_dt,
                mocap_latency=s.sim_mocap_latency,
                feedback_rate_hz=s.feedback_rate_hz,
            )
            self.simulator.start()
        return self

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        run = self.current
        if run is not None and not run.finished:
            run.abort()
            run.join(5.0)
        if self.driver is not None:
            with contextlib.suppress(Exception):
                self.driver.stop_all()
            self.driver.shutdown()
        self.mocap.close()
        if self.simulator is not None:
            self.simulator.stop()
        if isinstance(self.clock, SimClock):
            self.clock.close()
        if self.session is not None:
            with contextlib.suppress(Exception):
                self.session.close()
        self.store.close()

    # --------------------------------------------------------------------- runs
    def start_run(self, config: RobotConfig, install: str) -> CalibrationRun:
        assert self.driver is not None
        with self._lock:
            if self.current is not None and not self.current.finished:
                raise RunConflictError(f"calibration {self.current.id} is still running")
            run = CalibrationRun(
                DriverRobotIO(self.driver),
                self.mocap,
                config,
                clock=self.clock,
                data_dir=self.data_dir,
                kinematics_path=self.settings.kinematics_file,
                install=install,
                on_change=self._persist,
            )
            self.runs[run.id] = run
            self.current = run
        self._persist(run)
        # raw CAN traffic of the run, beside its dataset (candump format, our DBC decodes it)
        (run.run_dir / "dataset").mkdir(parents=True, exist_ok=True)
        self.driver.start_recording(str(run.run_dir / "dataset" / "can.log"))
        run.start()
        return run

    def _persist(self, run: CalibrationRun) -> None:
        if run.finished and self.driver is not None and run is self.current:
            self.driver.stop_recording()
        self.store.upsert(run.id, run.status.created, run.status.to_dict())
        if run.status.state is State.DONE and run.result_doc is not None:
            self.store.set_result(run.id, run.result_doc)

    def status(self, run_id: str) -> dict[str, Any] | None:
        run = self.runs.get(run_id)
        if run is not None:
            return run.status.to_dict()
        got = self.store.get(run_id)
        return None if got is None else got[0]

    def result(self, run_id: str) -> tuple[str, dict[str, Any] | None] | None:
        """``(state, result document or None)``; None if the run is unknown."""
        run = self.runs.get(run_id)
        if run is not None:
            return str(run.status.state), run.result_doc
        got = self.store.get(run_id)
        if got is None:
            return None
        return str(got[0]["state"]), got[1]

    def list_runs(self) -> list[dict[str, Any]]:
        return list(self.store.list())

    def run_states(self) -> dict[str, int]:
        counts: dict[str, int] = {str(s): 0 for s in State}
        for st in self.store.list():
            counts[str(st["state"])] = counts.get(str(st["state"]), 0) + 1
        return counts

    def running(self) -> bool:
        return self.current is not None and self.current.status.state not in TERMINAL
