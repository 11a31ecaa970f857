"""Measure how fast Python runs here, and pick the VM's time factor and time scale from it.

Standard library only (it runs inside the QEMU VM, started by ``deploy/vm/in-vm.sh``)::

    speed.py [--repeat 8] [--procs CPUS] [--ref-loop 0.5] [--factor 8] [--time-scale 0.3]

prints one shell line, e.g.
``LOOP_S=0.712 SLOWNESS=1.43 TIME_FACTOR=11.4 SIM_TIME_SCALE=0.2 DEADMAN_S=2.9``.

Why: under QEMU's software emulation (TCG) Python runs 12-25x slower than on the host,
and the host's own speed varies about 2x over a day (other tenants).  The driver suite
(``SWPC_TEST_TIME_FACTOR``) and the simulator (``--time-scale``) have real-time windows:
a controller watchdog, heartbeat supervision, a feedback rate.  Fixed values that pass
at one speed starve at half of it (2026-11-23: feedback counts 64-75 of 80-120, a
watchdog expiring mid-spin).  Keeping the CPU load constant instead: the work per
second of wall time is proportional to ``1 / TIME_FACTOR`` and to ``SIM_TIME_SCALE``,
and the CPU time of that work to the loop time ``LOOP_S``; so

    slowness        s = LOOP_S / REF_LOOP_S
    TIME_FACTOR     F = F_ref * s
    SIM_TIME_SCALE  k = k_ref / s

    DEADMAN_S       D = D_ref * s

where ``REF_LOOP_S`` is a loop time measured in VMs in which ``F_ref`` and ``k_ref``
passed.  ``D`` is the dead-man of the kernel's watchdog refresh for the ``deadman`` step
(``deploy/vm/deadman.py``): the driver renews it every ``D / 2`` from its Python I/O
thread, which beside two busy loops in the VM renewed it up to 0.5-1.1 s late (the same
work takes that thread 1 % of a CPU on the host, 25-45 % in the VM, where it also waits
for a CPU as long as it runs), where the robot's ``D`` of 0.5 s allows 0.25 s.  Both are
clamped: F to [F_MIN, F_MAX], k to [K_MIN, K_MAX], and never beyond the reference values
on a faster host.  The loop time is only a proxy of the load the simulator and the service
put on the emulated CPUs: on a host whose loop ran 1.3x faster than the reference, k = 0.4
put the simulator at 1.4-2.2 of the 2 emulated CPUs (against 1.3 at k = 0.3) and the spins
slowed down 3x, so a faster host keeps the reference values.
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import statistics
import sys
import time
from typing import Any

REF_LOOP_S = 0.5
"""Loop time (s) of :func:`loop_seconds` in the VM on a full-speed host, conservatively
(2026-11-23: one loop 0.34-0.55 s; one loop per CPU with a busy loop on one host core
0.58-0.80 s, and at k = 0.3 that run saturated the simulator and lost a watchdog)."""
F_REF, K_REF = 8.0, 0.3
"""The time factor and time scale that passed with margin at ``REF_LOOP_S``."""
F_MIN, F_MAX = F_REF, 24.0
K_MIN, K_MAX = 0.1, K_REF
D_REF = 2.0
"""The dead-man (s) at the reference speed.  Its renewal, due every ``D / 2``, came up to
0.12-0.58 s late at s ~ 2-3.3 and once 1.07 s late at s = 1.9 (2026-11-25): ``D / 2`` of
``D_REF * s`` leaves about twice that."""
D_MIN, D_MAX = 0.5, 8.0
"""Never below the robot's own dead-man (services.config.timing.DEADMAN_S)."""


def loop_seconds(n: int = 300_000) -> float:
    """Wall time of a pure-Python loop of ``n`` integer operations (interpreter speed)."""
    t0 = time.perf_counter()
    x = 0
    for i in range(n):
        x += i * i % 7
    return time.perf_counter() - t0


def _worker(n: int, repeat: int, barrier: Any, out: Any) -> None:
    barrier.wait()
    out.put(statistics.fmean(loop_seconds(n) for _ in range(repeat)))


def loaded_loop_seconds(procs: int, repeat: int = 8, n: int = 300_000) -> float:
    """The slowest of ``procs`` processes timing :func:`loop_seconds` at the same time
    (the mean of ``repeat`` loops each: a median of 5 dropped the loops a host tenant
    preempted, and read 0.58 s where the probes around it read 0.70-0.76 s).  One process
    per CPU: a host whose other tenants take a core slows one of the VM's two CPU
    threads, which a single loop on the idle second emulated CPU would not see
    (2026-11-23: 0.38 s with a busy loop on the host, as fast as without)."""
    ctx = multiprocessing.get_context("fork")
    barrier, out = ctx.Barrier(procs), ctx.Queue()
    workers = [ctx.Process(target=_worker, args=(n, repeat, barrier, out)) for _ in range(procs)]
    for w in workers:
        w.start()
    times: list[float] = [float(out.get(timeout=600)) for _ in workers]
    for w in workers:
        w.join()
    return max(times)


def slowness(loop_s: float, ref_loop_s: float = REF_LOOP_S) -> float:
    """``s = loop_s / ref_loop_s``: how many times slower than the reference VM."""
    if not (loop_s > 0 and ref_loop_s > 0):
        raise ValueError(f"loop times must be > 0, got {loop_s} and {ref_loop_s}")
    return loop_s / ref_loop_s


def time_factor(s: float, f_ref: float = F_REF) -> float:
    """``F = clamp(f_ref * s, F_MIN, F_MAX)``, rounded up to 0.1."""
    return min(F_MAX, max(F_MIN, _ceil1(f_ref * s)))


def sim_time_scale(s: float, k_ref: float = K_REF) -> float:
    """``k = clamp(k_ref / s, K_MIN, K_MAX)``, rounded down to 0.01."""
    return min(K_MAX, max(K_MIN, int(k_ref / s * 100) / 100))


def deadman(s: float, d_ref: float = D_REF) -> float:
    """``D = clamp(d_ref * s, D_MIN, D_MAX)``, rounded up to 0.1."""
    return min(D_MAX, max(D_MIN, _ceil1(d_ref * s)))


def _ceil1(x: float) -> float:
    return -(-round(x * 1e6) // 100_000) / 10


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeat", type=int, default=8, help="loops timed; their mean counts")
    ap.add_argument(
        "--procs", type=int, default=os.cpu_count() or 1, help="loops at once (default: CPUs)"
    )
    ap.add_argument("--ref-loop", type=float, default=REF_LOOP_S)
    ap.add_argument("--factor", type=float, default=F_REF, help="F at the reference speed")
    ap.add_argument("--time-scale", type=float, default=K_REF, help="k at the reference speed")
    a = ap.parse_args(argv)
    loop = loaded_loop_seconds(max(1, a.procs), max(1, a.repeat))
    s = slowness(loop, a.ref_loop)
    print(
        f"LOOP_S={loop:.3f} SLOWNESS={s:.2f} TIME_FACTOR={time_factor(s, a.factor):g}"
        f" SIM_TIME_SCALE={sim_time_scale(s, a.time_scale):g} DEADMAN_S={deadman(s):g}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
