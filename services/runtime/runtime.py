"""What the service holds while it runs: clock, bus, driver, zenoh session, mocap, runs.

Opened by ``swpc serve`` before its HTTP server starts (so that an error opening it is
one line on stderr), else in the FastAPI lifespan, and injected into the app, so tests
run the real app against the in-process simulator.  With no CAN interface configured
(``SWPC_CAN_INTERFACE`` unset) it runs on the *in-process simulator*: the virtual robot in
this process on a python-can ``virtual`` bus and zenoh on a loopback endpoint, in
simulated time (one :class:`swpc_hw.clock.SimClock` shared by the simulator, the driver,
the mocap ingest and the calibration runs).  Otherwise the clock is the host's, scaled by
``time_scale`` for an external simulator (:mod:`services.config.timing`).

Long-running resources are bounded: one service per data dir and per CAN channel
(:mod:`services.store.locks`, taken before anything is touched); the CAN traffic goes to a
rolling log of at most ``SWPC_CAN_LOG_BYTES`` in ``<data dir>/can/`` (every frame during
a run; between runs, the periodic frames once per ``SWPC_CAN_LOG_IDLE_PERIOD`` per CAN id
and every event) plus one recording per run; a run starts only within the disk budget
(:mod:`services.store.disk`) and fails when the disk fills.  A run's state that cannot be
saved (the store unwritable) ends the run FAILED; what the API lists is then the
in-memory state, saved again once the store takes writes.
"""

from __future__ import annotations

import contextlib
import grp
import logging
import os
import secrets
import stat
import sys
import threading
import time
import uuid
from pathlib import Path
from typing import Any

from services.config.robot import RobotConfig, load_robot_config
from services.config.settings import ServiceSettings, SettingsError
from services.config.timing import TimingBudget, robot_drives, timing_budget
from services.plan.planner import Planner
from services.runs.protocol import CalibrationRun
from services.runs.state import TERMINAL, now_iso
from services.runtime.errors import NoResultError
from services.runtime.events import EventBus
from services.runtime.launch import RunLauncher
from services.runtime.simulator import in_process_simulator, simulated_robot
from services.sensors.gyro import GyroIngest
from services.sensors.mocap import MocapIngest, SourceStatus
from services.store.locks import ChannelLock, DataDirLock
from services.store.logs import event
from services.store.runs import RunStore
from simulators.virtual_robot import VirtualRobot
from swpc_hw.clock import Clock, SimClock, SystemClock
from swpc_hw.drives.interface import Drives
from swpc_hw.files.kinematic_file import load_kinematics, load_robot
from swpc_hw.sensors.mocap import source_key
from swpc_hw.sensors.zenoh_session import (
    ZenohAuth,
    connect_endpoints,
    free_tcp_endpoint,
    open_session,
    publishers_acl,
)

SWITCH_INTERVAL_S = 0.001
SIM_USER = "simulator"
"""The in-process simulator's zenoh user: the only publisher of the robot's sensor keys."""
SIM_LINK_TIMEOUT_S = 10.0
"""Wall seconds the service waits for the in-process simulator's zenoh link to hear it
before its simulation starts anyway (then /health says motion capture stale, with why)."""
FIRST_CONTACT_RETRY_S = 5.0
"""Wall seconds between two attempts of the drives' first contact (drives silent until
set up, :meth:`Runtime._first_contact`)."""
ZENOH_USERS_FILE = ".zenoh-users"
"""In the data dir while the in-process simulator runs: its zenoh credential (0600)."""
log = logging.getLogger("swpc.service")


def give_group(path: Path, gid: int, bits: int) -> None:
    """``path`` gets the group ``gid`` and the mode bits ``bits``, each only if it lacks
    them: under the unit (``SystemCallFilter=~@privileged``) every chown is refused, even
    one that changes nothing, and systemd's StateDirectory= already has the right owner."""
    st = path.stat()
    if st.st_gid != gid:
        os.chown(path, -1, gid)
    mode = stat.S_IMODE(st.st_mode)
    if mode | bits != mode:
        os.chmod(path, mode | bits)


