"""What the HTTP API checks before a route runs (services/http/guard.py): the bearer token
before the body is read, the body's size, standard JSON; tokens that are weak, missing or
printed; validation errors that always render; /docs without internet.
"""

from __future__ import annotations

import asyncio
import logging
import math
import re
import stat
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from pydantic import SecretStr

from services.config.settings import ServiceSettings
from services.http.app import create_app
from services.runtime.runtime import Runtime
from tests.service_rig import (
    AUTH,
    app_without_robot,
)


def asgi_post(
    app: Any, path: str, headers: dict[str, str], chunks: int, chunk: int = 1 << 20
) -> tuple[int, int]:
    """POST ``chunks`` chunks of ``chunk`` bytes (1 MiB) to ``app`` as a streamed body;
    returns (status, chunks read)."""
    pulled = 0
    status: list[int] = []

    async def receive() -> dict[str, Any]:
        nonlocal pulled
        pulled += 1
        return {"type": "http.request", "body": b"x" * chunk, "more_body": pulled < chunks}

    async def send(msg: dict[str, Any]) -> None:
        if msg["type"] == "http.response.start":
            status.append(msg["status"])

    scope = {
        "type": "http",
        "method": "POST",
        "path": path,
        "raw_path": path.encode(),
        "query_string": b"",
        "headers": [(k.lower().encode(), v.encode()) for k, v in headers.items()],
        "client": ("127.0.0.1", 1),
        "server": ("127.0.0.1", 8080),
        "scheme": "http",
        "http_version": "1.1",
        "root_path": "",
        "app": app,
    }
    asyncio.run(app(scope, receive, send))
    return status[0], pulled


def test_a_body_without_the_token_is_never_read_and_size_is_bounded(tmp_path: Path) -> None:
    app = app_without_robot(tmp_path)
    # 200 MiB with a wrong token: 401, not one chunk of the body read (it was all read and
    # parsed before the token was checked)
    assert asgi_post(app, "/calibrations", {"authorization": "Bearer wrong"}, 200) == (401, 0)
    assert asgi_post(app, "/calibrations", {}, 200) == (401, 0)
    # with the token, chunked: 413 after the first MiB over the 64 KiB limit
    assert asgi_post(app, "/calibrations", AUTH, 200) == (413, 1)
    # by its Content-Length: 413 before reading anything
    sized = {**AUTH, "content-length": str(200 << 20)}
    assert asgi_post(app, "/calibrations", sized, 200) == (413, 0)


def test_only_an_abort_passes_without_the_token_and_its_body_is_still_bounded(
    tmp_path: Path,
) -> None:
    """Stopping is never refused for want of a token (issue 45, item 1): an abort reaches
    its route without one (here 404: no such run); nothing else that changes anything
    does, not even a path that only looks like an abort."""
    app = app_without_robot(tmp_path)
    with TestClient(app) as client:  # the lifespan: the runtime the route asks
        for path in ("/calibrations/x1/abort", "/checks/x1/abort"):
            r = client.post(path)
            assert r.status_code == 404 and "x1" in r.text, (path, r.text)
    for path in ("/calibrations/x1/abort", "/checks/x1/abort"):
        assert asgi_post(app, path, {"content-length": str(200 << 20)}, 200) == (413, 0)
    for path in ("/calibrations/x1/abort/x", "/calibrations/x1/install", "/kinematics/rollback",
                 "/calibrations//abort", "/calibrations/abort"):  # fmt: skip
        assert asgi_post(app, path, {}, 1) == (401, 0), path


@pytest.mark.parametrize(
    "body",
    [
        '{"overrides":{"limits":{"watchdog_ms":Infinity}}}',
        '{"overrides":{"protocol":{"sweep_deg":NaN}}}',
        '{"overrides":{"limits":{"max_yaw_rate":-Infinity}}}',
        '{"overrides":{"limits":{"max_yaw_rate":1e400}}}',
        '{"overrides":{"limits":{"watchdog_ms":' + "9" * 5000 + "}}}",
        '{"overrides":' + "[" * 5000 + "]" * 5000 + "}",
    ],
    ids=["inf", "nan", "-inf", "1e400", "5000-digit int", "deep nesting"],
)
def test_non_standard_json_is_a_422_naming_it(tmp_path: Path, body: str) -> None:
    with TestClient(app_without_robot(tmp_path)) as client:
        r = client.post(
            "/calibrations", content=body, headers={**AUTH, "content-type": "application/json"}
        )
    assert r.status_code == 422, r.text
    detail = r.json()["detail"][0]
    assert detail["type"] == "json_invalid" and detail["loc"][0] == "body"
    assert any(w in detail["msg"] for w in ("NaN", "Infinity", "too large", "digits", "nesting"))


