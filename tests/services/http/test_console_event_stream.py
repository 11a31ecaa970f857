"""The console's event stream over the real HTTP server: an open stream does not hold up
a SIGTERM, a stream broken during a run and resumed with ``Last-Event-ID`` gets exactly the
events it missed, an id too old or unknown starts over with a snapshot; and a node's
liveness in the live snapshot is unknown while no heartbeat is watched.

The runs are real ones of the state machine on the fake robot (the rig:
:mod:`tests.services.http.console_rig`), each test on a runtime of its own.
"""

from __future__ import annotations

import contextlib
import json
import signal
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import httpx

from services.http.app import create_app
from services.runtime.events import EventBus
from services.runtime.runtime import Runtime
from tests.service_rig import served
from tests.services.http.console_rig import bare_runtime, new_run


def test_an_open_event_stream_does_not_hold_up_a_sigterm(tmp_path: Path) -> None:
    """The server waits for every open response before it stops the runtime, and with it
    a run in progress: a console left open kept ``swpc serve`` up after SIGTERM for as
    long as it stayed open.  Its stream now ends when the service stops."""
    rt = bare_runtime(tmp_path)
    app = create_app(rt.settings, runtime_factory=lambda _: rt)
    lines: list[str] = []
    with served(app) as (srv, port):

        def listen() -> None:
            with httpx.stream("GET", f"http://127.0.0.1:{port}/events", timeout=30) as r:
                lines.extend(r.iter_lines())

        listening = threading.Thread(target=listen, daemon=True)
        listening.start()
        deadline = time.monotonic() + 30
        while "event: live" not in lines:
            assert listening.is_alive() and time.monotonic() < deadline, lines
            time.sleep(0.01)
        srv.handle_exit(signal.SIGTERM, None)  # what the signal handler calls
        listening.join(10)
        assert not listening.is_alive() and app.state.stop_signal == "SIGTERM", (
            "the server still waits for the open stream"
        )


@contextlib.contextmanager
def http_service(rt: Runtime) -> Iterator[str]:
    """The app on ``rt`` behind the real HTTP server, in this process; its base URL."""
    with served(create_app(rt.settings, runtime_factory=lambda _: rt)) as (_srv, port):
        yield f"http://127.0.0.1:{port}"


SSE = tuple[str, str, Any]
"""An event as a client reads it: its id, its name, its data."""


def read_sse(lines: Iterator[str], stop: Callable[[list[SSE]], bool]) -> list[SSE]:
    """Events from a text/event-stream's lines until ``stop(events so far)``."""
    out: list[SSE] = []
    fields: dict[str, str] = {}
    for line in lines:
        if line:
            name, _, value = line.partition(": ")
            fields[name] = value
            continue
        if "event" in fields:
            out.append((fields["id"], fields["event"], json.loads(fields["data"])))
            if stop(out):
                break
        fields = {}
    return out


def number(event_id: str) -> int:
    return int(event_id.split(":")[1])


def test_a_reconnect_with_last_event_id_gets_exactly_the_events_it_missed(
    tmp_path: Path,
) -> None:
    """The events had no ids: a page whose stream broke during a run (a Wi-Fi hand-over)
    came back with the run's state now, the states in between lost."""
    rt = bare_runtime(tmp_path)
    with http_service(rt) as url:
        seen: list[str] = []
        run = new_run(rt, seen=seen)  # published: PENDING
        with httpx.stream("GET", f"{url}/events", timeout=30) as r:
            assert r.headers["content-type"].startswith("text/event-stream")
            lines = r.iter_lines()
            first = read_sse(lines, lambda got: len(got) == 2)
            run.start()  # a whole run in about a second of host time
            first += read_sse(lines, lambda got: [e for _, e, _ in got].count("run") == 4)
        # the stream broke after 4 changes of state; the run goes on to its end
        run.join(30)
        assert run.status.state == "DONE", run.status.errors
        last_id = first[-1][0]
        with httpx.stream(
            "GET", f"{url}/events", headers={"Last-Event-ID": last_id}, timeout=30
        ) as r:
            again = read_sse(r.iter_lines(), lambda got: got[-1][1] == "live")
    # a new stream: hello, the run's state as it began; every id of a stream larger
    assert [e for _, e, _ in first[:2]] == ["hello", "run"] and first[1][2]["state"] == "PENDING"
    for events in (first, again):
        ids = [number(i) for i, _, _ in events]
        assert ids == sorted(set(ids)), ids
        assert len({i.split(":")[0] for i, _, _ in events}) == 1  # one epoch
    # the reconnect: no hello, exactly the states published after the last one it had,
    # then the live view again
    got = [d["state"] for _, e, d in first[2:] if e == "run"]
    missed = [d["state"] for _, e, d in again if e == "run"]
    assert len(got) == 4 and [e for _, e, _ in again][-1] == "live"
    assert "hello" not in [e for _, e, _ in again]
    assert got + missed == seen[1:], (got, missed, seen)
    assert missed[-1] == "DONE" and len(missed) > 20


def test_a_last_event_id_too_old_or_unknown_starts_over_with_a_snapshot(
    tmp_path: Path,
) -> None:
    rt = bare_runtime(tmp_path)
    rt.events = EventBus(history=8)  # a run publishes more than that
    with http_service(rt) as url:
        run = new_run(rt)
        with httpx.stream("GET", f"{url}/events", timeout=30) as r:
            first = read_sse(r.iter_lines(), lambda got: got[-1][1] == "live")
        run.start()
        run.join(30)
        assert run.status.state == "DONE", run.status.errors
        epoch = first[0][0].split(":")[0]
        huge = f"{epoch}:" + "9" * 5000  # int() refuses over 4300 digits: was a traceback
        for last_id in (first[-1][0], "0badc0de:3", f"{epoch}:99999", first[0][0], "junk", huge):
            with httpx.stream(
                "GET", f"{url}/events", headers={"Last-Event-ID": last_id}, timeout=30
            ) as r:
                again = read_sse(r.iter_lines(), lambda got: got[-1][1] == "live")
            # too old (forgotten), another process's, not one yet, hello's, not an id, too
            # long to be one:
            # hello and the run's state now, as for a new client
            assert [e for _, e, _ in again] == ["hello", "run", "live"], (last_id, again)
            assert again[1][2]["state"] == "DONE"


def test_node_liveness_is_unknown_while_no_heartbeat_is_watched(tmp_path: Path) -> None:
    """After a run on the in-process simulator the console showed "Alive yes" beside
    "CAN bus: inactive": between runs simulated time stands still, and no heartbeat is
    watched.  Its liveness is now unknown (null) there; the rest of a node stays."""
    from services.http.console.router import _LiveCursor, live_snapshot
    from tests.service_rig import sim_service

    with sim_service(tmp_path) as sim:
        rt = sim.rt
        assert rt.simulator is not None and not rt.running()
        snap = live_snapshot(rt, _LiveCursor())
        nodes = snap["nodes"]
        assert [n["module"] for n in nodes] == [1, 2, 3, 4]
        assert all(n["alive"] is None for n in nodes), nodes
        assert all(n["homed"] in (True, False) for n in nodes)
        health = sim.client.get("/health").json()
        assert health["simulated_time_still"] is True
