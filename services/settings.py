"""Service settings (pydantic-settings): environment variables ``SWPC_*`` and an env file.

With no CAN interface configured the service runs on the *embedded default*: the
simulator in-process on a python-can ``virtual`` bus and zenoh on loopback.
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

    can_interface: str | None = Field(None, description="python-can interface; unset: embedded")
    can_channel: str = "vcan0"
    can_bitrate: int = 1_000_000
    feedback_rate: int = Field(
        200,
        ge=1,
        le=500,
        description="encoder feedback rate the controllers are asked for, Hz of robot time "
        "(4 nodes x 2 frames at 200 Hz = 31 % of a 1 Mbit/s bus)",
    )
    heartbeat_timeout: float | None = Field(
        None,
        gt=0,
        description="host seconds without a heartbeat = node lost; default 0.3 s on a robot, "
        "1 s against a simulator (which shares a possibly loaded host)",
    )

    zenoh_mode: str = "peer"
    zenoh_listen: list[str] = Field(default_factory=list)
    zenoh_connect: list[str] = Field(default_factory=list)
    zenoh_config_file: str | None = None
    pose_encoding: str = Field("auto", description="native | ros2-cdr | auto")
    mocap_stale_after: float | None = Field(
        None,
        gt=0,
        description="host seconds without poses = stale; default 0.5 s on a robot, 1.5 s "
        "against a simulator (it stalls with a loaded host, and so does its robot)",
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

    time_scale: float = Field(1.0, gt=0, description="simulated-time speed-up (simulator only)")
    sim_seed: int = 1
    sim_physics_dt: float = Field(
        0.005, gt=0, le=0.01, description="embedded simulator: longest physics step, s"
    )
    sim_watchdog_host_s: float = Field(
        1.0,
        gt=0,
        le=30.0,
        description="against a simulator: the controllers' watchdog lasts at least this many "
        "host seconds (the simulator shares a possibly loaded host; an emulated one, the lab's "
        "VM, stalls for longer); a robot uses its config's limits.watchdog_ms",
    )
    sim_mocap_latency: float = Field(
        0.0, ge=0, le=5.0, description="embedded simulator: pose publication delay, robot s"
    )

    @property
    def embedded(self) -> bool:
        return self.can_interface is None

    @property
    def simulated(self) -> bool:
        """Talking to a simulator (embedded, or time-scaled) rather than a robot."""
        return self.embedded or self.time_scale != 1.0

    @property
    def heartbeat_timeout_s(self) -> float:
        if self.heartbeat_timeout is not None:
            return self.heartbeat_timeout
        return 1.0 if self.simulated else 0.3

    @property
    def mocap_stale_s(self) -> float:
        if self.mocap_stale_after is not None:
            return self.mocap_stale_after
        return 1.5 if self.simulated else 0.5

    @property
    def kinematics_file(self) -> Path:
        return self.kinematics_path or self.data_dir / "kinematics.yaml"

    def ensure_token(self) -> str:
        """The configured token, or a freshly generated one (embedded demo)."""
        if self.token is None:
            self.token = SecretStr(secrets.token_urlsafe(24))
        return self.token.get_secret_value()
