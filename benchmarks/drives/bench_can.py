"""CAN driver benchmark on python-can's virtual bus (emulated controllers in-process).

1. 4 nodes stream both feedback frames at 500 Hz for 30 s (4000 frames/s): frames lost,
   driver CPU (receive + supervisor threads) as a share of one core, p99 receive latency.
2. Sweep of the total feedback frame rate (more nodes / higher emulated rates, driver
   listening): the highest rate with 0 loss, as a ratio to the 1 Mbit/s worst-case limit
   (1e6 / 135 bits = 7407 frames/s).
3. Fault -> last FREE/DISABLE frame on the bus, p99 over 100 trials each for
   ``stop_all()`` and for heartbeat loss.

``python -m benchmarks can`` (``make bench``).  ``SWPC_BENCH_CAN_SECONDS`` shortens the
30 s stream.
"""

from __future__ import annotations

import logging
import os
import threading
import time
import uuid

import can
import numpy as np

from firmware_protocol import busload, codec
from firmware_protocol.codec import Axis, Command, ControlMode
from simulators.drives.swpc import ControllerEmulator, VirtualController
from swpc_hw.drives.bus import CanConfig
from swpc_hw.drives.swpc.driver import SwpcDriver
from swpc_hw.drives.types import Lifecycle

FRAME_LIMIT = 1e6 / busload.frame_bits(8)


class _Observer(can.Listener):
    def __init__(self, channel: str) -> None:
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.frames: list[can.Message] = []
        self.lock = threading.Lock()
        self.notifier = can.Notifier(self.bus, [self], timeout=0.05)

    def on_message_received(self, msg: can.Message) -> None:
        with self.lock:
            self.frames.append(msg)

    def take(self) -> list[can.Message]:
        with self.lock:
            out, self.frames = self.frames, []
        return out

    def close(self) -> None:
        self.notifier.stop()
        self.bus.shutdown()


def _cpu(threads: list[threading.Thread]) -> float:
    total = 0.0
    for t in threads:
        if t.ident is not None and t.is_alive():
            total += time.clock_gettime(time.pthread_getcpuclockid(t.ident))
    return total


def _channel() -> str:
    return f"bench-{uuid.uuid4().hex[:8]}"


def _is_stop(msg: can.Message) -> bool:
    _node, cmd = codec.split_id(msg.arbitration_id)
    if cmd == Command.SET_CONTROL:
        d = codec.parse(msg.arbitration_id, bytes(msg.data))
        return isinstance(d, codec.SetControl) and d.mode == ControlMode.FREE
    if cmd == Command.SET_AXIS_STATE:
        d = codec.parse(msg.arbitration_id, bytes(msg.data))
        return isinstance(d, codec.SetAxisState) and not d.enabled
    return False


def stream(seconds: float) -> None:
    ch = _channel()
    nodes = (1, 2, 3, 4)
    emu = ControllerEmulator([VirtualController(n) for n in nodes], channel=ch)
    emu.record_received = False
    cfg = CanConfig(channel=ch, feedback_rate_hz=500, history_len=500 * int(seconds + 10))
    drv = SwpcDriver(cfg)
    drv.configure()
    emu.start()
    drv.activate()
    time.sleep(0.3)
    fb_ids = {
        codec.frame_id(n, c)
        for n in nodes
        for c in (Command.FEEDBACK_POSITION, Command.FEEDBACK_VELOCITY_TORQUE)
    }
    threads = drv.threads()
    sent0 = sum(emu.sent[i] for i in fb_ids)
    recv0 = sum(drv.module_state(m).feedback_frames for m in nodes)
    drv.clear_latencies()
    c0, w0 = _cpu(threads), time.monotonic()
    time.sleep(seconds)
    c1, w1 = _cpu(threads), time.monotonic()
    for node in (1, 2, 3, 4):
        emu.mute(node)
    time.sleep(0.2)  # let the driver drain its queue
    sent = sum(emu.sent[i] for i in fb_ids) - sent0
    recv = sum(drv.module_state(m).feedback_frames for m in nodes) - recv0
    lat = drv.latencies()
    st = drv.stats()
    drv.shutdown()
    emu.stop()
    print(
        f"stream: 4 nodes x 2 feedback frames x 500 Hz for {w1 - w0:.1f} s: "
        f"sent {sent} ({sent / (w1 - w0):.0f} frames/s), received {recv}, "
        f"lost {sent - recv} (counter gaps {st.feedback_gaps}, unpaired {st.unpaired_feedback})"
    )
    print(
        f"stream: driver CPU {100 * (c1 - c0) / (w1 - w0):.1f} % of one core "
        f"(receive + supervisor threads, {len(threads)} threads); receive latency "
        f"p50 {1e3 * np.percentile(lat, 50):.3f} ms, p99 {1e3 * np.percentile(lat, 99):.3f} ms, "
        f"max {1e3 * lat.max():.2f} ms"
    )


