"""The driver's pure cores, without threads, buses or sleeps: node tracking and supervision
as functions of state and time; and the kernel refresh's dead-man on python-can's own
periodic tasks."""

from __future__ import annotations

import itertools
import math
import time

import can
import pytest

from firmware_protocol import codec
from firmware_protocol.codec import Axis, AxisState, ControlMode, ErrorFlag, HomingState
from swpc_hw.drives.periodic import KernelRefresh
from swpc_hw.drives.swpc.tracking import apply_frame, check
from swpc_hw.drives.tracking import FeedbackRing, NodeTrack, frame_time
from swpc_hw.drives.types import DriverStats, EventKind, Severity

ENABLED = (AxisState.ENABLED, AxisState.ENABLED)
FREE = (ControlMode.FREE, ControlMode.FREE)


def track(node: int = 2, module: int = 7) -> NodeTrack:
    return NodeTrack(module, node, FeedbackRing(64))


def msg(frame: codec.Frame, stamp: float = 0.0) -> can.Message:
    return can.Message(
        arbitration_id=frame.arbitration_id, data=frame.data, is_extended_id=False, timestamp=stamp
    )


def heartbeat(node: int, states: tuple[AxisState, AxisState] = ENABLED, homed: bool = True,
              errors: tuple[int, int] = (0, 0)) -> codec.Frame:  # fmt: skip
    return codec.make_heartbeat(node, states, FREE, errors, homed, False, 0)


def test_heartbeats_make_a_node_alive_at_their_arrival_time() -> None:
    nd, stats = track(), DriverStats()
    out = apply_frame({2: nd}, msg(heartbeat(2)), 10.25, stats)
    assert out.observations == [] and not out.fault
    assert nd.alive and nd.t_heartbeat == 10.25 and nd.heartbeats == 1 and nd.homed
    # a late-handled older heartbeat never moves the time back
    apply_frame({2: nd}, msg(heartbeat(2)), 10.0, stats)
    assert nd.t_heartbeat == 10.25 and stats.rx_frames == 2


def test_a_heartbeat_reporting_fault_is_a_fault_once() -> None:
    nd, stats = track(), DriverStats()
    apply_frame({2: nd}, msg(heartbeat(2)), 1.0, stats)
    faulted = (AxisState.ENABLED, AxisState.FAULT)
    out = apply_frame({2: nd}, msg(heartbeat(2, faulted, errors=(0, 1))), 1.1, stats)
    assert out.fault
    [obs] = out.observations
    assert obs.kind is EventKind.NODE_FAULT and obs.severity is Severity.FAULT
    assert obs.message == (
        "module 7 (node 2) axis 1 (wheel): heartbeat reports FAULT (WATCHDOG_TIMEOUT)"
    )
    assert not apply_frame({2: nd}, msg(heartbeat(2, faulted, errors=(0, 1))), 1.2, stats).fault


def test_feedback_pairs_unwraps_and_counts_gaps() -> None:
    nd, stats = track(), DriverStats()
    by = {2: nd}
    span = codec.WHEEL_SPAN
    p0 = span / 2 - 0.05  # just below the wheel's wrap point
    apply_frame(by, msg(codec.make_feedback_position(2, 0.1, p0, 254), 5.0), 1.0, stats)
    vt = codec.make_feedback_velocity_torque(2, 0.5, 20.0, 0.1, 0.2, 254)
    apply_frame(by, msg(vt, 5.0), 1.0, stats)
    # counter 254 -> 1: samples 255 and 0 lost; the wheel wrapped in between
    out = apply_frame(by, msg(codec.make_feedback_position(2, 0.1, p0 + 0.2 - span, 1), 5.015),
                      1.015, stats)  # fmt: skip
    assert out.sample is not None and out.sample[0] == 7
    s = out.sample[1]
    assert s.seq == 257 and s.counter == 1 and s.t == 1.015 and s.t_bus == 5.015
    assert s.psi == pytest.approx(p0 + 0.2, abs=1e-4)  # unwrapped: no jump of a span
    assert math.isnan(s.wheel_velocity)
    assert stats.feedback_gaps == 2 and stats.unpaired_feedback == 0
    [gap] = out.observations
    assert gap.kind is EventKind.FEEDBACK_GAP and "2 feedback sample(s) missing" in gap.message
    cols = nd.history.columns()
    assert cols["wheel_velocity"][0] == pytest.approx(20.0, abs=2e-3)  # paired
    assert math.isnan(cols["wheel_velocity"][1])


