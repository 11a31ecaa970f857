"""Keep CPython's cyclic garbage collector from pausing a long-running process.

A full (generation 2) collection walks every container object the process holds; it
runs with the GIL held, so every thread stops for its duration.  With the ~100 000
objects the service's imports and start-up leave behind it costs ~75 ms on the lab
machine, with millions (a feedback history kept as objects) 0.5-2 s were measured:
long enough for the CAN driver to declare every controller lost (heartbeat timeout
0.3 s on a robot).  The per-sample data are numpy arrays
(:mod:`swpc_hw.drives.tracking`, :mod:`services.sensors.mocap`); what is left is the start-up
heap, which :func:`freeze_startup_heap` moves to the permanent generation once the
process is up (:func:`gc.freeze`, CPython >= 3.7).
"""

from __future__ import annotations

import gc
import time


def freeze_startup_heap() -> tuple[int, float]:
    """Collect once, then exclude every surviving object from future collections.

    Frozen objects are still freed by reference counting; only cycles among them leak,
    which is what start-up objects (modules, classes, configuration) never become.
    Returns (objects frozen, seconds the collection took).
    """
    t = time.perf_counter()
    gc.collect()
    dt = time.perf_counter() - t
    gc.freeze()
    return gc.get_freeze_count(), dt
