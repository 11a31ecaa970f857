"""Log lines (services/store/logs.py): one format for swpc's and uvicorn's lines, text or
JSON, the level and format from the settings or the flags, and ``swpc serve`` writing
them for real, its access log included, with no secret in them.
"""

from __future__ import annotations

import io
import json
import logging
import os
import re
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import httpx
import pytest
from pydantic import ValidationError

from services.config.settings import ServiceSettings
from services.store.logs import JsonFormatter, TextFormatter, event, formatter, journald_stream
from swpc_hw.sensors.zenoh_session import free_tcp_endpoint
from tests.service_rig import TOKEN

TIME = r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}[+-]\d\d:\d\d"
"""ISO 8601 with milliseconds and the UTC offset."""


def lines_of(fmt: logging.Formatter, emit: Any) -> list[str]:
    """What ``emit(logger)`` writes through a handler with ``fmt``."""
    buf = io.StringIO()
    h = logging.StreamHandler(buf)
    h.setFormatter(fmt)
    lg = logging.getLogger("swpc.test_logs")
    lg.addHandler(h)
    lg.setLevel(logging.DEBUG)
    try:
        emit(lg)
    finally:
        lg.removeHandler(h)
    return buf.getvalue().splitlines()


def install(lg: logging.Logger) -> None:
    event(
        lg, logging.INFO, "kinematics.install", run="r1", path="/var/lib/swpc/k.yaml",
        sha256="ab12", backup=None, time=3, ratio=0.125, ok=True,
    )  # fmt: skip


def test_text_lines_have_the_time_level_logger_and_message() -> None:
    out = lines_of(TextFormatter(), install)
    assert len(out) == 1
    m = re.fullmatch(rf"({TIME}) INFO swpc\.test_logs (.*)", out[0])
    assert m is not None, out
    assert m.group(2) == (
        "event=kinematics.install run=r1 path=/var/lib/swpc/k.yaml sha256=ab12 time=3 "
        "ratio=0.125 ok=true"
    )
    # under journald, which stamps every line itself: no time of ours
    out = lines_of(TextFormatter(timestamps=False), lambda lg: lg.warning("disk %s", "low"))
    assert out == ["WARNING swpc.test_logs disk low"]


def test_json_lines_carry_the_events_fields_as_keys() -> None:
    out = lines_of(JsonFormatter(), install)
    doc = json.loads(out[0])
    assert re.fullmatch(TIME, doc.pop("time"))
    assert doc == {
        "level": "INFO",
        "logger": "swpc.test_logs",
        "message": "kinematics.install",
        "run": "r1",
        "path": "/var/lib/swpc/k.yaml",
        "sha256": "ab12",
        "time_": 3,  # a field named as a key of every line keeps its value beside it
        "ratio": 0.125,
        "ok": True,
    }

    def plain(lg: logging.Logger) -> None:
        lg.info("a line with\nno fields")
        try:
            raise ValueError("boom")
        except ValueError:
            lg.exception("failed")
        event(lg, logging.ERROR, "x", value=float("nan"), where=Path("/a b"))

    a, b, c = (json.loads(line) for line in lines_of(JsonFormatter(), plain))
    assert a["message"] == "a line with\nno fields" and set(a) == {
        "time", "level", "logger", "message"
    }  # fmt: skip
    assert b["level"] == "ERROR" and b["message"] == "failed"
    assert b["traceback"].endswith("ValueError: boom")
    assert c["value"] == "nan" and c["where"] == "/a b"  # standard JSON, every value


def test_the_time_is_left_out_only_when_stderr_is_the_journal(tmp_path: Path) -> None:
    with (tmp_path / "journal").open("w") as journal, (tmp_path / "other").open("w") as other:
        st = os.fstat(journal.fileno())
        env = {"JOURNAL_STREAM": f"{st.st_dev}:{st.st_ino}"}
        assert journald_stream(env, journal)
        assert not journald_stream(env, other)  # the unit redirected stderr elsewhere
        assert not journald_stream({}, journal) and not journald_stream(
            {"JOURNAL_STREAM": "garbage"}, journal
        )
        assert isinstance(formatter("json", journal), JsonFormatter)  # JSON: always a time


def test_log_level_and_format_settings(tmp_path: Path) -> None:
    env = tmp_path / "swpc.env"
    env.write_text("SWPC_LOG_LEVEL=WARNING\nSWPC_LOG_FORMAT=json\n")
    s = ServiceSettings(_env_file=str(env))  # type: ignore[call-arg]
    assert (s.log_level, s.log_format) == ("warning", "json")
    assert ServiceSettings().log_level == "info" and ServiceSettings().log_format == "text"
    env.write_text("SWPC_LOG_LEVEL=loud\n")
    with pytest.raises(ValidationError, match="'debug', 'info', 'warning', 'error' or 'crit"):
        ServiceSettings(_env_file=str(env))  # type: ignore[call-arg]