def test_unknown_bad_and_error_frames_are_observed_not_applied() -> None:
    nd, stats = track(), DriverStats()
    by = {2: nd}
    out = apply_frame(by, can.Message(arbitration_id=0x7FF, data=b"\x01", is_extended_id=False),
                      0.0, stats)  # fmt: skip
    assert [o.kind for o in out.observations] == [EventKind.UNKNOWN_ID] and not out.fault
    out = apply_frame(by, can.Message(arbitration_id=2 << 5 | 6, data=bytes(3),
                                      is_extended_id=False), 0.0, stats)  # fmt: skip
    assert [o.kind for o in out.observations] == [EventKind.BAD_DLC]
    out = apply_frame(by, can.Message(is_error_frame=True, arbitration_id=0x040), 0.0, stats)
    assert out.fault and out.observations[0].kind is EventKind.BUS_OFF
    assert (stats.unknown_ids, stats.bad_dlc, stats.bus_off, stats.error_frames) == (1, 1, 1, 1)
    assert not nd.alive and nd.heartbeats == 0


def test_fault_report_and_homing_status() -> None:
    nd, stats = track(), DriverStats()
    report = codec.make_fault_report(2, Axis.WHEEL, ErrorFlag.OVER_SPEED, ErrorFlag.OVER_SPEED,
                                     AxisState.FAULT)  # fmt: skip
    out = apply_frame({2: nd}, msg(report), 3.0, stats)
    assert out.fault and nd.states[Axis.WHEEL] == AxisState.FAULT
    assert nd.errors[Axis.WHEEL] == ErrorFlag.OVER_SPEED and stats.node_faults == 1
    done = codec.make_homing_status(2, Axis.STEER, HomingState.DONE, 0.25)
    out = apply_frame({2: nd}, msg(done), 3.1, stats)
    assert nd.homed and nd.homing == HomingState.DONE and not out.fault
    assert out.observations[0].message == (
        "module 7 (node 2) axis 0 (steer): homing DONE, sensor at 0.2500 rad"
    )


def test_homing_done_read_from_heartbeats_when_the_status_frame_is_lost() -> None:
    nd, stats = track(), DriverStats()
    nd.homing = HomingState.IN_PROGRESS
    homing = (AxisState.HOMING, AxisState.ENABLED)
    apply_frame({2: nd}, msg(heartbeat(2, homing, homed=False)), 1.0, stats)
    assert nd.homing == HomingState.IN_PROGRESS and nd.homing_seen
    out = apply_frame({2: nd}, msg(heartbeat(2, ENABLED, homed=True)), 1.1, stats)
    assert nd.homing == HomingState.DONE
    assert out.observations[0].severity is Severity.WARNING


def test_frame_time_takes_the_bus_stamp_only_when_plausible() -> None:
    assert frame_time(1e9 + 5.0, handled=10.0, mapped=9.2) == 9.2
    assert frame_time(1e9 + 5.0, handled=10.0, mapped=10.5) == 10.0  # from the future
    assert frame_time(1e9 + 5.0, handled=10.0, mapped=2.0) == 10.0  # older than 5 s
    assert frame_time(0.0, handled=10.0, mapped=9.9) == 10.0  # no stamp


