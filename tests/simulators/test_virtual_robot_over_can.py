"""The virtual robot end to end: driven only through CAN frames, observed only through zenoh.

Every test runs the real simulator thread on a python-can ``virtual`` bus and a zenoh
session on a loopback tcp endpoint; the host side is the real CAN driver
(:class:`swpc_hw.drives.swpc.driver.SwpcDriver`) or raw frames from :mod:`firmware_protocol.codec`.

Tests of what the simulator computes (geometry, watchdog, heartbeat) run it in lockstep
on a :class:`swpc_hw.clock.SimClock` (``rig(lockstep=True)``, the test thread a
participant), so a busy host slows them down and never changes them; tests of the
real-time mode itself (time scale, host stamps, the separate process) assert only what a
starved host cannot change.
"""

from __future__ import annotations

import contextlib
import json
import math
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import can
import numpy as np
import pytest

from firmware_protocol import codec
from firmware_protocol.codec import Axis, AxisState, ErrorFlag
from simulators.options import SimOptions
from simulators.sensors.gyro import imu_key
from simulators.sensors.mocap import MocapOptions, pose_key, truth_params_key, truth_pose_key
from simulators.virtual_robot import VirtualRobot
from swpc_hw.clock import SimClock
from swpc_hw.drives.bus import CanConfig
from swpc_hw.drives.swpc.config import SwpcDrives
from swpc_hw.drives.swpc.driver import SwpcDriver
from swpc_hw.robot.model import RobotParams, rot
from swpc_hw.sensors.gyro import GyroOptions, decode_imu
from swpc_hw.sensors.mocap import PoseEncoding, decode_pose
from swpc_hw.sensors.zenoh_session import free_tcp_endpoint, open_session

DEG = math.pi / 180.0


@dataclass
class PoseLog:
    """Poses received over zenoh: (t_source, x, y, yaw, t_recv wall monotonic).

    With a ``clock`` (lockstep) it is a receiver the simulator waits for, on ``key``, and
    its waits are in simulated time."""

    rows: list[tuple[float, float, float, float, float]] = field(default_factory=list)
    frame_ids: set[str] = field(default_factory=set)
    encodings: set[PoseEncoding] = field(default_factory=set)
    cond: threading.Condition = field(default_factory=threading.Condition)
    clock: SimClock | None = None
    key: str = ""

    def on_sample(self, sample: Any) -> None:
        payload = sample.payload.to_bytes()
        p = decode_pose(payload)
        now = time.monotonic()
        with self.cond:
            self.rows.append((p.t, p.x, p.y, p.yaw, now))
            self.frame_ids.add(p.frame_id)
            self.cond.notify_all()
        if self.clock is not None:
            self.clock.arrived(self.key)

    def last_t(self) -> float:
        with self.cond:
            return self.rows[-1][0] if self.rows else -math.inf

    def wait_until(self, t_source: float, timeout: float = 30.0) -> None:
        if self.clock is not None:  # lockstep: a participant's wait, in simulated time
            clock = self.clock
            deadline = clock.now() + timeout
            with self.cond:
                while not self.rows or self.rows[-1][0] < t_source:
                    assert clock.now() < deadline, f"no pose at source time {t_source}"
                    clock.wait(self.cond, deadline)
            return
        deadline = time.monotonic() + timeout
        with self.cond:
            while not self.rows or self.rows[-1][0] < t_source:
                left = deadline - time.monotonic()
                assert left > 0, f"no pose at source time {t_source} (last {self.last_t()})"
                self.cond.wait(left)

    def wait_for(self, dt: float) -> None:
        """Wait ``dt`` seconds of simulated (mocap) time."""
        self.wait_until(self.last_t() + dt)

    def array(self, t0: float = -math.inf, t1: float = math.inf) -> np.ndarray:
        with self.cond:
            a = np.array(self.rows)
        return a[(a[:, 0] >= t0) & (a[:, 0] <= t1)]


