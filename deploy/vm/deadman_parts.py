"""What the dead-man step (deploy/vm/deadman.py) reads and starts: its threads' and
ksoftirqd's scheduler figures, the bus as candump records it (decoded only for the
commands asked), the frames a hold is judged on, and the processes it spawns.  Beside
deadman.py (run as a script, its folder on sys.path), so that neither file passes the
house's 600 lines."""

from __future__ import annotations

import itertools
import os
import signal
import subprocess
import time
from pathlib import Path
from typing import Any

from firmware_protocol import codec
from firmware_protocol.codec import Command, ErrorFlag

ROOT = Path(__file__).resolve().parents[2]


def schedstat(tid: int | None) -> tuple[float, float]:
    """CPU time and run-queue wait (s) of thread ``tid`` of this process."""
    if tid is None:
        return (0.0, 0.0)
    cpu, wait, _ = Path(f"/proc/self/task/{tid}/schedstat").read_text().split()
    return (int(cpu) / 1e9, int(wait) / 1e9)


def gaps(times: list[float]) -> dict[str, float | int]:
    """Intervals between successive instants: count, median, 99th percentile, max (s)."""
    d = sorted(b - a for a, b in itertools.pairwise(times))
    if not d:
        return {"n": 0}
    p99 = d[min(len(d) - 1, int(0.99 * len(d)))]
    return {"n": len(d), "p50": round(d[len(d) // 2], 3), "p99": round(p99, 3),
            "max": round(d[-1], 3)}  # fmt: skip


class Observer:
    """Every frame on the bus with its kernel receive stamp (epoch s), recorded by candump
    (C: a Python observer beside the driver takes the emulated CPUs the driver needs)."""

    def __init__(self, channel: str, path: Path) -> None:
        self.path = path
        # a bus analyser: at real-time priority, with a 4 MiB receive buffer, reporting the
        # frames its socket dropped (-d); line-buffered: a frame is in the file once
        # received, not 4 KiB later
        cmd = ["chrt", "-f", "40", "stdbuf", "-oL", "candump", "-L", "-d", "-r", str(4 << 20)]
        self.proc = subprocess.Popen(
            [*cmd, channel],
            stdout=path.open("w"),
            stderr=subprocess.DEVNULL,
        )
        time.sleep(0.5)

    def drops(self) -> int:
        """Frames the recording lost (candump -d: "DROPCOUNT: dropped N CAN frames ...")."""
        n = 0
        for line in self.path.read_text().splitlines():
            if line.startswith("DROPCOUNT"):
                n += int(line.split()[2])
        return n

    def frames(self, commands: set[Command]) -> list[tuple[float, int, Any]]:
        """The recorded frames of these commands, decoded (the others are not parsed:
        Python under emulation takes seconds for every frame of a minute's recording)."""
        out = []
        for line in self.path.read_text().splitlines():
            try:  # (1700000000.123456) vcan40 022#000300000000
                ts_s, _, frame = line.split()
                ident, data = frame.split("#")
                i = int(ident, 16)
                if i & 0x1F not in commands:
                    continue
                out.append((float(ts_s.strip("()")), i, codec.parse(i, bytes.fromhex(data))))
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


def fault_frames(frames: list[tuple[float, int, Any]]) -> int:
    return sum(isinstance(d, codec.FaultReport) for _, _, d in frames)


def refresh_frames(frames: list[tuple[float, int, Any]]) -> list[float]:
    return [ts for ts, _, d in frames if isinstance(d, codec.SetControl)]


def per_second(stamps: list[float]) -> list[int]:
    """Frames in each second from the first one (the last second partial)."""
    if not stamps:
        return []
    out = [0] * (int(stamps[-1] - stamps[0]) + 1)
    for ts in stamps:
        out[int(ts - stamps[0])] += 1
    return out


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
            raise RuntimeError(f"process {p.args!r} ended before {prefix!r}")
        if line.startswith(prefix):
            return line[len(prefix) :].strip()
    raise RuntimeError(f"no {prefix!r} from {p.args!r} within {timeout} s")


def stop_process(p: subprocess.Popen[Any]) -> None:
    if p.poll() is None:
        p.send_signal(signal.SIGTERM)
        try:
            p.wait(30)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


def softirq_threads() -> list[int]:
    """PIDs of the kernel's softirq threads (ksoftirqd/N)."""
    out = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                if (d / "comm").read_text().startswith("ksoftirqd/"):
                    out.append(int(d.name))
            except OSError:
                continue
    return out


def softirq_schedstat() -> tuple[float, float]:
    """CPU time and run-queue wait (s) of every ksoftirqd thread, summed."""
    cpu = wait = 0
    for pid in softirq_threads():
        c, w, _ = Path(f"/proc/{pid}/schedstat").read_text().split()
        cpu, wait = cpu + int(c), wait + int(w)
    return (cpu / 1e9, wait / 1e9)


def set_softirq_priority(rt: bool) -> list[str]:
    """ksoftirqd/N at SCHED_FIFO 60 (``rt``) or back to SCHED_OTHER.

    The broadcast manager's timer is a soft hrtimer: its callback runs in the timer softirq,
    on a real computer as an interrupt returns.  Under QEMU's emulation softirq work that
    overruns the kernel's budget is handed to ksoftirqd, an ordinary thread, which the busy
    loops delay.  Once the refresh of every node stopped for 0.22-0.26 s while the
    real-time emulator ran on, and the watchdog tripped; without this ksoftirqd waited
    3.5 s for a CPU over a hold.  A precaution (the evidence is thin: see
    docs/history/2026-11-25-deadman-vm.md): at real-time priority ksoftirqd runs that work
    ahead of every task, as the hardware would.
    """
    done = []
    for pid in softirq_threads():
        if rt:
            os.sched_setscheduler(pid, os.SCHED_FIFO, os.sched_param(60))
        else:
            os.sched_setscheduler(pid, os.SCHED_OTHER, os.sched_param(0))
        done.append(Path(f"/proc/{pid}/comm").read_text().strip())
    return done