def test_supervision_judges_loss_on_heartbeat_arrival_times() -> None:
    a, b = track(1, 1), track(2, 2)
    stats = DriverStats()
    apply_frame({1: a}, msg(heartbeat(1)), 1.00, stats)
    apply_frame({2: b}, msg(heartbeat(2)), 1.25, stats)
    kw = {"t_configured": 0.0, "loss_after": 0.3, "refresh_period": 0.02, "refresh": False}
    res = check([a, b], 1.2999, **kw)  # type: ignore[arg-type]
    assert res.lost == [] and res.next_deadline == pytest.approx(1.30)
    res = check([a, b], 1.30, **kw)  # type: ignore[arg-type]
    assert res.lost == [a] and not a.alive and b.alive
    assert res.next_deadline == pytest.approx(1.55)
    assert check([a, b], 1.31, **kw).lost == []  # type: ignore[arg-type]  # once
    # loss counts from the newest heartbeat's arrival (its bus time), however late it was
    # handled: arrived at 2.28, so alive until 2.58
    c = track(3, 3)
    apply_frame({3: c}, msg(heartbeat(3)), 2.0, stats)
    apply_frame({3: c}, msg(heartbeat(3)), 2.28, stats)
    assert check([c], 2.579, **kw).lost == []  # type: ignore[arg-type]
    assert check([c], 2.581, **kw).lost == [c]  # type: ignore[arg-type]
    # never heard: lost from the configuration time
    d = track(4, 4)
    assert check([d], 0.31, **kw).lost == [d]  # type: ignore[arg-type]


def test_supervision_refreshes_idle_commanded_nodes_only() -> None:
    a, b = track(1, 1), track(2, 2)
    for n in (a, b):
        n.t_heartbeat, n.alive = 10.0, True
    a.commanded = {Axis.WHEEL: (ControlMode.TORQUE, -0.6), Axis.STEER: (ControlMode.FREE, 0.0)}
    a.last_tx = 10.0
    kw = {"t_configured": 0.0, "loss_after": 0.3, "refresh_period": 0.02}
    res = check([a, b], 10.019, refresh=True, **kw)  # type: ignore[arg-type]
    assert res.refresh == [] and res.next_deadline == pytest.approx(10.02)
    res = check([a, b], 10.021, refresh=True, **kw)  # type: ignore[arg-type]
    decoded = [codec.parse(f.arbitration_id, f.data) for f in res.refresh]
    got = {(d.node, d.axis, d.mode, round(d.setpoint, 4)) for d in decoded}  # type: ignore[union-attr]
    assert got == {
        (1, Axis.WHEEL, ControlMode.TORQUE, -0.6),
        (1, Axis.STEER, ControlMode.FREE, 0.0),
    }
    assert check([a, b], 10.05, refresh=False, **kw).refresh == []  # type: ignore[arg-type]
    # a lost node: nothing is refreshed (the fault path stops the motors)
    res = check([a, b], 10.31, refresh=True, **kw)  # type: ignore[arg-type]
    assert res.lost == [a, b] and res.refresh == []


def test_kernel_refresh_deadman_stops_unless_renewed() -> None:
    """The dead-man on python-can's periodic tasks (thread-based on the virtual bus; the
    same calls go to the kernel's broadcast manager on SocketCAN): a task renewed keeps
    sending past its dead-man; left alone it stops within it."""
    channel = f"deadman-{time.monotonic_ns()}"
    with can.Bus(interface="virtual", channel=channel) as tx, can.Bus(
        interface="virtual", channel=channel
    ) as rx:
        ref = KernelRefresh(tx, period=0.02, deadman=0.4)
        ref.set_node(3, [codec.make_set_control(3, Axis.WHEEL, ControlMode.HOLD)])
        t0 = time.monotonic()
        while time.monotonic() - t0 < 1.0:  # renewed every 0.1 s for 1 s
            ref.renew()
            time.sleep(0.1)
        stamps = []
        while (m := rx.recv(0)) is not None:
            stamps.append(m.timestamp)
        late = sum(ts > time.time() - 0.3 for ts in stamps)
        assert late >= 1, "renewed: still sending after two dead-man periods"
        # and without a gap as long as the dead-man: a renewal moves the end of a running
        # task (a task that ran out between renewals was silent until the next renewal;
        # shorter gaps are a starved sender thread's, not the dead-man's)
        assert max(b - a for a, b in itertools.pairwise(stamps)) < 0.4
        t_last_renewal = time.monotonic()
        time.sleep(1.2)  # no renewal: the task runs out
        stamps = []
        while (m := rx.recv(0)) is not None:
            stamps.append(m.timestamp)
        assert stamps and max(stamps) - time.time() < 0  # sanity: stamps are wall times
        wall_of_last_renewal = time.time() - (time.monotonic() - t_last_renewal)
        # the task checks its end before each send; a send preempted after the check is
        # stamped late by the preemption
        assert max(stamps) <= wall_of_last_renewal + 0.4 + 0.25
        assert rx.recv(0.3) is None  # silent
        ref.set_node(3, [])  # stop: no task left
        assert ref.nodes() == []
        ref.close()


