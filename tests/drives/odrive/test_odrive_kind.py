"""The odrive drive kind's pure parts: CAN Simple frames, the virtual ODrive's axis logic,
and both against peers we did not write (ODrive's documented byte layouts, the odrive-can
package's own decoder and mock ODrive).

No sleeps: the virtual axis is driven with explicit times; the one test against the
odrive-can mock (asyncio, real time) asserts only what a slow host cannot change.
"""

from __future__ import annotations

import asyncio
import itertools
import math
import struct
import threading
import time
import uuid

import can
import numpy as np
import pytest

from firmware_protocol import codec as swpc_codec
from firmware_protocol.codec import Axis, ErrorFlag
from firmware_protocol.odrive import can_simple as cs
from simulators.drives.odrive import VirtualODriveAxis, odrive_virtual_drive
from swpc_hw.drives.bus import CanConfig
from swpc_hw.drives.errors import NodeError
from swpc_hw.drives.odrive.config import ODriveAxis, ODriveDrives
from swpc_hw.drives.odrive.driver import ODriveDriver
from swpc_hw.drives.odrive.tracking import apply_frame, new_axis
from swpc_hw.drives.types import DriverStats

LINES = ("0.5", "0.6")


# ---------------------------------------------------------------- frames vs ODrive's table
@pytest.mark.parametrize("line", LINES)
def test_frames_are_odrives_documented_byte_layouts(line: str) -> None:
    """Each frame swpc uses, packed by hand from ODrive's documented table (ODrive's
    can-protocol table and its CAN example: little-endian, floats IEEE 754, Set_Input_Pos'
    feed-forwards int16 x 0.001), equals what the codec makes of the DBC, both ways."""
    c = cs.can_simple(line)
    node = 37
    closed_loop, position = cs.AxisState.CLOSED_LOOP_CONTROL, cs.ControlMode.POSITION_CONTROL
    cases = [
        (c.set_axis_state(node, closed_loop), 0x07, struct.pack("<I", 8) + bytes(4)),
        (c.set_controller_mode(node, position), 0x0B, struct.pack("<ii", 3, 1)),
        (c.set_input_pos(node, -12.375), 0x0C, struct.pack("<fhh", -12.375, 0, 0)),
        (c.set_input_vel(node, 2.5), 0x0D, struct.pack("<ff", 2.5, 0.0)),
        (c.set_input_torque(node, -0.125), 0x0E, struct.pack("<f", -0.125) + bytes(4)),
        (c.set_limits(node, 10.0, 20.5), 0x0F, struct.pack("<ff", 10.0, 20.5)),
        (c.encoder_estimates(node, 1234.5, -3.25), 0x09, struct.pack("<ff", 1234.5, -3.25)),
    ]  # fmt: skip
    for frame, cmd, data in cases:
        assert frame.arbitration_id == node << 5 | cmd
        assert frame.data == data, (cmd, frame.data.hex(), data.hex())
    hb = c.heartbeat(node, c.watchdog_bit, cs.AxisState.IDLE, procedure_result=3,
                     trajectory_done=True, component_errors=0b101)  # fmt: skip
    err, state, b5, b6, b7 = struct.unpack("<IBBBB", hb.data)
    assert (err, state) == (c.watchdog_bit, 1)
    if line == "0.5":  # motor, encoder, controller flag bytes; trajectory done in bit 63
        assert (b5, b6, b7) == (1, 0, 0x81)
        assert c.watchdog_bit == 0x800
    else:  # procedure result, trajectory done flag
        assert (b5, b6, b7) == (3, 1, 0)
        assert c.watchdog_bit == 0x01000000
    got = c.decode(hb.arbitration_id, hb.data)
    assert isinstance(got, cs.Heartbeat) and got.axis_error == c.watchdog_bit and got.state == 1
    assert got.procedure_result == (None if line == "0.5" else 3)
    est = c.decode(*(lambda f: (f.arbitration_id, f.data))(c.encoder_estimates(5, 0.5, -1.0)))
    assert est == cs.EncoderEstimates(5, 0.5, -1.0)
    # the clear errors frame differs between the lines (0.6.x has an Identify byte)
    assert len(c.clear_errors(1).data) == (0 if line == "0.5" else 1)


