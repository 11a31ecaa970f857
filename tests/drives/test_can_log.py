"""The rolling CAN log of the data dir (swpc_hw/drives/recording.py): within its bytes across
restarts, a sample of the periodic frames between runs and every event, every frame while
a run records, and a log that cannot write stops and says why.
"""

from __future__ import annotations

import uuid
from pathlib import Path
from typing import Any

import can

from swpc_hw.drives.recording import Recorder


def test_the_rolling_can_log_stays_within_its_bytes_across_restarts(tmp_path: Path) -> None:
    from swpc_hw.drives.recording import ROLLING_FILES, rolling_files

    base = tmp_path / "can" / "can.log"
    base.parent.mkdir()
    total = 512 << 10  # 512 KiB over all its files: 64 KiB each
    msg = can.Message(arbitration_id=0x123, data=bytes(range(8)), timestamp=1.0)
    frames = 0
    for _restart in range(3):  # the service restarts: the rolling log goes on, bounded
        rec = Recorder(str(base), total_bytes=total)
        for _ in range(6000):  # ~44 bytes a line: 260 KB per start
            rec.write(msg)
            frames += 1
        rec.stop()
        assert rec.error is None
    files = [base, *rolling_files(base)]
    size = sum(f.stat().st_size for f in files)
    assert size <= total and len(files) <= ROLLING_FILES + 1, (size, len(files))
    assert size > total // 2  # and it keeps the newest traffic, not nothing
    lines = sum(f.read_text().count("\n") for f in files)
    assert 0 < lines < frames
    # python-can reads every file back
    assert sum(1 for f in files for _ in can.LogReader(str(f))) == lines


def frame(f: Any, t: float) -> can.Message:
    return can.Message(
        arbitration_id=f.arbitration_id, data=f.data, timestamp=t, is_extended_id=False
    )


