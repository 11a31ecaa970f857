"""The miswired robot as the simulator's hidden truth (issue 43, item 4): crossed nodes,
steering and wheel swapped, an axis the other way round, a wrong ratio, a rotated
motion-capture body.  The drives' own encoders agree with what the host commanded in every
case: only an outside reference (motion capture, the gyro, the other wheels) can tell, which
is what commissioning is for."""

from __future__ import annotations

import math
import uuid
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np
import pytest

from firmware_protocol.codec import Axis
from simulators.drives.base import quantize
from simulators.drives.wiring import BODY_HEIGHT, Wiring
from simulators.options import SimOptions
from simulators.virtual_robot import VirtualRobot
from swpc_hw.clock import SimClock
from swpc_hw.drives.bus import CanConfig
from swpc_hw.drives.cia402.config import Cia402Drives
from swpc_hw.drives.cia402.driver import Cia402Driver
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED

W, S = Axis.WHEEL, Axis.STEER


def test_a_wiring_that_does_not_fit_the_robot_is_refused() -> None:
    with pytest.raises(ValueError, match=r"not a permutation of 0\.\.3"):
        Wiring(drive_of=(0, 0, 1, 2)).check(4)
    with pytest.raises(ValueError, match="no module index 4"):
        Wiring(swapped=frozenset({4})).check(4)
    with pytest.raises(ValueError, match="non-zero factor"):
        Wiring(scale={(1, W): 0.0}).check(4)
    w = Wiring(drive_of=(1, 0, 2, 3), swapped=frozenset({2}), scale={(3, W): -2.0})
    assert w.channel(0, S) == (1, S) and w.channel(2, S) == (2, W) and w.gain(3, W) == -2.0
    assert Wiring().identity and not w.identity
    assert Wiring(mocap_yaw=0.5).mocap_pose(1.0, 2.0, 0.1) == (1.0, 2.0, 0.6)
    assert Wiring(mocap_y_up=True).mocap_pose(1.0, 2.0, 0.1) == (1.0, BODY_HEIGHT, 0.0)


@contextmanager
def wired(wiring: Wiring) -> Iterator[tuple[SimClock, Cia402Driver, VirtualRobot]]:
    """CiA 402 host and virtual robot in lockstep, the robot wired as ``wiring`` says,
    every axis enabled and the steering homed."""
    clock = SimClock()
    ch = f"wiring-{uuid.uuid4().hex[:8]}"
    cfg = Cia402Drives(modules=None).for_modules(PAPER_CALIBRATED.ids)
    host = Cia402Driver(cfg, CanConfig(channel=ch, feedback_rate_hz=50), clock=clock)
    opts = SimOptions(drives=cfg, physics_dt=0.01, seed=2, theta0=[0.0] * 4,
                      sensor_positions=[0.0] * 4, wiring=wiring)  # fmt: skip
    sim = VirtualRobot.open(PAPER_CALIBRATED, channel=ch, clock=clock, options=opts)
    host.configure()
    sim.start()
    try:
        with clock.participant():
            host.activate()
            for m in host.modules():
                host.enable(m, S)
                host.enable(m, W)
                host.start_homing(m)
            host.wait_for(4, lambda s: s.homed, 5.0, "homed")
            yield clock, host, sim
    finally:
        sim.stop()
        host.shutdown()
        clock.close()


def steering(sim: VirtualRobot) -> list[float]:
    """The true steering angles less the homing errors (what a right wiring would read)."""
    r = sim.robot
    return [float(r.theta[i] - r.arrays.beta[i]) for i in range(4)]


@pytest.mark.parametrize(
    ("wiring", "moved", "expect"),
    [
        (Wiring(), 0, 0.3),  # as configured: module 1's steering turns 0.3 rad
        (Wiring(drive_of=(1, 0, 2, 3)), 1, 0.3),  # crossed: module 2's turns
        (Wiring(scale={(0, S): -1.0}), 0, -0.3),  # mounted the other way round
        (Wiring(scale={(0, S): 2.0}), 0, 0.15),  # twice the ratio configured
    ],
    ids=["as-configured", "crossed", "inverted", "ratio"],
)
def test_the_host_sees_its_command_done_while_the_robot_did_otherwise(
    wiring: Wiring, moved: int, expect: float
) -> None:
    with wired(wiring) as (clock, host, sim):
        before = steering(sim)
        target = host.module_state(1).theta_hat + 0.3
        host.set_position(1, S, target)
        clock.sleep(1.0)
        after = steering(sim)
        change = [a - b for a, b in zip(after, before, strict=True)]
        # the host's encoder says module 1 turned to where it was told, whatever moved
        assert host.module_state(1).theta_hat == pytest.approx(target, abs=1e-3)
        assert change[moved] == pytest.approx(expect, abs=2e-3), change
        assert all(abs(c) < 2e-3 for k, c in enumerate(change) if k != moved), change


def test_steering_and_wheel_swapped_turn_the_wheel_for_a_steering_command() -> None:
    with wired(Wiring(swapped=frozenset({0}))) as (clock, host, sim):
        psi0 = float(sim.robot.psi[0])
        target = host.module_state(1).theta_hat + 0.3
        host.set_position(1, S, target)
        clock.sleep(1.0)
        print(f"\nswapped: the wheel turned {float(sim.robot.psi[0]) - psi0:.4f} rad for a "
              "steering command of 0.3 rad")
        assert float(sim.robot.psi[0]) - psi0 == pytest.approx(0.3, abs=2e-3)
        assert host.module_state(1).theta_hat == pytest.approx(target, abs=1e-3)


def test_a_held_steering_rests_within_its_count_not_on_the_setpoint() -> None:
    """A position loop holds its encoder's reading at the setpoint; the shaft rests
    wherever within that count the approach leaves it (WiredAxes.rest_offset), so the
    reading is off the true angle by up to half a count, spread as the solvers assume
    (q / sqrt(12)).  An ideal loop that ended on the setpoint read a held steering
    exactly, and the gyro solver's covariance came out twice too wide (issue 44)."""
    q = 2 * math.pi / SimOptions().steer_counts
    with wired(Wiring()) as (clock, host, sim):
        errors = []
        for k in range(16):
            target = host.module_state(1).theta_hat + (0.05 if k % 2 else -0.04)
            host.set_position(1, S, target)
            clock.sleep(0.5)
            true = steering(sim)[0]
            errors.append(quantize(true, SimOptions().steer_counts) - true)
    e = np.array(errors)
    print(f"\nheld steering's reading error: RMS {np.sqrt(np.mean(e**2)) / q:.3f} counts "
          f"(uniform: {1 / math.sqrt(12):.3f}), largest {np.abs(e).max() / q:.3f}")
    assert np.abs(e).max() <= 0.5 * q * (1 + 1e-9)
    assert 0.5 < np.sqrt(np.mean(e**2)) / (q / math.sqrt(12)) < 1.5