@pytest.mark.parametrize("line", LINES)
def test_enums_are_the_dbcs_value_tables(line: str) -> None:
    c = cs.can_simple(line)
    states = c.message(cs.Cmd.HEARTBEAT).get_signal_by_name("Axis_State").choices
    for s in cs.AxisState:
        assert str(states[int(s)]) == s.name
    modes = c.message(cs.Cmd.SET_CONTROLLER_MODE)
    for m in cs.ControlMode:
        assert str(modes.get_signal_by_name("Control_Mode").choices[int(m)]) == m.name
    for i in cs.InputMode:
        assert str(modes.get_signal_by_name("Input_Mode").choices[int(i)]) == i.name
    if line == "0.6":
        res = c.message(cs.Cmd.HEARTBEAT).get_signal_by_name("Procedure_Result").choices
        for r in cs.ProcedureResult:
            assert str(res[int(r)]) == r.name


@pytest.mark.parametrize("line", LINES)
def test_a_frame_of_swpcs_protocol_is_never_read_as_an_odrive_frame(line: str) -> None:
    """swpc's own ids have the same node << 5 | cmd layout: every swpc frame of every node
    either fails the codec (DLC, remote) or is a frame swpc does not act on, and the host's
    tracking core changes nothing for it."""
    c = cs.can_simple(line)
    rng = np.random.default_rng(1)
    stats = DriverStats()
    axes = {n: new_axis(1, Axis.STEER if n % 2 == 0 else Axis.WHEEL, ODriveAxis(node=n))
            for n in range(0, 9)}  # fmt: skip
    from swpc_hw.drives.tracking import FeedbackRing, NodeTrack

    modules = {1: NodeTrack(1, 0, FeedbackRing(10))}
    for msg in swpc_codec.database().messages:
        for node in range(0, swpc_codec.MAX_NODE + 1):
            fid = msg.frame_id & swpc_codec.COMMAND_MASK | node << 5
            data = bytes(rng.integers(0, 256, msg.length, dtype=np.uint8))
            try:
                dec = c.decode(fid, data)
            except cs.ProtocolError:
                continue
            assert dec is None, (msg.name, node, dec)
            before = [(a.pos, a.t_heartbeat, a.axis_error) for a in axes.values()]
            out = apply_frame(c, axes, modules, can.Message(arbitration_id=fid, data=data,
                              is_extended_id=False), 1.0, stats, True)  # fmt: skip
            assert not out.fault and out.sample is None
            assert [(a.pos, a.t_heartbeat, a.axis_error) for a in axes.values()] == before


# ---------------------------------------------------------------- a peer's decoder
@pytest.mark.parametrize("line", LINES)
def test_odrive_cans_own_decoder_reads_our_frames(line: str) -> None:
    """odrive-can's decoding (its DBC loader, by frame id and message name) reads what our
    host and our virtual ODrive send, node by node within its DBC's nodes 0..7."""
    from odrive_can.utils import get_dbc

    theirs = get_dbc(cs.FIRMWARE_LINES[line])
    c = cs.can_simple(line)
    for node in range(8):
        f = c.set_input_pos(node, 3.5)
        msg = theirs.get_message_by_frame_id(f.arbitration_id)
        assert msg.name == f"Axis{node}_Set_Input_Pos"
        assert msg.decode(f.data)["Input_Pos"] == 3.5
        f = c.heartbeat(node, c.watchdog_bit, cs.AxisState.CLOSED_LOOP_CONTROL)
        dec = theirs.get_message_by_frame_id(f.arbitration_id).decode(f.data)
        assert dec["Axis_Error"] == "WATCHDOG_TIMER_EXPIRED"
        assert dec["Axis_State"] == "CLOSED_LOOP_CONTROL"
        f = c.set_axis_state(node, cs.AxisState.ENCODER_INDEX_SEARCH)
        dec = theirs.get_message_by_frame_id(f.arbitration_id).decode(f.data)
        assert dec["Axis_Requested_State"] == "ENCODER_INDEX_SEARCH"


