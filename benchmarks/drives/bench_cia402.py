"""Bus load of a CiA 402 robot at the robot's rates: 4 modules, 8 single-axis drives.

The host (:mod:`swpc_hw.drives.cia402`) and the virtual robot's CiA 402 drives
(:mod:`simulators.drives.cia402`) in lockstep on python-can's virtual bus, with the
service's robot timing (:func:`services.config.timing.bus_config` for a robot: feedback
(SYNC) 200 Hz, the host's heartbeat every ``T_ref`` = 20 ms, the drives' every 0.1 s):
set-up, homing, then a spin (module 1 locked: steering and wheel in cyclic synchronous
position; the others' steering free, wheel torque) for 10 s of robot time.  Every frame
on the bus is counted with its worst-case stuffed length
(:func:`firmware_protocol.busload.frame_bits`) over the spin's last 8 s, and the load
printed at 500 kbit/s and 1 Mbit/s, by traffic class, next to the budget the PDO mapping
predicts.

``python -m benchmarks cia402`` (``make bench``).
"""

from __future__ import annotations

import uuid
from collections import Counter

import can
from pydantic import SecretStr

from firmware_protocol import busload, cia402
from firmware_protocol.codec import Axis
from services.config.robot import RobotConfig
from services.config.settings import ServiceSettings
from services.config.timing import bus_config
from simulators.options import SimOptions
from simulators.virtual_robot import VirtualRobot
from swpc_hw.clock import SimClock
from swpc_hw.drives.cia402.config import Cia402Drives
from swpc_hw.drives.cia402.driver import Cia402Driver
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED

BITRATES = (500_000, 1_000_000)
SPIN_S = 10.0
WINDOW_S = 8.0


def _class(can_id: int) -> str:
    if can_id == cia402.SYNC_ID:
        return "SYNC"
    base = can_id & 0x780
    return {
        0x180: "TPDO 1 (statusword, position, mode)",
        0x280: "TPDO 2 (velocity, torque)",
        0x200: "RPDO 1 (controlword, mode, torque)",
        0x300: "RPDO 2 (targets)",
        0x700: "heartbeats (8 drives + host)",
        0x080: "EMCY",
        0x580: "SDO",
        0x600: "SDO",
    }.get(base, "other")


def predicted(rate: float, heartbeat: float, host_heartbeat: float, axes: int) -> float:
    """bit/s the mapping streams whatever the motion: SYNC + both TPDOs of every axis per
    sample, every drive's heartbeat and the host's."""
    tpdo = sum(
        busload.frame_bits(sum(bits for *_, bits in entries) // 8)
        for entries in cia402.TPDO_MAP.values()
    )
    per_sample = busload.frame_bits(0) + axes * tpdo
    beats = busload.frame_bits(1) * (axes * heartbeat + host_heartbeat)
    return rate * per_sample + beats


def main() -> None:
    settings = ServiceSettings(can_interface="socketcan", token=SecretStr("x" * 16))
    robot = RobotConfig.model_validate({"drives": "cia402"})
    drives = robot.drives
    assert isinstance(drives, Cia402Drives)
    ch = f"bench-cia402-{uuid.uuid4().hex[:8]}"
    bus = bus_config(settings, robot, interface="virtual", channel=ch)
    rate = bus.feedback_rate_hz
    clock = SimClock()
    host = Cia402Driver(drives, bus, clock=clock)
    host.configure()
    opts = SimOptions(drives=drives, physics_dt=1.0 / rate, seed=1)  # a tick per SYNC
    sim = VirtualRobot.open(PAPER_CALIBRATED, channel=ch, options=opts, clock=clock)
    obs = can.Bus(interface="virtual", channel=ch, preserve_timestamps=True)
    sim.start()
    try:
        with clock.participant():
            host.activate()
            for m in host.modules():
                host.enable(m, Axis.STEER)
                host.enable(m, Axis.WHEEL)
                host.start_homing(m)
            for m in host.modules():
                host.wait_for(m, lambda s: s.homed, 5.0, "homed")
            host.set_position(1, Axis.STEER, 0.8)
            host.hold(1, Axis.WHEEL)
            for m in host.modules()[1:]:
                host.free(m, Axis.STEER)
                host.set_torque(m, Axis.WHEEL, robot.limits.spin_torque)
            t0 = clock.now()
            clock.sleep(SPIN_S)
            t1 = clock.now()
            host.stop_all()
    finally:
        sim.stop()
        host.shutdown()
        clock.close()
    bits: Counter[str] = Counter()
    frames: Counter[str] = Counter()
    start = t1 - WINDOW_S
    msg = obs.recv(0)
    while msg is not None:
        t = clock.from_wall(msg.timestamp)
        if start <= t < t1 and not msg.is_error_frame:
            k = _class(msg.arbitration_id)
            bits[k] += busload.frame_bits(len(msg.data))
            frames[k] += 1
        msg = obs.recv(0)
    obs.shutdown()
    total = sum(bits.values()) / WINDOW_S
    print(f"CiA 402 robot: {len(host.modules())} modules, 8 drives; SYNC {rate} Hz, host "
          f"heartbeat every {bus.refresh_period_s * 1e3:g} ms, drives' every "
          f"{bus.heartbeat_period_s * 1e3:g} ms; spin {t1 - t0:g} s, counted over the last "
          f"{WINDOW_S:g} s (robot time), worst-case bit stuffing")  # fmt: skip
    print(f"{'traffic':40s} {'frames/s':>9s} {'kbit/s':>8s}")
    for k in sorted(bits, key=lambda k: -bits[k]):
        print(f"{k:40s} {frames[k] / WINDOW_S:9.1f} {bits[k] / WINDOW_S / 1e3:8.1f}")
    pred = predicted(rate, 1 / bus.heartbeat_period_s, 1 / bus.refresh_period_s, 8)
    print(f"{'total':40s} {sum(frames.values()) / WINDOW_S:9.1f} {total / 1e3:8.1f}   "
          f"(the mapping's streaming budget: {pred / 1e3:.1f} kbit/s)")  # fmt: skip
    for br in BITRATES:
        print(f"bus load at {br / 1e3:g} kbit/s: {100 * total / br:.1f} %")
    if total / 1e6 >= 0.6:
        raise SystemExit(f"bus load {100 * total / 1e6:.1f} % at 1 Mbit/s: not under 60 %")
