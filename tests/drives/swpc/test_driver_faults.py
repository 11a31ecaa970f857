"""Back-to-back: the driver stops every axis on a fault: the controller's watchdog and
the driver's refresh that feeds it, over-speed, heartbeat loss (reported before any event
callback runs), bus-off; unknown ids and bad DLCs are counted, not fatal; a listener
exception stops; stop_all() frees then disables every axis.

The driver against emulated controllers on a real python-can bus (the rig and the bus:
:mod:`tests.drives.swpc.back_to_back_rig`); the same module runs on SocketCAN in the VM
(``deploy/vm/in-vm.sh``).
"""

from __future__ import annotations

import can
import pytest

from firmware_protocol import codec
from firmware_protocol.codec import Axis, AxisState, Command, ControlMode, ErrorFlag
from swpc_hw.drives.errors import LifecycleError
from swpc_hw.drives.types import DriverEvent, EventKind, Lifecycle, Severity
from tests.can_rig import WATCHDOG_MS, T, now, sleep, wait_until
from tests.drives.swpc.back_to_back_rig import ALL_AXES, NODES, Rig, stop_frames, virtual_only


# ---------------------------------------------------------------------------- watchdog
def test_watchdog_expiry_frees_and_disables_the_axis(rig: Rig) -> None:
    """A host that stops commanding: the controller faults the axis within its timeout."""
    rig.drv.configure()  # inactive driver: only listens and reports
    ctrl = rig.ctrl(1)
    t0 = now()
    for f in (
        codec.make_set_watchdog(1, WATCHDOG_MS),
        codec.make_set_axis_state(1, Axis.WHEEL, True),
        codec.make_set_control(1, Axis.WHEEL, ControlMode.VELOCITY, 3.0),
    ):
        rig.obs.send(
            can.Message(arbitration_id=f.arbitration_id, data=f.data, is_extended_id=False)
        )
    assert wait_until(lambda: ctrl.axes[Axis.WHEEL].state == AxisState.ENABLED, 0.5)
    assert wait_until(lambda: ctrl.axes[Axis.WHEEL].state == AxisState.FAULT, 1.0)
    t_fault = now()
    assert T(0.09) <= t_fault - t0 <= T(0.3)
    with rig.emu.lock:
        ax = ctrl.axes[Axis.WHEEL]
        assert ax.errors == ErrorFlag.WATCHDOG_TIMEOUT
        assert ax.mode == ControlMode.FREE and ax.torque == 0.0
    fault_ids = rig.obs.ids(lambda i: i == codec.frame_id(1, Command.FAULT_REPORT))
    assert wait_until(
        lambda: rig.obs.ids(lambda i: i == codec.frame_id(1, Command.FAULT_REPORT)) != []
    )
    del fault_ids
    rig.drv.wait_axis_state(1, Axis.WHEEL, AxisState.FAULT)
    ev = [e for e in rig.drv.events() if e.kind == EventKind.NODE_FAULT]
    assert ev and "WATCHDOG_TIMEOUT" in ev[0].message and ev[0].axis == Axis.WHEEL


def test_driver_refresh_keeps_the_watchdog_fed(active: Rig) -> None:
    drv = active.drv
    drv.enable(4, Axis.WHEEL)
    drv.set_velocity(4, Axis.WHEEL, 1.0)
    sleep(T(0.6))  # six watchdog timeouts without a user command
    assert drv.module_state(4).states[1] == AxisState.ENABLED
    assert active.ctrl(4).axes[Axis.WHEEL].errors == 0
    refreshes = [f for f in active.host_frames() if isinstance(f, codec.SetControl) and f.node == 4]
    assert 15 <= len(refreshes) <= 40  # one per 20 ms refresh period


def test_over_speed_limit_stops_everything(active: Rig) -> None:
    drv = active.drv
    drv.set_limits(2, Axis.WHEEL, max_torque=1.0, max_velocity=2.0)
    drv.enable(2, Axis.WHEEL)
    drv.enable(1, Axis.WHEEL)
    drv.set_velocity(1, Axis.WHEEL, 1.0)
    t0 = now()
    drv.set_torque(2, Axis.WHEEL, 0.5)  # accelerates past 1.2 x 2 rad/s
    drv.wait_axis_state(2, Axis.WHEEL, AxisState.FAULT)
    assert drv.module_state(2).errors[1] == ErrorFlag.OVER_SPEED
    assert wait_until(lambda: stop_frames(active.host_frames(t0)) == (ALL_AXES, ALL_AXES))
    assert drv.state == Lifecycle.INACTIVE
    drv.wait_axis_state(1, Axis.WHEEL, AxisState.DISABLED)  # the healthy module stopped too


