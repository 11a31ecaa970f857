"""The service's timing budget, stated once, and the one derivation of the CAN settings
and of the robot's drives from them.

Every duration here is in seconds of the service's clock (:mod:`swpc_hw.clock`), i.e.
robot time:

* on a robot, and against ``swpc sim`` at time scale 1, the host's monotonic clock;
* against ``swpc sim --time-scale k`` (a separate process on vcan), the host clock times
  ``k`` (``SystemClock(rate=k)``): the simulator's own time;
* against the in-process simulator, its simulated time in lockstep (``SimClock``): a busy
  host slows the run down and never faults it, so the robot's own windows apply.

The budget (robot defaults in brackets; ``W`` comes from the robot config)::

    T_fb  = 1 / feedback_rate                 encoder feedback period     [5 ms; 20 ms in-process]
    T_hb  = 0.1                               controller heartbeat period (firmware)
    W     = limits.watchdog_ms / 1000         controller command watchdog       [0.2 s]
    T_ref = min(0.02 max(1, k), W / 4)        driver re-sends the last command  [20 ms;
                                              W / 4 = 50 ms in-process (lockstep: no jitter)]
    L     = heartbeat_timeout                 node lost without a heartbeat     [0.3 s]
    S     = mocap_stale_after                 motion capture stale              [0.5 s]
    D     = deadman                           kernel refresh ends unless renewed [0.5 s]
    A     = max(1, 2 L)                       activate() waits for every node   [1 s]

Invariants (:meth:`TimingBudget.check`):

* ``T_ref <= W / 4``: three refreshes in a row may be lost before the watchdog trips;
* ``L >= 2 T_hb``: one lost heartbeat is not a lost node;
* ``D >= 2 T_ref``: the dead-man is renewed every ``D / 2`` while refreshes go on;
* ``S >= 2 / mocap rate`` is the operator's to keep (the mocap rate is not known here).

Stop bound: a hung or stopped service frees every axis within ``W`` when the host refreshes
the watchdog, within ``D + W`` when the kernel does (SocketCAN broadcast manager).  The
same bound holds for every drive kind whose dead-man the host refreshes: on ODrive drives
``W`` is each axis' own watchdog (``watchdog_timeout``, set on the ODrive to ``W``) and the
refresh is the axis' last setpoint frame; its heartbeat reports the stop ``T_hb`` later,
and ``activate()`` proves the watchdog first, ``W + L`` at most (docs/drives.md).

What carries the refresh and the watchdog depends on the drive kind (:mod:`swpc_hw.drives`);
the windows are the same, none is added:

* ``swpc``: the driver re-sends each node's last command every ``T_ref``; a controller
  without one for ``W`` frees its axes (its command watchdog).
* ``cia402``: the host's heartbeat (node ``drives.host_node``) goes out every ``T_ref``;
  every drive's heartbeat consumer (0x1016) is set to ``W`` and faults its axis (EMCY
  0x8130, the power stage off) without one.  The drives' own heartbeat (0x1017) is
  ``T_hb``, judged lost after ``L``; the SYNC that samples their feedback is ``T_fb``.

So the stop bound above holds for both kinds: ``W`` from Python, ``D + W`` from the kernel.

Against an external time-scaled simulator (``k != 1``) a host stall of ``J`` seconds is
``k J`` seconds of robot time, so ``W``, ``L`` and ``S`` are floored at ``k`` times
``sim_host_window_s`` host seconds (the simulator shares, possibly emulates, the host).
A refresh faster than every 20 ms of host time only burns CPU, hence ``max(1, k)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

from firmware_protocol.codec import HEARTBEAT_PERIOD_S
from services.config.robot import RobotConfig
from services.config.settings import ServiceSettings
from swpc_hw.clock import Clock
from swpc_hw.drives.bus import DEADMAN_S, HEARTBEAT_LOSS_S, CanConfig, deadman_problem
from swpc_hw.drives.errors import CanConfigError
from swpc_hw.drives.interface import Drives
from swpc_hw.drives.registry import open_drives

HOST_REFRESH_FLOOR_S = 0.02
"""The driver refreshes a node's last command at most this often in host time."""
ROBOT_MOCAP_STALE_S = 0.5


class TimingError(CanConfigError):
    """The timing budget breaks one of its invariants (names which, with the values)."""


