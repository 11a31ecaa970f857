"""schemathesis against the service's own OpenAPI schema: no 5xx, no schema violation.

The real service (``swpc serve`` on the in-process simulator, a separate process on a free
loopback port) is fuzzed with and without the bearer token.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Iterator
from http.cookiejar import DefaultCookiePolicy
from pathlib import Path
from typing import Any

import httpx
import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings
from schemathesis.checks import not_a_server_error
from schemathesis.specs.openapi.checks import (
    content_type_conformance,
    response_headers_conformance,
    response_schema_conformance,
    status_code_conformance,
)
from schemathesis.transport.requests import SameHostRedirectsSession

from swpc_hw.sensors.zenoh_session import free_tcp_endpoint
from tests.service_rig import TOKEN

#: no 5xx, and every response matches the schema (status code, content type, headers, body)
CHECKS = [
    not_a_server_error,
    status_code_conformance,
    content_type_conformance,
    response_headers_conformance,
    response_schema_conformance,
]


@pytest.fixture(scope="module")
def base_url(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    port = int(free_tcp_endpoint().rsplit(":", 1)[1])
    data: Path = tmp_path_factory.mktemp("schema")
    env = dict(
        os.environ,
        SWPC_TOKEN=TOKEN,
        SWPC_DATA_DIR=str(data),
        SWPC_PORT=str(port),
    )
    env.pop("SWPC_CAN_INTERFACE", None)
    log = (data / "service.log").open("w")
    proc = subprocess.Popen(
        [sys.executable, "-m", "services.cli", "serve", "--log-level", "warning"],
        env=env,
        stdout=log,
        stderr=subprocess.STDOUT,
    )
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                if httpx.get(f"{url}/health", timeout=2).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            assert proc.poll() is None, (data / "service.log").read_text()
            assert time.monotonic() < deadline, "service did not start"
            time.sleep(0.2)
        yield url
    finally:
        proc.terminate()
        proc.wait(timeout=20)
        log.close()
        assert proc.returncode in (0, -15), (data / "service.log").read_text()[-3000:]


@pytest.fixture(scope="module")
def operations(base_url: str) -> list[Any]:
    """The service's operations, from its schema: loaded and parsed once for both tests."""
    schema = schemathesis.openapi.from_url(f"{base_url}/openapi.json")
    return [op.ok() for op in schema.get_all_operations()]


def session() -> SameHostRedirectsSession:
    """schemathesis's own session for the calls (what it opens for each call without one),
    kept open: one keep-alive connection rather than a new one per call.  It keeps no
    cookies (the service sets none), so no call carries anything from another."""
    s = SameHostRedirectsSession()
    s.cookies.set_policy(DefaultCookiePolicy(allowed_domains=[]))
    return s


def fuzz(
    base_url: str, operations: list[Any], headers: dict[str, str], examples: int
) -> dict[str, int]:
    """Every operation, ``examples`` hypothesis-generated cases each (hypothesis tries the
    edges first: empty, missing and extreme values); returns how many calls per status."""
    statuses: dict[str, int] = {}
    http = session()
    for op in operations:

        @settings(max_examples=examples, deadline=None, suppress_health_check=list(HealthCheck))
        @given(case=op.as_strategy())
        def check(case: Any) -> None:
            response = case.call(base_url=base_url, headers=headers, session=http)
            key = f"{case.method} {case.path} {response.status_code}"
            statuses[key] = statuses.get(key, 0) + 1
            assert response.status_code < 500, (key, response.text)
            case.validate_response(response, checks=CHECKS)
            if case.path == "/calibrations" and response.status_code == 202:
                # keep fuzzing fast: a started run is aborted right away (motion stops)
                rid = response.json()["id"]
                r = httpx.post(f"{base_url}/calibrations/{rid}/abort", headers=headers, timeout=30)
                assert r.status_code in (200, 409), r.text

        check()
    http.close()
    codes = sorted({int(k.rsplit(" ", 1)[1]) for k in statuses})
    print(f"\nschemathesis: {sum(statuses.values())} calls, status codes {codes}")
    return statuses


def test_with_token(base_url: str, operations: list[Any]) -> None:
    statuses = fuzz(base_url, operations, {"Authorization": f"Bearer {TOKEN}"}, 12)
    assert any(k.startswith("POST /calibrations 202") for k in statuses), statuses
    assert any(k.endswith(" 422") for k in statuses), statuses


def test_without_token(base_url: str, operations: list[Any]) -> None:
    """Without the token every operation but the open ones answers 401 whatever the body:
    fewer cases say it."""
    statuses = fuzz(base_url, operations, {}, 5)
    assert any(k == "POST /calibrations 401" for k in statuses), statuses
    assert not any(k.startswith("POST /calibrations 202") for k in statuses), statuses