def sweep(seconds: float) -> None:
    """Driver listening (inactive) while N emulated nodes stream at rate f (set directly)."""
    best = 0.0
    for n_nodes, rate in ((4, 500), (8, 463), (8, 750), (8, 1000), (8, 1250)):
        ch = _channel()
        nodes = tuple(range(1, n_nodes + 1))
        ctrls = [VirtualController(n, rate_hz=rate) for n in nodes]
        emu = ControllerEmulator(ctrls, channel=ch)
        emu.record_received = False
        drv = SwpcDriver(CanConfig(channel=ch, modules={n: n for n in nodes}, history_len=10_000))
        drv.configure()
        emu.start()
        time.sleep(seconds)
        for n in nodes:
            emu.mute(n)
        time.sleep(0.3)
        fb_ids = {
            codec.frame_id(n, c)
            for n in nodes
            for c in (Command.FEEDBACK_POSITION, Command.FEEDBACK_VELOCITY_TORQUE)
        }
        sent = sum(emu.sent[i] for i in fb_ids)
        recv = sum(drv.module_state(m).feedback_frames for m in nodes)
        lat = drv.latencies()
        drv.shutdown()
        emu.stop()
        achieved = sent / seconds
        p99 = 1e3 * float(np.percentile(lat, 99))
        ok = sent == recv and p99 < 50.0
        if ok:
            best = max(best, achieved)
        print(
            f"sweep: {n_nodes} nodes x 2 x {rate} Hz = {2 * n_nodes * rate} frames/s target, "
            f"{achieved:.0f} achieved ({achieved / FRAME_LIMIT:.2f} of {FRAME_LIMIT:.0f}); "
            f"lost {sent - recv}; p99 latency {p99:.2f} ms -> {'ok' if ok else 'NOT sustained'}"
        )
    print(
        f"sweep: highest sustained rate with 0 loss {best:.0f} frames/s = "
        f"{best / FRAME_LIMIT:.2f} x the 1 Mbit/s worst-case limit ({FRAME_LIMIT:.0f} frames/s)"
    )


def fault_latency(trials: int) -> None:
    ch = _channel()
    nodes = (1, 2, 3, 4)
    hb = 0.01  # shortened heartbeat period so that 100 loss trials fit the time budget
    ctrls = [VirtualController(n, heartbeat_period=hb) for n in nodes]
    emu = ControllerEmulator(ctrls, channel=ch)
    emu.record_received = False
    obs = _Observer(ch)
    drv = SwpcDriver(CanConfig(channel=ch, heartbeat_period_s=hb, refresh_period_s=0.02))
    drv.configure()
    emu.start()
    stop_lat: list[float] = []
    hb_lat: list[float] = []
    for _ in range(trials):
        drv.activate()
        for m in nodes:
            drv.enable(m, Axis.WHEEL)
        time.sleep(0.005)
        obs.take()
        t0 = time.time()
        drv.stop_all()
        time.sleep(0.01)
        stops = [m for m in obs.take() if _is_stop(m)][-16:]  # earlier ones: refreshes
        stop_lat.append(max(m.timestamp for m in stops) - t0)
        drv.deactivate()
    hb_id = codec.frame_id(2, Command.HEARTBEAT)
    for _ in range(trials):
        obs.take()
        drv.activate()
        for m in nodes:
            drv.enable(m, Axis.WHEEL)
        time.sleep(0.02)
        emu.mute(2)
        while drv.state == Lifecycle.ACTIVE:
            time.sleep(0.002)
        time.sleep(0.01)
        frames = obs.take()
        last_hb = max(m.timestamp for m in frames if m.arbitration_id == hb_id)
        stops = [m for m in frames if _is_stop(m)][-16:]
        deadline = last_hb + drv.config.heartbeat_loss_periods * hb
        hb_lat.append(max(m.timestamp for m in stops) - deadline)
        emu.mute(2, False)
        drv.wait_for(2, lambda s: s.alive, 1.0)
    drv.shutdown()
    emu.stop()
    obs.close()
    for name, vals in (("stop_all() call", stop_lat), ("heartbeat loss deadline", hb_lat)):
        a = 1e3 * np.array(vals)
        print(
            f"fault: {name} -> last of 16 FREE/DISABLE frames on the bus, {len(a)} trials: "
            f"p50 {np.percentile(a, 50):.2f} ms, p99 {np.percentile(a, 99):.2f} ms, "
            f"max {a.max():.2f} ms (goal p99 <= 20 ms)"
        )


def main() -> None:
    logging.getLogger("swpc_hw.drives").setLevel(logging.ERROR)  # expected losses at the end
    seconds = float(os.environ.get("SWPC_BENCH_CAN_SECONDS", "30"))
    stream(seconds)
    sweep(min(2.5, seconds))
    fault_latency(100)


if __name__ == "__main__":
    main()
