"""The service's timing budget: one derivation of the CAN settings, its invariants."""

from __future__ import annotations

import pytest
from pydantic import SecretStr

from services.config.robot import RobotConfig
from services.config.settings import ServiceSettings
from services.config.timing import TimingError, bus_config, timing_budget


def settings(**kw: object) -> ServiceSettings:
    return ServiceSettings(token=SecretStr("t"), **kw)  # type: ignore[arg-type]


def test_the_in_process_simulator_gets_the_robots_own_windows() -> None:
    """Lockstep: a busy host cannot fault the run, so nothing is widened."""
    cfg = RobotConfig()
    b = timing_budget(settings(), cfg)
    assert (b.watchdog, b.heartbeat_loss, b.mocap_stale) == (0.2, 0.3, 0.5)
    # refreshed exactly on time in lockstep: the longest period the budget allows, W / 4
    assert b.refresh == 0.05 and b.deadman == 0.5 and b.stop_bound == pytest.approx(0.7)
    c = bus_config(settings(), cfg, interface="virtual", channel="x")
    assert (c.watchdog_timeout_ms, c.refresh_period_s, c.heartbeat_loss_periods) == (200, 0.05, 3)
    assert c.activate_timeout_s == 1.0 and c.feedback_rate_hz == 50  # the simulator's CPU
    assert c.modules == {1: 1, 2: 2, 3: 3, 4: 4}
    assert c.max_torque == (2.0, 2.0) and c.max_velocity == (3.0, 20.0)


def test_a_robot_is_the_same_budget_on_its_own_interface() -> None:
    cfg = RobotConfig.model_validate({"limits": {"watchdog_ms": 100}})
    st = settings(can_interface="socketcan", can_channel="can0")
    b = timing_budget(st, cfg)
    assert (b.watchdog, b.refresh, b.heartbeat_loss, b.mocap_stale) == (0.1, 0.02, 0.3, 0.5)
    assert b.feedback_period == 0.005  # 200 Hz on a bus
    c = bus_config(settings(feedback_rate=150), cfg, interface="virtual", channel="x")
    assert c.feedback_rate_hz == 150


@pytest.mark.parametrize(
    ("scale", "host_window", "watchdog_ms", "loss", "refresh"),
    [
        (4.0, None, 4000, 4.0, 0.08),  # 1 host s at 4x; refresh every 20 ms of host time
        (4.0, 2.5, 10000, 10.0, 0.08),
        (0.3, 5.0, 1500, 1.5, 0.02),  # the VM: slower than real time
    ],
)
def test_an_external_time_scaled_simulator_widens_the_windows_in_host_seconds(
    scale: float, host_window: float | None, watchdog_ms: int, loss: float, refresh: float
) -> None:
    """``swpc sim --time-scale k`` shares (or emulates) the host: each window lasts at least
    sim_host_window_s of host time, i.e. k times that of robot time (the service's clock)."""
    extra = {} if host_window is None else {"sim_host_window_s": host_window}
    st = settings(can_interface="socketcan", time_scale=scale, **extra)
    b = timing_budget(st, RobotConfig())
    c = bus_config(st, RobotConfig(), interface="socketcan", channel="vcan0")
    assert c.watchdog_timeout_ms == watchdog_ms
    assert b.heartbeat_loss == pytest.approx(loss) and b.mocap_stale == pytest.approx(loss)
    assert c.refresh_period_s == pytest.approx(refresh)
    assert c.heartbeat_loss_periods * c.heartbeat_period_s >= b.heartbeat_loss - 1e-9
    # explicit windows win over the floor
    st = settings(can_interface="socketcan", time_scale=scale, heartbeat_timeout=0.4)
    assert timing_budget(st, RobotConfig()).heartbeat_loss == 0.4


def test_a_budget_that_breaks_an_invariant_is_refused_naming_it() -> None:
    with pytest.raises(TimingError, match=r"heartbeat timeout 0.15 s must be at least two"):
        timing_budget(settings(heartbeat_timeout=0.15), RobotConfig())
    cfg = RobotConfig.model_validate({"limits": {"watchdog_ms": 20}})
    b = timing_budget(settings(), cfg)  # the refresh follows a short watchdog down
    assert b.refresh == pytest.approx(0.005)
