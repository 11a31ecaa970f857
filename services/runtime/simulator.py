"""The in-process simulator: the virtual robot the service runs against when no CAN is set.

It runs in the service's own process on a python-can ``virtual`` bus, publishes its
motion capture over zenoh on loopback, and keeps simulated time in lockstep with the
service (:class:`swpc_hw.clock.SimClock`): a busy host slows a run down and never faults
it, so the service uses the robot's own timing windows against it, and the same seed gives
the same run.

Hidden truth: the paper's Table 4 calibrated values (``SWPC_SIM_TRUTH``: a kinematic file's
instead, e.g. a worn or re-homed robot for a check, docs/check.md); the service's robot
config claims the nominal design.  Default sensor noise: mocap 0.5 mm / 0.05 deg at 100 Hz, encoders
2**17 counts per turn, a gyro of 0.005 deg/s/sqrt(Hz), bias 0.1 deg/s walking
1e-4 deg/s/sqrt(s), scale error 0.3 % at 200 Hz (``SWPC_SIM_GYRO_*``).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

from services.config.robot import RobotConfig, load_robot_config
from services.config.settings import ServiceSettings, SettingsError
from simulators.drives.wiring import WIRED_AS_CONFIGURED, Wiring, load_wiring
from simulators.options import SimOptions
from simulators.sensors.mocap import MocapOptions
from simulators.virtual_robot import VirtualRobot
from swpc_hw.clock import SimClock
from swpc_hw.robot.model import RobotParams
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED
from swpc_hw.sensors.gyro import GyroOptions
from swpc_hw.sensors.zenoh_session import ZenohAuth

DEFAULT_MOCAP = MocapOptions(rate=100.0, sigma_xy=0.5e-3, sigma_yaw=math.radians(0.05))


def simulated_robot(settings: ServiceSettings, config: RobotConfig) -> tuple[RobotConfig, Wiring]:
    """What the in-process simulator is built as, for a service (or ``swpc validate``) on
    ``config``: the robot config it was built from (``SWPC_SIM_ROBOT_CONFIG``; unset:
    ``config``) and how its drives are really wired (``SWPC_SIM_WIRING``; unset: as that
    config says).  Raises :class:`SettingsError` naming the setting for a file that does
    not fit the robot."""
    built = (
        config
        if settings.sim_robot_config is None
        else load_robot_config(settings.sim_robot_config)
    )
    if settings.sim_wiring is None:
        return built, WIRED_AS_CONFIGURED
    try:
        return built, load_wiring(settings.sim_wiring, config.nominal.ids)
    except ValueError as exc:
        raise SettingsError(f"SWPC_SIM_WIRING: {exc}") from exc


def in_process_simulator(
    *,
    config: RobotConfig,
    channel: str,
    zenoh_endpoints: Sequence[str],
    clock: SimClock,
    seed: int = 1,
    truth: RobotParams | None = None,
    mocap: MocapOptions | None = None,
    physics_dt: float = 0.01,
    mocap_latency: float | None = None,
    mocap_qtm_port: int | None = None,
    feedback_rate_hz: int = 50,
    gyro: GyroOptions | None = None,
    zenoh_auth: ZenohAuth | None = None,
    wiring: Wiring = WIRED_AS_CONFIGURED,
) -> VirtualRobot:
    """A simulator on the in-process virtual bus ``channel``, publishing poses to the
    service's zenoh endpoint (it connects to ``zenoh_endpoints``), and its gyro
    (``gyro``, default :class:`~swpc_hw.sensors.gyro.GyroOptions`), master of ``clock``.
    (Publishing on the service's own session instead was measured slower: 10 % more CPU
    for the demo, the ingest's callback then runs in the master's put.)"""
    if truth is None:
        truth = PAPER_CALIBRATED if config.nominal.ids == PAPER_CALIBRATED.ids else config.nominal
    base = mocap or DEFAULT_MOCAP
    opts = SimOptions(
        robot=config.robot,
        drives=config.drives,
        physics_dt=physics_dt,
        watchdog_ms=config.limits.watchdog_ms,
        feedback_rate_hz=feedback_rate_hz,
        mocap=dataclasses.replace(
            base,
            seed=seed,
            latency=base.latency if mocap_latency is None else mocap_latency,
            qtm_port=mocap_qtm_port,
        ),
        gyro=gyro or GyroOptions(),
        seed=seed,
        wiring=wiring,
    )
    return VirtualRobot.open(
        truth,
        interface="virtual",
        channel=channel,
        zenoh_connect=list(zenoh_endpoints),
        zenoh_auth=zenoh_auth,
        options=opts,
        clock=clock,
    )