# ---------------------------------------------------------------------------- faults
def test_heartbeat_loss_raises_fault_and_stops_all(active: Rig) -> None:
    drv = active.drv
    drv.enable(1, Axis.WHEEL)
    drv.set_velocity(1, Axis.WHEEL, 2.0)
    queued_when_inactive: list[EventKind] = []
    queued_messages: list[str] = []
    begin_fault = drv._begin_fault

    def probe(cause: str) -> bool:  # the moment the driver drops to INACTIVE
        queued = list(drv._events.queue)
        queued_when_inactive.extend(e.kind for e in queued)
        queued_messages.extend(e.message for e in queued)
        return begin_fault(cause)

    drv._begin_fault = probe  # type: ignore[method-assign]
    sleep(T(0.05))
    t0 = now()
    active.emu.mute(3)
    assert wait_until(lambda: drv.state == Lifecycle.INACTIVE, 1.0)
    # whoever sees INACTIVE finds the cause already queued
    assert EventKind.HEARTBEAT_LOST in queued_when_inactive, queued_messages
    dt = now() - t0
    assert T(0.2) <= dt <= T(0.6)  # 3 heartbeat periods after the last heartbeat
    lost = [e for e in drv.events() if e.kind == EventKind.HEARTBEAT_LOST]
    assert [e.node for e in lost] == [3] and "module 3 (node 3)" in lost[0].message
    assert wait_until(lambda: stop_frames(active.host_frames(t0)) == (ALL_AXES, ALL_AXES))
    drv.wait_axis_state(1, Axis.WHEEL, AxisState.DISABLED)
    assert drv.stats().heartbeat_losses == 1
    # a command refused after the fault stop names the fault, not only the state
    assert drv.fault_cause == lost[0].message
    with pytest.raises(
        LifecycleError,
        match=r"module 1 \(node 1\) axis 1 \(wheel\): cannot .* in state inactive "
        r"\(stopped by a fault: module 3 \(node 3\): no heartbeat for",
    ):
        drv.hold(1, Axis.WHEEL)
    active.emu.mute(3, False)
    assert wait_until(lambda: drv.module_state(3).alive, 1.0)
    assert any(e.kind == EventKind.HEARTBEAT_RESTORED for e in drv.events())
    drv.activate()
    assert drv.fault_cause is None
    drv.deactivate()  # an orderly stop has no fault cause
    assert drv.fault_cause is None
    with pytest.raises(LifecycleError, match=r"in state inactive$"):
        drv.hold(1, Axis.WHEEL)


def test_robot_io_reports_a_fault_stop_before_its_event_callback_runs(active: Rig) -> None:
    """The state machine polls take_faults() between commands.  The driver drops out of
    ACTIVE before it runs the event callbacks; a callback ahead of the RobotIO's (which
    may be slow) must not leave a window in which take_faults() is empty yet the next
    command is refused, and the motors stop before any callback runs.  Checked from
    inside that first callback, at the moment it runs."""
    from swpc_hw.drives.robot_io import DrivesRobotIO

    drv = active.drv
    seen: list[dict[str, object]] = []
    io: DrivesRobotIO | None = None

    def first(ev: DriverEvent) -> None:  # registered first: runs before the RobotIO's
        if ev.severity is not Severity.FAULT or io is None:
            return
        refused = ""
        try:
            io.wheel_hold(1)
        except LifecycleError as exc:
            refused = str(exc)
        seen.append(
            {
                "message": ev.message,
                "t": now(),
                "stop_all_calls": drv.stats().stop_all_calls,
                "faults": io.take_faults(),
                "refused": refused,
            }
        )

    drv.add_event_callback(first)
    io = DrivesRobotIO(drv)
    drv.enable(1, Axis.WHEEL)
    drv.hold(1, Axis.WHEEL)
    assert io.take_faults() == []
    t0 = now()
    active.emu.mute(3)
    assert wait_until(lambda: len(seen) >= 1, 1.0)
    got = seen[0]
    assert "module 3 (node 3): no heartbeat" in str(got["message"])
    # every axis freed and disabled before the first callback ran: stop_all() had been
    # called, and its frames are on the bus stamped no later than the callback
    assert got["stop_all_calls"] == 1
    t_cb = got["t"]
    assert isinstance(t_cb, float)

    def stops_by_callback() -> tuple[set[tuple[int, Axis]], set[tuple[int, Axis]]]:
        frames = [
            codec.parse(m.arbitration_id, bytes(m.data))
            for t, m in active.obs.snapshot()
            if t0 <= t <= t_cb and codec.split_id(m.arbitration_id)[1] in codec.HOST_COMMANDS
        ]
        return stop_frames(frames)

    assert wait_until(lambda: stops_by_callback() == (ALL_AXES, ALL_AXES))
    # the RobotIO's own callback had not run, yet it reported the fault (once)
    faults = got["faults"]
    assert isinstance(faults, list) and len(faults) == 1
    assert "module 3 (node 3): no heartbeat" in faults[0], faults
    assert "stopped by a fault: module 3" in str(got["refused"])
    sleep(T(0.1))
    assert io.take_faults() == []  # its late event is not a second fault
    # after close() the RobotIO no longer listens; the driver keeps its other callbacks
    io.close()
    drv.remove_event_callback(first)
    io.close()  # idempotent
    active.emu.mute(3, False)
    assert wait_until(lambda: drv.module_state(3).alive, 1.0)
    drv.activate()
    n = len(seen)
    active.emu.mute(3)
    assert wait_until(lambda: drv.state == Lifecycle.INACTIVE, 1.0)
    sleep(T(0.1))
    assert len(seen) == n  # removed: not called
    active.emu.mute(3, False)