def test_a_validation_error_with_non_finite_input_renders(tmp_path: Path) -> None:
    """The service itself never renders NaN: a validation error about a non-finite value
    says what was sent, as a string (it was a 500 while rendering)."""
    from fastapi.exceptions import RequestValidationError

    app = app_without_robot(tmp_path)

    @app.get("/_probe")
    def probe() -> None:
        error = {"loc": ["body"], "msg": "bad", "type": "x", "input": math.inf}
        raise RequestValidationError([error])

    with TestClient(app) as client:
        r = client.get("/_probe")
    assert r.status_code == 422 and r.json()["detail"][0]["input"] == "inf"


@pytest.mark.parametrize(
    ("settings", "message"),
    [
        ({"token": SecretStr("change-me")}, "placeholder"),
        ({"token": SecretStr("")}, "empty"),
        ({"token": SecretStr("short-token")}, "at least 16"),
        ({"host": "0.0.0.0"}, "required when binding to 0.0.0.0"),
    ],
)
def test_weak_or_missing_tokens_are_refused(
    tmp_path: Path, settings: dict[str, Any], message: str
) -> None:
    from services.config.settings import SettingsError

    with pytest.raises(SettingsError, match=message):
        create_app(ServiceSettings(data_dir=tmp_path, **settings), runtime_factory=Runtime)


def test_a_generated_token_is_kept_private_and_never_printed(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.DEBUG)
    app = create_app(ServiceSettings(data_dir=tmp_path), runtime_factory=Runtime)
    token = app.state.token
    path = tmp_path / "api-token"
    assert path.read_text().strip() == token and len(token) >= 16
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    out = capsys.readouterr()
    assert token not in out.out + out.err + caplog.text
    # the same token after a restart
    again = create_app(ServiceSettings(data_dir=tmp_path), runtime_factory=Runtime)
    assert again.state.token == token


def test_docs_are_served_without_internet(tmp_path: Path) -> None:
    with TestClient(app_without_robot(tmp_path)) as client:
        for page, asset in (("/docs", "swagger-ui-bundle.js"), ("/redoc", "redoc.standalone.js")):
            html = client.get(page).text
            urls = [u for u in html.split('"') if u.startswith(("http://", "https://", "//"))]
            assert urls == [], urls  # nothing from a CDN (or fonts from Google)
            # every URL the page names (scripts, styles, the logo, the spec) is a path of
            # this service that answers
            refs = re.findall(r"""(?:src|href|spec-url)="([^"]*)"|url: '([^']*)'""", html)
            paths = {a or b for a, b in refs}
            assert {f"/docs/assets/{asset}", "/docs/assets/favicon.png", "/openapi.json"} <= paths
            for path in paths:
                assert path.startswith("/") and not path.startswith("//"), (page, path)
                assert client.get(path).status_code == 200, (page, path)
            assert client.get("/docs/assets/favicon.png").headers["content-type"] == "image/png"
            assert "x-logo" not in client.get("/openapi.json").json()["info"]  # ReDoc's logo
            js = client.get(f"/docs/assets/{asset}")
            assert js.status_code == 200 and len(js.content) > 500_000
        assert client.get("/docs/assets/swagger-ui.css").status_code == 200
        lic = client.get("/docs/assets/LICENSE").text
        assert "Apache License 2.0" in lic and "Permission is hereby granted" in lic


@pytest.mark.parametrize(
    ("host", "status"),
    [
        ("evil.example", 400),
        ("evil.example:8080", 400),
        ("localhost:8080", 200),
        ("127.0.0.1:8080", 200),
        ("[::1]:8080", 200),
        ("192.168.1.10", 200),
        ("robot.lab.example", 200),
    ],
)
def test_only_the_services_own_names_are_answered(tmp_path: Path, host: str, status: int) -> None:
    """A request with ``Host: evil.example`` read /kinematics and a run's dataset.zip: a
    page of another site, its name rebound to the robot's address, could read them."""
    app = app_without_robot(tmp_path, allowed_hosts=["robot.lab.example"])
    with TestClient(app) as client:
        r = client.get("/kinematics", headers={"host": host})
        got = r.status_code if r.status_code == 400 else 200  # 404: no file, but answered
        assert got == status, r.text
        if status == 400:
            assert "not a name of this service" in r.json()["detail"]
