"""Exact-byte tests of every protocol message, the DBC's node copies, the generated C code.

Expected bytes are derived by hand from the DBC layout (Intel byte order, two's complement)
and written next to each case.
"""

from __future__ import annotations

import math
import re
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import cantools
import pytest

from firmware_protocol import busload, codec, dbc_nodes
from firmware_protocol.codec import (
    Axis,
    AxisState,
    Command,
    ControlMode,
    Frame,
    HomingState,
)
from tests.service_rig import ROOT

# Every position on the bus (feedback steer and wheel, PositionSetpoint, SensorPosition)
# is 2**17 counts per turn.  Written out here, not taken from the codec, so that the byte
# expectations below check the DBC's scale.
LSB = 2 * math.pi / 2**17  # 4.7936899621e-05 rad; 1 rad = 2**17 / (2 pi) = 20860.7567 counts
STEER_LSB = WHEEL_LSB = LSB

# (builder, frame id, data hex, decoded record)
CASES: list[tuple[Callable[[], Frame], int, str, codec.Decoded]] = [
    # SyncCounter 5
    (lambda: codec.make_sync(5), 0x000, "05", codec.Sync(0, 5)),
    # Axis 1, RequestedState 1
    (
        lambda: codec.make_set_axis_state(1, Axis.WHEEL, True),
        0x021,
        "0101",
        codec.SetAxisState(1, Axis.WHEEL, True),
    ),
    (
        lambda: codec.make_set_axis_state(3, Axis.STEER, False),
        0x061,
        "0000",
        codec.SetAxisState(3, Axis.STEER, False),
    ),
    # velocity 3.5 rad/s / 1e-4 = 35000 = 0x000088B8
    (
        lambda: codec.make_set_control(2, Axis.WHEEL, ControlMode.VELOCITY, 3.5),
        0x042,
        "0103b8880000",
        codec.SetControl(2, Axis.WHEEL, ControlMode.VELOCITY, 3.5),
    ),
    # position -1 rad / (2 pi / 2**17) = -20860.76 -> -20861; 20861 = 0x517D, so
    # int32 -20861 = 0xFFFFFFFF - 0x517D + 1 = 0xFFFFAE83 -> LE 83 AE FF FF
    (
        lambda: codec.make_set_control(1, Axis.STEER, ControlMode.POSITION, -1.0),
        0x022,
        "000283aeffff",
        codec.SetControl(1, Axis.STEER, ControlMode.POSITION, -20861 * LSB),
    ),
    # torque 1.25 N.m / 1e-4 = 12500 = 0x30D4
    (
        lambda: codec.make_set_control(1, Axis.WHEEL, ControlMode.TORQUE, 1.25),
        0x022,
        "0104d4300000",
        codec.SetControl(1, Axis.WHEEL, ControlMode.TORQUE, 1.25),
    ),
    (
        lambda: codec.make_set_control(1, Axis.STEER, ControlMode.HOLD),
        0x022,
        "000100000000",
        codec.SetControl(1, Axis.STEER, ControlMode.HOLD, 0.0),
    ),
    (
        lambda: codec.make_set_control(4, Axis.WHEEL, ControlMode.FREE),
        0x082,
        "010000000000",
        codec.SetControl(4, Axis.WHEEL, ControlMode.FREE, 0.0),
    ),
    # Axis 1, NewErrors 0x0001, ActiveErrors 0x0003, AxisState 3
    (
        lambda: codec.make_fault_report(3, Axis.WHEEL, 0x0001, 0x0003, AxisState.FAULT),
        0x063,
        "010100030003",
        codec.FaultReport(3, Axis.WHEEL, 1, 3, AxisState.FAULT),
    ),
    # steer raw 100 (bits 0-19), wheel raw -1 (bits 20-55 all ones), counter 7:
    # 0x07_FFFFFFFFF_00064 -> LE 64 00 F0 FF FF FF FF 07
    (
        lambda: codec.make_feedback_position(1, 100 * STEER_LSB, -WHEEL_LSB, 7),
        0x024,
        "6400f0ffffffff07",
        codec.FeedbackPosition(1, 100 * STEER_LSB, -WHEEL_LSB, 7),
    ),
    # steer raw -1 = 0xFFFFF, wheel 1000 turns = 1000 * 2**17 = 131_072_000 = 0x7D00000
    # (0x20000 * 0x3E8), counter 0: 0x00_007D00000_FFFFF -> LE FF FF 0F 00 00 7D 00 00
    (
        lambda: codec.make_feedback_position(2, -STEER_LSB, 1000 * 2 * math.pi, 0),
        0x044,
        "ffff0f00007d0000",
        codec.FeedbackPosition(2, -STEER_LSB, 1000 * 2 * math.pi, 0),
    ),
    # steer 1.0 rad -> 20860.76 -> 20861 = 0x0517D (20 bits);
    # wheel -0.5 rad -> -10430.38 -> -10430; 10430 = 0x28BE, int36 = 0xFFFFFD742;
    # counter 42 = 0x2A: 0x2A_FFFFFD742_0517D -> LE 7D 51 20 74 FD FF FF 2A
    (
        lambda: codec.make_feedback_position(5, 1.0, -0.5, 42),
        0x0A4,
        "7d512074fdffff2a",
        codec.FeedbackPosition(5, 20861 * STEER_LSB, -10430 * WHEEL_LSB, 42),
    ),
    # 1.0 rad/s -> 1000 = 0x03E8; -2.0 rad/s / 0.002 = -1000 = 0xFC18; 0.5 N.m -> 50 = 0x032;
    # -0.01 N.m -> -1 = 0xFFF; counter 9: 0x09_FFF_032_FC18_03E8
    (
        lambda: codec.make_feedback_velocity_torque(1, 1.0, -2.0, 0.5, -0.01, 9),
        0x025,
        "e80318fc32f0ff09",
        codec.FeedbackVelocityTorque(1, 1.0, -2.0, 0.5, -0.01, 9),
    ),
    # byte0 = SteerState 3 | SteerMode 0 << 4; byte1 = WheelState 1 | WheelMode 3 << 4;
    # SteerErrors 0x0001, WheelErrors 0, Homed bit 48, Counter 200 = 0xC8
    (
        lambda: codec.make_heartbeat(
            4,
            (AxisState.FAULT, AxisState.ENABLED),
            (ControlMode.FREE, ControlMode.VELOCITY),
            (0x0001, 0),
            True,
            False,
            200,
        ),
        0x086,
        "03310100000001c8",
        codec.Heartbeat(
            4,
            (AxisState.FAULT, AxisState.ENABLED),
            (ControlMode.FREE, ControlMode.VELOCITY),
            (1, 0),
            True,
            False,
            200,
        ),
    ),
    (lambda: codec.make_clear_errors(1, 0b11), 0x027, "03", codec.ClearErrors(1, 3)),
    # 2.5 N.m / 0.001 = 2500 = 0x09C4; 10 rad/s / 0.01 = 1000 = 0x03E8
    (
        lambda: codec.make_set_limits(2, Axis.STEER, 2.5, 10.0),
        0x048,
        "00c409e803",
        codec.SetLimits(2, Axis.STEER, 2.5, 10.0),
    ),
    (lambda: codec.make_set_watchdog(1, 100), 0x029, "6400", codec.SetWatchdog(1, 100)),
    (
        lambda: codec.make_set_feedback(1, 200, True),
        0x02A,
        "c80001",
        codec.SetFeedback(1, 200, True),
    ),
    (lambda: codec.make_start_homing(8), 0x10B, "00", codec.StartHoming(8, Axis.STEER)),
    # 0.3 rad / (2 pi / 2**17) = 6258.23 -> 6258 = 0x1872 -> LE 72 18 00 00
    (
        lambda: codec.make_homing_status(1, Axis.STEER, HomingState.DONE, 0.3),
        0x02C,
        "000272180000",
        codec.HomingStatus(1, Axis.STEER, HomingState.DONE, 6258 * LSB),
    ),
]