# ---------------------------------------------------------------- the virtual axis
def axis(line: str, watchdog: float = 0.2) -> VirtualODriveAxis:
    a = VirtualODriveAxis(node=3, line=line, spec=ODriveAxis(node=3), encoder_rate_hz=100,
                          watchdog_timeout=watchdog)  # fmt: skip
    a.step(0.0)
    return a


def send(a: VirtualODriveAxis, frame: swpc_codec.Frame, t: float) -> None:
    a.handle(can.Message(arbitration_id=frame.arbitration_id, data=frame.data,
                         is_extended_id=False), t)  # fmt: skip


def poll(a: VirtualODriveAxis, t: float) -> list[swpc_codec.Frame]:
    return a.handle(can.Message(arbitration_id=a.node << 5 | cs.Cmd.GET_ENCODER_ESTIMATES,
                                is_remote_frame=True, is_extended_id=False), t)  # fmt: skip


def run(a: VirtualODriveAxis, t0: float, t1: float, every: float, feed: object) -> None:
    """Step ``a`` from t0 to t1 in 1 ms steps, calling ``feed(t)`` every ``every`` s."""
    next_feed = t0
    for t in np.arange(t0, t1, 0.001):
        if feed is not None and t >= next_feed:
            feed(float(t))  # type: ignore[operator]
            next_feed += every
        a.step(float(t))


def test_a_05_axis_is_kept_alive_by_remote_polls_and_a_06_axis_is_not() -> None:
    """The issue's pitfall: on 0.5.x every frame to the axis feeds its watchdog, remote
    polls included, so a host that polls never trips it; on 0.6.x only setpoints do."""
    for line in LINES:
        a = axis(line)
        c = a.codec
        send(a, c.set_axis_state(3, cs.AxisState.CLOSED_LOOP_CONTROL), 0.0)
        run(a, 0.0, 2.0, 0.05, lambda t, a=a: poll(a, t))
        if line == "0.5":
            assert a.state == cs.AxisState.CLOSED_LOOP_CONTROL and a.axis_error == 0
        else:
            assert a.state == cs.AxisState.IDLE and a.axis_error == c.watchdog_bit
        # a setpoint every 50 ms keeps either line armed; silence disarms within W
        send(a, c.clear_errors(3), 2.0)
        send(a, c.set_axis_state(3, cs.AxisState.CLOSED_LOOP_CONTROL), 2.0)
        run(a, 2.0, 3.0, 0.05, lambda t, a=a, c=c: send(a, c.set_input_torque(3, 0.0), t))
        assert a.state == cs.AxisState.CLOSED_LOOP_CONTROL, line
        last = 3.0 - 0.05 + 0.001
        run(a, 3.0, 3.3, 1.0, None)
        assert a.axis_error == c.watchdog_bit and a.state == cs.AxisState.IDLE
        assert a.watchdog_due() == math.inf  # latched: counting again only once cleared
        assert last + 0.2 < 3.3


def test_a_05_axis_left_alone_reports_its_watchdog_even_idle() -> None:
    for line in LINES:
        a = axis(line)
        run(a, 0.0, 1.0, 1.0, None)
        assert a.axis_error == (a.codec.watchdog_bit if line == "0.5" else 0), line


def test_the_virtual_axis_refuses_closed_loop_with_an_error_and_searches_its_index() -> None:
    a = axis("0.6")
    c = a.codec
    a.inject("MOTOR_OVER_TEMP")
    send(a, c.set_axis_state(3, cs.AxisState.CLOSED_LOOP_CONTROL), 0.1)
    assert a.state == cs.AxisState.IDLE and a.procedure_result == cs.ProcedureResult.DISARMED
    send(a, c.clear_errors(3), 0.2)
    send(a, c.set_axis_state(3, cs.AxisState.ENCODER_INDEX_SEARCH), 0.2)
    assert a.state == cs.AxisState.ENCODER_INDEX_SEARCH and not a.index_found
    run(a, 0.2, 0.45, 1.0, None)
    assert a.state == cs.AxisState.IDLE and a.index_found
    assert a.procedure_result == cs.ProcedureResult.SUCCESS


