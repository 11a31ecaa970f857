"""Service settings (pydantic-settings): environment variables ``SWPC_*`` and an env file.

With no CAN interface configured the service runs on the *in-process simulator* (the
default of ``make demo``): the virtual robot in the service's own process, on a python-can
``virtual`` bus and zenoh on loopback, in simulated time (lockstep).  Durations are
seconds of robot time; :mod:`services.config.timing` derives every window from them.
"""

from __future__ import annotations

import ipaddress
import os
import secrets
import socket
from pathlib import Path
from typing import Literal

from pydantic import ByteSize, Field, SecretStr, field_validator, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from services.config.fleet import CONSOLE_URL, CONSOLE_URL_RULE, MAX_FLEET_PERIOD_S
from services.config.log_options import LogFormat, LogLevel
from swpc_hw.errors import SwpcError
from swpc_hw.sensors.gyro import GyroOptions

_GYRO = GyroOptions().human()
"""The in-process simulator's gyro by default: GyroOptions' defaults, in human units."""

MIN_TOKEN_LENGTH = 16
PLACEHOLDER_TOKENS = frozenset({"change-me", "changeme", "token", "secret", "password"})
"""Values a token must not have (``deploy/swpc.env.example`` ships ``change-me``)."""
KINEMATICS_BACKUPS = 20
"""Backups kept beside the kinematic file in force unless ``SWPC_KINEMATICS_BACKUPS`` says."""
TOKEN_FILE = "api-token"
"""Generated on loopback when no token is set: ``<data dir>/api-token``, mode 0600."""


def default_data_dir() -> Path:
    """The data dir when ``SWPC_DATA_DIR`` is unset: ``$XDG_STATE_HOME/swpc``, else
    ``~/.local/state/swpc`` (the XDG base directories' place for an application's state),
    never the current directory (a bare ``swpc serve`` in a checkout must not write into
    it).  The robot's units set ``/var/lib/swpc``."""
    state = os.environ.get("XDG_STATE_HOME", "")
    base = Path(state) if os.path.isabs(state) else Path.home() / ".local" / "state"
    return base / "swpc"


class SettingsError(SwpcError, ValueError):
    """The service's settings cannot be used as they are (names the setting)."""


