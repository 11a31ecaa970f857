"""Virtual robot benchmark: sustained rates in real time, CPU share, and the time-scale speed-up.

1. Real time (time scale 1), the robot spinning about a locked module: 4 nodes streaming
   feedback at 500 Hz (both frames) and mocap poses at 1 kHz over zenoh.  Rates are
   counted at the receivers (a second python-can bus on the channel, a second zenoh
   session on loopback); CPU is the simulator thread's CPU time and the whole process's
   (receivers included) per wall second (1.0 = one core).
2. Time-scale sweep (feedback 200 Hz, poses 100 Hz, same spin): the achieved speed-up
   (simulated s per wall s) and CPU share for each requested scale, with the default
   2 ms physics step and with a 5 ms one.

``python -m benchmarks sim`` (``make bench``).  ``SWPC_BENCH_SIM_SECONDS`` sets the length
of part 1 (default 10 s); the whole benchmark takes about 50 s.  The python-can ``virtual`` bus
deep-copies every frame for every other bus on the channel, so the benchmark keeps one.
"""

from __future__ import annotations

import os
import threading
import time
import uuid
from collections import Counter
from dataclasses import replace
from typing import Any

import can

from firmware_protocol import codec
from firmware_protocol.codec import Axis, ControlMode
from simulators.options import SimOptions
from simulators.sensors.mocap import MocapOptions
from simulators.virtual_robot import VirtualRobot
from swpc_hw.sensors.zenoh_session import free_tcp_endpoint, open_session


class _Receiver:
    """Counts feedback frames per node on its own bus, and poses from its own zenoh session."""

    def __init__(self, channel: str, session: Any, key: str) -> None:
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.frames: Counter[int] = Counter()
        self.poses = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        self._sub = session.declare_subscriber(key, self._on_pose)

    def _on_pose(self, sample: Any) -> None:
        self.poses += 1

    def _run(self) -> None:
        fb = int(codec.Command.FEEDBACK_POSITION)
        while not self._stop.is_set():
            msg = self.bus.recv(0.05)
            if msg is not None and msg.arbitration_id & codec.COMMAND_MASK == fb:
                self.frames[msg.arbitration_id >> codec.NODE_SHIFT] += 1

    def snapshot(self) -> tuple[dict[int, int], int]:
        return dict(self.frames), self.poses

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self._sub.undeclare()
        self.bus.shutdown()


def _spin(bus: can.BusABC) -> None:
    """Watchdog off; module 1 steering held and wheel braked; the others at -0.6 N.m."""
    frames = []
    for n in (1, 2, 3, 4):
        frames += [codec.make_set_watchdog(n, 0), codec.make_set_axis_state(n, Axis.WHEEL, True)]
    frames += [
        codec.make_set_axis_state(1, Axis.STEER, True),
        codec.make_set_control(1, Axis.STEER, ControlMode.HOLD),
        codec.make_set_control(1, Axis.WHEEL, ControlMode.HOLD),
    ]
    frames += [codec.make_set_control(n, Axis.WHEEL, ControlMode.TORQUE, -0.6) for n in (2, 3, 4)]
    for f in frames:
        bus.send(can.Message(arbitration_id=f.arbitration_id, data=f.data, is_extended_id=False))


def _run(opts: SimOptions, seconds: float, sessions: tuple[Any, Any]) -> dict[str, float]:
    channel = f"bench-sim-{uuid.uuid4().hex[:8]}"
    sim_session, rx_session = sessions
    opts = replace(opts, robot=channel)  # a fresh pose key per run
    bus = can.Bus(interface="virtual", channel=channel)
    sim = VirtualRobot(bus=bus, session=sim_session, options=opts)
    rx = _Receiver(channel, rx_session, f"mocap/{opts.robot}/pose")  # the only other bus
    try:
        time.sleep(0.3)  # zenoh routes the subscriber
        sim.start()
        _spin(rx.bus)
        time.sleep(0.5)  # spin up
        f0, p0 = rx.snapshot()
        s0 = sim.stats()
        c0, w0 = time.process_time(), time.monotonic()
        time.sleep(seconds)
        f1, p1 = rx.snapshot()
        s1 = sim.stats()
        c1, w1 = time.process_time(), time.monotonic()
        spin_rate = abs(sim.truth_snapshot()["twist"][2])
    finally:
        sim.stop()
        rx.close()
        bus.shutdown()
    wall = w1 - w0
    sim_dt = s1.sim_time - s0.sim_time
    fb = [(f1.get(n, 0) - f0.get(n, 0)) / wall for n in (1, 2, 3, 4)]
    return {
        "scale": sim_dt / wall,
        "sim_cpu": (s1.cpu_time - s0.cpu_time) / wall,
        "proc_cpu": (c1 - c0) / wall,
        "fb_min": min(fb) / (sim_dt / wall),  # per simulated second
        "fb_max": max(fb) / (sim_dt / wall),
        "poses": (p1 - p0) / sim_dt,
        "overruns": float(s1.overruns - s0.overruns),
        "yaw_rate": spin_rate,
    }


def main() -> None:
    ep = free_tcp_endpoint()
    sessions = (open_session(listen=[ep]), open_session(connect=[ep]))
    try:
        _main(sessions)
    finally:
        for s in sessions:
            s.close()


def _main(sessions: tuple[Any, Any]) -> None:
    seconds = float(os.environ.get("SWPC_BENCH_SIM_SECONDS", "10"))
    print(f"cores: {os.cpu_count()}, load average {os.getloadavg()[0]:.2f}")
    print(f"\n1. real time, {seconds:g} s: 4 nodes x 500 Hz feedback + 1 kHz poses (native)")
    r = _run(
        SimOptions(
            time_scale=1.0,
            feedback_rate_hz=500,
            mocap=MocapOptions(rate=1000.0),
            theta0=[0.0, 0.0, 0.0, 0.0],
        ),
        seconds,
        sessions,
    )
    print(
        f"   achieved: feedback {r['fb_min']:.1f}..{r['fb_max']:.1f} samples/s per node "
        f"(received), poses {r['poses']:.1f}/s (received), time scale {r['scale']:.3f}, "
        f"overruns {r['overruns']:.0f}, robot spinning at {r['yaw_rate']:.2f} rad/s"
    )
    print(
        f"   CPU: simulator thread {100 * r['sim_cpu']:.1f} % of one core, whole process "
        f"(with both receivers and zenoh) {100 * r['proc_cpu']:.1f} %"
    )
    print("\n2. time-scale sweep (feedback 200 Hz, poses 100 Hz, 3 s wall each)")
    print("   physics_dt  requested  achieved  sim CPU  overruns")
    sweep = [(0.002, s) for s in (1.0, 5.0, 20.0)] + [(0.005, s) for s in (1.0, 2, 5, 10, 20)]
    for dt, scale in sweep:
        r = _run(
            SimOptions(
                time_scale=scale,
                physics_dt=dt,
                feedback_rate_hz=200,
                watchdog_ms=0,
                mocap=MocapOptions(rate=100.0),
                theta0=[0.0, 0.0, 0.0, 0.0],
            ),
            3.0,
            sessions,
        )
        print(
            f"   {dt * 1e3:7.0f} ms  {scale:9.0f}  {r['scale']:8.2f}  "
            f"{100 * r['sim_cpu']:6.1f} %  {r['overruns']:8.0f}"
        )