@dataclass(frozen=True)
class TimingBudget:
    """The windows the service runs with (seconds of the service clock)."""

    feedback_period: float
    heartbeat_period: float
    watchdog: float
    refresh: float
    heartbeat_loss: float
    mocap_stale: float
    deadman: float
    activate_timeout: float

    def check(self) -> TimingBudget:
        """Raise :class:`TimingError` unless the invariants of the module docstring hold."""
        if self.refresh > self.watchdog / 4 + 1e-12:
            raise TimingError(
                f"refresh period {self.refresh:g} s must be at most a quarter of the "
                f"watchdog {self.watchdog:g} s"
            )
        if self.heartbeat_loss < 2 * self.heartbeat_period - 1e-12:
            raise TimingError(
                f"heartbeat timeout {self.heartbeat_loss:g} s must be at least two heartbeat "
                f"periods ({2 * self.heartbeat_period:g} s)"
            )
        problem = deadman_problem(self.deadman, self.refresh)
        if problem is not None:
            raise TimingError(problem)
        return self

    @property
    def stop_bound(self) -> float:
        """Longest time from a hung service to every axis free (kernel refresh)."""
        return self.deadman + self.watchdog

    def as_dict(self) -> dict[str, float]:
        return {k: float(getattr(self, k)) for k in self.__dataclass_fields__}


def timing_budget(settings: ServiceSettings, config: RobotConfig) -> TimingBudget:
    """The windows for this service and robot (module docstring)."""
    k = settings.external_time_scale
    floor = k * settings.sim_host_window_s if k != 1.0 else 0.0
    watchdog = max(config.limits.watchdog_ms / 1000.0, floor)
    loss = settings.heartbeat_timeout or HEARTBEAT_LOSS_S
    stale = settings.mocap_stale_after or ROBOT_MOCAP_STALE_S
    if settings.heartbeat_timeout is None:
        loss = max(loss, floor)
    if settings.mocap_stale_after is None:
        stale = max(stale, floor)
    refresh = min(HOST_REFRESH_FLOOR_S * max(1.0, k), watchdog / 4)
    if settings.in_process:
        # lockstep: every refresh goes out exactly on time, so the longest period the
        # invariant allows (a quarter of the watchdog) loses nothing and halves the
        # frames the driver and the simulated controllers handle
        refresh = watchdog / 4
    return TimingBudget(
        feedback_period=1.0 / settings.feedback_rate_hz,
        heartbeat_period=HEARTBEAT_PERIOD_S,  # swpc's firmware (its DBC)
        watchdog=watchdog,
        refresh=refresh,
        heartbeat_loss=loss,
        mocap_stale=stale,
        deadman=max(DEADMAN_S, 2 * refresh),
        activate_timeout=max(1.0, 2 * loss),
    ).check()


def bus_config(
    settings: ServiceSettings,
    config: RobotConfig,
    *,
    interface: str,
    channel: str,
    log_path: Path | None = None,
    log_total_bytes: int | None = None,
) -> CanConfig:
    """The bus and timing settings of the robot's drives for this service and robot: the
    only place they are made (:func:`robot_drives`)."""
    b = timing_budget(settings, config)
    lim = config.limits
    return CanConfig(
        interface=interface,
        channel=channel,
        bitrate=settings.can_bitrate,
        feedback_rate_hz=settings.feedback_rate_hz,
        watchdog_timeout_ms=math.ceil(1000.0 * b.watchdog),
        refresh_period_s=b.refresh,
        heartbeat_period_s=b.heartbeat_period,
        heartbeat_loss_periods=max(1, math.ceil(b.heartbeat_loss / b.heartbeat_period - 1e-9)),
        max_torque=(lim.max_wheel_torque, lim.max_wheel_torque),
        max_velocity=(lim.max_steer_velocity, lim.max_wheel_velocity),
        activate_timeout_s=b.activate_timeout,
        deadman_s=b.deadman,
        log_path=None if log_path is None else str(log_path),
        log_total_bytes=log_total_bytes,
        log_idle_period_s=settings.can_log_idle_period,
    )


def robot_drives(
    settings: ServiceSettings,
    config: RobotConfig,
    *,
    interface: str,
    channel: str,
    clock: Clock,
    log_path: Path | None = None,
    log_total_bytes: int | None = None,
) -> Drives:
    """The robot's drives (its config's kind, :func:`swpc_hw.drives.registry.open_drives`) on
    :func:`bus_config`'s settings, UNCONFIGURED: what ``swpc serve`` and ``swpc validate``
    open."""
    bus = bus_config(
        settings,
        config,
        interface=interface,
        channel=channel,
        log_path=log_path,
        log_total_bytes=log_total_bytes,
    )
    return open_drives(config.drives, bus, config.nominal.ids, clock=clock)