class ServiceSettings(BaseSettings):
    model_config = SettingsConfigDict(
        env_prefix="SWPC_", env_file=None, extra="ignore", env_nested_delimiter="__"
    )

    host: str = Field("127.0.0.1", description="bind address (loopback by default)")
    allowed_hosts: list[str] = Field(
        default_factory=list,
        description="host names the API answers to, beyond an IP address, localhost and this "
        "host's own names (another Host header is refused 400: DNS rebinding)",
    )
    port: int = Field(8080, ge=0, le=65535)
    token: SecretStr | None = Field(
        None,
        description="bearer token for motion/write endpoints, at least 16 characters; "
        "required when binding beyond loopback",
    )
    max_body_bytes: int = Field(
        65536, ge=1024, le=16 << 20, description="largest request body accepted, bytes"
    )
    header_timeout: float = Field(
        10.0,
        gt=0,
        le=300,
        description="host seconds a connection may take to send a complete request head "
        "(and stay idle between requests) before it is closed",
    )
    max_connections: int = Field(
        128,
        ge=4,
        le=8192,
        description="open HTTP connections at most; beyond it the one idle longest, else the "
        "oldest event stream, else the oldest read in progress is closed for the new one",
    )
    max_streams: int = Field(
        32,
        ge=2,
        description="open event streams (GET /events) at most, at most half of "
        "max_connections: the rest stay for control (abort, /health); half of them for "
        "clients without the token",
    )
    streams_per_client: int = Field(
        4, ge=1, description="open event streams without the token at most, per client address"
    )
    log_level: LogLevel = Field(
        "info",
        description="the lowest level of swpc's and uvicorn's log lines written (other "
        "libraries': warning at least); `swpc serve --log-level` overrides it",
    )
    log_format: LogFormat = Field(
        "text",
        description="'text' (time, level, logger, message; no time when stderr is the "
        "journal, which stamps each line) or 'json' (one object per line: time, level, "
        "logger, message and the event's fields); `swpc serve --log-format` overrides it",
    )

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
        "default 200 on a CAN interface (4 nodes x 2 frames = 31 % of a 1 Mbit/s bus), 50 "
        "against the in-process simulator (with its 10 ms physics step: 40 % less CPU "
        "than 200 Hz / 5 ms, errors on the paper robot within 0.02 mm / 0.002 deg)",
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
    zenoh_users_file: Path | None = Field(
        None,
        description="zenoh peers allowed to connect to this service, as user:password lines "
        "(zenoh's user-password dictionary); with it, only zenoh_publishers may publish the "
        "robot's poses and gyro (a service that listens; one that connects trusts its peer)",
    )
    zenoh_publishers: list[str] = Field(
        default_factory=lambda: ["mocap"],
        description="with zenoh_users_file: the users that may publish the robot's sensor keys",
    )
    fleet_publish: bool = Field(
        False,
        description="publish this robot's state (the file in force, the last check, the "
        "history of calibrations, health) to the fleet over zenoh (docs/fleet.md)",
    )
    fleet_robot: str | None = Field(
        None, description="this robot's name in the fleet; unset: the robot config's robot:"
    )
    fleet_period: float = Field(
        5.0,
        gt=0,
        le=MAX_FLEET_PERIOD_S,
        description="host seconds between two publications of the state when nothing changed "
        "(the fleet period; each such publication is a repeat); a change is published "
        "within 0.5 s",
    )
    fleet_mode: str = Field(
        "peer",
        description="zenoh mode of the fleet session (peer: it retries the router in the "
        "background, so a router that is down never stops the service)",
    )
    fleet_connect: list[str] = Field(
        default_factory=list,
        description="zenoh endpoints of the fleet's router (a session of its own, apart from "
        "the sensors')",
    )
    fleet_config_file: str | None = Field(
        None, description="zenoh JSON5 config of the fleet session"
    )
    fleet_console_url: str | None = Field(
        None,
        description="where the lab reaches this robot's operator console (e.g. "
        "http://robot07.lab:8080/): the fleet page links each robot to it; the service "
        "cannot know the name the lab uses for it",
    )
    fleet_user: str | None = Field(
        None, description="zenoh user of the fleet session; unset: the robot's fleet name"
    )
    fleet_password: SecretStr | None = Field(
        None,
        description="zenoh password of the fleet session (the fleet's router admits only "
        "its users, and each robot publishes under its own name only: docs/fleet.md)",
    )
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

    metrology: Literal["mocap", "imu", "both"] = Field(
        "mocap",
        description="what this lab measures the robot's motion with: 'mocap' (motion "
        "capture), 'imu' (no motion capture: the robot's gyro and a tape measure) or 'both'. "
        "GET /health requires these sensors live; a run's metrology defaults to 'imu' with "
        "'imu', else to 'mocap'",
    )

    robot_config: Path | None = Field(None, description="robot config YAML; unset: paper robot")
    data_dir: Path = Field(
        default_factory=default_data_dir,
        description="runs, datasets, logs, the kinematic file and a generated token "
        "(default: $XDG_STATE_HOME/swpc, else ~/.local/state/swpc)",
    )
    kinematics_path: Path | None = Field(None, description="default: <data_dir>/kinematics.yaml")
    kinematics_backups: int = Field(
        KINEMATICS_BACKUPS,
        ge=1,
        le=10_000,
        description="backups kept beside the kinematic file in force (each install keeps the "
        "file it replaces, unless identical to the newest backup; the oldest beyond this "
        "number are removed)",
    )
    file_group: str | None = Field(
        None,
        description="group that may read what the service writes (the kinematic file, run "
        "data): the data dir is given this group and the setgid bit, so every file in it "
        "inherits it; the service must be a member",
    )
    can_log_bytes: ByteSize = Field(
        ByteSize(64 << 20),
        ge=0,
        description="rolling log of the CAN traffic (python-can's rotating logger, candump "
        "format) in <data_dir>/can/: at most this many bytes over all its files; 0: none "
        "(can_log_idle_period: what it keeps between runs)",
    )
    can_log_idle_period: float = Field(
        1.0,
        ge=0,
        le=3600,
        description="between runs the rolling CAN log keeps each periodic frame (heartbeat, "
        "encoder feedback, another device's) once per this many seconds per CAN id, and "
        "every event (a command, a fault report, a homing status, an error frame, a "
        "heartbeat that changed) at once; during a run, every frame; 0: every frame always "
        "(an idle robot at 200 Hz feedback: ~360 MB an hour written, ~3 MB at 1 s)",
    )
    disk_budget: ByteSize = Field(
        ByteSize(4 << 30),
        ge=1 << 20,
        description="most bytes the data dir may hold; the raw recordings (can.log, "
        "run.mcap) of the oldest runs are pruned to stay within it, and a run that cannot "
        "fit fails",
    )
    mcap_profile: Literal["foxglove", "ros2"] = Field(
        "foxglove",
        description="the run's MCAP (run.mcap): foxglove (JSON, Foxglove's schemas) or ros2 "
        "(CDR, ROS 2 ros2msg schemas: PoseStamped, TFMessage, JointState; docs/ros2.md)",
    )
    min_free: ByteSize = Field(
        ByteSize(256 << 20),
        ge=0,
        description="free space to leave on the data dir's file system: no run starts, and a "
        "running one fails, below it",
    )

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
    sim_truth: Path | None = Field(
        None,
        description="in-process simulator: a kinematic file of the robot's hidden truth "
        "(its module ids the robot config's); unset: the paper's Table 4 calibrated values",
    )
    sim_wiring: Path | None = Field(
        None,
        description="in-process simulator: a YAML file of how its drives are really wired "
        "(crossed, swapped, inverted, another ratio, a turned motion-capture body; "
        "simulators/drives/wiring.py); unset: as the robot config says",
    )
    sim_robot_config: Path | None = Field(
        None,
        description="in-process simulator: the robot config the robot was built from (its "
        "drives' kind and nodes, which SWPC_SIM_WIRING is relative to) when the service's "
        "differs (a config corrected by commissioning); unset: the service's",
    )
    sim_physics_dt: float = Field(
        0.01,
        gt=0,
        le=0.01,
        description="in-process simulator: longest physics step, s (it also steps at every "
        "frame and pose due in between)",
    )
    sim_host_window_s: float = Field(
        1.0,
        gt=0,
        le=30.0,
        description="against an external time-scaled simulator: the watchdog, heartbeat and "
        "stale windows last at least this many host seconds (the simulator shares, or "
        "emulates, the host); a robot and the in-process simulator use the robot's windows",
    )
    sim_mocap_qtm_port: int | None = Field(
        None,
        ge=0,
        le=65535,
        description="in-process simulator: serve its motion capture as a QTM real-time server "
        "on this loopback port (0: a free one) instead of publishing the poses; `swpc mocap "
        "--source qtm://127.0.0.1:PORT` then puts them on the pose key (docs/mocap-bridge.md)",
    )
    sim_mocap_latency: float = Field(
        0.0, ge=0, le=5.0, description="in-process simulator: pose publication delay, robot s"
    )
    sim_gyro_rate: float = Field(
        _GYRO[0], gt=0, le=2000, description="in-process simulator: gyro samples per robot s, Hz"
    )
    sim_gyro_noise: float = Field(
        _GYRO[1], ge=0, le=10, description="in-process simulator: gyro white noise, deg/s/sqrt(Hz)"
    )
    sim_gyro_bias: float = Field(
        _GYRO[2], ge=-100, le=100, description="in-process simulator: gyro bias at start, deg/s"
    )
    sim_gyro_bias_walk: float = Field(
        _GYRO[3],
        ge=0,
        le=10,
        description="in-process simulator: random walk of the gyro bias, deg/s/sqrt(s)",
    )
    sim_gyro_scale_error: float = Field(
        _GYRO[4], gt=-50, lt=50, description="in-process simulator: gyro scale error, %"
    )

    @model_validator(mode="after")
    def _streams_leave_room(self) -> ServiceSettings:
        if self.max_streams > self.max_connections // 2:
            raise ValueError(
                f"max_streams {self.max_streams} is over half of max_connections "
                f"{self.max_connections}: event streams would leave no room for an abort"
            )
        return self

    @field_validator("fleet_console_url")
    @classmethod
    def _console_url(cls, v: str | None) -> str | None:
        if v is not None and not CONSOLE_URL.fullmatch(v):
            raise ValueError(f"{CONSOLE_URL_RULE} is needed")
        return v

    @field_validator("log_level", "log_format", mode="before")
    @classmethod
    def _lower(cls, value: object) -> object:
        return value.strip().lower() if isinstance(value, str) else value

    @property
    def in_process(self) -> bool:
        """No CAN interface: the simulator runs in this process, in simulated time."""
        return self.can_interface is None

    @property
    def feedback_rate_hz(self) -> int:
        """The feedback rate in effect (``feedback_rate``, or its default)."""
        if self.feedback_rate is not None:
            return self.feedback_rate
        return 50 if self.in_process else 200

    @property
    def external_time_scale(self) -> float:
        """Rate of the service clock against the host's (1 on a robot and in-process)."""
        return 1.0 if self.in_process else self.time_scale

    @property
    def sim_gyro(self) -> GyroOptions:
        """The in-process simulator's gyro (``sim_gyro_*``), also the gyro a plan without
        motion capture assumes (docs/plan.md)."""
        return GyroOptions.from_human(
            self.sim_gyro_rate,
            self.sim_gyro_noise,
            self.sim_gyro_bias,
            self.sim_gyro_bias_walk,
            self.sim_gyro_scale_error,
        )

    @property
    def run_metrology(self) -> Literal["mocap", "imu"]:
        """A run's metrology when its request names none (``metrology``'s rule)."""
        return "imu" if self.metrology == "imu" else "mocap"

    @property
    def kinematics_file(self) -> Path:
        return self.kinematics_path or self.data_dir / "kinematics.yaml"

    @property
    def loopback_only(self) -> bool:
        """The bind address is a loopback address (or ``localhost``)."""
        if self.host == "localhost":
            return True
        try:
            return ipaddress.ip_address(self.host).is_loopback
        except ValueError:
            return False

    def check_token(self) -> str | None:
        """The configured token after the checks (``None`` when none is set).

        Raises :class:`SettingsError` for an empty, placeholder or short token, and for no
        token when binding beyond loopback (a generated one would have to be shown to
        someone: the journal is no place for it).
        """
        if self.token is None:
            if not self.loopback_only:
                raise SettingsError(
                    f"SWPC_TOKEN is required when binding to {self.host} (beyond loopback): "
                    f"set one of at least {MIN_TOKEN_LENGTH} characters "
                    "(e.g. openssl rand -base64 24)"
                )
            return None
        token = self.token.get_secret_value()
        if not token.strip():
            raise SettingsError("SWPC_TOKEN is empty: set a token or remove the setting")
        if token.strip().lower() in PLACEHOLDER_TOKENS:
            raise SettingsError(
                "SWPC_TOKEN is the example's placeholder: set a token of your own "
                "(e.g. openssl rand -base64 24)"
            )
        if len(token) < MIN_TOKEN_LENGTH:
            raise SettingsError(
                f"SWPC_TOKEN is {len(token)} characters: at least {MIN_TOKEN_LENGTH} are needed"
            )
        return token

    def host_names(self) -> frozenset[str]:
        """The names in a Host header the API answers to (an IP address always passes)."""
        names = {"localhost", socket.gethostname(), socket.getfqdn(), self.host}
        names.update(self.allowed_hosts)
        return frozenset(n.strip().lower().rstrip(".") for n in names if n.strip())

    @property
    def token_file(self) -> Path:
        return self.data_dir / TOKEN_FILE

    def ensure_data_dir(self) -> Path:
        """The data dir, made if missing; :class:`SettingsError` naming ``SWPC_DATA_DIR``
        when it cannot be one (a file is there, no permission, ...)."""
        path = self.data_dir
        if path.exists() and not path.is_dir():
            raise SettingsError(
                f"SWPC_DATA_DIR={path}: not a directory (a file is there): point it at a "
                "directory, or remove the file"
            )
        try:
            path.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise SettingsError(
                f"SWPC_DATA_DIR={path}: cannot make the data dir: {exc.strerror or exc}"
            ) from exc
        return path

    def ensure_token(self) -> str:
        """The configured token (checked); on loopback with none set, the one kept in
        ``<data dir>/api-token`` (mode 0600, created on first use, tightened to 0600 when
        found looser).  Never printed."""
        token = self.check_token()
        if token is not None:
            return token
        path = self.token_file
        self.ensure_data_dir()
        try:
            kept = path.read_text(encoding="utf-8").strip()
            if path.stat().st_mode & 0o077:
                os.chmod(path, 0o600)  # a secret: the service's user only
        except FileNotFoundError:
            kept = ""
        except (OSError, UnicodeDecodeError) as exc:
            raise SettingsError(f"{path}: cannot read the generated token: {exc}") from exc
        if len(kept) < MIN_TOKEN_LENGTH:
            kept = secrets.token_urlsafe(24)
            try:
                path.parent.mkdir(parents=True, exist_ok=True)
                fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
                with os.fdopen(fd, "w", encoding="utf-8") as fh:
                    fh.write(kept + "\n")
                os.chmod(path, 0o600)
            except OSError as exc:
                raise SettingsError(f"{path}: cannot keep the generated token: {exc}") from exc
        self.token = SecretStr(kept)
        return kept
