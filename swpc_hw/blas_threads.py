"""One BLAS thread per process: the solvers' matrices are small.

The calibration solvers factorise matrices of tens to a few hundred rows, thousands of
times per solve.  A multi-threaded BLAS (OpenBLAS starts one thread per core) gains
nothing on such sizes and, on a host whose cores are busy, its workers spin-wait for each
other: measured on the 2-core development machine at load ~5, two solver tests took
12.8 s with OpenBLAS's default threads and 3.3 s with one.  A robot's computer is such a
host (navigation, perception), and the service's CAN driver and simulator need the CPU
the spinning workers take.  Every swpc entry point (the ``swpc`` command, the benchmarks)
calls :func:`single_blas_thread` first; ``OPENBLAS_NUM_THREADS=1`` in the environment
does the same for any other process.
"""

from __future__ import annotations

from threadpoolctl import threadpool_limits


def single_blas_thread() -> None:
    """Limit the BLAS libraries numpy and scipy loaded in this process to one thread
    (process-wide and lasting: threadpoolctl sets the libraries' own limit)."""
    threadpool_limits(limits=1, user_api="blas")
