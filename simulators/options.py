"""Settings and counters of the virtual robot (:class:`simulators.virtual_robot.VirtualRobot`)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

from firmware_protocol import codec
from simulators.drives.wiring import WIRED_AS_CONFIGURED, Wiring
from simulators.physics.robot import PhysicsOptions
from simulators.sensors.gyro import check_gyro
from simulators.sensors.mocap import MocapOptions
from swpc_hw.drives.registry import DrivesConfig
from swpc_hw.drives.swpc.config import SwpcDrives
from swpc_hw.files.kinematic_file import kinematics_document
from swpc_hw.robot.model import RobotParams
from swpc_hw.sensors.gyro import GyroOptions


@dataclass(frozen=True)
class SimOptions:
    """Settings of the virtual robot (SI units; simulated time)."""

    robot: str = "swpc"
    drives: DrivesConfig = field(default_factory=SwpcDrives)
    """The drive kind and each module's CAN nodes (default: swpc's own, nodes 1..N in
    module order), as in a robot config (:mod:`swpc_hw.drives.registry`)."""
    time_scale: float = 1.0
    physics_dt: float = 0.005
    """Longest physics step (s); a tick is also no longer than the fastest feedback period."""
    start_time: float | None = None
    """Simulated clock at start (default: the wall clock, ``time.time()``)."""
    steer_counts: int = 2**17
    wheel_counts: int = 2**17
    """Encoder counts per turn (0: no quantisation before the frame's own)."""
    position_tau: float = 0.02
    feedback_rate_hz: int = codec.POWER_UP_FEEDBACK_RATE_HZ
    watchdog_ms: int = codec.POWER_UP_WATCHDOG_MS
    homing_duration: float = 0.2
    sensor_positions: Sequence[float] | None = None
    """Power-up steering coordinate of each homing sensor (default: seeded random)."""
    pose0: tuple[float, float, float] = (0.0, 0.0, 0.0)
    theta0: Sequence[float] | None = None
    """Initial true steering angles (default: seeded random)."""
    physics: PhysicsOptions = field(default_factory=PhysicsOptions)
    mocap: MocapOptions = field(default_factory=MocapOptions)
    gyro: GyroOptions = field(default_factory=GyroOptions)
    """The z gyro fixed to R (:mod:`simulators.sensors.gyro`), published on ``imu/<robot>/data``."""
    truth_rate: float = 50.0
    bus_error_rate: float = 0.0
    max_lag: float = 0.05
    """Wall seconds the simulation may fall behind before its clock is slowed down."""
    mocap_clock: str = "host"
    """Pose time stamps: ``"host"`` wall clock at sampling, or ``"sim"`` simulated time."""
    seed: int = 0
    wiring: Wiring = WIRED_AS_CONFIGURED
    """How the drives are really wired (crossed, swapped, inverted, another ratio; a rotated
    motion-capture body): the hidden truth beside the config (:mod:`simulators.drives.wiring`)."""

    def __post_init__(self) -> None:
        if not self.time_scale > 0.0:
            raise ValueError("time_scale must be > 0")
        if self.mocap_clock not in ("host", "sim"):
            raise ValueError(f"mocap_clock must be 'host' or 'sim', not {self.mocap_clock!r}")
        if not 0.0 < self.physics_dt <= 0.01:
            raise ValueError("physics_dt must be in (0, 0.01] s")
        check_gyro(self.gyro)


@dataclass
class SimStats:
    """Counters since :meth:`VirtualRobot.start` (times in s)."""

    sim_time: float = 0.0
    wall_time: float = 0.0
    cpu_time: float = 0.0
    ticks: int = 0
    overruns: int = 0
    frames_tx: int = 0
    frames_rx: int = 0
    tx_errors: int = 0
    bus_errors_injected: int = 0
    feedback_frames: dict[int, int] = field(default_factory=dict)
    heartbeats: dict[int, int] = field(default_factory=dict)
    """Per module id: the feedback frames and heartbeats its drives sent."""
    poses_published: int = 0
    gyro_published: int = 0
    truth_published: int = 0

    @property
    def achieved_time_scale(self) -> float:
        return self.sim_time / self.wall_time if self.wall_time > 0 else 0.0

    @property
    def cpu_share(self) -> float:
        """CPU seconds of the simulator thread per wall second (1.0 = one full core)."""
        return self.cpu_time / self.wall_time if self.wall_time > 0 else 0.0

    def rates(self) -> dict[str, float]:
        """Per-module feedback frames/s and heartbeats/s, poses/s, in *simulated* time."""
        t = self.sim_time if self.sim_time > 0 else math.inf
        out: dict[str, float] = {"poses_hz": self.poses_published / t}
        for module, n in sorted(self.feedback_frames.items()):
            out[f"module{module}_feedback_hz"] = n / t
        for module, n in sorted(self.heartbeats.items()):
            out[f"module{module}_heartbeat_hz"] = n / t
        return out


def _signal_scale(name: str) -> float:
    msg = codec.message_for(1, codec.Command.FEEDBACK_POSITION)
    return float(msg.get_signal_by_name(name).scale)


def params_document(
    truth: RobotParams,
    drives: Mapping[int, Mapping[str, Any]],
    opt: SimOptions,
    sensors: Sequence[float],
) -> dict[str, Any]:
    """The ``sim/<robot>/truth/params`` document: the true robot as a kinematic file, each
    module's drives (kind, CAN nodes) and the simulator's settings (``sensors``: the homing
    sensors' power-up steering coordinates)."""
    doc = kinematics_document(
        truth, extra={"note": "simulator ground truth (tests and validation only)"}
    )
    doc["drives"] = {str(m): dict(d) for m, d in drives.items()}
    doc["simulator"] = {
        "time_scale": opt.time_scale,
        "physics_dt": opt.physics_dt,
        "steer_counts": opt.steer_counts,
        "wheel_counts": opt.wheel_counts,
        "frame_steer_counts": round(2 * math.pi / _signal_scale("SteerPosition")),
        "frame_wheel_counts": round(2 * math.pi / _signal_scale("WheelPosition")),
        "sensor_positions": list(sensors),
        "physics": asdict(opt.physics),
        "mocap": asdict(opt.mocap),
        "gyro": asdict(opt.gyro),
    }
    return doc