def test_the_virtual_drive_converts_with_the_gear_ratios() -> None:
    cfg = ODriveDrives(modules={1: {"steer": {"node": 4, "gear_ratio": 8.0},
                                    "wheel": {"node": 5, "gear_ratio": 4.0}}})  # fmt: skip
    d = odrive_virtual_drive(cfg, 1, feedback_rate_hz=50, watchdog_ms=200, homing_duration=0.2,
                             sensor_position=0.3)  # fmt: skip
    d.sense(Axis.STEER, 0.5, 0.25, None)
    d.sense(Axis.WHEEL, 2 * math.pi, -1.0, 0.0)
    assert d.axes[0].position == pytest.approx(0.5 * 8 / (2 * math.pi))
    assert d.axes[1].position == pytest.approx(4.0) and d.axes[1].velocity == pytest.approx(
        -4 / (2 * math.pi)
    )
    c = d.axes[0].codec
    d.step(0.0)
    for m in (c.set_axis_state(4, cs.AxisState.CLOSED_LOOP_CONTROL),
              c.set_controller_mode(4, cs.ControlMode.POSITION_CONTROL),
              c.set_input_pos(4, 2.0), c.set_limits(4, 8.0, 100.0)):  # fmt: skip
        d.receive(can.Message(arbitration_id=m.arbitration_id, data=m.data,
                              is_extended_id=False), 0.0)  # fmt: skip
    kind, rate = d.drive(Axis.STEER, 0.5, 0.01, 0.02)
    # 2 axis turns = pi/2 rad at the output; the limit 8 turns/s = 2 pi rad/s
    assert kind == "rate" and rate == pytest.approx(2 * math.pi)
    kind, _ = d.drive(Axis.WHEEL, 0.0, 0.01, 0.02)
    assert kind == "passive"  # the wheel axis is idle
    assert d.inject_fault(Axis.WHEEL, ErrorFlag.OVER_TEMPERATURE) == []
    assert d.axes[1].axis_error == c.error_bit("MOTOR_OVER_TEMP")


# ---------------------------------------------------------------- a peer's mock ODrive
def test_our_driver_refuses_odrive_cans_mock_which_has_no_watchdog() -> None:
    """Against odrive-can's mock ODrive (its asyncio ODriveCANMock on the same virtual bus,
    real time): our driver reads its heartbeats and encoder estimates, its mock takes our
    closed-loop request, and our activation refuses it, naming the axis, because nothing
    in the mock disarms an axis the host stops feeding."""
    from odrive_can.mock import ODriveCANMock

    channel = f"odrive-peer-{uuid.uuid4().hex[:8]}"
    buses = [can.Bus(interface="virtual", channel=channel) for _ in (0, 1)]
    mocks = [ODriveCANMock(axis_id=n, can_bus=b) for n, b in zip((0, 1), buses, strict=True)]
    for m in mocks:
        # its notifier waits for a frame 1 s at a time (python-can's default) and stop()
        # below joins that wait: 50 ms (read at each wait; frames flow until the end)
        m.notifier.timeout = 0.05
    loop = asyncio.new_event_loop()
    tasks: list[asyncio.Task[None]] = []

    def serve() -> None:
        asyncio.set_event_loop(loop)
        for m in mocks:
            tasks.append(loop.create_task(m.main()))
        loop.run_forever()

    th = threading.Thread(target=serve, daemon=True)
    th.start()
    drives = ODriveDrives(firmware="0.6", modules={1: {"steer": {"node": 0}, "wheel": {"node": 1}}})
    bus = CanConfig(interface="virtual", channel=channel, modules={1: 1}, feedback_rate_hz=10,
                    watchdog_timeout_ms=200, refresh_period_s=0.05, heartbeat_period_s=0.2,
                    heartbeat_loss_periods=10, activate_timeout_s=10.0)  # fmt: skip
    drv = ODriveDriver(drives, bus)
    try:
        drv.configure()
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and not (
            drv.module_state(1).alive and drv.module_state(1).feedback is not None
        ):
            time.sleep(0.05)
        st = drv.module_state(1)
        assert st.alive and st.feedback is not None and st.errors == (0, 0)
        with pytest.raises(NodeError, match=r"module 1 \(node 0\) axis 0 \(steer\).*still armed"):
            drv.activate()
        # the mock took our closed-loop request (its heartbeat says so) and ignored the rest
        states = drv.axis_states()
        assert {states[n]["state"] for n in (0, 1)} <= {cs.AxisState.CLOSED_LOOP_CONTROL,
                                                          cs.AxisState.IDLE}  # fmt: skip
        assert mocks[0].odrive.axis_state in ("CLOSED_LOOP_CONTROL", "IDLE")
    finally:
        drv.shutdown()

        async def cancel() -> None:
            for t in tasks:
                t.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)

        asyncio.run_coroutine_threadsafe(cancel(), loop).result(timeout=5)
        loop.call_soon_threadsafe(loop.stop)
        th.join(timeout=5)
        for m in mocks:
            m.notifier.stop()
        for b in buses:
            b.shutdown()


