"""Service settings (pydantic-settings): environment variables ``SWPC_*`` and an env file.

With no CAN interface configured the service runs on the *in-process simulator* (the
default of ``make demo``): the virtual robot in the service's own process, on a python-can
``virtual`` bus and zenoh on loopback, in simulated time (lockstep).  Durations are
seconds of robot time; :mod:`services.timing` derives every window from them.
"""

from __future__ import annotations

import secrets
from pathlib import Path
from typing import Literal

from pydantic import Field, SecretStr
from pydantic_settings import BaseSettings, SettingsConfigDict


class ServiceSettings(BaseSettings):
    model_config = SettingsConfigDict(
        env_prefix="SWPC_", env_file=None, extra="ignore", env_nested_delimiter="__"
    )

    host: str = Field("127.0.0.1", description="bind address (loopback by default)")
    port: int = Field(8080, ge=0, le=65535)
    token: SecretStr | None = Field(None, description="bearer token for motion/write endpoints")

    can_interface: str | None = Field(
        None, description="python-can interface; unset: in-process simulator"
    )
    can_channel: str = "vcan0"
    can_bitrate: int = 1_000_000
    feedback_rate: int | None = Field(
        None,
        ge=1,
        le=500,
        description="encoder feedback rate the controllers are asked for, Hz of robot time; "
        "default 200 on a CAN interface (4 nodes x 2 frames = 31 % of a 1 Mbit/s bus), 100 "
        "against the in-process simulator (half its CPU; the same accuracy)",
    )
    heartbeat_timeout: float | None = Field(
        None,
        gt=0,
        le=60,
        description="robot seconds without a heartbeat = node lost (default 0.3; against an "
        "external time-scaled simulator at least time_scale x sim_host_window_s)",
    )

    zenoh_mode: str = "peer"
    zenoh_listen: list[str] = Field(default_factory=list)
    zenoh_connect: list[str] = Field(default_factory=list)
    zenoh_config_file: str | None = None
    pose_encoding: str = Field("auto", description="native | ros2-cdr | auto")
    mocap_stale_after: float | None = Field(
        None,
        gt=0,
        le=60,
        description="robot seconds without poses = stale (default 0.5; against an external "
        "time-scaled simulator at least time_scale x sim_host_window_s)",
    )
    mocap_clock: Literal["source", "receive", "wall"] = Field(
        "source",
        description="pose time base: 'source' (the mocap's time stamps mapped to the host "
        "clock by the lower envelope of the delays: any mocap, late by the smallest "
        "transport delay), 'wall' (the stamps are this host's wall clock: `swpc sim` on "
        "this machine, or a mocap synchronised by PTP/chrony; exact) or 'receive' (host "
        "receive time: transport jitter)",
    )

    robot_config: Path | None = Field(None, description="robot config YAML; unset: paper robot")
    data_dir: Path = Path("swpc-data")
    kinematics_path: Path | None = Field(None, description="default: <data_dir>/kinematics.yaml")

    time_scale: float = Field(
        1.0,
        gt=0,
        le=100,
        description="an external simulator (`swpc sim --time-scale k` on a CAN interface) runs "
        "k times faster than real time: the service's clock runs at the same rate",
    )
    sim_speed: float = Field(
        0.0,
        ge=0,
        le=1000,
        description="in-process simulator: most simulated seconds per wall second (0: as fast "
        "as the host can; 1: real time, to watch a run); it never faults when slower",
    )
    sim_seed: int = 1
    sim_physics_dt: float = Field(
        0.005, gt=0, le=0.01, description="in-process simulator: longest physics step, s"
    )
    sim_host_window_s: float = Field(
        1.0,
        gt=0,
        le=30.0,
        description="against an external time-scaled simulator: the watchdog, heartbeat and "
        "stale windows last at least this many host seconds (the simulator shares, or "
        "emulates, the host); a robot and the in-process simulator use the robot's windows",
    )
    sim_mocap_latency: float = Field(
        0.0, ge=0, le=5.0, description="in-process simulator: pose publication delay, robot s"
    )

    @property
    def in_process(self) -> bool:
        """No CAN interface: the simulator runs in this process, in simulated time."""
        return self.can_interface is None

    @property
    def feedback_rate_hz(self) -> int:
        """The feedback rate in effect (``feedback_rate``, or its default)."""
        if self.feedback_rate is not None:
            return self.feedback_rate
        return 100 if self.in_process else 200

    @property
    def external_time_scale(self) -> float:
        """Rate of the service clock against the host's (1 on a robot and in-process)."""
        return 1.0 if self.in_process else self.time_scale

    @property
    def kinematics_file(self) -> Path:
        return self.kinematics_path or self.data_dir / "kinematics.yaml"

    def ensure_token(self) -> str:
        """The configured token, or a freshly generated one."""
        if self.token is None:
            self.token = SecretStr(secrets.token_urlsafe(24))
        return self.token.get_secret_value()