@virtual_only
def test_error_frames_counted_and_bus_off_is_a_fault(active: Rig) -> None:
    drv = active.drv
    active.emu.send_raw(can.Message(is_error_frame=True, arbitration_id=0x004, dlc=8))
    assert wait_until(lambda: drv.stats().error_frames == 1)
    assert drv.state == Lifecycle.ACTIVE
    assert [e.kind for e in drv.events()].count(EventKind.ERROR_FRAME) == 1
    t0 = now()
    active.emu.send_raw(can.Message(is_error_frame=True, arbitration_id=0x040, dlc=8))
    assert wait_until(lambda: drv.state == Lifecycle.INACTIVE)
    assert drv.stats().bus_off == 1
    assert any(e.kind == EventKind.BUS_OFF for e in drv.events())
    assert wait_until(lambda: stop_frames(active.host_frames(t0)) == (ALL_AXES, ALL_AXES))


def test_unknown_ids_and_bad_dlc_are_counted_not_fatal(active: Rig) -> None:
    drv = active.drv
    before = drv.stats().rx_frames
    for msg in (
        can.Message(arbitration_id=0x7FF, data=b"\x01", is_extended_id=False),
        can.Message(arbitration_id=0x1234567, data=b"", is_extended_id=True),
        can.Message(arbitration_id=9 << 5 | 6, data=bytes(8), is_extended_id=False),  # node 9
        can.Message(arbitration_id=0x0AF, data=bytes(8), is_extended_id=False),  # cmd 15
    ):
        active.obs.send(msg)
    active.obs.send(can.Message(arbitration_id=0x026, data=bytes(7), is_extended_id=False))
    active.obs.send(can.Message(arbitration_id=0x044, data=bytes(3), is_extended_id=False))
    # in-range DLC but SteerState 7 > DBC max 3
    active.obs.send(
        can.Message(
            arbitration_id=0x066, data=bytes([7, 0, 0, 0, 0, 0, 0, 0]), is_extended_id=False
        )
    )
    assert wait_until(lambda: drv.stats().bad_dlc == 2 and drv.stats().unknown_ids == 4)
    assert wait_until(lambda: drv.stats().decode_errors == 1)
    kinds = [e.kind for e in drv.events()]
    assert kinds.count(EventKind.UNKNOWN_ID) == 4 and kinds.count(EventKind.BAD_DLC) == 2
    assert drv.state == Lifecycle.ACTIVE
    assert wait_until(lambda: drv.stats().rx_frames > before + 20)  # reception continues


def test_listener_exception_is_reported_and_stops(active: Rig) -> None:
    drv = active.drv
    calls: list[int] = []

    def bad_callback(module: int, sample: object) -> None:
        calls.append(module)
        if len(calls) == 3:
            raise RuntimeError("consumer bug")

    drv.enable(1, Axis.WHEEL)
    drv.add_feedback_callback(bad_callback)
    assert wait_until(lambda: drv.stats().listener_errors == 1)
    assert drv.state == Lifecycle.INACTIVE
    ev = [e for e in drv.events() if e.kind == EventKind.LISTENER_ERROR]
    assert ev and "RuntimeError: consumer bug" in ev[0].message
    assert isinstance(drv.last_exception, RuntimeError)
    n = len(calls)
    assert wait_until(lambda: len(calls) > n + 10)  # the Notifier thread keeps running
    drv.wait_axis_state(1, Axis.WHEEL, AxisState.DISABLED)


def test_stop_all_sends_free_then_disable_to_every_axis(active: Rig) -> None:
    drv = active.drv
    for m in NODES:
        drv.enable(m, Axis.WHEEL)
        drv.set_velocity(m, Axis.WHEEL, 1.0)
    t0 = now()
    drv.stop_all()

    def stops() -> list[codec.Decoded]:
        return [
            f
            for f in active.host_frames(t0)
            if (isinstance(f, codec.SetControl) and f.mode == ControlMode.FREE)
            or (isinstance(f, codec.SetAxisState) and not f.enabled)
        ]

    assert wait_until(lambda: len(stops()) >= 16)
    frames = stops()[:16]
    assert stop_frames(frames) == (ALL_AXES, ALL_AXES)
    assert all(isinstance(f, codec.SetControl) for f in frames[:8])  # all FREE first
    for m in NODES:
        drv.wait_axis_state(m, Axis.WHEEL, AxisState.DISABLED)
    sleep(T(0.1))  # no refresh of the old setpoints after stop_all()
    assert [f for f in stops()[16:] if isinstance(f, codec.SetControl)] == []
    n = len(active.host_frames(t0))
    sleep(T(0.1))
    assert len(active.host_frames(t0)) == n
