"""``make console`` (``python -m services.demo --console``): a newcomer's one command.

It must keep the service up with the simulated robot, print the address and the token a
newcomer needs, accept a calibration with that token, and stop the service (by its PID)
on Ctrl-C, leaving nothing in the current directory.
"""

from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx

REPO = Path(__file__).resolve().parents[3]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_a_console_port_that_is_taken_is_refused_naming_it(tmp_path: Path) -> None:
    """``make console PORT=N`` with N taken: exit status 2 and what to do, at once (no
    service started on another port the operator did not ask for)."""
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        out = subprocess.run(
            [sys.executable, "-m", "services.demo", "--console", "--out", str(tmp_path / "c"),
             "--port", str(port)],
            cwd=tmp_path, env=dict(os.environ, PYTHONPATH=str(REPO)), capture_output=True,
            text=True, timeout=60, check=False,
        )
    assert out.returncode == 2, out
    assert f"port {port} on 127.0.0.1 is not free" in out.stderr
    assert "make console PORT=N" in out.stderr
    assert "swpc serve started" not in out.stdout


def test_console_command_serves_until_ctrl_c_and_its_token_starts_a_run(
    tmp_path: Path,
) -> None:
    env = dict(os.environ, PYTHONPATH=str(REPO), PYTHONUNBUFFERED="1")
    port = free_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "services.demo", "--console", "--out", str(tmp_path / "c"),
         "--port", str(port)],
        cwd=tmp_path,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,  # Ctrl-C of a terminal: SIGINT to the whole group
    )
    lines: list[str] = []
    try:
        assert proc.stdout is not None
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            lines.append(line)
            if line.startswith("Ctrl-C stops the service"):
                break
        out = "".join(lines)
        address = re.search(r"open (http://127\.0\.0\.1:\d+)/ in a browser", out)
        token = re.search(r"bearer token: (\S+)", out)
        pid = re.search(r"swpc serve started \(pid (\d+)\)", out)
        assert address and token and pid, out
        base = address.group(1)
        assert base == f"http://127.0.0.1:{port}", out  # make console PORT=N
        with httpx.Client(base_url=base, timeout=10.0) as http:
            page = http.get("/")
            assert page.status_code == 200 and "<html" in page.text.lower()
            assert http.post("/calibrations").status_code == 401  # the token is needed
            auth = {"Authorization": f"Bearer {token.group(1)}"}
            r = http.post("/calibrations", json={}, headers=auth)
            assert r.status_code == 202, r.text
            run_id = r.json()["id"]
            assert http.post(f"/calibrations/{run_id}/abort", headers=auth).status_code == 200
        os.killpg(proc.pid, signal.SIGINT)
        rest, _ = proc.communicate(timeout=30)
        assert f"service (pid {pid.group(1)}) stopped" in rest
        assert proc.returncode == 0, out + rest
        # the service is gone, and the data went where the command said, not into cwd
        assert not Path(f"/proc/{pid.group(1)}").exists()
        assert (tmp_path / "c" / "service.log").is_file()
        assert sorted(p.name for p in tmp_path.iterdir()) == ["c"]
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