def _close(a: object, b: object) -> bool:
    if isinstance(a, float) and isinstance(b, float):
        return math.isclose(a, b, rel_tol=1e-12, abs_tol=1e-12)
    if isinstance(a, tuple) and isinstance(b, tuple):
        return len(a) == len(b) and all(_close(x, y) for x, y in zip(a, b, strict=True))
    return a == b


@pytest.mark.parametrize(("build", "fid", "hexdata", "record"), CASES)
def test_encode_decode_exact_bytes(
    build: Callable[[], Frame], fid: int, hexdata: str, record: codec.Decoded
) -> None:
    frame = build()
    assert frame.arbitration_id == fid
    assert frame.data.hex() == hexdata
    decoded = codec.parse(fid, bytes.fromhex(hexdata))
    assert type(decoded) is type(record)
    for name in record.__dataclass_fields__:
        assert _close(getattr(decoded, name), getattr(record, name)), name


def test_every_message_has_a_case() -> None:
    commands = {codec.split_id(fid)[1] for _, fid, _, _ in CASES}
    assert commands == {int(c) for c in Command}


RANGE_CASES: list[tuple[Callable[[], Frame], str]] = [
    (lambda: codec.make_sync(256), "SyncCounter"),
    (lambda: codec.make_set_axis_state(1, 2, True), "Axis"),  # type: ignore[arg-type]
    (
        lambda: codec.make_set_control(1, Axis.WHEEL, ControlMode.VELOCITY, 200.5),
        "VelocitySetpoint",
    ),
    (lambda: codec.make_set_control(1, Axis.WHEEL, ControlMode.TORQUE, -51.0), "TorqueSetpoint"),
    # int32 at 2 pi / 2**17 spans +-2**14 turns = +-102943.7 rad
    (
        lambda: codec.make_set_control(1, Axis.STEER, ControlMode.POSITION, 1.03e5),
        "PositionSetpoint",
    ),
    (lambda: codec.make_fault_report(1, Axis.STEER, 1 << 16, 0, AxisState.FAULT), "NewErrors"),
    (lambda: codec.make_feedback_position(1, 0.0, 0.0, 256), "Counter"),
    (lambda: codec.make_feedback_velocity_torque(1, 33.0, 0.0, 0.0, 0.0, 0), "SteerVelocity"),
    (lambda: codec.make_feedback_velocity_torque(1, 0.0, 0.0, 0.0, 21.0, 0), "WheelTorque"),
    (
        lambda: codec.make_heartbeat(
            1,
            (AxisState.FAULT, AxisState.FAULT),
            (ControlMode.FREE, ControlMode.FREE),
            (0, 70000),
            False,
            False,
            0,
        ),
        "WheelErrors",
    ),
    (lambda: codec.make_clear_errors(1, 4), "AxisMask"),
    (lambda: codec.make_set_limits(1, Axis.WHEEL, 70.0, 1.0), "MaxTorque"),
    (lambda: codec.make_set_limits(1, Axis.WHEEL, 1.0, -1.0), "MaxVelocity"),
    (lambda: codec.make_set_watchdog(1, 60001), "TimeoutMs"),
    (lambda: codec.make_set_feedback(1, 501), "RateHz"),
    (lambda: codec.make_start_homing(1, 3), "Axis"),  # type: ignore[arg-type]
    (lambda: codec.make_homing_status(1, Axis.STEER, 4, 0.0), "Status"),  # type: ignore[arg-type]
]


