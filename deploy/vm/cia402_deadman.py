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
   within ``--bound`` s of the STOP: ``D`` plus the consumer time ``W`` (scaled to wall
   time by the caller) plus the emulation's slack;
4. ``kill -CONT`` (the caller then stops the service).

Prints, per drive, the EMCY's delay after the STOP and after the host's last heartbeat on
the bus (kernel time stamps); exit status 0 only if every drive faulted within the bound.
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
    ap.add_argument("--bound", type=float, required=True, help="s of wall time")
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
    beats_after = 0
    try:
        deadline = time.monotonic() + 4 * args.bound + 10.0
        while set(emcy) != nodes and time.monotonic() < deadline:
            msg = bus.recv(0.5)
            if msg is None:
                continue
            if msg.arbitration_id == host_hb:
                last_hb = max(last_hb, msg.timestamp)
                beats_after += msg.timestamp > t_stop
            elif msg.arbitration_id - EMCY in nodes and msg.data[:2] == b"\x30\x81":
                emcy.setdefault(msg.arbitration_id - EMCY, msg.timestamp)
    finally:
        os.kill(args.pid, signal.SIGCONT)
        bus.shutdown()
    rows = {
        n: {"after_stop_s": emcy[n] - t_stop, "after_last_heartbeat_s": emcy[n] - last_hb}
        for n in sorted(emcy)
    }
    print(f"the host's heartbeat (0x{host_hb:03X}): {beats_after} frames after the STOP, the "
          f"last {last_hb - t_stop:+.3f} s from it (the kernel's, until the dead-man)")  # fmt: skip
    for n, r in rows.items():
        print(f"  node {n}: EMCY 0x8130 {r['after_stop_s']:.3f} s after the STOP, "
              f"{r['after_last_heartbeat_s']:.3f} s after the host's last heartbeat")  # fmt: skip
    worst = max((r["after_stop_s"] for r in rows.values()), default=float("inf"))
    ok = set(emcy) == nodes and worst <= args.bound
    missing = sorted(nodes - set(emcy))
    verdict = "PASS" if ok else "FAIL"
    print(f"every drive stopped: {set(emcy) == nodes} (missing {missing}); slowest "
          f"{worst:.3f} s after the STOP, bound {args.bound:.3f} s: {verdict}")  # fmt: skip
    Path(args.out).write_text(json.dumps(
        {"nodes": rows, "missing": missing, "worst_s": worst, "bound_s": args.bound,
         "last_host_heartbeat_after_stop_s": last_hb - t_stop if last_hb else None,
         "host_heartbeats_after_stop": beats_after},
        indent=1,
    ))  # fmt: skip
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
