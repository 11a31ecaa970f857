"""A python-can exchange of SWPC protocol frames between two buses (run inside the VM).

    python deploy/vm/can_exchange.py --interface socketcan --tx vcan0 --rx vcan0
    python deploy/vm/can_exchange.py --interface socketcan --tx can0 --rx can1
    python deploy/vm/can_exchange.py --interface virtual --tx t --rx t   # on any host

A "host" bus sends ``Sync`` frames and a "controller" bus answers each with a
``N<node>_FeedbackPosition`` whose angles encode the sync counter; both sides decode with
the DBC codec (``firmware_protocol.codec``).  The script checks every frame arrives once,
in order, with the right values, and prints the round-trip latency (median, max).  On
``socketcan`` the kernel's receive timestamps are checked to be increasing.

Exit status 0 when every check passes, 1 otherwise.
"""

from __future__ import annotations

import argparse
import itertools
import statistics
import sys
import time
from collections.abc import Sequence

import can

from firmware_protocol import codec

NODE = 1
STEER_STEP = 0.01  # rad per sync counter step
WHEEL_STEP = 0.25  # rad per sync counter step


def _recv(bus: can.BusABC, arbitration_id: int, timeout: float) -> can.Message:
    """The next frame with this id (others are an error: the bus is ours alone)."""
    msg = bus.recv(timeout)
    if msg is None:
        raise TimeoutError(f"no frame 0x{arbitration_id:03x} within {timeout} s")
    if msg.arbitration_id != arbitration_id:
        raise AssertionError(f"expected 0x{arbitration_id:03x}, got {msg}")
    return msg


def exchange(interface: str, tx: str, rx: str, count: int, timeout: float) -> list[float]:
    """Run ``count`` sync/feedback round trips; return the round-trip times (s)."""
    host = can.Bus(interface=interface, channel=tx, receive_own_messages=False)
    ctrl = can.Bus(interface=interface, channel=rx, receive_own_messages=False)
    sync_id = codec.frame_id(codec.BROADCAST_NODE, codec.Command.SYNC)
    fb_id = codec.frame_id(NODE, codec.Command.FEEDBACK_POSITION)
    host.set_filters([{"can_id": fb_id, "can_mask": 0x7FF}])
    ctrl.set_filters([{"can_id": sync_id, "can_mask": 0x7FF}])
    rtts: list[float] = []
    stamps: list[float] = []
    try:
        for k in range(count):
            counter = k % 256
            sync = codec.make_sync(counter)
            t0 = time.perf_counter()
            host.send(can.Message(arbitration_id=sync.arbitration_id, data=sync.data,
                                  is_extended_id=False))
            got = _recv(ctrl, sync_id, timeout)
            decoded = codec.parse(got.arbitration_id, bytes(got.data))
            assert isinstance(decoded, codec.Sync), decoded
            assert decoded.counter == counter, (decoded, counter)
            fb = codec.make_feedback_position(
                NODE, steer=STEER_STEP * counter, wheel=WHEEL_STEP * k, counter=counter
            )
            ctrl.send(can.Message(arbitration_id=fb.arbitration_id, data=fb.data,
                                  is_extended_id=False))
            back = _recv(host, fb_id, timeout)
            rtts.append(time.perf_counter() - t0)
            stamps.append(back.timestamp)
            pos = codec.parse(back.arbitration_id, bytes(back.data))
            assert isinstance(pos, codec.FeedbackPosition), pos
            assert pos.node == NODE and pos.counter == counter, pos
            assert abs(pos.steer - STEER_STEP * counter) <= 2e-4, (pos.steer, counter)
            assert abs(pos.wheel - WHEEL_STEP * k) <= 1e-4, (pos.wheel, k)
        extra = host.recv(0.05) or ctrl.recv(0.05)
        assert extra is None, f"unexpected extra frame {extra}"
    finally:
        host.shutdown()
        ctrl.shutdown()
    if interface == "socketcan":
        assert all(b > a for a, b in itertools.pairwise(stamps)), "timestamps"
    return rtts


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--interface", default="socketcan")
    ap.add_argument("--tx", default="vcan0", help="host-side channel")
    ap.add_argument("--rx", default="vcan0", help="controller-side channel")
    ap.add_argument("--count", type=int, default=200)
    ap.add_argument("--timeout", type=float, default=2.0)
    args = ap.parse_args(argv)
    try:
        rtts = exchange(args.interface, args.tx, args.rx, args.count, args.timeout)
    except (AssertionError, TimeoutError, can.CanError, OSError) as exc:
        print(f"can_exchange: FAIL on {args.interface} {args.tx}->{args.rx}: {exc!r}")
        return 1
    print(
        f"can_exchange: OK {args.interface} {args.tx}->{args.rx}: {len(rtts)} round trips, "
        f"rtt median {statistics.median(rtts) * 1e3:.2f} ms, max {max(rtts) * 1e3:.2f} ms"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