@pytest.mark.parametrize(("build", "signal"), RANGE_CASES)
def test_encode_range_error_names_signal(build: Callable[[], Frame], signal: str) -> None:
    with pytest.raises(codec.SignalRangeError) as info:
        build()
    assert info.value.signal == signal
    assert f'"{signal}"' in str(info.value)
    assert re.match(r"node [01] (Sync|N1_)", str(info.value))


def test_decode_errors_name_signal_length_and_id() -> None:
    # SteerState raw 5 fits 4 bits but the DBC range is 0..3
    with pytest.raises(codec.SignalRangeError, match='"SteerState"') as info:
        codec.parse(0x026, bytes.fromhex("0500000000000000"))
    assert info.value.signal == "SteerState"
    # RateHz raw 600 > 500
    with pytest.raises(codec.SignalRangeError, match='"RateHz"'):
        codec.parse(0x02A, (600).to_bytes(2, "little") + b"\x00")
    with pytest.raises(codec.FrameLengthError, match="N2_FeedbackPosition: DLC 7"):
        codec.parse(0x044, bytes(7))
    with pytest.raises(codec.UnknownFrameError, match="0x03f"):
        codec.parse(0x03F, bytes(8))
    with pytest.raises(codec.UnknownFrameError):
        codec.parse(9 << 5 | 6, bytes(8))  # node 9 is not in the DBC
    with pytest.raises(codec.SignalRangeError, match=r"signal \"Mode\" = 9 outside \[0, 4\]"):
        codec.parse(0x022, bytes.fromhex("000900000000"))
    with pytest.raises(codec.ProtocolError):
        codec.frame_id(0, Command.HEARTBEAT)