@dataclass
class GyroLog:
    """Gyro samples received over zenoh ``(t_source, wz)``; lockstep as :class:`PoseLog`."""

    rows: list[tuple[float, float]] = field(default_factory=list)
    clock: SimClock | None = None
    key: str = ""

    def on_sample(self, sample: Any) -> None:
        g = decode_imu(sample.payload.to_bytes())
        self.rows.append((g.t, g.wz))
        if self.clock is not None:
            self.clock.arrived(self.key)

    def array(self, t0: float, t1: float) -> np.ndarray:
        a = np.array(self.rows)
        return a[(a[:, 0] >= t0) & (a[:, 0] <= t1)]


@dataclass
class Rig:
    sim: VirtualRobot
    channel: str
    session: Any
    poses: PoseLog
    clock: SimClock | None = None
    gyro: GyroLog = field(default_factory=GyroLog)

    def truth_params(self) -> dict[str, Any]:
        replies = list(self.session.get(truth_params_key(self.sim.options.robot), timeout=5.0))
        assert replies, "no reply from the truth params queryable"
        doc: dict[str, Any] = json.loads(replies[0].ok.payload.to_bytes())
        return doc


@contextmanager
def rig(lockstep: bool = False, **opts: Any) -> Iterator[Rig]:
    """A simulator on a fresh virtual channel and zenoh endpoint; ``lockstep``: master of
    a fresh :class:`SimClock` whose participant is the calling thread."""
    channel = f"test-sim-{uuid.uuid4().hex[:8]}"
    ep = free_tcp_endpoint()
    sim_session = open_session(listen=[ep])
    client = open_session(connect=[ep])
    clock = SimClock() if lockstep else None
    # lockstep: frames carry the simulated clock's wall time
    bus = can.Bus(interface="virtual", channel=channel, preserve_timestamps=lockstep)
    opts.setdefault("start_time", 0.0)
    # these tests read pose times as simulated time (test_host_mocap_clock_... the default)
    opts.setdefault("mocap_clock", "sim")
    sim = VirtualRobot(bus=bus, session=sim_session, options=SimOptions(**opts), clock=clock)
    log = PoseLog(clock=clock, key=pose_key(sim.options.robot))
    sub = client.declare_subscriber(log.key, log.on_sample)
    gyro = GyroLog(clock=clock, key=imu_key(sim.options.robot))
    gyro_sub = client.declare_subscriber(gyro.key, gyro.on_sample)
    participant = clock.participant() if clock is not None else contextlib.nullcontext()
    try:
        if clock is not None:
            clock.subscribe(log.key)
            clock.subscribe(gyro.key)
        with participant:
            sim.start()
            log.wait_until(0.0, timeout=10.0)
            yield Rig(sim, channel, client, log, clock, gyro)
    finally:
        sim.stop()
        sim.stop()  # idempotent
        if clock is not None:
            clock.close()
        sub.undeclare()
        gyro_sub.undeclare()
        client.close()
        sim_session.close()
        bus.shutdown()
    assert sim.error is None


def fixed_point(poses: np.ndarray) -> tuple[np.ndarray, float]:
    """Body point C (in R) fixed in W over ``poses`` (rows t, x, y, yaw): least squares of
    ``p_i + R(yaw_i) C = C_W``; returns C and the RMS residual (m)."""
    R = rot(poses[:, 3])
    n = poses.shape[0]
    M = np.zeros((2 * n, 4))
    M[:, :2] = R.reshape(2 * n, 2)
    M[0::2, 2] = -1.0
    M[1::2, 3] = -1.0
    rhs = -poses[:, 1:3].reshape(-1)
    sol, *_ = np.linalg.lstsq(M, rhs, rcond=None)
    res = M @ sol - rhs
    return sol[:2], float(np.sqrt(np.mean(res**2)))


def slope(t: np.ndarray, y: np.ndarray) -> float:
    return float(np.polyfit(t - t.mean(), y, 1)[0])


