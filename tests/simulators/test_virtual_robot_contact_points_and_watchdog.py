"""The virtual robot end to end, what it must show: driven only through the CAN driver,
its poses only from zenoh, a lock, spin, re-steer and spin gives the true contact points
and the gyro reads the poses' yaw rate (1 and 2); raw frames show that the controllers'
watchdog frees the axes and that a node that loses its heartbeat falls silent (3).

Both run in lockstep on a :class:`swpc_hw.clock.SimClock`: the bounds are the
simulator's, whatever the host's load (the rig: :mod:`tests.simulators.virtual_robot_rig`).
"""

from __future__ import annotations

import math

import can
import numpy as np
import pytest

from firmware_protocol import codec
from firmware_protocol.codec import Axis, AxisState, ErrorFlag
from simulators.sensors.mocap import MocapOptions
from swpc_hw.drives.bus import CanConfig
from swpc_hw.drives.swpc.driver import SwpcDriver
from swpc_hw.robot.model import RobotParams
from swpc_hw.sensors.gyro import GyroOptions
from tests.simulators.virtual_robot_rig import DEG, RawHost, fixed_point, rig, slope

# --------------------------------------------------------------------------- 1 and 2


def test_lock_spin_resteer_spin_through_can_and_zenoh_gives_the_true_contact_points() -> None:
    """What it must show 1 and 2, driven only through the CAN driver, poses only from zenoh;
    and the gyro reads the poses' yaw rate with its bias and scale error (a steady spin:
    the mean over 3 s, 600 samples, is within 1e-4 rad/s of ``(1 + eps) omega + bias``).

    Physics steps of 10 ms, the in-process simulator's (``sim_physics_dt``): the casters
    trail and the wheels roll as with 4 ms (the rolling rates agree with ``D dyaw / r`` to
    1e-4 either way), at half the CPU."""
    gyro_opt = GyroOptions(bias=math.radians(0.5), scale_error=0.01, bias_walk=0.0)
    with rig(
        lockstep=True,
        physics_dt=0.01,
        feedback_rate_hz=50,
        watchdog_ms=1000,
        mocap=MocapOptions(rate=100),
        gyro=gyro_opt,
        seed=7,
    ) as r:
        truth = RobotParams.model_validate(r.truth_params())  # the ground-truth channel
        T = truth.arrays()
        k, a1, a2 = 1, 45 * DEG, 165 * DEG
        ik = truth.index(k)
        others = [m for m in truth.ids if m != k]
        drv = SwpcDriver(
            CanConfig(
                channel=r.channel,
                watchdog_timeout_ms=1000,
                feedback_rate_hz=50,
                heartbeat_loss_periods=10,
                activate_timeout_s=5.0,
            ),
            clock=r.clock,
        )
        assert r.clock is not None
        try:
            drv.configure()
            drv.activate()
            for m in truth.ids:
                drv.clear_errors(m)
                drv.enable(m, Axis.STEER)
                drv.enable(m, Axis.WHEEL)
                drv.start_homing(m)
            for m in truth.ids:
                drv.wait_for(m, lambda s: s.homed and s.feedback is not None, 5.0, "homed")

            def spin_and_measure(a: float) -> np.ndarray:
                for m in others:  # casters start from wherever they are
                    drv.free(m, Axis.STEER)
                    drv.set_torque(m, Axis.WHEEL, -0.6)
                r.poses.wait_for(3.0)  # settle
                t0 = r.poses.last_t()
                w0 = r.clock.now()  # the driver stamps samples on its clock
                r.poses.wait_until(t0 + 3.0)
                w1 = r.clock.now()
                P = r.poses.array(t0, t0 + 3.0)
                C_meas, rms = fixed_point(P)
                C_true = T.P_s[ik] + T.b[ik] * np.array(
                    [math.cos(a + T.beta[ik]), math.sin(a + T.beta[ik])]
                )
                faults = [e.message for e in drv.events() if e.severity.value == "fault"]
                assert not faults
                assert rms < 1e-6
                err = float(np.linalg.norm(C_meas - C_true))
                print(f"angle {a / DEG:.0f} deg: fixed point error {err * 1e6:.3f} um")
                assert err <= 0.1e-3
                # 2: settled casters are perpendicular to the radius from the pivot, and the
                # wheel encoders turn by D d(yaw) / r.  Rates per simulated second: poses carry
                # their source time; feedback samples come every 1/50 s, numbered by `seq`.
                yaw_rate = slope(P[:, 0], np.unwrap(P[:, 3]))
                assert 0.3 < abs(yaw_rate) < 1.0
                G = r.gyro.array(t0, t0 + 3.0)
                assert G.shape[0] == 601  # 200 Hz on the simulated clock, stamped with it
                want = (1 + gyro_opt.scale_error) * yaw_rate + gyro_opt.bias
                assert float(np.mean(G[:, 1])) == pytest.approx(want, abs=1e-4)
                for m in others:
                    j = truth.index(m)
                    h = drv.history_arrays(m)
                    sel = (h["t"] >= w0) & (h["t"] <= w1)
                    th = h["theta_hat"][sel][-1] + T.beta[j]
                    u = np.array([math.cos(th), math.sin(th)])
                    P_w = T.P_s[j] + T.b[j] * u
                    D = np.linalg.norm(P_w - C_true)
                    assert abs((P_w - C_true) @ u) < 0.3e-3  # even at 2**14 counts/turn on the wire
                    psi_rate = slope(h["seq"][sel] / 50.0, h["psi"][sel])
                    print(
                        f"  module {m}: (P_w - C).u = {((P_w - C_true) @ u) * 1e6:.2f} um, "
                        f"dpsi/dt {psi_rate:.5f} vs -D |dyaw/dt| / r "
                        f"{-D * abs(yaw_rate) / T.r[j]:.5f} rad/s"
                    )
                    assert psi_rate == pytest.approx(-D * abs(yaw_rate) / T.r[j], rel=1e-3)
                return C_meas

            drv.set_position(k, Axis.STEER, a1)
            drv.hold(k, Axis.WHEEL)
            r.poses.wait_for(1.0)
            P1 = spin_and_measure(a1)
            for m in others:  # stop: torque off, wheels held
                drv.hold(m, Axis.WHEEL)
            r.poses.wait_for(0.5)
            for m in others:  # re-steer with the dynamic modules free
                drv.free(m, Axis.WHEEL)
                drv.free(m, Axis.STEER)
            yaw_before = r.poses.array()[-1, 3]
            drv.set_position(k, Axis.STEER, a2)
            r.poses.wait_for(2.5)
            assert abs(r.poses.array()[-1, 3] - yaw_before) > 10 * DEG  # body moved about the pin
            assert drv.module_state(k).theta_hat == pytest.approx(a2, abs=1e-3)
            P2 = spin_and_measure(a2)
            chord = 2 * T.b[ik] * math.sin((a2 - a1) / 2)
            assert np.linalg.norm(P2 - P1) == pytest.approx(chord, abs=0.2e-3)
            assert not [e for e in drv.events() if e.severity.value == "fault"]
        finally:
            drv.shutdown()
        st = r.sim.stats()
        assert st.sim_time > 15.0 and st.frames_rx > 100


