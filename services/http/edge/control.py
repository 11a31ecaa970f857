"""Threads kept for control: ``/health`` and the wait of an abort never queue behind other
requests, and other requests leave the event loop its share of the interpreter.

FastAPI runs a plain ``def`` route in one shared thread pool (anyio's): slow reads
(exports, plots, datasets) in progress would make ``/health`` and an abort wait for a
free thread.  The control routes are ``async`` and hand their blocking part to pools of
their own: :data:`HEALTH` (the health check reads the disk and the kinematic file in
force) and :data:`ABORT` (an abort stops every axis on the event loop itself, then waits
here for its run's thread to end).

The shared pool is held to :data:`ROUTE_THREADS` (anyio's default is 40): the routes are
Python, so more threads than that buy no throughput on a robot's few cores, and each
runnable one takes turns at the interpreter lock with the event loop, where an abort
runs (50 clients asking for plans at once had it wait seconds).
"""

from __future__ import annotations

import asyncio
import functools
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import ParamSpec, TypeVar

import anyio.to_thread

P = ParamSpec("P")
T = TypeVar("T")

ROUTE_THREADS = 4
"""Threads of the pool that runs the plain ``def`` routes (module docstring)."""
HEALTH = ThreadPoolExecutor(max_workers=2, thread_name_prefix="swpc-health")
ABORT = ThreadPoolExecutor(max_workers=4, thread_name_prefix="swpc-abort")


async def run_in(
    pool: ThreadPoolExecutor, fn: Callable[P, T], *args: P.args, **kwargs: P.kwargs
) -> T:
    """``fn(*args, **kwargs)`` in ``pool``, awaited."""
    loop = asyncio.get_running_loop()
    return await loop.run_in_executor(pool, functools.partial(fn, *args, **kwargs))


def limit_route_threads() -> None:
    """Hold the running event loop's pool of ``def`` routes to :data:`ROUTE_THREADS`."""
    anyio.to_thread.current_default_thread_limiter().total_tokens = ROUTE_THREADS
