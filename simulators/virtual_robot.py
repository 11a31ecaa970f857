"""The virtual SWPC robot: controllers on CAN + physics + motion capture, on a simulated clock.

:class:`VirtualRobot` stands in for the robot's motor controllers (one
:class:`simulators.drives.swpc.VirtualController` per module, speaking the DBC's frames on
any python-can bus) and for the motion-capture system (poses over zenoh, see
:mod:`simulators.sensors.mocap`); :class:`simulators.physics.robot.RobotPhysics` moves the hidden
true
robot under what the controllers do.  It runs in one thread started by :meth:`start` and
ended by :meth:`stop` (idempotent), on a bus and a zenoh session that the caller gives or
that it opens itself (:meth:`VirtualRobot.open`, used by ``swpc sim`` and by the service's
in-process simulator).

Every tick of simulated time (``physics_dt``, at most 5 ms by default, and never longer than
the fastest feedback period the host has set, so 2 ms at 500 Hz):

1. each module's axes are turned into drives from their controller's state and mode
   (:func:`simulators.drives.base.axis_drive`): FREE/disabled/fault -> passive, HOLD ->
   locked (a held wheel is braked), POSITION -> a first-order loop on the true position
   (time constant ``position_tau``, clamped to MaxVelocity), VELOCITY -> the setpoint,
   TORQUE -> a wheel torque (a steering torque drives the steering through ``J dv/dt =
   tau - c v`` of the controller's axis), homing -> the steering turns at 0.5 rad/s;
2. the physics advances by one tick;
3. the encoders are written into the controllers: steering ``theta_hat = theta - beta``
   after homing (``+ sensor_position`` before: the power-up coordinate), wheel ``psi``
   plus slip, both quantised to ``steer_counts`` / ``wheel_counts`` per turn (the
   feedback frame then carries them at the DBC's resolution, which ``truth/params``
   reports as ``frame_steer_counts`` / ``frame_wheel_counts``; 2**17 per turn for both
   at the time of writing, so the defaults lose nothing on the wire);
4. mocap samples due in the tick are taken (exact SE(2) interpolation inside the tick)
   and published when their latency has elapsed; the truth pose when due;
5. the controllers run their firmware logic at the new time (watchdog, homing,
   heartbeat, feedback) and their frames go on the bus.

A received frame takes effect at the first tick at or after the simulated time of its
arrival (from its bus time stamp), never earlier: commands act within one tick, and a
simulation that lags and catches up does not shorten the watchdog.

Time
----
On a :class:`swpc_hw.clock.SimClock` (``clock=``; the service's in-process simulator, the
validation drive) the simulator is the clock's *master*, in lockstep: it handles the
frames sent up to the current time, steps the physics to the next instant anything is due
(a tick, a controller's frame, a waiting participant), sends the frames and poses stamped
with that instant, and moves the clock on once everything sent has been delivered.  A
starved host slows the run down and never changes it: the same seed gives the same run.

Otherwise (``swpc sim``, a separate process on a CAN interface) it runs in real time,
scaled: with ``time_scale = s`` the simulated clock runs ``s`` times faster than wall time:
``t_sim = start_time + s (t_wall - t_wall_at_start)``.  Everything is in simulated time:
feedback rate, heartbeat period, watchdog timeout, homing duration, mocap rate and
latency.  A client matches it by dividing its own periods by ``s`` (e.g. the driver's
command refresh period must be shorter than ``watchdog_ms / s`` of wall time, or the
watchdog raised with ``SetWatchdog``).  If the machine cannot keep up, the simulated clock
slows down rather than bursting (counted in ``overruns``; :meth:`VirtualRobot.stats` gives
the achieved scale).

Pose time stamps (``mocap_clock``): ``"host"`` (default) stamps each pose with the host's
wall clock (``time.time()``) at the tick that samples it, ``t_wall_tick - (t_tick -
t_sample) / s`` (plus the mocap clock offset): the CAN frames of that tick carry the same
time in their bus time stamps, and to a client the simulated mocap is a real one, a clock
at real rate with a transport delay (:class:`services.sensors.mocap.MocapIngest` in its
``source`` mode).  ``"sim"`` stamps the simulated time itself (deterministic; a client
divides it by ``s``, and must take receive times when the simulator slows its clock).

Fault injection: :meth:`VirtualRobot.mute` (heartbeat loss: the node sends nothing),
:meth:`VirtualRobot.inject_fault` (a latched hardware error and its FaultReport),
``bus_error_rate`` (error frames, or on buses that cannot send them, frames with an
unknown id), slip bursts (:class:`simulators.physics.robot.PhysicsOptions`) and the mocap
options (noise, dropouts, outliers, latency, clock offset).
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
from collections import deque
from collections.abc import Iterable, Sequence
from dataclasses import replace
from typing import Any

import can
import numpy as np

from firmware_protocol.codec import Axis, ErrorFlag
from simulators.drives.base import VirtualDrive
from simulators.drives.factory import virtual_drives
from simulators.drives.wiring import WiredAxes
from simulators.options import SimOptions, SimStats, params_document
from simulators.physics.core import FloatArray, se2_step
from simulators.physics.robot import ModuleDrive, RobotPhysics
from simulators.sensors.gyro import (
    GyroSim,
    PoseHistory,
    axis_travel,
    measure_axis_distances,
    tape_measure,
)
from simulators.sensors.mocap import MocapSim, TruthPublisher, truth_pose_document
from swpc_hw.clock import SimClock, SystemClock, next_instant
from swpc_hw.robot.model import RobotParams
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED
from swpc_hw.sensors.zenoh_session import ZenohAuth, open_session

# --------------------------------------------------------------------------- simulator


class VirtualRobot:
    """The virtual robot on a python-can bus and a zenoh session (module docstring)."""

    def __init__(
        self,
        truth: RobotParams = PAPER_CALIBRATED,
        *,
        bus: can.BusABC,
        session: Any = None,
        options: SimOptions | None = None,
        own_bus: bool = False,
        own_session: bool = False,
        clock: SimClock | None = None,
    ) -> None:
        self.truth = truth
        self.options = opt = options or SimOptions()
        self.clock = clock
        self.bus = bus
        self.session = session
        self._own_bus = own_bus
        self._own_session = own_session
        n = len(truth.modules)
        rng = np.random.default_rng(opt.seed)
        theta0 = opt.theta0 if opt.theta0 is not None else rng.uniform(-math.pi, math.pi, n)
        sensors = (
            list(opt.sensor_positions)
            if opt.sensor_positions is not None
            else list(rng.uniform(-math.pi, math.pi, n))
        )
        self.robot = RobotPhysics(truth, opt.physics, opt.pose0, list(theta0))
        opt.wiring.check(n)
        self.drives: list[VirtualDrive] = virtual_drives(
            opt.drives,
            truth.ids,
            feedback_rate_hz=opt.feedback_rate_hz,
            watchdog_ms=opt.watchdog_ms,
            homing_duration=opt.homing_duration,
            sensor_positions=sensors,
        )
        self.axes = WiredAxes(
            opt.wiring, self.robot, self.drives, (opt.steer_counts, opt.wheel_counts)
        )
        self._wired = self.axes.wired
        self.mocap = MocapSim(opt.robot, opt.mocap, session, clock=clock)
        self.gyro = GyroSim(opt.robot, opt.gyro, session, seed=opt.seed, clock=clock)
        self.history = PoseHistory()  # the true poses, for the tape measure
        self.truth_pub = TruthPublisher(
            opt.robot, self._params_doc(), session, rate=opt.truth_rate, clock=clock
        )
        self.start_time = 0.0
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._started = False
        self._stopped = False
        self._stats = SimStats()
        # real time: the host's clock at the simulator's rate, and the host-clock time of
        # robot time 0 (moved on when the host cannot keep up)
        self._host = SystemClock(rate=opt.time_scale)
        self._origin = 0.0
        self._cpu = 0.0
        self._pending: deque[tuple[float, can.Message]] = deque()
        self._next_bus_error = 0.0
        self._rng = rng
        self.error: BaseException | None = None
        self._last_pose = self.robot.pose.copy()
        self._t_exact: float | None = None

    # ------------------------------------------------------------------ construction
    @classmethod
    def open(
        cls,
        truth: RobotParams = PAPER_CALIBRATED,
        *,
        interface: str = "virtual",
        channel: str = "swpc",
        bitrate: int | None = None,
        zenoh_listen: Sequence[str] = (),
        zenoh_connect: Sequence[str] = (),
        zenoh_config: str | None = None,
        zenoh_auth: ZenohAuth | None = None,
        options: SimOptions | None = None,
        clock: SimClock | None = None,
    ) -> VirtualRobot:
        """Open its own bus and zenoh session (both closed by :meth:`stop`).

        ``clock``: run in lockstep on this simulated clock (in-process bus only)."""
        kwargs: dict[str, Any] = {}
        if bitrate is not None:
            kwargs["bitrate"] = bitrate
        if clock is not None:
            if interface != "virtual":
                raise ValueError(
                    f"a simulated clock needs the in-process bus ('virtual'), not {interface!r}"
                )
            kwargs["preserve_timestamps"] = True  # frames carry the simulated wall time
        bus = can.Bus(interface=interface, channel=channel, **kwargs)
        try:
            session = open_session(
                listen=zenoh_listen,
                connect=zenoh_connect,
                config_file=zenoh_config,
                auth=zenoh_auth,
            )
        except BaseException:
            bus.shutdown()
            raise
        return cls(
            truth,
            bus=bus,
            session=session,
            options=options,
            own_bus=True,
            own_session=True,
            clock=clock,
        )

    def _params_doc(self) -> dict[str, Any]:
        drives = {m: d.params() for m, d in zip(self.truth.ids, self.drives, strict=True)}
        sensors = [d.sensor_position for d in self.drives]
        return params_document(self.truth, drives, self.options, sensors)

    # ------------------------------------------------------------------ lifecycle
    def __enter__(self) -> VirtualRobot:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def heard(self) -> bool:
        """Its poses have a subscriber (zenoh's matching status): a service waits for this
        before it starts the simulation in lockstep, so that its first pose is the
        simulation's first, whatever the wall time its zenoh link takes.  (A service
        subscribes to the gyro at its first run without motion capture.)"""
        return self.mocap.heard()

    def start(self) -> None:
        """Start the simulation thread (once)."""
        with self._lock:
            if self._started:
                raise RuntimeError("the simulator was already started")
            self._started = True
            opt = self.options
            if self.clock is not None:
                self.start_time = self.clock.now()  # the simulation's time is the clock's
                self._t_exact = self.start_time
            else:
                self.start_time = time.time() if opt.start_time is None else opt.start_time
            self._origin = self._host.now()
            self._write_encoders()
            for d in self.drives:
                self._transmit(d.step(self.now))  # first call initialises its clocks
            self.truth_pub.maybe_publish_params(self.now)
            self._sample_mocap(self.now, self.now, self.robot.pose, np.zeros(3))
            self._thread = threading.Thread(target=self._run, name="swpc-sim", daemon=True)
            self._thread.start()

    def stop(self) -> None:
        """Stop the thread and close what the simulator opened itself (idempotent)."""
        if self._stopped:
            return
        self._stopped = True
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        self.mocap.close()
        self.gyro.close()
        self.truth_pub.close()
        if self._own_bus:
            with contextlib.suppress(Exception):
                self.bus.shutdown()
        if self._own_session and self.session is not None:
            with contextlib.suppress(Exception):
                self.session.close()

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    @property
    def now(self) -> float:
        """Current simulated time (s, on the simulated clock; lockstep: the clock's own,
        exactly)."""
        if self._t_exact is not None:
            return self._t_exact
        return self.start_time + self.robot.t

    # ------------------------------------------------------------------ injection
    def mute(self, module: int, muted: bool = True) -> None:
        """Heartbeat loss: the module's drives send nothing while muted."""
        with self._lock:
            self.drives[self.truth.index(module)].muted = muted

    def inject_fault(self, module: int, axis: Axis, error: ErrorFlag) -> None:
        """Latch a hardware error on an axis (it goes to FAULT and reports it)."""
        with self._lock:
            self._transmit(self.drives[self.truth.index(module)].inject_fault(axis, error))

    def push(self, f_x: float = 0.0, f_y: float = 0.0, torque: float = 0.0) -> None:
        """Push the body with a constant wrench in R (N, N, N m about R's origin) until
        the next call; ``push()`` lets go.  A robot pushed while its wheels are free
        moves; braked wheels hold it."""
        with self._lock:
            self.robot.push = np.array([f_x, f_y, torque], dtype=float)

    def set_bus_error_rate(self, rate_hz: float) -> None:
        with self._lock:
            self.options = replace(self.options, bus_error_rate=float(rate_hz))
            self._next_bus_error = self.robot.t

    # ------------------------------------------------------------------ observation
    def stats(self) -> SimStats:
        with self._lock:
            st = self._stats
            st.sim_time = self.robot.t
            elapsed = self._host.now() - self._origin if self._started else 0.0
            st.wall_time = self._host_seconds(elapsed)
            st.cpu_time = self._cpu
            st.poses_published = self.mocap.counters.published
            st.gyro_published = self.gyro.counters.published
            st.truth_published = self.truth_pub.published
            by_module = list(zip(self.truth.ids, self.drives, strict=True))
            st.feedback_frames = {m: d.feedback_frames for m, d in by_module}
            st.heartbeats = {m: d.heartbeats for m, d in by_module}
            return replace(st)

    def truth_snapshot(self) -> dict[str, Any]:
        """The true state now (the same document as the truth pose key)."""
        with self._lock:
            return self._truth_doc()

    def _truth_doc(self) -> dict[str, Any]:
        return truth_pose_document(self.now, self.robot, [d.homed for d in self.drives])

    # ------------------------------------------------------------------ the loop
    def _run(self) -> None:
        """The thread body: the real-time loop, or the lockstep master on a SimClock."""
        cpu0 = time.thread_time()
        try:
            if self.clock is None:
                self._run_real_time(cpu0)
            else:
                self._run_lockstep(cpu0)
        except BaseException as exc:  # surfaced through .error; the thread ends
            self.error = exc
            if not self._stop.is_set():
                raise
        finally:
            self._cpu = time.thread_time() - cpu0

    def _run_real_time(self, cpu0: float) -> None:
        """Simulated time follows the wall clock times ``time_scale`` (module docstring)."""
        while not self._stop.is_set():
            dt = self.tick_dt()
            target = self._host.now() - self._origin  # robot time due now
            with self._lock:
                n = 0
                while self.robot.t + dt <= target + 1e-12 and not self._stop.is_set():
                    self._tick(dt)
                    self._receive_pending()
                    n += 1
                    if n >= 64:
                        break
                lag = target - self.robot.t
                if lag > self.options.max_lag * self.options.time_scale:
                    # cannot keep up: slow the simulated clock down instead of bursting
                    self._slow_down(lag - dt)
                self._cpu = time.thread_time() - cpu0
            timeout = self._host_seconds(self._origin + self.robot.t + dt - self._host.now())
            msg = self.bus.recv(timeout=max(timeout, 0.0)) if timeout > 0 else self.bus.recv(0)
            if msg is not None:
                self._queue_frame(msg)
                self._receive_pending()

    def _run_lockstep(self, cpu0: float) -> None:
        """The master of a :class:`SimClock` (lockstep, see :mod:`swpc_hw.clock`).

        Each step: the frames the host sent up to ``t`` take effect at ``t``; the physics
        advances to ``t_next`` (the next tick, or sooner when a controller or a waiting
        participant is due), the controllers' frames and the poses go out stamped with it;
        then the clock moves to ``t_next`` once everything sent has been delivered.
        """
        clock = self.clock
        assert clock is not None
        while not self._stop.is_set():
            if not clock.wait_for_demand(self._stop):
                continue
            with self._lock:
                t = clock.now()
                msg = self.bus.recv(0)
                while msg is not None:
                    self._on_message(msg)
                    msg = self.bus.recv(0)
                due = min(d.next_due() for d in self.drives)
                t_next = next_instant(t, [t + self.tick_dt(), due, clock.next_wake()])
                self._tick(t_next - t, t_end=t_next)
                self._cpu = time.thread_time() - cpu0
            clock.advance_to(t_next, self._stop)

    def _slow_down(self, shift: float) -> None:
        """Move robot time 0 ``shift`` later on the host clock (real time): the simulated
        clock slows down.  The frames already queued keep their arrival on the host clock,
        so on the new origin they are due ``shift`` sooner: without that, a burst of frames
        queued before a long stall waited until the simulation had run the whole stall
        (seconds under QEMU), and an ODrive axis handled its commands that late."""
        self._origin += shift
        self._pending = deque((t - shift, m) for t, m in self._pending)
        self._stats.overruns += 1

    def _stamp(self, t: float) -> float:
        """The bus / pose time stamp of simulated time ``t`` (lockstep: the simulated
        clock's wall time; real time: the host's wall clock now)."""
        return self.clock.to_wall(t) if self.clock is not None else time.time()

    def _queue_frame(self, msg: can.Message) -> None:
        """Queue a received frame for the simulated time of its arrival.

        The arrival is the frame's bus time stamp (wall clock) on the host clock
        (:meth:`~swpc_hw.clock.Clock.from_wall`, the one mapping) when it is plausible (at
        most one host second old), else now; ``t_sim = arrival - origin``.
        """
        now = self._host.now()
        arrival = now
        if msg.timestamp:
            stamped = self._host.from_wall(msg.timestamp)
            if now - self.options.time_scale < stamped <= now:
                arrival = stamped
        self._pending.append((arrival - self._origin, msg))

    def _host_seconds(self, robot_seconds: float) -> float:
        """Host seconds of a span of robot time (real time at ``time_scale``)."""
        return robot_seconds / self.options.time_scale

    def _receive_pending(self) -> None:
        """Read what the bus holds, then handle every frame whose arrival time has been
        reached: a frame takes effect at the first tick at or after its arrival, never
        before it (so a lagging simulation cannot shorten the watchdog)."""
        msg = self.bus.recv(0)
        while msg is not None:
            self._queue_frame(msg)
            msg = self.bus.recv(0)
        q = self._pending
        while q and q[0][0] <= self.robot.t + 1e-9:
            self._on_message(q.popleft()[1])

    def tick_dt(self) -> float:
        """``min(physics_dt, 1 / fastest free-running feedback rate)`` (s)."""
        rates = [r for r in (d.feedback_rate() for d in self.drives) if r > 0]
        dt = self.options.physics_dt
        return min(dt, 1.0 / max(rates)) if rates else dt

    def _on_message(self, msg: can.Message) -> None:
        if msg.is_error_frame:
            return
        with self._lock:
            self._stats.frames_rx += 1
            now = self.now
            for d in self.drives:
                self._transmit(d.receive(msg, now))

    def _tick(self, dt: float, t_end: float | None = None) -> None:
        """Advance by ``dt`` (``t_end``: the simulated time reached, exactly: lockstep)."""
        opt = self.options
        r = self.robot
        drives = self.axes.module_drives(dt, opt.position_tau)
        t0 = self.now
        pose0 = r.pose.copy()
        r.step(dt, drives)
        if t_end is not None:
            self._t_exact = t_end
        now = self.now
        self._write_encoders(drives)
        self._sample_mocap(t0, now, pose0, r.twist)
        if self.truth_pub.due(now):
            self.truth_pub.publish_pose(self._truth_doc())
        self.truth_pub.maybe_publish_params(now)
        for d in self.drives:
            was_homed = d.homed
            self._transmit(d.step(now))
            if d.homed and not was_homed:
                self._write_encoders(drives)
        if opt.bus_error_rate > 0.0 and r.t >= self._next_bus_error:
            self._next_bus_error = r.t + float(self._rng.exponential(1.0 / opt.bus_error_rate))
            self._inject_bus_error()
        self._stats.ticks += 1

    def _write_encoders(self, drives: Sequence[ModuleDrive] | None = None) -> None:
        """The encoders after a tick into the drives (``drives``: what each module's axes
        did in it; None at the start: nothing applied yet): :class:`WiredAxes`."""
        opt = self.options
        self.axes.write_encoders(drives, opt.steer_counts, opt.wheel_counts)

    def _sample_mocap(self, t0: float, t1: float, pose0: FloatArray, twist: FloatArray) -> None:
        """The poses and gyro samples due in ``(t0, t1]``, stamped like the tick's frames
        (the twist is constant within the tick); the true pose to the history."""
        host = self.options.mocap_clock == "host"
        wall = self._stamp(t1)  # this tick's moment: its feedback frames go out right after
        scale = 1.0 if self.clock is not None else self.options.time_scale

        def stamp(tp: float) -> float:
            st = self._stamp(tp) if self.clock is not None else wall - (t1 - tp) / scale
            return st if host else tp

        wiring = self.options.wiring
        for tp in self.mocap.due_times(t0, t1):
            pose = se2_step(pose0, twist[:2], float(twist[2]), tp - t0) if tp > t0 else pose0
            if self._wired:
                pose = np.array(wiring.mocap_pose(float(pose[0]), float(pose[1]), float(pose[2])))
            self.mocap.sample(tp, pose, stamp=stamp(tp))
        self.mocap.flush(t1)
        for tg in self.gyro.due_times(t0, t1):
            self.gyro.sample(float(twist[2]), stamp(tg))
        self.history.add(t1, self.robot.pose)

    def tape_measure(self, start: float, end: float, stddev: float, seed: int = 0) -> float:
        """What a tape measures (m, error ``N(0, stddev^2)``, seeded) between floor marks at
        the first module's steering axis at simulated times ``start`` and ``end``."""
        with self._lock:
            p0, p1 = self.history.at(start), self.history.at(end)
        travel = axis_travel(p0, p1, self.robot.arrays.P_s[0])
        return tape_measure(travel, stddev, np.random.default_rng([self.options.seed, seed]))

    def axis_distances(
        self, stddev: float, seed: int = 0, readings: int = 2
    ) -> list[tuple[int, int, list[float]]]:
        """What a tape measures between the steering axes of every pair of modules (m): per
        pair ``(a, b, [reading, ...])``, ``readings`` readings each with the error
        ``N(0, stddev^2)`` (seeded), of the true distance ``|P_s,a - P_s,b|``."""
        rng = np.random.default_rng([self.options.seed, seed, 20])
        return measure_axis_distances(self.robot.arrays.P_s, self.truth.ids, stddev, rng, readings)

    def _transmit(self, frames: Iterable[can.Message]) -> None:
        stamp = self.clock.to_wall(self.now) if self.clock is not None else 0.0
        for f in frames:
            f.timestamp = stamp
            try:
                self.bus.send(f)
            except (can.CanError, OSError):
                self._stats.tx_errors += 1
                continue
            self._stats.frames_tx += 1

    def _inject_bus_error(self) -> None:
        self._stats.bus_errors_injected += 1
        try:
            self.bus.send(can.Message(is_error_frame=True, arbitration_id=0x4, dlc=8))
            return
        except (can.CanError, OSError, ValueError):
            pass
        with contextlib.suppress(can.CanError, OSError):  # unknown id instead
            self.bus.send(can.Message(arbitration_id=0x7FF, data=bytes(8), is_extended_id=False))
