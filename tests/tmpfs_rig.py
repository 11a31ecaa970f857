"""A real full file system for a test: a child Python process whose data dir is a small
tmpfs, mounted in a user + mount namespace of its own (``unshare``), no root needed."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from tests.service_rig import ROOT

no_unshare = pytest.mark.skipif(shutil.which("unshare") is None, reason="no unshare(1)")
"""Mark a test that needs ``unshare(1)``."""


def run_in_tmpfs(tmp_path: Path, script: str, options: str, timeout: float = 120) -> Any:
    """Run ``script`` (Python; its ``sys.argv[1]`` the mount point) on a tmpfs mounted
    with ``options`` (e.g. ``size=160k``); the JSON of its last line of output.  Skips
    where user namespaces are not allowed."""
    path = tmp_path / "script.py"
    path.write_text(script)
    mnt = tmp_path / "mnt"
    mnt.mkdir()
    probe = subprocess.run(
        ["unshare", "--user", "--map-root-user", "--mount", "true"], capture_output=True
    )
    if probe.returncode != 0:
        pytest.skip(f"no user namespaces here: {probe.stderr.decode().strip()}")
    # The script's process ends with os._exit once its output is flushed: what is tested is
    # done by then, and an interpreter finalizing beside zenoh's runtime threads (one of
    # them calling back into Python) was once aborted by glibc, "FATAL: exception not
    # rethrown", on a busy host (2026-11-29).
    run = f"import runpy, os, sys; runpy.run_path({str(path)!r}, run_name='__main__'); "
    run += "sys.stdout.flush(); sys.stderr.flush(); os._exit(0)"
    cmd = f"mount -t tmpfs -o {options} tmpfs {mnt} && exec {sys.executable} -c \"{run}\" {mnt}"
    p = subprocess.run(
        ["unshare", "--user", "--map-root-user", "--mount", "sh", "-c", cmd],
        capture_output=True,
        timeout=timeout,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    assert p.returncode == 0, p.stderr.decode()[-3000:]
    return json.loads(p.stdout.decode().strip().splitlines()[-1])