def test_host_frames_are_counted_not_reported_and_the_kernel_keeps_them_out() -> None:
    """A host's command seen on the bus (another tool's, or the kernel's periodic refresh
    looped back on SocketCAN) is counted, never an unknown id; the receive filters the
    driver gives SocketCAN keep host commands out and let everything else in."""
    nd, stats = track(), DriverStats()
    for f in (codec.make_set_control(2, Axis.WHEEL, ControlMode.HOLD), codec.make_sync(3)):
        out = apply_frame({2: nd}, msg(f), 1.0, stats)
        assert out.observations == [] and not out.fault
    assert stats.host_frames == 2 and stats.unknown_ids == 0
    filters = codec.host_receive_filters()
    channel = f"filters-{time.monotonic_ns()}"
    with can.Bus(interface="virtual", channel=channel) as tx, can.Bus(
        interface="virtual", channel=channel, can_filters=filters
    ) as rx:  # python-can applies the same filters in software here
        sent = [
            codec.make_set_control(1, Axis.STEER, ControlMode.FREE),
            codec.make_set_watchdog(4, 200),
            codec.make_sync(0),
            heartbeat(3),
            codec.make_feedback_position(2, 0.1, 0.2, 5),
        ]
        for f in sent:
            tx.send(msg(f))
        tx.send(can.Message(arbitration_id=0x7FF, data=b"\x01", is_extended_id=False))
        tx.send(can.Message(arbitration_id=0x1234567, data=b"", is_extended_id=True))
        got = []
        while (m := rx.recv(0.05)) is not None:
            got.append(m.arbitration_id)
    assert got == [sent[3].arbitration_id, sent[4].arbitration_id, 0x7FF, 0x1234567]


def test_a_drain_step_ends_although_frames_never_stop_coming() -> None:
    """A receive path that cannot empty its queue (frames arriving as fast as it applies
    them) still supervises: a step ends once it has applied a frame that arrived after it
    began, and judges at that start, so a lost node is still found (and the dead-man
    renewed)."""
    from swpc_hw.clock import VirtualClock
    from swpc_hw.drives.bus import CanConfig
    from swpc_hw.drives.swpc.driver import SwpcDriver

    clock = VirtualClock(start=50.0)

    class Endless:
        """A bus whose queue is never empty: each frame arrived 1 ms after the last."""

        def __init__(self) -> None:
            self.t = clock.now() - 0.01
            self.served = 0

        def recv(self, timeout: float | None = None) -> can.Message:
            self.t += 0.001
            self.served += 1
            clock.sleep(0.0002)  # applying a frame takes time
            return msg(heartbeat(1), clock.wall() - clock.now() + self.t)

    drv = SwpcDriver(CanConfig(modules={1: 1, 2: 2}), clock=clock)
    lost: list[str] = []
    drv.add_event_callback(lambda ev: lost.append(ev.message) if ev.node == 2 else None)
    bus = Endless()
    drv._io_step(bus)  # type: ignore[arg-type]
    assert 10 <= bus.served < 40  # the backlog of the step's start, then one more
    assert drv.module_state(1).alive and not drv.module_state(2).alive
    assert lost == ["module 2 (node 2): no heartbeat for 0.300 s"]