def test_host_mocap_clock_stamps_the_wall_time_of_sampling() -> None:
    """The default pose clock: the host's wall clock at the tick that samples the pose, so
    a client sees a mocap at real rate with a transport delay, whatever the time scale."""
    scale = 2.0
    with rig(time_scale=scale, mocap=MocapOptions(rate=100), mocap_clock="host") as r:
        wall_minus_mono = time.time() - time.monotonic()
        t0 = r.poses.last_t()
        st0 = r.sim.stats()
        deadline = time.monotonic() + 10.0
        while r.poses.last_t() < t0 + 1.5 and time.monotonic() < deadline:
            time.sleep(0.05)
        st1 = r.sim.stats()
    P = r.poses.array(t0)
    assert P.shape[0] > 50  # 1.5 s of wall time: 300 poses at full speed, fewer if starved
    delay = P[:, 4] + wall_minus_mono - P[:, 0]  # receive (wall) - stamp
    print(f"stamp -> receive: median {np.median(delay) * 1e3:.2f} ms, max {delay.max() * 1e3:.2f}")
    assert delay.min() > -1e-3  # never stamped after it arrived (clocks read 1 ms apart)
    # a wall-clock stamp, whatever the host's load (a simulated-time stamp would be off by
    # the epoch; how small the transport delay is, is make bench's figure)
    assert np.median(delay) < 1.0
    assert np.all(np.diff(P[:, 0]) > 0)
    # 100 Hz of simulated time = 200 Hz of wall time at scale 2, never more; less where
    # the host lagged (the simulator then slows its clock, as its stats say)
    rate = (P.shape[0] - 1) / (P[-1, 0] - P[0, 0])
    window_scale = (st1.sim_time - st0.sim_time) / (st1.wall_time - st0.wall_time)
    assert window_scale <= scale * 1.15  # catching up a lag of up to max_lag
    assert rate <= 100 * scale * 1.15
    assert SimOptions(mocap_clock="sim").mocap_clock == "sim"
    with pytest.raises(ValueError, match="mocap_clock"):
        SimOptions(mocap_clock="gps")


# --------------------------------------------------------------------------- 1 and 2