def test_position_resolution_and_spans_are_2_17_counts_per_turn() -> None:
    assert codec.STEER_LSB == codec.WHEEL_LSB == LSB
    assert codec.STEER_COUNTS_PER_TURN == codec.WHEEL_COUNTS_PER_TURN == 2**17
    for name, cmd in (
        ("PositionSetpoint", Command.SET_CONTROL),
        ("SensorPosition", Command.HOMING_STATUS),
    ):
        assert codec.signal_scale(name, cmd) == LSB, name
        # int32: 2**32 counts / 2**17 counts per turn = 2**15 turns, i.e. +-2**14 turns
        assert codec.signal_span(name, cmd) == 2**15 * 2 * math.pi, name
    # int20 steer: 2**20 / 2**17 = 8 turns; int36 wheel: 2**36 / 2**17 = 2**19 turns
    assert codec.STEER_SPAN == codec.signal_span("SteerPosition") == 8 * 2 * math.pi
    assert codec.WHEEL_SPAN == codec.signal_span("WheelPosition") == 2**19 * 2 * math.pi


def test_positions_keep_precision_over_hours_and_unwrap() -> None:
    # 20 h of a 0.054 m wheel at 1 m/s: 1.33e6 rad = 2.1e5 turns, inside the +-2**18-turn
    # range; the step stays 2 pi / 2**17 rad.
    psi = 1.0 / 0.054 * 20 * 3600 + 0.123456
    f = codec.make_feedback_position(1, 0.7, psi, 0)
    dec = codec.parse(f.arbitration_id, f.data)
    assert isinstance(dec, codec.FeedbackPosition)
    assert abs(dec.wheel - psi) <= WHEEL_LSB / 2 + 1e-9
    # beyond the 2**18-turn range (24 h at 3 rev/s) the counter wraps; unwrap() restores it
    big = codec.WHEEL_SPAN * 0.5 + 10.0
    f = codec.make_feedback_position(1, 0.0, big, 0)
    dec = codec.parse(f.arbitration_id, f.data)
    assert isinstance(dec, codec.FeedbackPosition)
    assert dec.wheel < 0
    assert abs(codec.unwrap(big - 0.5, dec.wheel, codec.WHEEL_SPAN) - big) <= WHEEL_LSB
    # steering: 2 pi / 2**17 rad (0.0027 deg) per count; -3.0 rad -> -62582.27 -> -62582,
    # an error of 0.27 count = 1.3e-5 rad (at 2**14 counts/turn: -7822.78 -> -7823, an
    # error of 0.22 x 2 pi / 2**14 = 8.3e-5 rad, over the bound below)
    f = codec.make_feedback_position(1, -3.0, 0.0, 0)
    dec = codec.parse(f.arbitration_id, f.data)
    assert isinstance(dec, codec.FeedbackPosition)
    assert dec.steer == -62582 * STEER_LSB
    assert abs(dec.steer + 3.0) <= STEER_LSB / 2


def test_steering_wraps_at_4_turns_and_unwraps() -> None:
    # 4 turns + 0.1 rad is past the int20 maximum (2**19 - 1 counts): the counter wraps by
    # 2**20 counts = 8 turns, to -4 turns + 0.1 rad
    steer = 4 * 2 * math.pi + 0.1
    f = codec.make_feedback_position(1, steer, 0.0, 0)
    dec = codec.parse(f.arbitration_id, f.data)
    assert isinstance(dec, codec.FeedbackPosition)
    assert dec.steer == pytest.approx(steer - 8 * 2 * math.pi, abs=STEER_LSB / 2)
    # a whole number of turns: the steering direction survives the wrap
    assert math.cos(dec.steer) == pytest.approx(math.cos(steer), abs=STEER_LSB)
    assert math.sin(dec.steer) == pytest.approx(math.sin(steer), abs=STEER_LSB)
    # from the previous (unwrapped) reading just below 4 turns, unwrap() adds the 8 turns
    prev = 4 * 2 * math.pi - 0.05
    assert codec.unwrap(prev, dec.steer, codec.STEER_SPAN) == pytest.approx(
        steer, abs=STEER_LSB / 2
    )
    # and on the way back down through -4 turns
    f = codec.make_feedback_position(1, -steer, 0.0, 0)
    dec = codec.parse(f.arbitration_id, f.data)
    assert isinstance(dec, codec.FeedbackPosition)
    assert dec.steer > 0
    assert codec.unwrap(-prev, dec.steer, codec.STEER_SPAN) == pytest.approx(
        -steer, abs=STEER_LSB / 2
    )


