"""The run store (services/store/runs.py): past runs across restarts, interrupted runs
finished when found, a damaged store refused at start with the way out."""

from __future__ import annotations

import datetime as dt
import json
import sqlite3
from pathlib import Path

import pytest

from services.store.runs import RunStore, RunStoreError
from tests.service_rig import TOKEN


def test_restart_lists_past_runs_and_fails_interrupted_ones(tmp_path: Path) -> None:
    store = RunStore(tmp_path / "runs.sqlite")
    store.upsert("a1", "2026-01-01T00:00:00Z", {"id": "a1", "state": "DONE", "created": "x"})
    store.set_result("a1", {"run": "a1", "modules": []})
    store.upsert("b2", "2026-01-01T00:01:00Z", {"id": "b2", "state": "SPIN", "created": "y"})
    store.close()
    store = RunStore(tmp_path / "runs.sqlite")  # "restart"
    assert store.mark_interrupted(found="2026-01-02T00:00:00.000Z") == ["b2"]
    states = {r["id"]: r["state"] for r in store.list()}
    assert states == {"a1": "DONE", "b2": "FAILED"}
    got = store.get("b2")
    assert got is not None and got[0]["reason"] == "service restarted during the run"
    assert got[0]["finished"] == "2026-01-02T00:00:00.000Z"
    got = store.get("a1")
    assert got is not None and got[1] == {"run": "a1", "modules": []}


def test_a_run_interrupted_by_a_restart_is_finished_when_found(tmp_path: Path) -> None:
    """It stayed ``finished: null`` for ever; now it is the time the restart found it."""
    from pydantic import SecretStr

    from services.config.settings import ServiceSettings
    from services.runtime.runtime import Runtime

    store = RunStore(tmp_path / "runs.sqlite")
    store.upsert("c3", "2026-01-01T00:00:00Z", {"id": "c3", "state": "SPIN", "created": "z"})
    store.close()
    before = dt.datetime.now(dt.UTC)
    rt = Runtime(ServiceSettings(data_dir=tmp_path, token=SecretStr(TOKEN)))
    try:
        st = rt.status("c3")
    finally:
        rt.close()
    assert st is not None and st["state"] == "FAILED" and st["finished"] is not None
    found = dt.datetime.fromisoformat(st["finished"].replace("Z", "+00:00"))
    assert before - dt.timedelta(seconds=1) <= found <= dt.datetime.now(dt.UTC)


def damaged(path: Path, how: str) -> None:
    if how == "garbage":
        path.write_bytes(b"this is not a database\n" * 100)
        return
    store = RunStore(path)
    for i in range(200):
        store.upsert(
            f"r{i}",
            "2026-01-01T00:00:00Z",
            {"id": f"r{i}", "state": "DONE", "created": "x", "pad": "p" * 500},
        )
    store.close()
    con = sqlite3.connect(path)
    con.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    con.close()
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])  # truncated: a disk that lost its tail


@pytest.mark.parametrize("how", ["garbage", "truncated"])
def test_a_damaged_run_store_is_one_line_naming_it_and_the_way_out(
    tmp_path: Path, how: str
) -> None:
    """swpc serve exited with a Python traceback (a crash loop under systemd)."""
    path = tmp_path / "runs.sqlite"
    damaged(path, how)
    with pytest.raises(RunStoreError) as exc:
        RunStore(path)
    msg = str(exc.value)
    assert str(path) in msg and "move it aside" in msg and "\n" not in msg, msg


@pytest.mark.parametrize("how", ["garbage", "truncated"])
def test_swpc_serve_on_a_damaged_run_store_says_so_in_one_line(
    tmp_path: Path, how: str, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    from services.cli import main

    monkeypatch.setenv("SWPC_TOKEN", TOKEN)
    monkeypatch.delenv("SWPC_CAN_INTERFACE", raising=False)
    damaged(tmp_path / "runs.sqlite", how)
    assert main(["serve", "--port", "0", "--data-dir", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "the run store is damaged" in err[0], err
    assert f"mv {tmp_path / 'runs.sqlite'} " in err[0]
    json.dumps(err)  # one plain line


def test_a_long_lived_service_keeps_a_bounded_number_of_runs_in_memory(
    tmp_path: Path,
) -> None:
    """Every run ever started stayed in memory (the soak's resident memory grew with every
    run): the runtime keeps the current one and the newest finished ones, the store the
    rest, and lists them all."""
    from types import SimpleNamespace

    from pydantic import SecretStr

    from services.config.settings import ServiceSettings
    from services.runtime.records import RUNS_IN_MEMORY
    from services.runtime.runtime import Runtime

    rt = Runtime(ServiceSettings(data_dir=tmp_path, token=SecretStr(TOKEN)))
    try:
        for i in range(3 * RUNS_IN_MEMORY):
            rid = f"r{i:03d}"
            status = {
                "id": rid,
                "state": "DONE",
                "created": f"2026-01-01T00:{i // 60:02d}:{i % 60:02d}Z",
            }
            run = SimpleNamespace(
                id=rid,
                finished=True,
                status=SimpleNamespace(created=status["created"], to_dict=lambda s=status: s),
            )
            rt.runs[rid] = run  # type: ignore[assignment]
            rt.store.upsert(rid, status["created"], status)
            rt._retire()
        assert len(rt.runs) == RUNS_IN_MEMORY
        assert sorted(rt.runs) == [
            f"r{i:03d}" for i in range(2 * RUNS_IN_MEMORY, 3 * RUNS_IN_MEMORY)
        ]
        assert len(rt.list_runs()) == 3 * RUNS_IN_MEMORY
        assert rt.status("r000") is not None  # from the store
    finally:
        rt.close()
