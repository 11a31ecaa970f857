"""The CiA 402 drives' own dead-man on a real kernel: ``kill -STOP`` of the service.

Runs inside the QEMU VM (``make test-vcan``, step ``cia402``) while ``swpc sim --drives
cia402`` and ``swpc serve`` (robot config ``drives: cia402``) share a SocketCAN interface
and a calibration is spinning::

    cia402_deadman.py --channel vcan50 --pid SERVICE_PID --nodes 1-8 --host-node 127 \\
        --bound SECONDS --out result.json

1. waits until every drive's TPDO 1 reports OPERATION ENABLED (the service drives them);
2. ``kill -STOP`` of the service: its Python stops, the kernel's broadcast manager keeps
   sending its heartbeat (0x700 + host node) until the dead-man ``D`` runs out;
3. every drive's heartbeat consumer must then fault it (EMCY 0x8130, the power stage off)
   within ``D + W``, checked in two parts, each on the clock it is defined on:

   * the kernel's heartbeat ends within ``--deadman`` (``D``, host seconds) of the STOP
     (kernel time stamps of the frames);
   * each drive faults within ``--consumer`` (``W``, the drive's own time) of the last
     heartbeat it got, to one heartbeat period (``--drive-period``, 0x1017).  The drive's
     time is the simulator's robot time, which runs at most ``--time-scale`` (``S``) robot
     seconds per host second (a stalled simulator slows its clock, never speeds it up),
     so ``S x`` (the EMCY's kernel time stamp - the host's last heartbeat's) bounds the
     drive's time from above.  Counting the drive's own heartbeats in that window (printed
     too) is not a bound: a simulator that lags the host sends the heartbeats of the
     drive's time before it handled the host's last one after it on the wire (1.6-1.7 s
     counted where the wall clock gave 1.52 s, 2026-11-29);
4. ``kill -CONT`` (the caller then stops the service).

Prints, per drive, the EMCY's delay after the STOP (wall time) and after the host's last
heartbeat (the drive's time); exit status 0 only if every drive faulted within the bound.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import struct
import sys
import time
from pathlib import Path

import can

HEARTBEAT = 0x700
EMCY = 0x080
TPDO1 = 0x180


def nodes_arg(text: str) -> list[int]:
    lo, _, hi = text.partition("-")
    return list(range(int(lo), int(hi or lo) + 1))


def alive(pid: int | None) -> bool:
    if pid is None:
        return True
    try:
        os.kill(pid, 0)
    except OSError:
        return False
    return True


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--channel", required=True)
    ap.add_argument("--pid", type=int, required=True)
    ap.add_argument("--nodes", type=nodes_arg, default=nodes_arg("1-8"))
    ap.add_argument("--host-node", type=int, default=127)
    ap.add_argument("--deadman", type=float, required=True, help="D, host s")
    ap.add_argument("--consumer", type=float, required=True, help="W, the drives' s")
    ap.add_argument("--drive-period", type=float, default=0.1, help="0x1017 of the drives, s")
    ap.add_argument("--time-scale", type=float, default=1.0, help="S, robot s per host s")
    ap.add_argument("--enabled-timeout", type=float, default=900.0)
    ap.add_argument("--run-pid", type=int, help="the client of the run: give up once it ends")
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    bus = can.Bus(interface="socketcan", channel=args.channel)
    sock = getattr(bus, "socket", None)
    if isinstance(sock, socket.socket):  # a slow reader must not lose frames
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 22)
    nodes = set(args.nodes)
    host_hb = HEARTBEAT + args.host_node
    last_hb = 0.0
    enabled: set[int] = set()
    t0 = time.monotonic()
    while enabled != nodes:
        if time.monotonic() - t0 > args.enabled_timeout or not alive(args.run_pid):
            print(f"drives never all OPERATION ENABLED: {sorted(enabled)} of {sorted(nodes)}"
                  f"{'' if alive(args.run_pid) else ' (the run ended)'}")  # fmt: skip
            return 1
        msg = bus.recv(1.0)
        if msg is not None and msg.arbitration_id == host_hb:
            last_hb = max(last_hb, msg.timestamp)
        if msg is None or msg.arbitration_id - TPDO1 not in nodes or len(msg.data) < 2:
            continue
        (sw,) = struct.unpack_from("<H", msg.data)
        node = msg.arbitration_id - TPDO1
        if sw & 0x6F == 0x27:
            enabled.add(node)
        else:
            enabled.discard(node)
    t_stop = time.time()
    os.kill(args.pid, signal.SIGSTOP)
    print(f"every drive OPERATION ENABLED; kill -STOP {args.pid}", flush=True)
    emcy: dict[int, float] = {}
    beats: dict[int, list[float]] = {n: [] for n in nodes}  # each drive's heartbeats
    beats_after = 0
    try:
        deadline = time.monotonic() + 20 * (args.deadman + args.consumer) + 60.0
        while set(emcy) != nodes and time.monotonic() < deadline:
            msg = bus.recv(0.5)
            if msg is None:
                continue
            if msg.arbitration_id == host_hb:
                last_hb = max(last_hb, msg.timestamp)
                beats_after += msg.timestamp > t_stop
            elif msg.arbitration_id - EMCY in nodes and msg.data[:2] == b"\x30\x81":
                emcy.setdefault(msg.arbitration_id - EMCY, msg.timestamp)
            elif msg.arbitration_id - HEARTBEAT in nodes:
                beats[msg.arbitration_id - HEARTBEAT].append(msg.timestamp)
    finally:
        os.kill(args.pid, signal.SIGCONT)
        bus.shutdown()
    rows = {
        n: {
            "after_stop_wall_s": emcy[n] - t_stop,
            "after_last_heartbeat_wall_s": emcy[n] - last_hb,
            # the drive's own time, bounded from above (module docstring)
            "after_last_heartbeat_drive_s": args.time_scale * (emcy[n] - last_hb),
            # its heartbeats from the host's last one to its EMCY (not a bound)
            "after_last_heartbeat_beats_s": args.drive_period
            * sum(1 for t in beats[n] if last_hb < t <= emcy[n]),
        }
        for n in sorted(emcy)
    }
    print(f"the host's heartbeat (0x{host_hb:03X}): {beats_after} frames after the STOP, the "
          f"last {last_hb - t_stop:+.3f} s from it (the kernel's, until the dead-man)")  # fmt: skip
    for n, r in rows.items():
        print(f"  node {n}: EMCY 0x8130 {r['after_stop_wall_s']:.3f} s after the STOP (wall), "
              f"at most {r['after_last_heartbeat_drive_s']:.3f} s of the drive's time after "
              f"the host's last heartbeat ({r['after_last_heartbeat_wall_s']:.3f} s wall, "
              f"{r['after_last_heartbeat_beats_s']:.1f} s of its heartbeats)")  # fmt: skip
    kernel = last_hb - t_stop
    worst = max((r["after_last_heartbeat_drive_s"] for r in rows.values()), default=float("inf"))
    missing = sorted(nodes - set(emcy))
    ok_kernel = kernel <= args.deadman
    ok_drives = not missing and worst <= args.consumer + args.drive_period + 1e-9
    ok = ok_kernel and ok_drives
    print(f"the kernel's heartbeat ended {kernel:.3f} s after the STOP (D = {args.deadman:g} s): "
          f"{'PASS' if ok_kernel else 'FAIL'}; every drive faulted (missing {missing}) at most "
          f"{worst:.3f} s of its own time after the last heartbeat (W = {args.consumer:g} s, "
          f"to one heartbeat period): {'PASS' if ok_drives else 'FAIL'}")  # fmt: skip
    Path(args.out).write_text(json.dumps(
        {"nodes": rows, "missing": missing, "worst_drive_s": worst, "deadman_s": args.deadman,
         "consumer_s": args.consumer,
         "last_host_heartbeat_after_stop_s": last_hb - t_stop if last_hb else None,
         "host_heartbeats_after_stop": beats_after},
        indent=1,
    ))  # fmt: skip
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
