"""Run every benchmark: ``python -m benchmarks [NAME ...]`` (``make bench``).

Each ``benchmarks/bench_*.py`` module defines ``main() -> None`` that prints its figures.
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
    names = sorted(
        m.name for m in pkgutil.iter_modules(benchmarks.__path__) if m.name.startswith("bench_")
    )
    wanted = [n for n in names if not argv or any(a in n for a in argv)]
    for name in wanted:
        print(f"\n=== {name} ===", flush=True)
        t0 = time.perf_counter()
        importlib.import_module(f"benchmarks.{name}").main()
        print(f"({name}: {time.perf_counter() - t0:.1f} s)", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
