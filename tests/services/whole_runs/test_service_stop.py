"""An abort does not depend on HTTP alone (issue 40, item 1; docs/operating.md, "Stopping
the robot"): ``systemctl stop`` (SIGTERM) of a real ``swpc serve`` mid-spin, with an event
stream held open, stops every axis and ends the run FAILED with the signal's name.

The service runs as its own process on the in-process simulator; what it sent is read
back from the run's raw CAN recording (``dataset/can.log``, candump format) with
python-can's own log reader, and the run's state from its store after the process ended.
A service that hangs or is killed instead is stopped by the drives' own dead-man: the
``deadman``, ``odrive`` and ``cia402`` steps of ``make test-vcan`` (``kill -STOP`` of the
service on real SocketCAN) and the drive kinds' dead-man tests.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import can
import httpx

from firmware_protocol import codec
from firmware_protocol.codec import ControlMode
from services.store.runs import RunStore
from swpc_hw.sensors.zenoh_session import free_tcp_endpoint
from tests.service_rig import AUTH, MID_SPIN, TOKEN, wait_spinning

STOP_TIMEOUT = 20.0
"""The unit's ``TimeoutStopSec`` (deploy/systemd/swpc-service.service)."""


def test_sigterm_mid_spin_stops_every_axis_and_fails_the_run(tmp_path: Path) -> None:
    port = int(free_tcp_endpoint().rsplit(":", 1)[1])
    data = tmp_path / "data"
    env = {k: v for k, v in os.environ.items() if not k.startswith(("SWPC_", "JOURNAL_"))}
    env.update(SWPC_TOKEN=TOKEN, SWPC_PORT=str(port), SWPC_DATA_DIR=str(data))
    log = (tmp_path / "service.log").open("w")
    proc = subprocess.Popen(
        [sys.executable, "-m", "services.cli", "serve", "--log-level", "warning"],
        env=env, stdout=log, stderr=subprocess.STDOUT,
    )  # fmt: skip
    base = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                if not httpx.get(f"{base}/health", timeout=2).json()["mocap_stale"]:
                    break
            except httpx.TransportError:
                pass
            assert proc.poll() is None, (tmp_path / "service.log").read_text()
            assert time.monotonic() < deadline, "the service did not start"
            time.sleep(0.1)
        with httpx.Client(base_url=base, timeout=30) as c:
            r = c.post("/calibrations", json={"overrides": MID_SPIN}, headers=AUTH)
            assert r.status_code == 202, r.text
            run_id = r.json()["id"]
            wait_spinning(c, run_id)  # type: ignore[arg-type]

        def hold_a_stream() -> None:  # a console left open
            try:
                with httpx.stream("GET", f"{base}/events", timeout=60) as s:
                    for _ in s.iter_lines():
                        pass
            except httpx.TransportError:
                pass

        threading.Thread(target=hold_a_stream, daemon=True).start()
        time.sleep(0.5)
        t0 = time.monotonic()
        proc.send_signal(signal.SIGTERM)  # as systemctl stop
        status = proc.wait(STOP_TIMEOUT)
        took = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            proc.kill()  # by its PID
            proc.wait()
        log.close()
    assert status in (0, -signal.SIGTERM), (tmp_path / "service.log").read_text()
    print(f"\nSIGTERM mid-spin: the service ended in {took:.2f} s")

    store = RunStore(data / "runs.sqlite")
    try:
        got = store.get(run_id)
    finally:
        store.close()
    assert got is not None
    st = got[0]
    assert st["state"] == "FAILED", st
    assert st["reason"].startswith("the service was stopped (SIGTERM) during the run"), st

    # the host's last frame to each axis is a stop: FREE, then disable
    last: dict[tuple[int, int], object] = {}
    for msg in can.LogReader(data / "runs" / run_id / "dataset" / "can.log"):
        if msg.is_error_frame:
            continue
        node, kind = codec.split_id(msg.arbitration_id)
        if kind not in codec.HOST_COMMANDS:
            continue
        try:
            d = codec.parse(msg.arbitration_id, bytes(msg.data))
        except codec.ProtocolError:
            continue
        axis = getattr(d, "axis", None)
        if axis is None:
            continue
        last[(node, int(axis))] = d
    assert len(last) == 8, sorted(last)  # 4 modules x (steer, wheel)
    for key, d in last.items():
        stopped = (isinstance(d, codec.SetAxisState) and not d.enabled) or (
            isinstance(d, codec.SetControl) and d.mode == ControlMode.FREE
        )
        assert stopped, (key, d)