def test_node_numbers_of_the_default_map_and_refusals() -> None:
    cfg = ODriveDrives().for_modules([1, 2, 3, 4])
    assert cfg.nodes() == list(range(8))
    with pytest.raises(ValueError, match="its own node id"):
        ODriveDrives(modules={1: {"steer": {"node": 3}, "wheel": {"node": 3}}})
    with pytest.raises(ValueError, match="less than or equal to 63"):
        ODriveAxis(node=64)
    assert list(itertools.islice(cfg.module_map(), 2)) == [1, 2]


def test_the_kernel_refresh_takes_a_new_frame_id_for_an_axis() -> None:
    """An ODrive axis' refresh goes from Set_Input_Torque (enable, free) to Set_Input_Pos
    (hold after its index search): python-can's periodic tasks change their data, never
    their ids, so the new id takes a new task (the VM's SocketCAN run faulted here before)."""
    from swpc_hw.drives.periodic import KernelRefresh

    c = cs.can_simple("0.5")
    channel = f"odrive-refresh-{uuid.uuid4().hex[:8]}"
    with can.Bus(interface="virtual", channel=channel) as tx, can.Bus(
        interface="virtual", channel=channel
    ) as rx:
        ref = KernelRefresh(tx, period=0.02, deadman=2.0)
        try:
            ref.set_node(4, [c.set_input_torque(4, 0.0)])
            ref.set_node(4, [c.set_input_torque(4, 0.5)])  # same id: the data changes
            ref.set_node(4, [c.set_input_pos(4, 1.25)])  # another id: a new task
            assert ref.nodes() == [4]
            deadline = time.monotonic() + 5.0
            seen = None
            while time.monotonic() < deadline and seen is None:
                m = rx.recv(0.1)
                if m is not None and m.arbitration_id == 4 << 5 | cs.Cmd.SET_INPUT_POS:
                    seen = c.decode(m.arbitration_id, bytes(m.data))
            assert seen == cs.SetInputPos(4, 1.25, 0.0, 0.0)
        finally:
            ref.close()


