"""Bus load of ODrive drives at the robot's rates: computed, and counted on a running bus.

The robot's rates are the service's on a CAN interface (:func:`services.config.timing.
timing_budget`): encoder estimates at the feedback rate (200 Hz), heartbeats every
``T_hb``, every armed axis' setpoint refreshed every ``T_ref``; 4 modules, 8 axes (one node
each).  Frame lengths are worst-case stuffed (:func:`firmware_protocol.busload.frame_bits`)
with each frame's DLC from ODrive's DBC.

Then the same counted: the ODrive driver and the virtual robot's virtual ODrives in
lockstep on python-can's virtual bus, every axis armed and refreshed for 20 s of robot time,
every frame on the bus counted by kind (one more bus listening).

``python -m benchmarks odrive`` (``make bench``).
"""

from __future__ import annotations

import uuid
from collections import Counter

import can

from firmware_protocol.busload import frame_bits
from firmware_protocol.codec import Axis
from firmware_protocol.odrive import can_simple as cs
from services.config.robot import RobotConfig
from services.config.settings import ServiceSettings
from services.config.timing import bus_config, timing_budget
from simulators.options import SimOptions
from simulators.virtual_robot import VirtualRobot
from swpc_hw.clock import SimClock
from swpc_hw.drives.registry import open_drives
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED

SECONDS = 20.0
BITRATES = (500_000, 1_000_000)


def robot() -> tuple[ServiceSettings, RobotConfig]:
    config = RobotConfig.model_validate({"drives": {"kind": "odrive", "firmware": "0.6"}})
    return ServiceSettings(can_interface="socketcan", can_channel="can0"), config


def computed() -> dict[str, float]:
    """bit/s of each traffic class, 8 axes at the robot's rates."""
    settings, config = robot()
    b = timing_budget(settings, config)
    c = cs.can_simple("0.6")
    axes = len(config.drives.nodes())

    def bits(cmd: cs.Cmd) -> int:
        return frame_bits(c.message(cmd).length)

    return {
        "encoder estimates": axes / b.feedback_period * bits(cs.Cmd.GET_ENCODER_ESTIMATES),
        "heartbeats": axes / b.heartbeat_period * bits(cs.Cmd.HEARTBEAT),
        "setpoint refresh": axes / b.refresh * bits(cs.Cmd.SET_INPUT_POS),
    }


def counted() -> tuple[Counter[str], Counter[str], float]:
    """Frames and worst-case bits by kind over ``SECONDS`` of robot time, every axis armed."""
    settings, config = robot()
    clock = SimClock()
    channel = f"bench-odrive-{uuid.uuid4().hex[:8]}"
    bus = bus_config(settings, config, interface="virtual", channel=channel)
    sim_bus = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
    listen = can.Bus(interface="virtual", channel=channel)
    sim = VirtualRobot(
        PAPER_CALIBRATED,
        bus=sim_bus,
        options=SimOptions(
            drives=config.drives,
            feedback_rate_hz=bus.feedback_rate_hz,
            watchdog_ms=config.limits.watchdog_ms,
        ),
        clock=clock,
    )
    drives = open_drives(config.drives, bus, config.nominal.ids, clock=clock)
    c = cs.can_simple("0.6")
    frames: Counter[str] = Counter()
    bits: Counter[str] = Counter()
    with clock.participant():
        sim.start()
        drives.configure()
        try:
            drives.activate()
            for m in drives.modules():
                drives.enable(m, Axis.STEER)
                drives.enable(m, Axis.WHEEL)
                drives.free(m, Axis.STEER)
                drives.hold(m, Axis.WHEEL)
            while listen.recv(0) is not None:
                pass
            t0 = clock.now()
            while clock.now() < t0 + SECONDS:
                clock.sleep(0.05)
                msg = listen.recv(0)
                while msg is not None:
                    _, cmd = cs.split_id(msg.arbitration_id)
                    name = c.message(cmd).name[6:] if cmd in (*c.axis_cmds, *c.host_cmds) else "?"
                    frames[name] += 1
                    bits[name] += frame_bits(msg.dlc)
                    msg = listen.recv(0)
            span = clock.now() - t0
        finally:
            drives.shutdown()
            sim.stop()
            clock.close()
            sim_bus.shutdown()
            listen.shutdown()
    return frames, bits, span


def main() -> None:
    settings, config = robot()
    b = timing_budget(settings, config)
    print(f"ODrive drives, 4 modules = 8 axes (one node each), firmware 0.6: encoder "
          f"estimates {1 / b.feedback_period:g} Hz, heartbeat {1 / b.heartbeat_period:g} Hz, "
          f"setpoint refresh every {b.refresh * 1e3:g} ms per armed axis (worst-case bit "
          "stuffing)")  # fmt: skip
    comp = computed()
    total = sum(comp.values())
    for name, v in comp.items():
        print(f"  computed {name:18s} {v / 1e3:7.1f} kbit/s")
    print("  computed total             " + "; ".join(
        f"{total / 1e3:.1f} kbit/s = {100 * total / r:.1f} % of {r / 1e6:g} Mbit/s"
        for r in BITRATES
    ))  # fmt: skip
    frames, bits, span = counted()
    for name in sorted(frames):
        print(f"  counted  {name:22s} {frames[name] / span:7.1f} frames/s "
              f"{bits[name] / span / 1e3:7.1f} kbit/s")  # fmt: skip
    load = sum(bits.values()) / span
    print(f"  counted  total over {span:g} s of robot time, every axis armed: " + "; ".join(
        f"{load / 1e3:.1f} kbit/s = {100 * load / r:.1f} % of {r / 1e6:g} Mbit/s" for r in BITRATES
    ))  # fmt: skip