def test_kernel_refresh_cycles_a_nodes_axes_and_updates_in_place() -> None:
    channel = f"cycle-{time.monotonic_ns()}"
    with can.Bus(interface="virtual", channel=channel) as tx, can.Bus(
        interface="virtual", channel=channel
    ) as rx:
        ref = KernelRefresh(tx, period=0.01, deadman=2.0)
        hold = codec.make_set_control(1, Axis.WHEEL, ControlMode.HOLD)
        free = codec.make_set_control(1, Axis.STEER, ControlMode.FREE)
        seen: list[bytes] = []

        def read_until(data: bytes) -> None:  # a starved sender thread is late, not wrong
            deadline = time.monotonic() + 10.0
            while data not in seen and time.monotonic() < deadline:
                m = rx.recv(0.05)
                if m is not None:
                    seen.append(bytes(m.data))

        ref.set_node(1, [hold, free])
        read_until(hold.data)
        read_until(free.data)
        torque = codec.make_set_control(1, Axis.WHEEL, ControlMode.TORQUE, -0.5)
        ref.set_node(1, [torque, free])  # same count: data modified in place
        read_until(torque.data)
        ref.stop_all()
        while (m := rx.recv(0)) is not None:
            seen.append(bytes(m.data))
        assert hold.data in seen and free.data in seen and torque.data in seen
        assert seen.index(torque.data) > max(i for i, d in enumerate(seen) if d == hold.data)
        assert rx.recv(0.1) is None  # stopped


def test_driver_drains_its_queue_before_judging_heartbeat_loss() -> None:
    """The test is the clock's master: one jump of 1 s while heartbeats sat in the
    driver's receive queue (a starved receive path).  The I/O step applies them first,
    so the node is alive; loss counts from the newest one's bus time."""
    from swpc_hw.clock import SimClock
    from swpc_hw.drives.bus import CanConfig
    from swpc_hw.drives.swpc.driver import SwpcDriver

    clock = SimClock()
    channel = f"drain-{time.monotonic_ns()}"
    cfg = CanConfig(interface="virtual", channel=channel, modules={1: 1})
    with SwpcDriver(cfg, clock=clock) as drv, can.Bus(
        interface="virtual", channel=channel, preserve_timestamps=True
    ) as ctrl:
        for k in range(1, 10):  # 0.1 ... 0.9 s
            m = msg(heartbeat(1), clock.to_wall(0.1 * k))
            ctrl.send(m)
        clock.advance_to(1.0)
        assert drv.module_state(1).alive
        assert drv.module_state(1).t_heartbeat == pytest.approx(0.9)
        assert [e.kind for e in drv.events()] == []
        clock.advance_to(1.199)
        assert drv.module_state(1).alive
        clock.advance_to(1.201)
        assert not drv.module_state(1).alive
        [lost] = drv.events()
        assert lost.kind is EventKind.HEARTBEAT_LOST and lost.t == pytest.approx(1.201)