def test_lock_spin_resteer_spin_through_can_and_zenoh_gives_the_true_contact_points() -> None:
    """What it must show 1 and 2, driven only through the CAN driver, poses only from zenoh;
    and the gyro reads the poses' yaw rate with its bias and scale error (a steady spin:
    the mean over 3 s, 600 samples, is within 1e-4 rad/s of ``(1 + eps) omega + bias``)."""
    gyro_opt = GyroOptions(bias=math.radians(0.5), scale_error=0.01, bias_walk=0.0)
    with rig(
        lockstep=True,
        physics_dt=0.004,
        feedback_rate_hz=50,
        watchdog_ms=1000,
        mocap=MocapOptions(rate=100),
        gyro=gyro_opt,
        seed=7,
    ) as r:
        truth = RobotParams.model_validate(r.truth_params())  # the ground-truth channel
        T = truth.arrays()
        k, a1, a2 = 1, 45 * DEG, 165 * DEG
        ik = truth.index(k)
        others = [m for m in truth.ids if m != k]
        drv = SwpcDriver(
            CanConfig(
                channel=r.channel,
                watchdog_timeout_ms=1000,
                feedback_rate_hz=50,
                heartbeat_loss_periods=10,
                activate_timeout_s=5.0,
            ),
            clock=r.clock,
        )
        assert r.clock is not None
        try:
            drv.configure()
            drv.activate()
            for m in truth.ids:
                drv.clear_errors(m)
                drv.enable(m, Axis.STEER)
                drv.enable(m, Axis.WHEEL)
                drv.start_homing(m)
            for m in truth.ids:
                drv.wait_for(m, lambda s: s.homed and s.feedback is not None, 5.0, "homed")

            def spin_and_measure(a: float) -> np.ndarray:
                for m in others:  # casters start from wherever they are
                    drv.free(m, Axis.STEER)
                    drv.set_torque(m, Axis.WHEEL, -0.6)
                r.poses.wait_for(3.0)  # settle
                t0 = r.poses.last_t()
                w0 = r.clock.now()  # the driver stamps samples on its clock
                r.poses.wait_until(t0 + 3.0)
                w1 = r.clock.now()
                P = r.poses.array(t0, t0 + 3.0)
                C_meas, rms = fixed_point(P)
                C_true = T.P_s[ik] + T.b[ik] * np.array(
                    [math.cos(a + T.beta[ik]), math.sin(a + T.beta[ik])]
                )
                faults = [e.message for e in drv.events() if e.severity.value == "fault"]
                assert not faults
                assert rms < 1e-6
                err = float(np.linalg.norm(C_meas - C_true))
                print(f"angle {a / DEG:.0f} deg: fixed point error {err * 1e6:.3f} um")
                assert err <= 0.1e-3
                # 2: settled casters are perpendicular to the radius from the pivot, and the
                # wheel encoders turn by D d(yaw) / r.  Rates per simulated second: poses carry
                # their source time; feedback samples come every 1/50 s, numbered by `seq`.
                yaw_rate = slope(P[:, 0], np.unwrap(P[:, 3]))
                assert 0.3 < abs(yaw_rate) < 1.0
                G = r.gyro.array(t0, t0 + 3.0)
                assert G.shape[0] == 601  # 200 Hz on the simulated clock, stamped with it
                want = (1 + gyro_opt.scale_error) * yaw_rate + gyro_opt.bias
                assert float(np.mean(G[:, 1])) == pytest.approx(want, abs=1e-4)
                for m in others:
                    j = truth.index(m)
                    h = drv.history_arrays(m)
                    sel = (h["t"] >= w0) & (h["t"] <= w1)
                    th = h["theta_hat"][sel][-1] + T.beta[j]
                    u = np.array([math.cos(th), math.sin(th)])
                    P_w = T.P_s[j] + T.b[j] * u
                    D = np.linalg.norm(P_w - C_true)
                    assert abs((P_w - C_true) @ u) < 0.3e-3  # even at 2**14 counts/turn on the wire
                    psi_rate = slope(h["seq"][sel] / 50.0, h["psi"][sel])
                    print(
                        f"  module {m}: (P_w - C).u = {((P_w - C_true) @ u) * 1e6:.2f} um, "
                        f"dpsi/dt {psi_rate:.5f} vs -D |dyaw/dt| / r "
                        f"{-D * abs(yaw_rate) / T.r[j]:.5f} rad/s"
                    )
                    assert psi_rate == pytest.approx(-D * abs(yaw_rate) / T.r[j], rel=1e-3)
                return C_meas

            drv.set_position(k, Axis.STEER, a1)
            drv.hold(k, Axis.WHEEL)
            r.poses.wait_for(1.0)
            P1 = spin_and_measure(a1)
            for m in others:  # stop: torque off, wheels held
                drv.hold(m, Axis.WHEEL)
            r.poses.wait_for(0.5)
            for m in others:  # re-steer with the dynamic modules free
                drv.free(m, Axis.WHEEL)
                drv.free(m, Axis.STEER)
            yaw_before = r.poses.array()[-1, 3]
            drv.set_position(k, Axis.STEER, a2)
            r.poses.wait_for(2.5)
            assert abs(r.poses.array()[-1, 3] - yaw_before) > 10 * DEG  # body moved about the pin
            assert drv.module_state(k).theta_hat == pytest.approx(a2, abs=1e-3)
            P2 = spin_and_measure(a2)
            chord = 2 * T.b[ik] * math.sin((a2 - a1) / 2)
            assert np.linalg.norm(P2 - P1) == pytest.approx(chord, abs=0.2e-3)
            assert not [e for e in drv.events() if e.severity.value == "fault"]
        finally:
            drv.shutdown()
        st = r.sim.stats()
        assert st.sim_time > 15.0 and st.frames_rx > 100


# --------------------------------------------------------------------------- 3


