"""The watchdog refresh on real SocketCAN: held ACTIVE on a busy computer, and a stopped
service stops the robot (issue 18, point 6).  Run by ``deploy/vm/in-vm.sh`` (step
``deadman``) inside the VM; needs root (real-time priority for the emulated controllers).

    python deploy/vm/deadman.py run --channel vcan40 --hold 60 --out OUT/deadman.json

``run`` starts three processes on ``--channel`` and two busy loops beside them:

* ``emulate``: four emulated controllers (:class:`ControllerEmulator`), at real-time
  priority (``chrt -f``): they stand for the controllers' firmware, not for the robot's
  computer, whose load the busy loops are;
* ``hold``: the service side, at normal priority: a :class:`CanDriver` with the service's
  own CAN settings at the robot's windows (:func:`services.timing.driver_config`: watchdog
  200 ms, refresh 20 ms, heartbeat loss 0.3 s, dead-man 0.5 s; on SocketCAN the refresh
  goes through the kernel's broadcast manager), activated, every axis enabled and held,
  for ``--hold`` seconds; it reports the fault events it saw;
* this process observes the bus (kernel receive stamps) throughout.

Then ``kill -STOP`` of the ``hold`` process.  Measured: the last refresh frame on the bus
after the stop (the dead-man: at most ``deadman`` after the last renewal) and the
controllers' watchdog fault of every axis (``FaultReport`` WATCHDOG_TIMEOUT), against the
bound ``deadman + watchdog``.  Passes with 0 fault frames and 0 driver faults while held,
and every axis faulted (free) within the bound (plus the emulator's own reaction time,
reported apart).  ``--contrast S`` adds a hold of S seconds with the refresh sent from
Python instead (``refresh_in_kernel=False``) and reports its faults (informative).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import can

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from firmware_protocol import codec  # noqa: E402
from firmware_protocol.codec import Axis, ErrorFlag  # noqa: E402

NODES = (1, 2, 3, 4)


# --------------------------------------------------------------------------- emulate


def emulate(args: argparse.Namespace) -> int:
    from simulators.virtual_controller import ControllerEmulator, VirtualController

    ctrls = [VirtualController(n) for n in NODES]
    with ControllerEmulator(ctrls, interface="socketcan", channel=args.channel):
        print("EMULATING", flush=True)
        signal.sigwait({signal.SIGTERM, signal.SIGINT})
    return 0


# --------------------------------------------------------------------------- hold


def hold(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from pydantic import SecretStr

    from services.robot_config import RobotConfig
    from services.settings import ServiceSettings
    from services.timing import driver_config, timing_budget
    from swpc_hw.can import CanDriver, Severity

    st = ServiceSettings(can_interface="socketcan", can_channel=args.channel, token=SecretStr("x"))
    cfg = RobotConfig()
    budget = timing_budget(st, cfg)
    can_cfg = driver_config(st, cfg, interface="socketcan", channel=args.channel)
    # the feedback stream is not what this step tests (0: off; the heartbeats remain)
    can_cfg = replace(can_cfg, feedback_rate_hz=args.feedback_rate)
    if args.host_refresh:
        can_cfg = replace(can_cfg, refresh_in_kernel=False)
    faults: list[str] = []
    drv = CanDriver(can_cfg)
    # diagnostics: how often supervision ran, and in which state
    calls = {"supervise": 0, "supervise_active": 0}
    supervise = drv._supervise

    def counted(now: float) -> float:
        calls["supervise"] += 1
        calls["supervise_active"] += drv.state.value == "active"
        return supervise(now)

    drv._supervise = counted  # type: ignore[method-assign]
    drv.add_event_callback(
        lambda ev: faults.append(ev.message) if ev.severity is Severity.FAULT else None
    )
    with drv:
        # as the service: configured at start-up, activated later (here once every node's
        # heartbeat is in: a process just started beside busy loops under emulation)
        deadline = time.monotonic() + 120
        while not all(drv.module_state(m).alive for m in drv.modules()):
            if time.monotonic() > deadline:
                raise RuntimeError("no heartbeat from every node within 120 s")
            time.sleep(0.1)
        drv.activate()
        for m in drv.modules():
            drv.clear_errors(m)
            for axis in Axis:
                drv.enable(m, axis)
                drv.hold(m, axis)
        t0 = time.monotonic()
        while time.monotonic() - t0 < args.seconds and drv.state.value == "active":
            time.sleep(0.1)
        st = drv.stats()
        report = {
            "seconds": round(time.monotonic() - t0, 2),
            "state": drv.state.value,
            "fault_cause": drv.fault_cause,
            "faults": faults,
            "events": [f"{e.t:.3f} {e.kind.value} {e.message}" for e in drv.events()][-30:],
            "last_exception": repr(drv.last_exception),
            "refresh_in_kernel": drv.refresh_in_kernel,
            "renewals": st.periodic_renewals,
            "calls": calls,
            "next_renewal_in_s": round(drv._next_renewal - drv.clock.now(), 3),
            "kernel_tasks": drv._kernel.nodes() if drv._kernel is not None else None,
            "rx_frames": st.rx_frames,
            "tx_frames": st.tx_frames,
            "budget": budget.as_dict(),
        }
        print("REPORT " + json.dumps(report), flush=True)
        # held until stopped (kill -STOP) or killed
        signal.sigwait({signal.SIGTERM, signal.SIGINT})
    return 0


# --------------------------------------------------------------------------- run


class Observer:
    """Every frame on the bus with its kernel receive stamp (epoch s), recorded by candump
    (C: a Python observer beside the driver takes the emulated CPUs the driver needs)."""

    def __init__(self, channel: str, path: Path) -> None:
        self.path = path
        self.proc = subprocess.Popen(
            ["candump", "-L", channel], stdout=path.open("w"), stderr=subprocess.DEVNULL
        )
        time.sleep(0.5)

    def since(self, t: float) -> list[tuple[float, int, Any]]:
        out = []
        for line in self.path.read_text().splitlines():
            try:  # (1700000000.123456) vcan40 022#000300000000
                ts_s, _, frame = line.split()
                ident, data = frame.split("#")
                ts = float(ts_s.strip("()"))
                i = int(ident, 16)
                if ts >= t:
                    out.append((ts, i, codec.parse(i, bytes.fromhex(data))))
            except (ValueError, codec.ProtocolError):
                continue
        return out

    def close(self) -> None:
        self.proc.terminate()
        self.proc.wait(5)


def watchdog_faults(frames: list[tuple[float, int, Any]]) -> dict[tuple[int, int], float]:
    """First WATCHDOG_TIMEOUT fault report per (node, axis)."""
    out: dict[tuple[int, int], float] = {}
    for ts, i, d in frames:
        if isinstance(d, codec.FaultReport) and d.new_errors & ErrorFlag.WATCHDOG_TIMEOUT:
            out.setdefault((codec.split_id(i)[0], int(d.axis)), ts)
    return out


def refresh_frames(frames: list[tuple[float, int, Any]]) -> list[float]:
    return [ts for ts, _, d in frames if isinstance(d, codec.SetControl)]


def spawn(cmd: list[str], rt: bool = False, stderr: Path | None = None) -> subprocess.Popen[str]:
    if rt:
        cmd = ["chrt", "-f", "50", *cmd]
    err = None if stderr is None else stderr.open("w")
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=err, text=True, cwd=ROOT)


def wait_line(p: subprocess.Popen[str], prefix: str, timeout: float) -> str:
    assert p.stdout is not None
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        line = p.stdout.readline()
        if not line:
            raise RuntimeError(f"process {p.args} ended before {prefix!r}")
        if line.startswith(prefix):
            return line[len(prefix) :].strip()
    raise RuntimeError(f"no {prefix!r} from {p.args} within {timeout} s")


def one_hold(
    args: argparse.Namespace, host_refresh: bool, seconds: float, busy: int, stop: bool
) -> dict[str, Any]:
    me = [sys.executable, __file__]
    cmd = [*me, "hold", "--channel", args.channel, "--seconds", str(seconds),
           "--feedback-rate", str(args.feedback_rate)]  # fmt: skip
    if host_refresh:
        cmd.append("--host-refresh")
    name = "host" if host_refresh else f"kernel-busy{busy}"
    log = Path(args.out or "/tmp/deadman.json").with_suffix(f".{name}.log")
    obs = Observer(args.channel, log.with_suffix(".candump"))
    loops = [subprocess.Popen(["sh", "-c", "while :; do :; done"]) for _ in range(busy)]
    holder = spawn(cmd, stderr=log)
    result: dict[str, Any] = {"host_refresh": host_refresh, "busy_loops": busy}
    try:
        t_start = time.time()
        report = json.loads(wait_line(holder, "REPORT ", seconds + 120))
        result["hold"] = report
        held = obs.since(t_start)
        result["fault_frames_while_held"] = len(watchdog_faults(held))
        refresh = refresh_frames(held)
        if refresh:  # refresh frames per second over the hold (the kernel's, or the host's)
            t0 = refresh[0]
            per_s = [0] * (int(refresh[-1] - t0) + 1)
            for ts in refresh:
                per_s[int(ts - t0)] += 1
            result["refresh_frames_per_s"] = per_s
        if not stop:
            return result
        # stop the service as a hang would: no signal handler, no stop frames
        t_stop = time.time()
        os.kill(holder.pid, signal.SIGSTOP)
        time.sleep(args.after_stop)
        after = obs.since(t_stop)
        faults = watchdog_faults(after)
        refresh = refresh_frames(after)
        b = report["budget"]
        bound = b["deadman"] + b["watchdog"]
        result.update(
            stop_bound_s=bound,
            axes_faulted=len(faults),
            last_refresh_after_stop_s=(max(refresh) - t_stop) if refresh else 0.0,
            last_fault_after_stop_s=(max(faults.values()) - t_stop) if faults else None,
        )
        os.kill(holder.pid, signal.SIGCONT)
    finally:
        for p in loops:
            p.kill()
        if holder.poll() is None:
            holder.send_signal(signal.SIGTERM)
            try:
                holder.wait(10)
            except subprocess.TimeoutExpired:
                holder.kill()
        obs.close()
    return result


def probe(channel: str) -> dict[str, Any]:
    """python-can's own periodic task on SocketCAN against a second socket: frames of a
    finite task (0.5 s at 20 ms: 25), of one renewed by ``start()`` every 0.25 s for 1.5 s,
    and after ``modify_data``."""
    msg = can.Message(arbitration_id=0x022, data=bytes(6), is_extended_id=False)
    out: dict[str, Any] = {}
    with can.Bus(interface="socketcan", channel=channel) as tx, can.Bus(
        interface="socketcan", channel=channel
    ) as rx:

        def count(seconds: float) -> int:
            n, end = 0, time.monotonic() + seconds
            while (left := end - time.monotonic()) > 0:
                m = rx.recv(left)
                n += m is not None and m.arbitration_id == 0x022
            return n

        task = tx.send_periodic(msg, 0.02, duration=0.5)
        out["finite_0.5s_in_1s"] = count(1.0)
        task.stop()
        task = tx.send_periodic(msg, 0.02, duration=0.5)
        n = 0
        for _ in range(6):
            task.start()  # type: ignore[attr-defined]
            n += count(0.25)
        out["renewed_1.5s"] = n
        task.modify_data(can.Message(arbitration_id=0x022, data=b"\x01" * 6,  # type: ignore[attr-defined]
                                     is_extended_id=False))
        out["after_modify_0.5s"] = count(0.5)
        task.stop()
        out["after_stop_0.3s"] = count(0.3)
    return out


def run(args: argparse.Namespace) -> int:
    me = [sys.executable, __file__]
    emu = spawn([*me, "emulate", "--channel", args.channel], rt=True)
    results: dict[str, Any] = {"channel": args.channel, "feedback_rate": args.feedback_rate}
    results["probe"] = probe(args.channel)
    print("PROBE", json.dumps(results["probe"]), flush=True)
    try:
        wait_line(emu, "EMULATING", 120)
        if args.idle > 0:  # the same without load: separates "refresh broken" from "starved"
            results["idle"] = one_hold(args, False, args.idle, busy=0, stop=False)
        results["kernel"] = one_hold(args, False, args.hold, busy=args.busy, stop=True)
        if args.contrast > 0:
            results["host"] = one_hold(args, True, args.contrast, busy=args.busy, stop=False)
    finally:
        emu.send_signal(signal.SIGTERM)
        try:
            emu.wait(10)
        except subprocess.TimeoutExpired:
            emu.kill()
    k = results["kernel"]
    idle = results.get("idle")
    idle_ok = idle is None or (
        idle["hold"]["state"] == "active" and idle["fault_frames_while_held"] == 0
    )
    ok = idle_ok and (
        k["hold"]["refresh_in_kernel"]
        and k["hold"]["state"] == "active"
        and not k["hold"]["faults"]
        and k["fault_frames_while_held"] == 0
        and k["axes_faulted"] == 2 * len(NODES)
        and k["last_refresh_after_stop_s"] <= k["stop_bound_s"] - k["hold"]["budget"]["watchdog"]
        and k["last_fault_after_stop_s"] is not None
        and k["last_fault_after_stop_s"] <= k["stop_bound_s"] + args.reaction
    )
    results["pass"] = bool(ok)
    text = json.dumps(results, indent=2)
    print(text)
    if args.out:
        Path(args.out).write_text(text + "\n", encoding="utf-8")
    return 0 if ok else 1


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    sub = p.add_subparsers(dest="cmd", required=True)
    e = sub.add_parser("emulate")
    e.add_argument("--channel", required=True)
    h = sub.add_parser("hold")
    h.add_argument("--channel", required=True)
    h.add_argument("--seconds", type=float, default=60.0)
    h.add_argument("--feedback-rate", type=int, default=0)
    h.add_argument("--host-refresh", action="store_true")
    r = sub.add_parser("run")
    r.add_argument("--channel", required=True)
    r.add_argument("--hold", type=float, default=60.0, help="s held ACTIVE (kernel refresh)")
    r.add_argument("--contrast", type=float, default=0.0, help="s held with host refresh")
    r.add_argument("--busy", type=int, default=2, help="busy loops beside")
    r.add_argument(
        "--feedback-rate", type=int, default=0,
        help="Hz asked of the controllers (0: heartbeats only; Python under emulation runs "
        "~15x slower than on a robot's computer)",
    )
    r.add_argument("--idle", type=float, default=10.0, help="s held first without busy loops")
    r.add_argument("--after-stop", type=float, default=3.0, help="s observed after the stop")
    r.add_argument(
        "--reaction", type=float, default=0.5,
        help="s allowed for the emulated controllers to report a fault they have hit",
    )
    r.add_argument("--out")
    args = p.parse_args()
    return {"emulate": emulate, "hold": hold, "run": run}[args.cmd](args)


if __name__ == "__main__":
    sys.exit(main())