def test_a_command_hands_its_setpoint_to_the_kernel_before_its_frame_goes_out() -> None:
    """With the refresh in the kernel, the periodic task gets a command's setpoint before
    the command's frame goes out, and a node's new task starts before its old one stops:
    an axis is never enabled without a refresh, however long the commanding thread is then
    held off the CPU.  A frame that cannot be sent gives the kernel its old setpoint back."""
    from swpc_hw.drives.bus import CanConfig
    from swpc_hw.drives.errors import CanBusError
    from swpc_hw.drives.swpc.driver import SwpcDriver
    from swpc_hw.drives.types import Lifecycle

    log: list[tuple[str, list[bytes]]] = []

    class Task:
        def __init__(self, msgs: list[can.Message]) -> None:
            self.data = [bytes(m.data) for m in msgs]

        def modify_data(self, msgs: list[can.Message]) -> None:
            self.data = [bytes(m.data) for m in msgs]
            log.append(("modify", self.data))

        def stop(self) -> None:
            log.append(("stop", self.data))

    class Bus:
        channel_info = "fake"
        fail = False

        def send(self, m: can.Message) -> None:
            if self.fail:
                raise can.CanError("no buffer space")
            log.append(("send", [bytes(m.data)]))

        def send_periodic(self, msgs: list[can.Message], period: float, duration: float) -> Task:
            log.append(("periodic", [bytes(m.data) for m in msgs]))
            return Task(msgs)

    drv = SwpcDriver(CanConfig(modules={1: 1}))
    bus = Bus()
    drv._bus = bus  # type: ignore[assignment]
    drv._kernel = KernelRefresh(bus, period=0.02, deadman=0.5)  # type: ignore[arg-type]
    drv._state = Lifecycle.ACTIVE
    free_steer = codec.make_set_control(1, Axis.STEER, ControlMode.FREE).data
    free_wheel = codec.make_set_control(1, Axis.WHEEL, ControlMode.FREE).data
    hold_wheel = codec.make_set_control(1, Axis.WHEEL, ControlMode.HOLD).data
    enable_steer = codec.make_set_axis_state(1, Axis.STEER, True).data

    drv.enable(1, Axis.STEER)
    assert log == [("periodic", [free_steer]), ("send", [enable_steer])]
    log.clear()
    drv.enable(1, Axis.WHEEL)  # two frames now: a new task, then the old one stops
    assert [k for k, _ in log] == ["periodic", "stop", "send"]
    assert log[0][1] == [free_steer, free_wheel] and log[1][1] == [free_steer]
    log.clear()
    bus.fail = True
    with pytest.raises(CanBusError, match="no buffer space"):
        drv.hold(1, Axis.WHEEL)
    assert log == [("modify", [free_steer, hold_wheel]), ("modify", [free_steer, free_wheel])]
    assert drv._nodes[1].commanded == {
        Axis.STEER: (ControlMode.FREE, 0.0),
        Axis.WHEEL: (ControlMode.FREE, 0.0),
    }
    bus.fail = False
    log.clear()
    drv.disable(1, Axis.STEER)  # no longer refreshed: out of the task, then the frame
    assert [k for k, _ in log] == ["periodic", "stop", "send"]
    assert log[0][1] == [free_wheel]


def test_the_kernel_refresh_runs_on_host_time_against_a_time_scaled_simulator() -> None:
    """Against ``swpc sim --time-scale k`` the clock runs k robot seconds a host second,
    and the kernel's timers on host time: the refresh period and the dead-man were taken
    as host seconds though the budget is robot time, and renewed every D / 2 robot
    seconds: at k < 1 the kernel's refresh lapsed between renewals."""
    import uuid

    from swpc_hw.clock import SystemClock
    from swpc_hw.drives.bus import CanConfig
    from swpc_hw.drives.swpc.driver import SwpcDriver
    from swpc_hw.drives.types import Lifecycle

    k = 0.25
    cfg = CanConfig(
        modules={1: 1}, channel=f"kr-{uuid.uuid4().hex[:8]}", refresh_period_s=0.02,
        deadman_s=0.5, refresh_in_kernel=True,
    )  # fmt: skip
    drv = SwpcDriver(cfg, clock=SystemClock(rate=k))
    drv.configure()
    try:
        ref = drv._kernel
        assert ref is not None
        assert ref.period == pytest.approx(0.02 / k) and ref.deadman == pytest.approx(0.5 / k)
        drv._state = Lifecycle.ACTIVE
        now = drv.clock.now()
        drv._next_renewal = now
        drv._supervise(now)
        later = drv.clock.now()
        # renewed every D / 2 of host time: D / 2 * k of robot time (the driver's own I/O
        # thread may renew too, from a later now: up to what has elapsed since)
        step = drv._next_renewal - now
        assert ref.renew_every * k - 1e-9 <= step <= ref.renew_every * k + (later - now) + 1e-9
        assert ref.renew_every * k == pytest.approx(0.25)
    finally:
        drv._state = Lifecycle.INACTIVE
        drv.shutdown()
