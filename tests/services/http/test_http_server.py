"""The real HTTP server (uvicorn with services.http.edge.server.GuardedH11) on a loopback port:
idle connections are closed and health still answers.
"""

from __future__ import annotations

import logging
import socket
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from pydantic import SecretStr

from services.config.settings import ServiceSettings
from services.http.app import create_app
from services.runtime.runtime import Runtime
from tests.service_rig import TOKEN, served


@pytest.fixture()
def server(tmp_path: Path) -> Iterator[tuple[str, int]]:
    app = create_app(
        ServiceSettings(data_dir=tmp_path, token=SecretStr(TOKEN)), runtime_factory=Runtime
    )
    with served(app, header_timeout=0.5) as (_srv, port):
        yield "127.0.0.1", port


def closed_by_peer(sock: socket.socket, within: float) -> bool:
    """The server closed ``sock`` within ``within`` host seconds (a guard: it may well
    be sooner)."""
    sock.settimeout(within)
    try:
        return sock.recv(1) == b""
    except TimeoutError:
        return False
    except ConnectionResetError:
        return True


def test_idle_connections_are_closed_and_health_still_answers(server: tuple[str, int]) -> None:
    host, port = server
    # 3 times the connection cap, silent or sending half a request head: each one held a
    # file descriptor for ever (256 of them: /health unanswered for 50 s)
    idle = []
    for i in range(24):
        s = socket.create_connection((host, port))
        if i % 2:
            s.sendall(b"GET /health HTTP/1.1\r\nHost: x\r\n")  # never finished
        idle.append(s)
        if i % 4 == 3:
            # answered in the middle of them too, on a new connection: the server accepts
            # in the order of connecting, so the ones before it are accepted by then and
            # the next four fit its listen backlog (the cap, 8; beyond it a SYN is
            # dropped and retried 1 s later, which was most of this test's time)
            assert httpx.get(f"http://{host}:{port}/health", timeout=20).status_code == 503
    r = httpx.get(f"http://{host}:{port}/health", timeout=20)
    assert r.status_code == 503  # answered (no robot here: failing)
    # every one of them is closed: the head timeout (0.5 s) or the cap (8)
    assert all(closed_by_peer(s, 20.0) for s in idle)
    for s in idle:
        s.close()
    # a client that sends its request in time is served, on a kept-alive connection too
    with httpx.Client(base_url=f"http://{host}:{port}", timeout=20) as c:
        assert c.get("/health").status_code == 503
        assert c.get("/kinematics").status_code == 404


def test_the_token_never_reaches_a_log(
    server: tuple[str, int], caplog: pytest.LogCaptureFixture
) -> None:
    """A token sent in the query string was refused (401) but uvicorn's access log wrote
    it down; so it did under ``?pw=``, ``?bearer=``, percent-encoded, or in the path."""
    host, port = server
    encoded = "".join(f"%{b:02X}" for b in TOKEN.encode())  # every character escaped
    caplog.set_level(logging.INFO, logger="uvicorn.access")
    with httpx.Client(base_url=f"http://{host}:{port}") as client:
        r = client.post(f"/calibrations?token={TOKEN}&x=1", json={})
        assert r.status_code == 401
        assert client.get("/health?access_token=s3cret-0123456789&run=abc").status_code in (
            200,
            503,
        )
        assert client.get(f"/calibrations/{TOKEN}").status_code == 404
        for query in (f"pw={TOKEN}", f"bearer={TOKEN}", "pw=an0ther-s3cret", f"q={encoded}",
                      f"%74oken={encoded.replace('%', '%25')}", "x=%0a200%20OK"):  # fmt: skip
            assert client.get(f"/health?{query}").status_code in (200, 503)
        assert client.get(f"/calibrations/{encoded}").status_code == 404
    lines = [r.getMessage() for r in caplog.records if r.name == "uvicorn.access"]
    assert len(lines) == 10, lines
    text = "\n".join(lines)
    assert TOKEN not in text and "s3cret" not in text and encoded not in text, text
    assert "token=[redacted]" in text and "run=abc" in text  # what is not secret stays
    assert "pw=[redacted]" in text and "bearer=[redacted]" in text
    assert "/calibrations/[redacted]" in text and "q=[redacted]" in text
    assert "x=\\x0a200 OK" in text and all("\n" not in line for line in lines)
