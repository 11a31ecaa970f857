"""The bus and timing settings every drive kind gets (:class:`CanConfig`), and the drive
facts the service's timing budget (:mod:`services.config.timing`) starts from, each stated
once: the command watchdog ``W`` (:data:`DEFAULT_WATCHDOG_MS`), the dead-man ``D``
(:data:`DEADMAN_S`), heartbeat loss ``L`` (:data:`HEARTBEAT_LOSS_PERIODS` heartbeat
periods, :data:`HEARTBEAT_LOSS_S`)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from typing import Any

from firmware_protocol import codec
from swpc_hw.drives.errors import CanConfigError


def deadman_problem(deadman_s: float, refresh_period_s: float) -> str | None:
    """Why a dead-man of ``deadman_s`` cannot guard a refresh every ``refresh_period_s``
    (None when it can): it is renewed every half of it, so it must last at least two
    refresh periods.  The one statement of the rule (CanConfig, the kernel refresh and the
    service's timing budget all ask it)."""
    if not 0 < 2 * refresh_period_s <= deadman_s + 1e-12:
        return (
            f"dead-man {deadman_s:g} s must be at least two refresh periods "
            f"({2 * refresh_period_s:g} s)"
        )
    return None


DEFAULT_WATCHDOG_MS = 200
"""The robot's command watchdog ``W`` (ms) unless its config says otherwise
(``limits.watchdog_ms``; services/config/timing.py states what it bounds)."""

DEADMAN_S = 0.5
"""The dead-man ``D`` (s): the kernel's refresh ends this long after the driver's last
renewal (:mod:`swpc_hw.drives.periodic`), so a stopped host frees every axis within
``D + W``."""

HEARTBEAT_LOSS_PERIODS = 3
"""A drive is lost after this many heartbeat periods without a heartbeat (``L``)."""

HEARTBEAT_LOSS_S = round(HEARTBEAT_LOSS_PERIODS * codec.HEARTBEAT_PERIOD_S, 9)
"""``L`` on a robot (s): :data:`HEARTBEAT_LOSS_PERIODS` of the drives' 0.1 s heartbeat."""


@dataclass(frozen=True)
class CanConfig:
    """Everything the driver needs to open a bus and talk to the module controllers.

    ``modules`` maps the module id of the kinematic file (1..N) to its controller's CAN
    node id (1..8).  Times are seconds unless the name says otherwise.
    """

    interface: str = "virtual"
    channel: str = "swpc"
    bitrate: int = 1_000_000
    modules: Mapping[int, int] = field(default_factory=lambda: {1: 1, 2: 2, 3: 3, 4: 4})
    feedback_rate_hz: int = 200
    sync_mode: bool = False
    watchdog_timeout_ms: int = DEFAULT_WATCHDOG_MS
    refresh_period_s: float = 0.02
    heartbeat_period_s: float = codec.HEARTBEAT_PERIOD_S
    heartbeat_loss_periods: int = HEARTBEAT_LOSS_PERIODS
    history_len: int = 200_000
    log_path: str | None = None
    log_total_bytes: int | None = None
    """A rolling log at ``log_path`` within this many bytes over all its files (python-can's
    sized rotating logger, :mod:`swpc_hw.drives.recording`); None: one unbounded file."""
    log_idle_period_s: float = 0.0
    """While no recording (``start_recording()``) is on, the log at
    ``log_path`` keeps each periodic frame once per this many seconds per CAN id and every
    event at once (:class:`swpc_hw.drives.recording.IdleSampler`); 0: every frame."""
    max_torque: tuple[float, float] | None = None
    """(steer, wheel) torque limits in N.m sent at activation; None keeps the controllers'."""
    max_velocity: tuple[float, float] | None = None
    """(steer, wheel) velocity limits in rad/s sent at activation."""
    activate_timeout_s: float = 1.0
    refresh_in_kernel: bool | None = None
    """Feed the watchdog from the kernel (SocketCAN broadcast manager, with a dead-man):
    None = on SocketCAN only."""
    deadman_s: float = DEADMAN_S
    """The kernel refresh stops this long after the driver's last renewal (renewed every
    half of it): a stopped service frees every axis within ``deadman_s`` + watchdog."""
    rx_buffer_bytes: int = 1 << 20
    """Kernel receive buffer asked for a socket bus (SocketCAN), bytes; 0 keeps the
    system default (net.core.rmem_default: ~300 frames, under 2 s of a 4-module robot's
    traffic, after which a stalled reader loses frames)."""
    bus_kwargs: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not self.modules:
            raise CanConfigError("modules: at least one module -> node mapping is needed")
        nodes = list(self.modules.values())
        for module, node in self.modules.items():
            if not 1 <= int(node) <= codec.MAX_NODE:
                raise CanConfigError(
                    f"modules[{module}]: node id {node} outside 1..{codec.MAX_NODE}"
                )
        if len(set(nodes)) != len(nodes):
            raise CanConfigError(f"modules: node ids must be distinct, got {nodes}")
        if not 0 <= self.feedback_rate_hz <= 500:
            raise CanConfigError(f"feedback_rate_hz: {self.feedback_rate_hz} outside 0..500")
        if not 0 <= self.watchdog_timeout_ms <= 60000:
            raise CanConfigError(
                f"watchdog_timeout_ms: {self.watchdog_timeout_ms} outside 0..60000"
            )
        if self.watchdog_timeout_ms and self.refresh_period_s * 1000 >= self.watchdog_timeout_ms:
            raise CanConfigError(
                f"refresh_period_s: {self.refresh_period_s} s must be shorter than the "
                f"watchdog timeout {self.watchdog_timeout_ms} ms"
            )
        if self.refresh_period_s <= 0 or self.heartbeat_period_s <= 0:
            raise CanConfigError("refresh_period_s and heartbeat_period_s must be > 0")
        if not 0 <= self.rx_buffer_bytes <= 1 << 28:
            raise CanConfigError(f"rx_buffer_bytes: {self.rx_buffer_bytes} outside 0..2**28")
        problem = deadman_problem(self.deadman_s, self.refresh_period_s)
        if problem is not None:
            raise CanConfigError(f"deadman_s: {problem}")
        if self.heartbeat_loss_periods < 1:
            raise CanConfigError("heartbeat_loss_periods must be >= 1")
        if not 0 <= self.log_idle_period_s <= 3600:
            raise CanConfigError(
                f"log_idle_period_s: {self.log_idle_period_s} outside 0..3600 s"
            )

    @property
    def loss_after_s(self) -> float:
        """Heartbeat loss ``L`` (s): a drive silent this long is lost (every kind's
        supervision and activation judge by it)."""
        return self.heartbeat_loss_periods * self.heartbeat_period_s

    @classmethod
    def from_mapping(cls, data: Mapping[str, Any]) -> CanConfig:
        """Build from a plain mapping (e.g. a YAML ``can:`` section); unknown keys are errors."""
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise CanConfigError(f"unknown CAN configuration key(s): {', '.join(unknown)}")
        kwargs = dict(data)
        if "modules" in kwargs:
            kwargs["modules"] = {int(k): int(v) for k, v in dict(kwargs["modules"]).items()}
        for key in ("max_torque", "max_velocity"):
            if kwargs.get(key) is not None:
                kwargs[key] = tuple(float(x) for x in kwargs[key])
        return cls(**kwargs)
