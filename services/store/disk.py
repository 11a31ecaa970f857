"""The data dir's disk budget: what it holds, what may be pruned, what a run may write.

The data dir holds the run store, the kinematic file and its backups, the rolling CAN log
(``can/``, bounded by ``SWPC_CAN_LOG_BYTES``) and one directory per run.  Within a run's
directory the raw recordings (``dataset/can.log``, ``run.mcap``) are most of its bytes and
can be pruned: the dataset's CSVs, the run's ``kinematics.yaml`` and plot are what its
result rests on and are never deleted.  Before a run starts, the recordings of the oldest
runs are deleted until the data dir leaves :func:`run_reserve` bytes of the budget free;
the run may then write what is left of the budget (:class:`services.runs.recording.SpaceGuard`).
"""

from __future__ import annotations

import contextlib
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

PRUNABLE = ("dataset/can.log", "run.mcap")
MIB = 1 << 20


def tree_bytes(path: Path) -> int:
    """Bytes of every regular file under ``path`` (apparent sizes)."""
    total = 0
    for root, _dirs, files in os.walk(path):
        for f in files:
            with contextlib.suppress(OSError):
                total += os.lstat(os.path.join(root, f)).st_size
    return total


def run_reserve(budget: int) -> int:
    """Bytes a run is given room for before it starts: a quarter of the budget, at most
    256 MiB (a 4-module run at 200 Hz writes about 30 MiB, most of it can.log)."""
    return min(budget // 4, 256 * MIB)


@dataclass
class BudgetReport:
    used: int
    budget: int
    free: int
    pruned: list[Path]

    @property
    def allowed(self) -> int:
        return max(0, self.budget - self.used)


def make_room(
    data_dir: Path,
    budget: int,
    *,
    keep: frozenset[str] | set[str] = frozenset(),
    reserve: int | None = None,
) -> BudgetReport:
    """Prune the oldest runs' raw recordings (never those of runs in ``keep``) until the
    data dir uses at most ``budget - reserve`` bytes, or nothing prunable is left."""
    reserve = run_reserve(budget) if reserve is None else reserve
    used = tree_bytes(data_dir)
    pruned: list[Path] = []
    runs = data_dir / "runs"
    if used > budget - reserve and runs.is_dir():
        dirs = sorted(
            (d for d in runs.iterdir() if d.is_dir() and d.name not in keep),
            key=lambda d: d.stat().st_mtime,
        )
        for d in dirs:
            for rel in PRUNABLE:
                p = d / rel
                if p.is_file():
                    size = p.stat().st_size
                    with contextlib.suppress(OSError):
                        p.unlink()
                        used -= size
                        pruned.append(p)
            if used <= budget - reserve:
                break
    return BudgetReport(used, budget, shutil.disk_usage(data_dir).free, pruned)
