"""The rig of the virtual robot's end-to-end tests
(``test_virtual_robot_contact_points_and_watchdog.py``,
``test_virtual_robot_mocap_truth_and_time.py``): the simulator driven only through CAN
frames, observed only through zenoh.

:func:`rig` runs the real simulator thread on a python-can ``virtual`` bus and a zenoh
session on a loopback tcp endpoint, the poses and gyro samples it publishes logged
(:class:`PoseLog`, :class:`GyroLog`); the host side is the real CAN driver
(:class:`swpc_hw.drives.swpc.driver.SwpcDriver`) or raw frames from
:mod:`firmware_protocol.codec` (:class:`RawHost`).

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
import threading
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import can
import numpy as np

from firmware_protocol import codec
from simulators.options import SimOptions
from simulators.sensors.gyro import imu_key
from simulators.sensors.mocap import truth_params_key
from simulators.virtual_robot import VirtualRobot
from swpc_hw.clock import SimClock
from swpc_hw.robot.model import rot
from swpc_hw.sensors.gyro import decode_imu
from swpc_hw.sensors.mocap import PoseEncoding, decode_pose, pose_key
from swpc_hw.sensors.zenoh_session import free_tcp_endpoint, open_session

DEG = math.pi / 180.0


@dataclass
class PoseLog:
    """Poses received over zenoh: (t_source, x, y, yaw, t_recv wall monotonic).

    With a ``clock`` (lockstep) it is a receiver the simulator waits for, on ``key``, and
    its waits are in simulated time."""

    rows: list[tuple[float, float, float, float, float]] = field(default_factory=list)
    received_wall: list[float] = field(default_factory=list)
    """``time.time()`` at each row's receipt: the host's wall clock may be slewed against
    its monotonic one (this VM's ran 0.5 % fast on 2026-12-01), so a wall stamp is held
    against the wall clock read at arrival, not a monotonic time plus an offset."""
    frame_ids: set[str] = field(default_factory=set)
    encodings: set[PoseEncoding] = field(default_factory=set)
    cond: threading.Condition = field(default_factory=threading.Condition)
    clock: SimClock | None = None
    key: str = ""

    def on_sample(self, sample: Any) -> None:
        payload = sample.payload.to_bytes()
        p = decode_pose(payload)
        now, wall = time.monotonic(), time.time()
        with self.cond:
            self.rows.append((p.t, p.x, p.y, p.yaw, now))
            self.received_wall.append(wall)
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
