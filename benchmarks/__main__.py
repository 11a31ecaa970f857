"""Run every benchmark: ``python -m benchmarks [NAME ...]`` (``make bench``).

Each ``benchmarks/<room>/bench_*.py`` module (the rooms as the code's: ``drives``,
``calibration``, ``onboard``, ``services``) defines ``main() -> None`` that prints its
figures; a ``NAME`` picks those whose module name (``bench_<name>``) contains it, in the
order of their names.
"""

from __future__ import annotations

import importlib
import pkgutil
import sys
import time

import benchmarks
from swpc_hw.blas_threads import single_blas_thread


def main(argv: list[str]) -> int:
    single_blas_thread()  # as every swpc process (swpc_hw/blas_threads.py)
    modules = {
        m.name.rpartition(".")[2]: m.name
        for m in pkgutil.walk_packages(benchmarks.__path__, "benchmarks.")
        if m.name.rpartition(".")[2].startswith("bench_")
    }
    wanted = [n for n in sorted(modules) if not argv or any(a in n for a in argv)]
    for name in wanted:
        print(f"\n=== {name} ===", flush=True)
        t0 = time.perf_counter()
        importlib.import_module(modules[name]).main()
        print(f"({name}: {time.perf_counter() - t0:.1f} s)", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
