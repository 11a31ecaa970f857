"""ODrive drives on SocketCAN: ``kill -STOP`` of the service mid-spin, every axis stopped by
its own watchdog within the bound (the ``odrive`` step of ``make test-vcan``).

    odrive_deadman.py --url URL --token T --service-pid PID --channel vcan41 \\
        --time-scale S --deadman D --watchdog W --heartbeat T_HB --out OUT.json

Starts a calibration with a long first spin through ``swpc serve`` (HTTP), waits until the
robot turns under the service's control (SPIN), listens on the bus, then ``kill -STOP`` of
the service: a hang, no signal handler runs.  The kernel's broadcast manager keeps
refreshing each axis' setpoint until the dead-man ends the tasks (``D`` robot seconds,
``D / S`` of the kernel's host time, after the driver's last renewal), then every ODrive
axis' watchdog (``W``, robot time) disarms it and its next heartbeat (``T_HB``) reports
WATCHDOG_TIMER_EXPIRED.  Bound in host seconds from the stop: ``(D + W + T_HB) / S`` (the
simulator and the service's clock run ``S`` times real time).  Prints,
per axis, when the refresh to it ended and when its heartbeat reported the expiry; writes
``OUT``; exit 0 only if every axis reported it within the bound.  Then SIGCONT (the caller
stops the service).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import time
import urllib.request
from pathlib import Path
from typing import Any

import can

from firmware_protocol.odrive import can_simple as cs


def _request(url: str, token: str, body: Any = None) -> Any:
    data = None if body is None else json.dumps(body).encode()
    req = urllib.request.Request(url, data=data, method="GET" if body is None else "POST")
    req.add_header("Content-Type", "application/json")
    req.add_header("Authorization", f"Bearer {token}")
    with urllib.request.urlopen(req, timeout=60) as resp:
        return json.loads(resp.read().decode())


def main() -> int:
    p = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    p.add_argument("--url", required=True)
    p.add_argument("--token", required=True)
    p.add_argument("--service-pid", type=int, required=True)
    p.add_argument("--channel", required=True)
    p.add_argument("--firmware", default="0.5")
    p.add_argument("--nodes", default="0,1,2,3,4,5,6,7")
    p.add_argument("--time-scale", type=float, required=True)
    p.add_argument(
        "--deadman", type=float, required=True, help="D, robot s (the budget's; the kernel "
        "holds it D / S host seconds)"
    )
    p.add_argument("--watchdog", type=float, required=True, help="W, robot s")
    p.add_argument("--heartbeat", type=float, required=True, help="T_hb, robot s")
    p.add_argument("--spin-timeout", type=float, default=1500.0, help="host s to reach SPIN")
    p.add_argument("--out", required=True)
    a = p.parse_args()
    c = cs.can_simple(a.firmware)
    nodes = {int(n) for n in a.nodes.split(",")}
    bound = (a.deadman + a.watchdog + a.heartbeat) / a.time_scale
    # no fast part: the stop is what is tested (sim-calibration runs one), and its four
    # probes took 100 s of the emulated machine before the spin
    body = {"overrides": {"protocol": {"sweep_deg": 1440, "precheck": False}}, "install": "never"}
    run = _request(f"{a.url}/calibrations", a.token, body)
    rid = run["id"]
    t0 = time.monotonic()
    while True:
        st = _request(f"{a.url}/calibrations/{rid}", a.token)
        if st["state"] in ("FAILED", "ABORTED", "DONE"):
            print(f"run {rid} ended {st['state']} before the stop: {st.get('reason')}")
            return 1
        if st["state"] == "SPIN" and st["sweep_deg"] >= 20:
            break
        if time.monotonic() - t0 > a.spin_timeout:
            print(f"run {rid} never reached a steady spin ({st['state']})")
            return 1
        time.sleep(0.5)
    bus = can.Bus(interface="socketcan", channel=a.channel)
    try:
        while bus.recv(0) is not None:
            pass
        t_stop = time.time()
        os.kill(a.service_pid, signal.SIGSTOP)
        print(f"kill -STOP {a.service_pid} mid-spin (sweep {st['sweep_deg']:.0f} deg); bound "
              f"(D + W + T_hb) / S = ({a.deadman:g} + {a.watchdog:g} + {a.heartbeat:g}) / "
              f"{a.time_scale:g} = {bound:.2f} s", flush=True)  # fmt: skip
        last_host: dict[int, float] = {}
        expired: dict[int, float] = {}
        beats: dict[int, list[float]] = {n: [] for n in nodes}  # each axis' heartbeats
        estimates: dict[int, list[float]] = {n: [] for n in nodes}
        deadline = time.monotonic() + 3 * bound + 5
        while time.monotonic() < deadline and set(expired) != nodes:
            msg = bus.recv(0.2)
            if msg is None or msg.is_error_frame:
                continue
            node, cmd = cs.split_id(msg.arbitration_id)
            if node not in nodes:
                continue
            if cmd in c.host_cmds:
                last_host[node] = msg.timestamp - t_stop
                continue
            try:
                dec = c.decode(msg.arbitration_id, bytes(msg.data), msg.is_remote_frame)
            except cs.ProtocolError:
                continue
            if isinstance(dec, cs.Heartbeat):
                beats[node].append(msg.timestamp - t_stop)
                if dec.axis_error & c.watchdog_bit:
                    expired.setdefault(node, msg.timestamp - t_stop)
            elif isinstance(dec, cs.EncoderEstimates):
                estimates[node].append(msg.timestamp - t_stop)
    finally:
        bus.shutdown()
        os.kill(a.service_pid, signal.SIGCONT)
    ok = set(expired) == nodes and max(expired.values()) <= bound
    def between(ts: list[float], n: int) -> int:
        lo, hi = last_host.get(n, 0.0), expired.get(n, float("inf"))
        return sum(1 for t in ts if lo < t <= hi)

    for n in sorted(nodes):
        print(f"  node {n:2d}: refresh ended {last_host.get(n, float('nan')):6.2f} s, watchdog "
              f"reported {expired.get(n, float('nan')):6.2f} s after the stop; between them "
              f"{between(beats[n], n)} heartbeats, {between(estimates[n], n)} encoder "
              "estimates")  # fmt: skip
    worst = max(expired.values(), default=float("nan"))
    print(f"every axis stopped by its watchdog within {worst:.2f} s (bound {bound:.2f} s): "
          f"{'PASS' if ok else 'FAIL'}")  # fmt: skip
    Path(a.out).write_text(json.dumps({
        "bound_s": bound, "worst_s": worst, "expired_s": expired, "refresh_ended_s": last_host,
        "time_scale": a.time_scale, "deadman_s": a.deadman, "watchdog_s": a.watchdog,
        "heartbeat_s": a.heartbeat, "passed": ok,
    }, indent=1))  # fmt: skip
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