def test_a_bad_log_level_is_an_argparse_error_naming_the_levels(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """It was a traceback: ValueError: Unknown level: 'FOO'."""
    from services.cli import main

    for flag, value, valid in (
        ("--log-level", "FOO", "'debug', 'info', 'warning', 'error', 'critical'"),
        ("--log-format", "xml", "'text', 'json'"),
    ):
        with pytest.raises(SystemExit) as exc:
            main(["serve", flag, value])
        assert exc.value.code == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert err[-1] == (
            f"swpc serve: error: argument {flag}: invalid choice: '{value.lower()}' "
            f"(choose from {valid})"
        ), err
        assert "Traceback" not in "\n".join(err)
    env = tmp_path / "swpc.env"
    env.write_text("SWPC_LOG_LEVEL=FOO\n")
    assert main(["serve", "--env-file", str(env), "--data-dir", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        "swpc serve: error: setting log_level: Input should be 'debug', 'info', 'warning', "
        "'error' or 'critical'"
    ]


def serve_log(tmp_path: Path, env_lines: list[str], flags: list[str]) -> list[str]:
    """``swpc serve`` in its own process: started, asked ``/health`` with the token in the
    query string (refused or not, uvicorn's access line names it), stopped; its stderr."""
    port = int(free_tcp_endpoint().rsplit(":", 1)[1])
    env_file = tmp_path / "swpc.env"
    env_file.write_text("\n".join([f"SWPC_TOKEN={TOKEN}", f"SWPC_PORT={port}", *env_lines]))
    env = {k: v for k, v in os.environ.items() if not k.startswith(("SWPC_", "JOURNAL_"))}
    err = tmp_path / "stderr.txt"
    with err.open("w") as fh:
        proc = subprocess.Popen(
            [sys.executable, "-m", "services.cli", "serve", "--env-file", str(env_file),
             "--data-dir", str(tmp_path / "data"), *flags],
            env=env, stdout=fh, stderr=fh,
        )  # fmt: skip
        try:
            deadline = time.monotonic() + 60
            url = f"http://127.0.0.1:{port}/health?token={TOKEN}"
            while True:
                try:
                    httpx.get(url, timeout=5)
                    break
                except httpx.TransportError:
                    pass
                assert proc.poll() is None, err.read_text()
                assert time.monotonic() < deadline, "the service did not start"
                time.sleep(0.1)
        finally:
            proc.terminate()
            assert proc.wait(30) in (0, -15), err.read_text()  # uvicorn re-raises SIGTERM
    text = err.read_text()
    assert TOKEN not in text
    return text.splitlines()


def test_swpc_serve_writes_every_line_in_one_text_format(tmp_path: Path) -> None:
    out = serve_log(tmp_path, [], [])
    line = re.compile(rf"{TIME} (DEBUG|INFO|WARNING|ERROR|CRITICAL) ([\w.]+) (.+)")
    assert all(line.fullmatch(x) for x in out), out
    loggers = {line.fullmatch(x).group(2) for x in out}  # type: ignore[union-attr]
    assert {"swpc.service", "uvicorn.error", "uvicorn.access"} <= loggers, out
    access = [x for x in out if " uvicorn.access " in x]
    assert len(access) == 1 and re.search(
        r' INFO uvicorn\.access 127\.0\.0\.1:\d+ - "GET /health\?token=\[redacted\] HTTP/1\.1" '
        r"(200|503)$",
        access[0],
    ), access
    assert any(" INFO swpc.service event=service.listen host=127.0.0.1 " in x for x in out)


def test_swpc_serve_json_from_the_env_file_its_level_from_the_flag(tmp_path: Path) -> None:
    # the env file says json and warning; the flag's info wins over the file's level
    out = serve_log(tmp_path, ["SWPC_LOG_FORMAT=json", "SWPC_LOG_LEVEL=warning"],
                    ["--log-level", "info"])  # fmt: skip
    docs = [json.loads(x) for x in out]  # every line one JSON object
    assert all(re.fullmatch(TIME, d["time"]) for d in docs)
    assert all({"time", "level", "logger", "message"} <= set(d) for d in docs)
    listen = [d for d in docs if d["message"] == "service.listen"]
    assert len(listen) == 1 and listen[0]["level"] == "INFO"
    assert listen[0]["host"] == "127.0.0.1" and isinstance(listen[0]["port"], int)
    (access,) = [d for d in docs if d["logger"] == "uvicorn.access"]
    assert access["method"] == "GET" and access["path"] == "/health?token=[redacted]"
    assert access["status"] in (200, 503) and access["client"].startswith("127.0.0.1:")