@dataclass
class RawHost:
    """Raw frames on the bus, decoded as they are read (no thread: every read drains what
    the virtual bus has delivered so far, so in lockstep a read sees everything sent up
    to the clock's time).  ``clock``: the time stamps of what it sends (real: wall)."""

    bus: can.BusABC
    clock: SimClock | None = None
    frames: list[tuple[float, codec.Decoded]] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.last_tx = -math.inf
        self.error_frames = 0
        self.tx_times: dict[int, list[float]] = {}

    def drain(self) -> None:
        while (msg := self.bus.recv(0.0)) is not None:
            if msg.is_error_frame:
                self.error_frames += 1
                continue
            _node, cmd = codec.split_id(msg.arbitration_id)
            if cmd not in codec.CONTROLLER_FRAMES:
                continue
            d = codec.parse(msg.arbitration_id, bytes(msg.data))
            self.frames.append((msg.timestamp, d))  # bus time stamp (wall clock)

    def now(self) -> float:
        """Wall time on the bus's time stamps (lockstep: the simulated clock's)."""
        return self.clock.wall() if self.clock is not None else time.time()

    def sleep(self, dt: float) -> None:
        if self.clock is not None:
            self.clock.sleep(dt)
        else:
            time.sleep(dt)

    def send(self, *frames: codec.Frame) -> None:
        for f in frames:
            self.bus.send(
                can.Message(arbitration_id=f.arbitration_id, data=f.data, is_extended_id=False)
            )
            now = self.now()
            self.last_tx = now
            self.tx_times.setdefault(codec.split_id(f.arbitration_id)[0], []).append(now)

    def of(self, kind: type, since: float = -math.inf, node: int | None = None) -> list[Any]:
        self.drain()
        return [
            (t, d)
            for t, d in self.frames
            if isinstance(d, kind) and t >= since and (node is None or d.node == node)
        ]

    def close(self) -> None:
        self.bus.shutdown()


def test_watchdog_frees_the_axes_and_heartbeat_loss_silences_a_node() -> None:
    """What it must show 3 (in lockstep: the bounds are the simulator's, whatever the
    host's load)."""
    watchdog = 0.2  # s; commands go every 10 ms
    with rig(lockstep=True, feedback_rate_hz=100, watchdog_ms=200, seed=3) as r:
        host = RawHost(
            can.Bus(interface="virtual", channel=r.channel, preserve_timestamps=True), r.clock
        )
        try:
            for n in (1, 2, 3, 4):
                host.send(codec.make_set_axis_state(n, Axis.WHEEL, True))
            host.send(codec.make_set_axis_state(1, Axis.STEER, True))
            # keep the commands flowing for 0.5 s: module 1 steer held and braked, wheels torqued
            t_end = host.now() + 0.5
            while host.now() < t_end:
                host.send(codec.make_set_control(1, Axis.STEER, codec.ControlMode.HOLD))
                host.send(codec.make_set_control(1, Axis.WHEEL, codec.ControlMode.HOLD))
                for n in (2, 3, 4):
                    host.send(codec.make_set_control(n, Axis.WHEEL, codec.ControlMode.TORQUE, -0.6))
                host.sleep(0.01)
            spinning = abs(r.sim.truth_snapshot()["twist"][2])
            assert spinning > 0.05
            t_last = host.last_tx  # stop sending: the watchdog runs out
            host.sleep(0.5)
            reports = host.of(codec.FaultReport)
            by_node = {
                d.node: t for t, d in reports if d.active_errors & ErrorFlag.WATCHDOG_TIMEOUT
            }
            assert sorted(by_node) == [1, 2, 3, 4]
            # from each node's last command to its FaultReport, on the bus time stamps
            delays = [(t - max(x for x in host.tx_times[n] if x < t)) for n, t in by_node.items()]
            # a command takes effect at the first tick after its arrival; the fault is sent
            # at the first tick after the timeout
            tick = r.sim.tick_dt()
            assert max(delays) <= watchdog + 2 * tick
            assert min(delays) >= watchdog - 1e-3
            print(f"watchdog {watchdog * 1e3:.0f} ms: FaultReports after {sorted(delays)} s")
            assert min(by_node.values()) > t_last  # it went off because the commands stopped
            hb = host.of(codec.Heartbeat, since=t_last + watchdog + 0.06)
            assert {d.node for _, d in hb} == {1, 2, 3, 4}
            for _, d in hb:
                assert d.states[Axis.WHEEL] == AxisState.FAULT
                assert d.errors[Axis.WHEEL] & ErrorFlag.WATCHDOG_TIMEOUT
            host.sleep(0.5)  # free wheels: the robot coasts to a stop
            assert abs(r.sim.truth_snapshot()["twist"][2]) < 0.05 * spinning

            # heartbeat loss: node 3 falls silent, the others go on
            r.sim.mute(3)
            t_mute = host.now()
            host.sleep(0.3)
            assert not host.of(codec.Heartbeat, since=t_mute + 0.01, node=3)
            assert not host.of(codec.FeedbackPosition, since=t_mute + 0.01, node=3)
            # 3 heartbeats of node 2 are due (one per 0.1 s)
            assert len(host.of(codec.Heartbeat, since=t_mute + 0.01, node=2)) == 3
            r.sim.mute(3, False)
            host.sleep(0.2)
            assert host.of(codec.Heartbeat, since=host.now() - 0.15, node=3)
            # an injected hardware fault is reported
            t_f = host.now()
            r.sim.inject_fault(2, Axis.STEER, ErrorFlag.OVER_TEMPERATURE)
            host.sleep(0.05)
            rep = host.of(codec.FaultReport, since=t_f, node=2)
            assert rep and rep[0][1].new_errors == ErrorFlag.OVER_TEMPERATURE
        finally:
            host.close()


