"""The runs a service keeps: in memory (the current one and the newest finished) and in the
run store (:mod:`services.store.runs`), saved on every change of a run's state; what the API
lists of them.  A save that fails is kept (health, the runs list shows the in-memory state)
and made again once the store takes writes.  Part of :class:`services.runtime.runtime.Runtime`.
"""

from __future__ import annotations

import logging
import threading
from typing import Any

from services.config.robot import RunKind
from services.runs.install import file_run, read_replaced
from services.runs.protocol import CalibrationRun
from services.runs.state import State, now_iso
from services.runtime.events import EventBus
from services.store.logs import event
from services.store.runs import RunStore
from swpc_hw.drives.interface import Drives

RUNS_IN_MEMORY = 8
"""Finished runs the runtime keeps in memory beside the current one (the others are read
from the run store)."""
log = logging.getLogger("swpc.service")


class RunRecords:
    """The runs of :class:`~services.runtime.runtime.Runtime`, which sets these attributes."""

    store: RunStore
    store_error: str | None
    runs: dict[str, CalibrationRun]
    current: CalibrationRun | None
    events: EventBus
    lock: threading.Lock
    drives: Drives | None
    _unsaved: set[str]

    def _persist(self, run: CalibrationRun) -> None:
        """Save a run's state (its on_change); a failure is kept (health, the runs list
        shows the in-memory state) and raised, so that a run still going fails."""
        if run.finished and self.drives is not None and run is self.current:
            err = self.drives.stop_recording()
            if err is not None:
                run.status.errors.append(f"CAN recording stopped early: {err}")
        try:
            self.store.upsert(run.id, run.status.created, run.status.to_dict())
            if run.status.state is State.DONE and run.result_doc is not None:
                self.store.set_result(run.id, run.result_doc)
                if run.status.installed:
                    self._record_install(run)
        except Exception as exc:
            self._unsaved.add(run.id)
            if self.store_error is None:
                event(log, logging.ERROR, "store.write_failed", run=run.id, error=str(exc))
            self.store_error = f"{type(exc).__name__}: {exc}"
            raise
        finally:  # the console's event stream: saved or not, as the runs list shows it
            self.events.publish({"type": "run", "run": run.status.to_dict()})
        self._unsaved.discard(run.id)
        if run.finished:
            self._retire()

    def _record_install(self, run: CalibrationRun) -> None:
        """A run installed its result at its end: a change of the file in force, with
        the file it replaced (its backup, made just before)."""
        b = run.backup
        self.store.add_change(
            {
                "time": run.status.finished or now_iso(),
                "action": "run",
                "run": run.id,
                "file": f"runs/{run.id}/kinematics.yaml",
                "replaced": None if b is None else b.name,
                "replaced_run": None if b is None else file_run(b),
            },
            read_replaced(b),
        )

    def _retire(self) -> None:
        """Keep in memory the current run and the :data:`RUNS_IN_MEMORY` newest finished
        ones (and any whose state the store has yet to take): the rest are read from the
        store, so a service that runs for months holds a bounded number of runs."""
        with self.lock:
            finished = [
                r for r in self.runs.values()
                if r.finished and r is not self.current and r.id not in self._unsaved
            ]  # fmt: skip
            finished.sort(key=lambda r: r.status.created)
            for r in finished[: max(0, len(finished) - RUNS_IN_MEMORY)]:
                del self.runs[r.id]

    def _save_unsaved(self) -> None:
        """Save again the runs whose last save failed (once the store takes writes)."""
        for rid in list(self._unsaved):
            run = self.runs.get(rid)
            if run is None:
                self._unsaved.discard(rid)
                continue
            try:
                self.store.upsert(run.id, run.status.created, run.status.to_dict())
                if run.status.state is State.DONE and run.result_doc is not None:
                    self.store.set_result(run.id, run.result_doc)
            except Exception as exc:
                self.store_error = f"{type(exc).__name__}: {exc}"
                return
            self._unsaved.discard(rid)
        if not self._unsaved and self.store_error is not None:
            event(log, logging.INFO, "store.recovered")
            self.store_error = None

    def _stored(self, run_id: str, kind: RunKind | None) -> tuple[dict[str, Any], Any] | None:
        """``(status, result document or None)`` of a run of ``kind`` (None: any kind),
        in memory or in the store; None if unknown (or of another kind)."""
        run = self.runs.get(run_id)
        if run is not None:
            got: tuple[dict[str, Any], Any] | None = (run.status.to_dict(), run.result_doc)
        else:
            got = self.store.get(run_id)
        if got is None or (kind is not None and got[0].get("kind", "calibration") != kind):
            return None
        return got

    def status(self, run_id: str, kind: RunKind | None = None) -> dict[str, Any] | None:
        """A run's status (of ``kind`` only, if given); None if unknown."""
        got = self._stored(run_id, kind)
        return None if got is None else got[0]

    def result(
        self, run_id: str, kind: RunKind | None = None
    ) -> tuple[str, dict[str, Any] | None] | None:
        """``(state, result document or None)``; None if the run is unknown (or not of
        ``kind``)."""
        got = self._stored(run_id, kind)
        return None if got is None else (str(got[0]["state"]), got[1])

    def list_runs(self, kind: RunKind | None = None) -> list[dict[str, Any]]:
        """Every run (of ``kind`` only, if given), oldest first: the store's, with the
        in-memory state of this service's runs over it (the store may have missed a
        write)."""
        if self._unsaved:
            self._save_unsaved()
        try:
            stored = list(self.store.list(kind))
        except Exception as exc:
            self.store_error = f"{type(exc).__name__}: {exc}"
            stored = []
        by_id = {str(st["id"]): st for st in stored}
        for rid, run in self.runs.items():
            if kind is None or run.status.kind == kind:
                by_id[rid] = run.status.to_dict()
        return sorted(by_id.values(), key=lambda st: str(st.get("created", "")))

    def run_states(self) -> dict[str, int]:
        counts: dict[str, int] = {str(s): 0 for s in State}
        for st in self.list_runs():
            counts[str(st["state"])] = counts.get(str(st["state"]), 0) + 1
        return counts
