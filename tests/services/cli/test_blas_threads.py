"""Every swpc process runs its BLAS on one thread (swpc_hw/blas_threads.py)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest


def test_the_swpc_command_limits_blas_to_one_thread() -> None:
    """In a fresh process without OPENBLAS_NUM_THREADS: BLAS starts with one thread per
    core, and the ``swpc`` entry point brings it to one before any work."""
    code = (
        "import json, numpy, scipy.linalg\n"
        "from threadpoolctl import threadpool_info\n"
        "from services.cli import main\n"
        "before = [d['num_threads'] for d in threadpool_info() if d['user_api'] == 'blas']\n"
        "try:\n"
        "    main(['--version'])\n"
        "except SystemExit:\n"
        "    pass\n"
        "after = [d['num_threads'] for d in threadpool_info() if d['user_api'] == 'blas']\n"
        "print(json.dumps([before, after]))\n"
    )
    env = {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_NUM_THREADS",
                                                             "OMP_NUM_THREADS")}
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=60,
        check=True,
    ).stdout.strip().splitlines()[-1]
    before, after = json.loads(out)
    assert after and all(n == 1 for n in after), (before, after)
    if (os.cpu_count() or 1) > 1 and max(before) == 1:
        pytest.fail(f"BLAS already had one thread before the limit: {before}")