# --------------------------------------------------------------------------- mocap, truth, time


def test_ros2_cdr_poses_truth_channel_and_time_scale() -> None:
    scale = 3.0
    with rig(
        time_scale=scale,
        physics_dt=0.004,
        mocap=MocapOptions(rate=200, encoding="ros2-cdr", frame_id="mocap"),
        theta0=[0.0, 0.0, 0.0, 0.0],
    ) as r:
        truth_rows: list[dict[str, Any]] = []
        sub = r.session.declare_subscriber(
            truth_pose_key("swpc"), lambda s: truth_rows.append(json.loads(s.payload.to_bytes()))
        )
        t0 = r.poses.last_t()
        st0 = r.sim.stats()
        r.poses.wait_until(t0 + 5.0)
        st = r.sim.stats()
        sub.undeclare()
        params = r.truth_params()
    P = r.poses.array(t0, t0 + 5.0)
    assert r.poses.frame_ids == {"mocap"}
    assert np.diff(P[:, 0]) == pytest.approx(np.full(len(P) - 1, 0.005), abs=1e-9)
    # the source clock runs at most `scale` times faster than the receiver's wall clock
    # (slower when this machine cannot keep up: how fast it keeps up is a real-time
    # figure, measured by `python -m benchmarks sim`, not asserted on a shared host; one
    # run in ten beside two busy loops reached 2.78 of 3 without an overrun counted yet)
    window_scale = (st.sim_time - st0.sim_time) / (st.wall_time - st0.wall_time)
    assert 0 < window_scale <= scale * 1.15  # catching up a lag of up to max_lag
    assert 0 < slope(P[:, 4], P[:, 0]) <= scale * 1.15
    assert 0 < st.achieved_time_scale <= scale * 1.15
    assert truth_rows and set(truth_rows[-1]) >= {"pose", "theta", "psi", "contact_points"}
    assert params["format"] == "swpc-kinematics/1"
    fb = codec.message_for(1, codec.Command.FEEDBACK_POSITION)
    for axis, sig in (("steer", "SteerPosition"), ("wheel", "WheelPosition")):
        step = fb.get_signal_by_name(sig).scale  # what the feedback frame carries
        assert params["simulator"][f"frame_{axis}_counts"] == round(2 * math.pi / step)
    assert next(m["beta"] for m in params["modules"]) == pytest.approx(0.6349 * DEG)