def test_dbc_node_copies_identical_and_up_to_date() -> None:
    assert dbc_nodes.render() == (ROOT / "firmware_protocol" / "swpc.dbc").read_text()
    db = codec.database()
    for cmd in Command:
        if cmd == Command.SYNC:
            continue
        ref = codec.message_for(1, cmd)
        assert ref.name == "N1_" + codec.COMMAND_NAMES[cmd]
        for node in range(2, codec.MAX_NODE + 1):
            m = db.get_message_by_frame_id(node << 5 | cmd)
            assert m.name == f"N{node}_{codec.COMMAND_NAMES[cmd]}"
            assert m.length == ref.length
            layout = [
                (s.name, s.start, s.length, s.is_signed, s.scale, s.minimum, s.maximum)
                for s in m.signals
            ]
            assert layout == [
                (s.name, s.start, s.length, s.is_signed, s.scale, s.minimum, s.maximum)
                for s in ref.signals
            ]
    assert {m.frame_id for m in db.messages} == {0} | {
        n << 5 | c for n in range(1, 9) for c in Command if c != Command.SYNC
    }
    assert all(not m.is_extended_frame and m.length <= 8 for m in db.messages)


def test_bus_load_budget_matches_readme() -> None:
    assert busload.frame_bits(8) == 135
    assert busload.frame_bits(6) == 115
    assert busload.frame_bits(1) == 65
    assert int(1e6 // busload.frame_bits(8)) == 7407
    b = busload.budget()
    assert b.total == pytest.approx(313_400)
    assert b.load < 0.5
    assert busload.budget(sync=True).load == pytest.approx(0.3264)
    assert busload.max_feedback_rate() == pytest.approx(650.6, abs=0.1)
    assert busload.max_feedback_rate(sync=True) == pytest.approx(613.6, abs=0.1)
    assert busload.budget(feedback_hz=500, sync=True).load == pytest.approx(0.6699)
    readme = (ROOT / "firmware_protocol" / "README.md").read_text()
    for figure in ("313.4 kbit/s", "31.3 %", "32.6 %", "650 Hz", "613 Hz", "67.0 %", "7407"):
        assert figure in readme, figure


C_MAIN = r"""
#include <stdio.h>
#include <string.h>
#include "swpc.h"
static void dump(const uint8_t *b, int n) {
    for (int i = 0; i < n; i++) printf("%02x", b[i]);
    printf("\n");
}
int main(void) {
    uint8_t buf[8];
    struct swpc_n1_heartbeat_t hb;
    swpc_n1_heartbeat_init(&hb);
    hb.steer_state = 3; hb.steer_mode = 0; hb.wheel_state = 1; hb.wheel_mode = 3;
    hb.steer_errors = 1; hb.wheel_errors = 0; hb.homed = 1; hb.sync_mode = 0; hb.counter = 200;
    dump(buf, swpc_n1_heartbeat_pack(buf, &hb, sizeof buf));
    struct swpc_n1_feedback_position_t fp;
    swpc_n1_feedback_position_init(&fp);
    fp.steer_position = swpc_n1_feedback_position_steer_position_encode(-3.0);
    fp.wheel_position = swpc_n1_feedback_position_wheel_position_encode(1300000.123456);
    fp.counter = 7;
    dump(buf, swpc_n1_feedback_position_pack(buf, &fp, sizeof buf));
    struct swpc_n1_feedback_velocity_torque_t fv;
    swpc_n1_feedback_velocity_torque_init(&fv);
    fv.steer_velocity = 1000; fv.wheel_velocity = -1000; fv.steer_torque = 50;
    fv.wheel_torque = -1; fv.counter = 9;
    dump(buf, swpc_n1_feedback_velocity_torque_pack(buf, &fv, sizeof buf));
    struct swpc_n1_set_control_t sc;
    const uint8_t in[6] = {0x01, 0x03, 0xb8, 0x88, 0x00, 0x00};
    if (swpc_n1_set_control_unpack(&sc, in, sizeof in) != 0) return 1;
    printf("%u %u %.4f\n", sc.axis, sc.mode,
           swpc_n1_set_control_velocity_setpoint_decode(sc.velocity_setpoint));
    return 0;
}
"""


def _strip_stamp(text: str) -> str:
    return re.sub(r"generated by cantools version .*", "", text)


def test_generated_c_is_current_and_compiles_strict(tmp_path: Path) -> None:
    gen = tmp_path / "gen"
    subprocess.run(
        [
            sys.executable, "-m", "cantools", "generate_c_source", "--node", "Ctrl1",
            "--use-round", "--database-name", "swpc", "-o", str(gen),
            str(ROOT / "firmware_protocol" / "swpc.dbc"),
        ],
        check=True,
        capture_output=True,
    )  # fmt: skip
    for name in ("swpc.c", "swpc.h"):
        committed = (ROOT / "firmware_protocol" / "c" / name).read_text()
        assert _strip_stamp((gen / name).read_text()) == _strip_stamp(committed), name
    gcc = shutil.which("gcc")
    if gcc is None:
        pytest.skip("gcc not installed: cannot compile the generated C code")
    (tmp_path / "main.c").write_text(C_MAIN)
    exe = tmp_path / "main"
    flags = ["-std=c99", "-Wall", "-Wextra", "-Werror"]
    subprocess.run(
        [
            gcc,
            *flags,
            "-I",
            str(gen),
            str(gen / "swpc.c"),
            str(tmp_path / "main.c"),
            "-o",
            str(exe),
            "-lm",
        ],
        check=True,
        capture_output=True,
    )
    lines = subprocess.run([str(exe)], check=True, capture_output=True, text=True).stdout.split()
    py_hb = codec.make_heartbeat(
        1,
        (AxisState.FAULT, AxisState.ENABLED),
        (ControlMode.FREE, ControlMode.VELOCITY),
        (1, 0),
        True,
        False,
        200,
    )
    py_fp = codec.make_feedback_position(1, -3.0, 1300000.123456, 7)  # inside +-2**18 turns
    assert lines[0] == py_hb.data.hex() == "03310100000001c8"
    assert lines[1] == py_fp.data.hex()
    assert lines[2] == "e80318fc32f0ff09"
    assert lines[3:] == ["1", "3", "3.5000"]


def test_compiled_layout_packs_and_unpacks_exactly_as_cantools() -> None:
    """The codec's fast path (a layout compiled from the DBC) against cantools itself: for
    every message, multiplexed ones per multiplexer value, random in-range values encode
    to cantools' strict bytes; cantools' decode of those bytes, and of random bytes, equals
    the fast unpack (same values, same types); an out-of-range value leaves the fast path
    and gets cantools' error, naming the signal."""
    import random

    rng = random.Random(7)
    checked = decoded = 0
    for msg in codec.database().messages:
        layout = codec.frame_layout(msg.frame_id)
        assert layout is not None, msg.name  # every message of our DBC compiles
        node, command = codec.split_id(msg.frame_id)
        mux = next((s for s in layout if s.is_mux), None)
        mux_values = [None] if mux is None else list(range(int(mux.low + 1), int(mux.high) + 1))
        for mv in mux_values:
            selected = [
                s for s in layout if s.mux_ids is None or (mv is not None and mv in s.mux_ids)
            ]
            for _ in range(25):
                values: dict[str, float | int] = {}
                for sig in selected:
                    lo, hi = max(sig.low, -1e6), min(sig.high, 1e6)
                    if sig.identity:
                        values[sig.name] = rng.randint(math.ceil(lo), math.floor(hi))
                    else:
                        values[sig.name] = rng.uniform(lo, hi)
                if mux is not None:
                    values[mux.name] = mv
                strict = bytes(msg.encode(values, scaling=True, padding=False, strict=True))
                assert codec._encode(node, codec.Command(command), values).data == strict
                ref = msg.decode(strict, decode_choices=False, scaling=True)
                fast = codec.unpack_frame(layout, strict)
                assert fast == ref and [type(v) for v in fast.values()] == [
                    type(ref[k]) for k in fast  # type: ignore[call-overload]
                ]
                checked += 1
        for _ in range(50):
            data = rng.randbytes(msg.length)
            try:
                ref = msg.decode(data, decode_choices=False, scaling=True)
            except cantools.database.DecodeError:
                continue
            assert codec.unpack_frame(layout, data) == ref, (msg.name, data.hex())
            decoded += 1
        ranged = [s for s in layout if math.isfinite(s.high) and s.mux_ids is None]
        sig = ranged[-1]
        bad = {s.name: (s.high + max(1.0, abs(s.high) * 1e-3) if s is sig else 0) for s in ranged}
        assert codec.pack_frame(layout, bad) is None
        with pytest.raises(codec.SignalRangeError) as info:
            codec._encode(node, codec.Command(command), bad)
        assert info.value.signal == sig.name
    assert checked >= 25 * 9 * 13 and decoded >= 50 * 9 * 8