# --------------------------------------------------------------------------- 3


def test_watchdog_frees_the_axes_and_heartbeat_loss_silences_a_node() -> None:
    """What it must show 3 (in lockstep: the bounds are the simulator's, whatever the
    host's load)."""
    watchdog = 0.2  # s; commands go every 10 ms
    with rig(lockstep=True, feedback_rate_hz=100, watchdog_ms=200, seed=3) as r:
        host = RawHost(
            can.Bus(interface="virtual", channel=r.channel, preserve_timestamps=True), r.clock
        )
        try:
            for n in (1, 2, 3, 4):
                host.send(codec.make_set_axis_state(n, Axis.WHEEL, True))
            host.send(codec.make_set_axis_state(1, Axis.STEER, True))
            # keep the commands flowing for 0.5 s: module 1 steer held and braked, wheels torqued
            t_end = host.now() + 0.5
            while host.now() < t_end:
                host.send(codec.make_set_control(1, Axis.STEER, codec.ControlMode.HOLD))
                host.send(codec.make_set_control(1, Axis.WHEEL, codec.ControlMode.HOLD))
                for n in (2, 3, 4):
                    host.send(codec.make_set_control(n, Axis.WHEEL, codec.ControlMode.TORQUE, -0.6))
                host.sleep(0.01)
            spinning = abs(r.sim.truth_snapshot()["twist"][2])
            assert spinning > 0.05
            t_last = host.last_tx  # stop sending: the watchdog runs out
            host.sleep(0.5)
            reports = host.of(codec.FaultReport)
            by_node = {
                d.node: t for t, d in reports if d.active_errors & ErrorFlag.WATCHDOG_TIMEOUT
            }
            assert sorted(by_node) == [1, 2, 3, 4]
            # from each node's last command to its FaultReport, on the bus time stamps
            delays = [(t - max(x for x in host.tx_times[n] if x < t)) for n, t in by_node.items()]
            # a command takes effect at the first tick after its arrival; the fault is sent
            # at the first tick after the timeout
            tick = r.sim.tick_dt()
            assert max(delays) <= watchdog + 2 * tick
            assert min(delays) >= watchdog - 1e-3
            print(f"watchdog {watchdog * 1e3:.0f} ms: FaultReports after {sorted(delays)} s")
            assert min(by_node.values()) > t_last  # it went off because the commands stopped
            hb = host.of(codec.Heartbeat, since=t_last + watchdog + 0.06)
            assert {d.node for _, d in hb} == {1, 2, 3, 4}
            for _, d in hb:
                assert d.states[Axis.WHEEL] == AxisState.FAULT
                assert d.errors[Axis.WHEEL] & ErrorFlag.WATCHDOG_TIMEOUT
            host.sleep(0.5)  # free wheels: the robot coasts to a stop
            assert abs(r.sim.truth_snapshot()["twist"][2]) < 0.05 * spinning

            # heartbeat loss: node 3 falls silent, the others go on
            r.sim.mute(3)
            t_mute = host.now()
            host.sleep(0.3)
            assert not host.of(codec.Heartbeat, since=t_mute + 0.01, node=3)
            assert not host.of(codec.FeedbackPosition, since=t_mute + 0.01, node=3)
            # 3 heartbeats of node 2 are due (one per 0.1 s)
            assert len(host.of(codec.Heartbeat, since=t_mute + 0.01, node=2)) == 3
            r.sim.mute(3, False)
            host.sleep(0.2)
            assert host.of(codec.Heartbeat, since=host.now() - 0.15, node=3)
            # an injected hardware fault is reported
            t_f = host.now()
            r.sim.inject_fault(2, Axis.STEER, ErrorFlag.OVER_TEMPERATURE)
            host.sleep(0.05)
            rep = host.of(codec.FaultReport, since=t_f, node=2)
            assert rep and rep[0][1].new_errors == ErrorFlag.OVER_TEMPERATURE
        finally:
            host.close()