def idle_bus(seconds: int) -> list[can.Message]:
    """What an idle 4-module robot sends (heartbeats 10 Hz, encoder feedback 200 Hz, one
    other device at 100 Hz), with node 2 reporting an error from 3.5 s to 6 s, a fault
    report at 5 s, a host command at 6.5 s and an error frame at 7 s."""
    from firmware_protocol import codec
    from firmware_protocol.codec import AxisState, ControlMode

    out = []
    for k in range(seconds * 200):
        t = k / 200
        for n in (1, 2, 3, 4):
            if k % 20 == 0:
                errors = (0, 4) if n == 2 and 3.5 <= t < 6.0 else (0, 0)
                states = (AxisState.DISABLED, AxisState.DISABLED)
                modes = (ControlMode.FREE, ControlMode.FREE)
                hb = codec.make_heartbeat(n, states, modes, errors, True, False, k // 20 % 256)
                out.append(frame(hb, t))
            out.append(frame(codec.make_feedback_position(n, 0.1, 0.2, k % 256), t))
            vt = codec.make_feedback_velocity_torque(n, 0.0, 0.0, 0.0, 0.0, k % 256)
            out.append(frame(vt, t))
        if k % 2 == 0:
            out.append(can.Message(arbitration_id=0x18FF0001, data=b"\x01", timestamp=t))
        if k == 1000:
            fault = codec.make_fault_report(2, codec.Axis.WHEEL, 4, 4, AxisState.FAULT)
            out.append(frame(fault, t))
        if k == 1300:
            cmd = codec.make_set_control(1, codec.Axis.WHEEL, ControlMode.FREE)
            out.append(frame(cmd, t))
        if k == 1400:
            out.append(can.Message(is_error_frame=True, arbitration_id=0x040, timestamp=t))
    return out


def test_between_runs_the_rolling_log_keeps_a_sample_and_every_event(tmp_path: Path) -> None:
    """An idle robot's traffic, 10 s: once a second per CAN id, and every event at once
    (it was every frame: 100 kB/s, 360 MB an hour of writes for a log that forgets)."""
    from firmware_protocol.codec import Command, frame_id

    frames = idle_bus(10)
    assert len(frames) == 17_403
    rec = Recorder(str(tmp_path / "idle.log"), sample_period_s=1.0)
    for msg in frames:
        rec.write(msg, sample=True)
    rec.stop()
    kept = list(can.LogReader(str(tmp_path / "idle.log")))
    by_id: dict[int, list[float]] = {}
    for msg in kept:
        by_id.setdefault(msg.arbitration_id, []).append(round(msg.timestamp, 3))
    seconds = [float(t) for t in range(10)]
    for n in (1, 3, 4):
        assert by_id[frame_id(n, Command.HEARTBEAT)] == seconds  # heartbeat: one a second
    # node 2's heartbeat also when its errors come (3.5 s) and go (6 s)
    changes = [0.0, 1.0, 2.0, 3.0, 3.5, 4.5, 5.5, 6.0, 7.0, 8.0, 9.0]
    assert by_id[frame_id(2, Command.HEARTBEAT)] == changes
    feedback = (Command.FEEDBACK_POSITION, Command.FEEDBACK_VELOCITY_TORQUE)
    for n in (1, 2, 3, 4):
        assert [by_id[frame_id(n, c)] for c in feedback] == [seconds, seconds]
    assert by_id[0x18FF0001] == seconds  # another device's frames: sampled too
    # events: every one
    assert by_id[frame_id(2, Command.FAULT_REPORT)] == [5.0]
    assert by_id[frame_id(1, Command.SET_CONTROL)] == [6.5]
    assert [m.timestamp for m in kept if m.is_error_frame] == [7.0]
    assert len(kept) == 41 + 80 + 10 + 3
    # written without sampling (a run's recording, or the setting 0): every frame
    every = Recorder(str(tmp_path / "all.log"), sample_period_s=0.0)
    for msg in frames[:5000]:
        every.write(msg, sample=True)
    every.stop()
    assert sum(1 for _ in can.LogReader(str(tmp_path / "all.log"))) == 5000


def test_the_driver_logs_every_frame_only_while_it_records_a_run(tmp_path: Path) -> None:
    import time

    from firmware_protocol import codec
    from firmware_protocol.codec import AxisState, ControlMode
    from swpc_hw.drives.bus import CanConfig
    from swpc_hw.drives.swpc.driver import SwpcDriver

    channel = f"swpc-idle-{uuid.uuid4().hex[:8]}"
    rolling = tmp_path / "can.log"
    driver = SwpcDriver(
        CanConfig(channel=channel, log_path=str(rolling), log_total_bytes=1 << 20,
                  log_idle_period_s=1.0)
    )  # fmt: skip
    driver.configure()
    t0 = time.time()
    off = (AxisState.DISABLED, AxisState.DISABLED), (ControlMode.FREE, ControlMode.FREE)

    def burst(bus: can.BusABC, start: float, sent: int) -> int:
        """50 heartbeats of node 1, 10 ms apart from ``start`` (their own stamps)."""
        for k in range(50):
            hb = codec.make_heartbeat(1, *off, (0, 0), True, False, k)
            bus.send(frame(hb, t0 + start + k * 0.01))
        deadline = time.monotonic() + 30  # a guard: the driver's thread takes them in
        while driver.stats().rx_frames < sent + 50:
            assert time.monotonic() < deadline, driver.stats()
            time.sleep(0.005)
        return sent + 50

    with can.Bus(interface="virtual", channel=channel, preserve_timestamps=True) as bus:
        sent = burst(bus, 0.0, 0)  # idle: one kept
        driver.start_recording(str(tmp_path / "run.log"))
        sent = burst(bus, 0.5, sent)  # a run: every one
        assert driver.stop_recording() is None
        sent = burst(bus, 1.2, sent)  # idle again: one
    driver.shutdown()
    stamps = [round(m.timestamp - t0, 2) for m in can.LogReader(str(rolling))]
    assert stamps == [0.0] + [round(0.5 + k * 0.01, 2) for k in range(50)] + [1.2]
    assert sum(1 for _ in can.LogReader(str(tmp_path / "run.log"))) == 50


def test_a_can_log_that_cannot_write_stops_and_says_why(tmp_path: Path) -> None:
    rec = Recorder(str(tmp_path / "x.log"))
    rec.logger.file.close()  # type: ignore[attr-defined]  # the file is gone from under it
    rec.write(can.Message(arbitration_id=1, data=b"\x00"))
    assert rec.closed and rec.error is not None and "x.log" in rec.error


def test_the_rolling_log_paused_by_a_full_disk_resumes_when_there_is_room(
    tmp_path: Path,
) -> None:
    """Issue 40 row 13: after a full disk the rolling log stayed stopped ("degraded: CAN
    log stopped" at /health) until a restart.  A real ENOSPC (``/dev/full`` under the
    log's name), then room again (a regular file there): the log resumes ``retry_s``
    later on the driver's clock, counts what it lost, and says nothing is wrong."""
    from swpc_hw.clock import VirtualClock

    clock = VirtualClock()
    base = tmp_path / "can.log"
    base.symlink_to("/dev/full")
    rec = Recorder(str(base), total_bytes=1 << 20, retry_s=10.0, now=clock.now)
    frame = can.Message(arbitration_id=0x123, data=bytes(8))
    for _ in range(2000):  # a buffer's worth and more: the flush meets ENOSPC
        rec.write(frame)
        if rec.closed:
            break
    assert rec.closed and rec.error is not None and "No space left" in rec.error
    clock.advance(9.9)
    rec.write(frame)  # not yet: still paused, the frame lost
    assert rec.closed and rec.lost == 1
    base.unlink()  # room again
    clock.advance(0.1)
    rec.write(frame)
    assert not rec.closed and rec.error is None and rec.lost == 1
    rec.stop()
    assert [m.arbitration_id for m in can.LogReader(str(base))] == [0x123]
    rec.write(frame)  # stopped for good: no retry brings it back
    assert rec.closed and rec.lost == 1