def test_simulator_lifecycle() -> None:
    sim = VirtualRobot.open(
        interface="virtual",
        channel=f"lc-{uuid.uuid4().hex[:6]}",
        zenoh_listen=[free_tcp_endpoint()],
        options=SimOptions(start_time=0.0),
    )
    with pytest.raises(RuntimeError):
        sim.start()
        sim.start()
    assert sim.running
    deadline = time.monotonic() + 10.0  # it ticks (how fast is the host's business)
    while sim.stats().ticks <= 10 and time.monotonic() < deadline:
        time.sleep(0.02)
    sim.stop()
    sim.stop()
    assert not sim.running and sim.error is None
    assert sim.stats().ticks > 10


def test_swpc_sim_runs_as_a_separate_process() -> None:
    ep = free_tcp_endpoint()
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "services.cli",
            "sim",
            "--interface",
            "virtual",
            "--channel",
            "proc",
            "--zenoh-listen",
            ep,
            "--duration",
            "60",  # a bound: the test stops it with SIGTERM once it has seen its poses
            "--time-scale",
            "2",
            "--pose-encoding",
            "ros2-cdr",
            "--pose-rate",
            "50",
            "--gyro-rate",
            "100",
            "--gyro-bias",
            "2.0",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    client = open_session(connect=[ep])
    log = PoseLog()
    gyro = GyroLog()
    sub = client.declare_subscriber("mocap/swpc/pose", log.on_sample)
    gyro_sub = client.declare_subscriber("imu/swpc/data", gyro.on_sample)
    try:
        log.wait_until(-1e18, timeout=20.0)
        t0 = log.last_t()
        log.wait_until(t0 + 1.0, timeout=30.0)
        proc.terminate()  # SIGTERM: a clean stop, with its summary
        out, _ = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
        sub.undeclare()
        gyro_sub.undeclare()
        client.close()
    assert proc.returncode == 0, out
    assert "swpc sim: robot 'swpc'" in out and "overruns" in out
    # its gyro too (a robot at rest: the bias, 2 deg/s), stamped with the host's wall clock
    G = np.array(gyro.rows)
    assert G.shape[0] > 20 and "gyro 100 Hz on imu/swpc/data" in out
    assert float(np.mean(G[:, 1])) == pytest.approx(math.radians(2.0), abs=2e-3)
    assert abs(float(G[-1, 0]) - time.time()) < 30.0


def test_custom_nodes_encoder_quantisation_and_bus_errors() -> None:
    truth = RobotParams.from_arrays(
        [10, 20, 30],
        [[0.2, 0.1], [-0.2, 0.1], [0.0, -0.2]],
        [0.01, 0.02, 0.03],
        [0.02, 0.02, 0.02],
        [0.05, 0.05, 0.05],
    )
    channel = f"test-sim-{uuid.uuid4().hex[:8]}"
    clock = SimClock()
    bus = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
    host = RawHost(can.Bus(interface="virtual", channel=channel), clock)
    sim = VirtualRobot(
        truth,
        bus=bus,
        options=SimOptions(
            drives=SwpcDrives(modules={10: 5, 20: 6, 30: 7}),
            steer_counts=2**10,
            wheel_counts=2**12,
            start_time=0.0,
        ),
        clock=clock,
    )
    try:
        with clock.participant():
            sim.start()
            host.sleep(0.3)
            heard = {d.node for _, d in host.of(codec.Heartbeat)}
            assert heard == {5, 6, 7}
            fb = host.of(codec.FeedbackPosition)
            q = 2 * math.pi / 2**10
            steer = np.array([d.steer for _, d in fb])
            assert np.abs(steer / q - np.round(steer / q)).max() < 1e-3  # 2**10 counts per turn
            host.drain()
            host.frames.clear()
            sim.set_bus_error_rate(100.0)
            host.sleep(0.3)
            sim.set_bus_error_rate(0.0)
            host.drain()
            n = host.error_frames
            assert 5 <= n <= 80 and sim.stats().bus_errors_injected >= n
    finally:
        sim.stop()
        clock.close()
        host.close()
        bus.shutdown()
    assert sim.error is None
