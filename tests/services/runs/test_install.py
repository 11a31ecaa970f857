"""Installing a kinematic file: an abort is either in time (nothing installed) or too late
(refused, the result stands), never both; the backups beside the file in force are bounded
and never duplicate one another."""

from __future__ import annotations

import inspect
import sys
import threading
import time
from pathlib import Path
from types import FrameType
from typing import Any

import pytest

import services.runs.install as install_module
from services.runs.install import backup_kinematics, backups
from services.runs.state import State
from services.runtime.runtime import Runtime
from swpc_hw.files.kinematic_file import save_kinematics
from tests.run_rig import NOMINAL, Rig
from tests.service_rig import AUTH, Sim

QUICK = {"protocol": {"angles_deg": [30, 150], "sweep_deg": 60}}


def test_an_abort_as_write_begins_is_in_time_and_installs_nothing(tmp_path: Path) -> None:
    """The in-time side of the commit point: an abort accepted as WRITE is entered ends the
    run ABORTED and leaves the file in force untouched."""
    rig = Rig(tmp_path, QUICK)
    save_kinematics(rig.kinematics, NOMINAL, created="2026-01-01T00:00:00Z")
    before = rig.kinematics.read_bytes()
    accepted: list[bool] = []
    rig.hooks[State.WRITE] = lambda run: accepted.append(run.abort())
    run = rig.run()
    assert accepted == [True]
    assert run.status.state is State.ABORTED, run.status.errors
    assert rig.kinematics.read_bytes() == before and not run.status.installed


def test_an_abort_once_the_install_has_begun_is_refused_and_the_result_stands(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The abort came while the run was writing its result: it was accepted (200), the run
    ended DONE and the new file was installed anyway.  Now it is refused (the API's 409)."""
    rig = Rig(tmp_path, QUICK)
    run = rig.make_run()
    answers: list[bool] = []
    threads: list[threading.Thread] = []
    real = install_module.install_kinematics

    def install_while_an_operator_aborts(*args: Any, **kwargs: Any) -> Any:
        t = threading.Thread(target=lambda: answers.append(run.abort()))
        t.start()  # the operator's abort, from the HTTP thread, mid-install
        threads.append(t)
        t.join(0.2)
        return real(*args, **kwargs)

    monkeypatch.setattr(install_module, "install_kinematics", install_while_an_operator_aborts)
    run._main()
    threads[0].join(10)
    assert answers == [False]  # too late: refused
    assert run.status.state is State.DONE and run.status.installed
    assert rig.kinematics.exists()


def test_backups_are_bounded_and_an_identical_file_is_not_kept_twice(tmp_path: Path) -> None:
    """56 installs left 56 backups, identical ones too."""
    path = tmp_path / "kinematics.yaml"
    save_kinematics(path, NOMINAL, created="2026-01-01T00:00:00Z")
    first = backup_kinematics(path, keep=5)
    assert first is not None and backup_kinematics(path, keep=5) == first  # the same file
    assert backups(path) == [first]
    made = []
    for i in range(12):
        save_kinematics(path, NOMINAL, created=f"2026-01-02T00:00:{i:02d}Z")
        made.append(backup_kinematics(path, keep=5))
    kept = backups(path)
    assert len(kept) == 5 and kept == sorted(made[-5:], key=lambda p: p.name, reverse=True)
    assert len({p.read_bytes() for p in kept}) == 5


def test_installs_through_the_api_keep_the_configured_number_of_backups(
    tmp_path: Path,
) -> None:
    from fastapi.testclient import TestClient

    from tests.service_rig import AUTH, app_without_robot

    app = app_without_robot(tmp_path, kinematics_backups=3)
    source = tmp_path / "runs" / "r1" / "kinematics.yaml"
    source.parent.mkdir(parents=True)
    with TestClient(app) as client:
        rt = app.state.runtime
        for i in range(6):
            save_kinematics(source, NOMINAL, created=f"2026-01-03T00:00:{i:02d}Z")
            rt.store.upsert("r1", "2026-01-03T00:00:00Z", {"id": "r1", "state": "DONE"})
            rt.store.set_result("r1", {"run": "r1"})
            r = client.post("/calibrations/r1/install", headers=AUTH)
            assert r.status_code == 200, r.text
        listed = client.get("/kinematics/files").json()["backups"]
    assert len(listed) == 3 and len(backups(rt.settings.kinematics_file)) == 3


def at_the_start_lock() -> FrameType | None:
    """The frame of a thread in :meth:`Runtime.start_run` at its ``with self.lock:`` (the
    runtime's lock, which an install holds), if one is there now."""
    lines, first = inspect.getsourcelines(Runtime.start_run)
    line = first + next(i for i, text in enumerate(lines) if "with self.lock:" in text)
    for top in sys._current_frames().values():
        f: FrameType | None = top
        while f is not None:
            if f.f_code is Runtime.start_run.__code__ and f.f_lineno == line:
                return f
            f = f.f_back
    return None


def test_an_install_and_a_new_start_never_overlap(
    sim: Sim, monkeypatch: pytest.MonkeyPatch
) -> None:
    """An install of an earlier run racing a new start: both were accepted, and the file in
    force changed after the new run had begun.  Now one lock: the start waits for the
    install, and an install never lands while a run exists."""
    import services.http.kinematics as kinematics

    client, rt = sim.client, sim.rt
    source = rt.data_dir / "runs" / "earlier" / "kinematics.yaml"
    source.parent.mkdir(parents=True, exist_ok=True)
    save_kinematics(source, NOMINAL, created="2026-01-04T00:00:00Z")
    rt.store.upsert("earlier", "2026-01-04T00:00:00Z", {"id": "earlier", "state": "DONE"})
    rt.store.set_result("earlier", {"run": "earlier"})
    starts: list[Any] = []
    seen: dict[str, bool] = {}
    real = kinematics.checked_text

    def check_while_a_run_is_started(path: Path) -> str:
        t = threading.Thread(
            target=lambda: starts.append(client.post("/calibrations", json={}, headers=AUTH))
        )
        t.start()
        # the start reaches the runtime's lock (10 s: a guard against a hang), and is still
        # waiting there, in the same frame, 0.1 s later: an acquire of a free lock passes
        # that line in microseconds
        deadline = time.monotonic() + 10.0
        while (waiting := at_the_start_lock()) is None:
            assert t.is_alive(), "the start went by without waiting for the install"
            assert time.monotonic() < deadline, "the start never reached the runtime's lock"
            time.sleep(0.005)
        time.sleep(0.1)
        seen["start waited for the install"] = at_the_start_lock() is waiting and t.is_alive()
        seen["no run during the install"] = not rt.running()
        threads.append(t)
        return real(path)

    threads: list[threading.Thread] = []
    monkeypatch.setattr(kinematics, "checked_text", check_while_a_run_is_started)
    r = client.post("/calibrations/earlier/install", headers=AUTH)
    threads[0].join(30)
    assert r.status_code == 200, r.text
    assert seen == {"start waited for the install": True, "no run during the install": True}
    assert len(starts) == 1 and starts[0].status_code == 202, starts[0].text
    run_id = starts[0].json()["id"]
    assert client.post(f"/calibrations/{run_id}/abort", headers=AUTH).status_code == 200
    sim.wait(run_id, {"ABORTED", "FAILED", "DONE"})
    # and the other way round: an install while that run existed would have been a 409
