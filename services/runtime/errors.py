"""Why the service refuses to start a run, or has nothing to show: each maps to one HTTP
status (:mod:`services.http.calibrations`)."""

from __future__ import annotations

import errno
from pathlib import Path

from swpc_hw.errors import SwpcError


class RunConflictError(RuntimeError):
    """A calibration is already running."""


class DiskSpaceError(SwpcError):
    """No room for a run: the disk budget or the file system's free space (HTTP 507)."""


class NoResultError(SwpcError):
    """The run has no result to plot (not DONE)."""


class NoFileError(SwpcError):
    """A check needs a kinematic file in force that loads (HTTP 409)."""


class StoreError(SwpcError):
    """The run store, or the data dir where a run keeps its files, cannot be written: no
    run starts (HTTP 503)."""


def room_error(path: Path, exc: OSError) -> SwpcError:
    """Why a run's directory or files could not be made: no room (ENOSPC, EDQUOT: bytes
    or inodes, 507) or another failure of the data dir (503)."""
    what = exc.strerror or str(exc)
    if exc.errno in (errno.ENOSPC, errno.EDQUOT):
        return DiskSpaceError(
            f"no room for the run's files: {path}: {what} (no bytes or no inodes left on the "
            "data dir's file system): no run started"
        )
    return StoreError(f"the data dir cannot keep a run: {path}: {what}: no run started")