class Runtime(RunLauncher):
    """Owns every long-lived resource of the service; :meth:`close` is idempotent.  Its
    runs: :class:`~services.runtime.records.RunRecords`, started by
    :class:`~services.runtime.launch.RunLauncher`."""

    def __init__(self, settings: ServiceSettings, config: RobotConfig | None = None) -> None:
        self.settings = settings
        self.config = config or load_robot_config(settings.robot_config)
        if settings.can_log_bytes and settings.can_log_bytes * 2 > settings.disk_budget:
            raise SettingsError(
                f"SWPC_CAN_LOG_BYTES ({settings.can_log_bytes}) must be at most half of "
                f"SWPC_DISK_BUDGET ({settings.disk_budget})"
            )
        # what the settings alone decide first: an error here leaves nothing to undo
        self.timing: TimingBudget = timing_budget(settings, self.config)
        self.planner = Planner()  # plans of {"plan": "auto"} runs, made in the background
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
        self.mocap_source = SourceStatus()  # the status of a lab's bridge (swpc mocap)
        # the robot's gyro (a run without motion capture), stamped with wall time
        self.gyro = GyroIngest(clock=self.clock, stale_after=self.timing.mocap_stale)
        self.data_dir = settings.ensure_data_dir()
        # before anything in the data dir is touched: a second service stops here
        self.dir_lock = DataDirLock(self.data_dir).acquire()
        self.channel_lock: ChannelLock | None = None
        try:
            self._apply_file_group()
            self.store = RunStore(self.data_dir / "runs.sqlite")
            self.interrupted = self.store.mark_interrupted(found=now_iso())
        except BaseException:
            self.dir_lock.release()
            raise
        for rid in self.interrupted:
            event(log, logging.WARNING, "run.interrupted", run=rid)
        self.store_error: str | None = None
        self._unsaved: set[str] = set()
        self._plot_lock = threading.Lock()
        self.runs: dict[str, CalibrationRun] = {}
        self.current: CalibrationRun | None = None
        self.events = EventBus()  # every run change, for the console's event stream
        self.lock = threading.Lock()
        """Held to start a run and to install a kinematic file: an install never lands
        while a run exists, and a run never starts during an install."""
        self.simulator: VirtualRobot | None = None
        self.can_channel = settings.can_channel
        self.can_interface = settings.can_interface or "virtual"
        self.session: Any = None
        self.zenoh_endpoints: list[str] = []
        """The endpoints the zenoh session listens on or connects to, once open."""
        self.zenoh_connect: list[str] = []
        """The endpoints the zenoh session connects to (settings or its config file): with
        none linked, ``/health`` says so."""
        self._sim_password = ""
        self._zenoh_users: Path | None = None
        self.drives: Drives | None = None
        self.started = time.time()
        self._opened = False
        self._closed = False
        self._contact: threading.Thread | None = None
        self._contact_stop = threading.Event()

    def _apply_file_group(self) -> None:
        """``SWPC_FILE_GROUP``: the data dir gets the group, group read and search, and
        the kinematic file and its backups, if any, the group too.  New files get the
        group as the service's primary group (the unit's ``Group=``), else from the data
        dir's setgid bit, set here (the unit's ``RestrictSUIDSGID=`` would refuse it)."""
        name = self.settings.file_group
        if not name:
            return
        try:
            gid = grp.getgrnam(name).gr_gid
        except KeyError:
            raise SettingsError(f"SWPC_FILE_GROUP: no group named {name!r}") from None
        setgid = 0 if os.getegid() == gid else stat.S_ISGID
        targets = [self.data_dir] + [
            d for d in (self.data_dir / "runs", self.data_dir / "can") if d.is_dir()
        ]
        kin = self.settings.kinematics_file
        try:
            for d in targets:
                give_group(d, gid, setgid | 0o050)
            for f in kin.parent.glob(f"{kin.stem}*{kin.suffix}"):
                if f.is_file():
                    give_group(f, gid, 0o040)
        except PermissionError as exc:
            raise SettingsError(
                f"SWPC_FILE_GROUP={name}: cannot give {exc.filename} the group (the service "
                "must own it and have the group: Group= in its unit, as deploy/systemd/"
                "swpc-service.service)"
            ) from None

    # ---------------------------------------------------------------- lifecycle
    def open(self) -> Runtime:
        """Open the CAN channel (its lock first), zenoh, the driver and, with no CAN
        interface, the in-process simulator.  On an error what was opened is closed again
        (the data dir's lock too) and the error raised: ``swpc serve`` calls this before
        the HTTP server starts, so that it is one line on stderr."""
        try:
            return self._open()
        except BaseException:
            self.close()
            raise

    def _open(self) -> Runtime:
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
        else:
            self.channel_lock = ChannelLock(interface, channel).acquire()
        self.can_channel, self.can_interface = channel, interface
        can_log = None
        if s.can_log_bytes:
            (self.data_dir / "can").mkdir(exist_ok=True)
            can_log = self.data_dir / "can" / "can.log"
        self.can_log = can_log
        guard = self._zenoh_guard(listen, connect)
        self.session = open_session(
            mode=s.zenoh_mode,
            listen=listen,
            connect=connect,
            config_file=s.zenoh_config_file,
            auth=guard,
            acl=None
            if guard is None
            else publishers_acl(
                [self.config.pose_key, self.config.imu_key, source_key(self.config.robot)],
                [SIM_USER] if s.in_process else s.zenoh_publishers,
            ),
        )
        self.zenoh_endpoints = listen or connect
        self.zenoh_connect = connect_endpoints(connect, s.zenoh_config_file)
        self.mocap.subscribe(self.session, self.config.pose_key)
        self.mocap_source.subscribe(self.session, source_key(self.config.robot))
        if s.metrology != "mocap":
            self.gyro.subscribe(self.session, self.config.imu_key)
        self.drives = robot_drives(
            s,
            self.config,
            interface=interface,
            channel=channel,
            clock=self.clock,
            log_path=can_log,
            log_total_bytes=int(s.can_log_bytes) or None,
        )
        self.drives.configure()
        event(
            log,
            logging.INFO,
            "service.open",
            data_dir=str(self.data_dir.resolve()),
            can=f"{interface}:{channel}",
            in_process_simulator=s.in_process,
            can_log=None if can_log is None else str(can_log),
            can_log_bytes=int(s.can_log_bytes),
            can_log_idle_period=s.can_log_idle_period,
            disk_budget=int(s.disk_budget),
        )
        if s.in_process:
            assert isinstance(self.clock, SimClock)
            truth = None if s.sim_truth is None else load_robot(s.sim_truth)
            if truth is not None and truth.ids != self.config.nominal.ids:
                raise SettingsError(
                    f"SWPC_SIM_TRUTH: {s.sim_truth} has modules {truth.ids}, the robot "
                    f"config {self.config.nominal.ids}"
                )
            built, wiring = simulated_robot(s, self.config)
            self.simulator = in_process_simulator(
                config=built,
                channel=channel,
                zenoh_endpoints=listen or connect,
                zenoh_auth=None if guard is None else ZenohAuth(SIM_USER, self._sim_password),
                clock=self.clock,
                seed=s.sim_seed,
                truth=truth,
                physics_dt=s.sim_physics_dt,
                mocap_latency=s.sim_mocap_latency,
                mocap_qtm_port=s.sim_mocap_qtm_port,
                feedback_rate_hz=s.feedback_rate_hz,
                gyro=s.sim_gyro,
                wiring=wiring,
            )
            # the link up before time flows: the run's first poses are then the same
            # whatever the wall time zenoh takes (bit for bit the same seed, the same run)
            deadline = time.monotonic() + SIM_LINK_TIMEOUT_S
            while not self.simulator.heard() and time.monotonic() < deadline:
                time.sleep(0.01)
            self.simulator.start()
        elif getattr(self.drives, "silent_until_set_up", False):
            self._contact = threading.Thread(
                target=self._first_contact, name="swpc-first-contact", daemon=True
            )
            self._contact.start()
        self._opened = True
        return self

    def _first_contact(self) -> None:
        """Drives silent until set up (CiA 402 from the factory) brought up at start and
        left inactive: from then on they heartbeat, and /health watches them between runs.
        Nothing moves (no axis is enabled).  Tried again every
        :data:`FIRST_CONTACT_RETRY_S` while it fails (drives powered after the service) and
        no run has started; each failure is logged, /health says the drives are silent,
        and a run's CONNECT brings them up itself."""
        assert self.drives is not None
        while not self._contact_stop.is_set():
            try:
                self.drives.activate()
                self.drives.deactivate()
            except Exception as exc:  # CanError, LifecycleError: said, not raised
                error = f"{type(exc).__name__}: {exc}"
                event(log, logging.WARNING, "drives.contact", ok=False, error=error)
                self._contact_stop.wait(FIRST_CONTACT_RETRY_S)
            else:
                event(log, logging.INFO, "drives.contact", ok=True)
                return

    def _zenoh_guard(self, listen: list[str], connect: list[str]) -> ZenohAuth | None:
        """Who may connect to this service's zenoh session, and publish its robot's sensor
        keys (zenoh's authentication and access control, :mod:`swpc_hw.sensors.zenoh_session`):

        * against the in-process simulator on its own loopback endpoint: the simulator
          only, with a password made for this run of the service (kept in a file of the
          data dir readable by the service alone, removed at close);
        * with ``SWPC_ZENOH_USERS_FILE``: the peers it lists, of which only
          ``SWPC_ZENOH_PUBLISHERS`` may publish the poses and the gyro;
        * else nobody is checked (a service that connects to a mocap PC or a router
          trusts it: that peer's listener is what requires authentication,
          deploy/zenoh/mocap-peer.json5)."""
        s = self.settings
        if s.in_process and listen and not connect:
            self._sim_password = secrets.token_urlsafe(24)
            path = self.data_dir / ZENOH_USERS_FILE
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
            with os.fdopen(fd, "w", encoding="utf-8") as fh:
                fh.write(f"{SIM_USER}:{self._sim_password}\n")
            self._zenoh_users = path
            return ZenohAuth(users_file=str(path))
        if s.zenoh_users_file is not None:
            if connect:
                raise SettingsError(
                    "SWPC_ZENOH_USERS_FILE guards the peers that connect to this service; "
                    "the peers it connects to (SWPC_ZENOH_CONNECT) cannot be checked by "
                    "it: require authentication on their listener instead"
                )
            return ZenohAuth(users_file=str(s.zenoh_users_file))
        return None

    def close(self, reason: str = "the service was stopped during the run") -> None:
        """Stop everything; a run in progress ends FAILED with ``reason``."""
        if self._closed:
            return
        self._closed = True
        run = self.current
        if run is not None and not run.finished:
            run.shutdown(reason)
            run.join(5.0)
        if self._contact is not None:
            self._contact_stop.set()
            self._contact.join(5.0)
        if self.drives is not None:
            with contextlib.suppress(Exception):
                self.drives.stop_all()
            self.drives.shutdown()
        self.mocap.close()
        self.mocap_source.close()
        self.gyro.close()
        if self.simulator is not None:
            self.simulator.stop()
        if isinstance(self.clock, SimClock):
            self.clock.close()
        if self.session is not None:
            with contextlib.suppress(Exception):
                self.session.close()
        if self._zenoh_users is not None:
            with contextlib.suppress(OSError):
                self._zenoh_users.unlink()
        self._save_unsaved()
        self.store.close()
        if self.channel_lock is not None:
            self.channel_lock.release()
        self.dir_lock.release()
        if self._opened:
            event(log, logging.INFO, "service.close")

    # ------------------------------------------------------------------ plot, kinematics
    def plot_path(self, run_id: str) -> Path:
        return self.data_dir / "runs" / run_id / "plot.png"

    def plot(self, run_id: str) -> Path | None:
        """The run's plot, rendered once and then served from ``runs/<id>/plot.png``
        (also after a restart: the result is solved again from the run's dataset).
        ``None``: no such run; :class:`NoResultError`: not DONE."""
        st = self.status(run_id, "calibration")
        if st is None:
            return None
        if st["state"] != "DONE":
            raise NoResultError(f"calibration {run_id} is {st['state']}: no result to plot")
        path = self.plot_path(run_id)
        with self._plot_lock:  # one rendering at a time; every later request reads the file
            if path.is_file():
                return path
            from services.runs.install import solve_run
            from services.runs.plots import calibration_plot
            from swpc_hw.files.dataset import load_dataset
            from swpc_hw.files.kinematic_file import atomic_write_bytes

            run = self.runs.get(run_id)
            result = run.result if run is not None else None
            if result is None:
                result = solve_run(path.parent)
            png = calibration_plot(load_dataset(path.parent / "dataset"), result)
            atomic_write_bytes(path, png)
        return path

    def kinematics_document(self) -> dict[str, Any] | None:
        """The kinematic file in force as a document (``None``: none installed); a file
        that does not load raises :class:`KinematicFileError` naming the problem."""
        path = self.settings.kinematics_file
        if not os.path.lexists(path):  # a dangling link is there, and unreadable
            return None
        k = load_kinematics(path)
        from swpc_hw.files.kinematic_file import kinematics_document

        doc = kinematics_document(k.params, created=k.created, extra=k.extra)
        doc["path"] = str(path)
        return doc

    # ------------------------------------------------------------------ health
    def running(self) -> bool:
        return self.current is not None and self.current.status.state not in TERMINAL