def test_a_frame_queued_before_the_simulator_slows_down_takes_effect_at_once() -> None:
    """The virtual robot in real time (``swpc sim``) slows its clock down when it cannot keep
    up.  A command queued just before (a burst: the watchdog proof's frames) must still take
    effect at its arrival, not after the stall has been simulated: in the VM, a 1.5 s stall
    held the proof's frames back until the service had given up on them."""
    from simulators.options import SimOptions
    from simulators.virtual_robot import VirtualRobot
    from swpc_hw.robot.paper_robot import PAPER_CALIBRATED

    channel = f"odrive-slow-{uuid.uuid4().hex[:8]}"
    drives = ODriveDrives(firmware="0.5")
    with can.Bus(interface="virtual", channel=channel) as host:
        sim_bus = can.Bus(interface="virtual", channel=channel)
        sim = VirtualRobot(PAPER_CALIBRATED, bus=sim_bus, own_bus=True,
                           options=SimOptions(drives=drives, watchdog_ms=200))  # fmt: skip
        try:
            # robot time due now is 5 s, the simulation is at 0: it has fallen 5 s behind
            sim.start_time, sim._origin = 0.0, sim._host.now() - 5.0
            for d in sim.drives:
                d.step(sim.now)
            c = cs.can_simple("0.5")
            f = c.set_axis_state(1, cs.AxisState.CLOSED_LOOP_CONTROL)  # module 1's wheel
            host.send(can.Message(arbitration_id=f.arbitration_id, data=f.data,
                                  is_extended_id=False))  # fmt: skip
            msg = sim_bus.recv(1.0)
            assert msg is not None
            sim._queue_frame(msg)
            # what _run_real_time does when it has fallen behind: the lag (robot time due
            # now, after the frame's arrival, minus the simulation's) less one tick
            dt = sim.tick_dt()
            lag = (sim._host.now() - sim._origin) - sim.robot.t
            assert lag >= 5.0
            sim._slow_down(lag - dt)
            sim._tick(dt)  # the frame arrived before the new "now": due by the next tick
            sim._receive_pending()
            axis = sim.drives[0].axes[1]  # type: ignore[attr-defined]
            assert axis.state == cs.AxisState.CLOSED_LOOP_CONTROL
        finally:
            sim.stop()


# ---------------------------------------------------------------- activation's refusals
@pytest.mark.parametrize("line", LINES)
def test_an_uncalibrated_axis_is_refused_for_its_calibration_not_its_watchdog(line: str) -> None:
    """An axis that refuses closed loop because it is not calibrated (0.5.x: axis error
    INVALID_STATE; 0.6.x: Procedure_Result NOT_CALIBRATED, no error) fails activation with
    its cause and the settings that fix it, not the watchdog's advice: its watchdog was
    never armed.  The others' watchdogs are proven as usual."""
    from simulators.options import SimOptions
    from simulators.virtual_robot import VirtualRobot
    from swpc_hw.clock import SimClock
    from swpc_hw.robot.paper_robot import PAPER_CALIBRATED

    clock = SimClock()
    channel = f"odrive-uncal-{uuid.uuid4().hex[:8]}"
    cfg = ODriveDrives(firmware=line, homing="absolute").for_modules(PAPER_CALIBRATED.ids)
    host = ODriveDriver(cfg, CanConfig(channel=channel, feedback_rate_hz=50,
                                       watchdog_timeout_ms=200), clock=clock)  # fmt: skip
    host.configure()
    sim = VirtualRobot.open(PAPER_CALIBRATED, channel=channel, clock=clock,
                            options=SimOptions(drives=cfg, physics_dt=0.01, watchdog_ms=200,
                                               feedback_rate_hz=50))  # fmt: skip
    sim.drives[1].axes[0].calibrated = False  # type: ignore[attr-defined]  # module 2 steer
    sim.start()
    try:
        with clock.participant(), pytest.raises(NodeError) as err:
            host.activate()
    finally:
        sim.stop()
        host.shutdown()
        clock.close()
    msg = str(err.value)
    print(f"\n{line}: {msg}")
    why = "axis error INVALID_STATE" if line == "0.5" else "procedure result NOT_CALIBRATED"
    assert f"module 2 (node 2) axis 0 (steer): refused closed loop ({why})" in msg
    assert "not calibrated" in msg and "FULL_CALIBRATION_SEQUENCE" in msg
    assert "startup_motor_calibration" in msg
    assert "enable_watchdog" not in msg and "still armed" not in msg
    assert err.value.node == 2
