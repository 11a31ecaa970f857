"""The swpc command's errors are one line and a non-zero exit: bad input, a data dir held by
another process, a CAN interface that cannot be opened, a port or zenoh endpoint in use.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap
import uuid
from pathlib import Path

import pytest

from tests.service_rig import (
    ROOT,
    TOKEN,
)


def test_cli_errors_are_one_line_with_a_nonzero_exit(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from services.cli import main
    from services.store.provenance import tool_version

    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0 and capsys.readouterr().out.startswith(f"swpc {tool_version()}")
    wiring = tmp_path / "wiring.yaml"
    wiring.write_text("swapped: [9]\n")
    cases = [
        (["serve", "--env-file", str(tmp_path / "none.env")], "--env-file", 2),
        (["sim", "--wiring", str(wiring), "--duration", "0.1"],
         "wiring.swapped: no module 9 (modules [1, 2, 3, 4])", 2),
        (["sim", "--channel", "swpcnone0", "--duration", "0.1"], "cannot open CAN interface", 2),
        (["can", "monitor", "--channel", "swpc-none", "--duration", "0.4", "--plain"],
         "no heartbeat from module 1 (node 1)", 1),
    ]  # fmt: skip
    for argv, what, code in cases:
        assert main(argv) == code, argv
        err = capsys.readouterr().err.strip().splitlines()
        mine = [line for line in err if line.startswith("swpc ")]
        assert len(mine) == 1 and what in mine[0], err  # one line, no traceback
        assert not any("Traceback" in line for line in err)
    with pytest.raises(SystemExit):
        main(["validate", "--help"])
    text = capsys.readouterr().out
    assert "``" not in text and ":mod:" not in text and "square" in text


HOLD_LOCK = textwrap.dedent(
    """
    import sys
    from pathlib import Path
    sys.path.insert(0, {root!r})
    from services.store.locks import DataDirLock

    DataDirLock(Path(sys.argv[1])).acquire()
    print("held", flush=True)
    sys.stdin.read()  # until the test closes our stdin
    """
)


def serve_error(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    """Run ``swpc serve`` in this process: it must return 2 with one line on stderr, the
    error (it was uvicorn's 29-50 line traceback and exit status 3)."""
    from services.cli import main

    assert main(["serve", "--port", "0", "--log-level", "warning", *argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("swpc serve: error: "), err
    return err[0]


def test_serve_on_a_data_dir_held_by_another_process_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("SWPC_TOKEN", TOKEN)
    monkeypatch.delenv("SWPC_CAN_INTERFACE", raising=False)
    data = tmp_path / "data"
    script = tmp_path / "hold.py"
    script.write_text(HOLD_LOCK.format(root=str(ROOT)))
    holder = subprocess.Popen(
        [sys.executable, str(script), str(data)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout is not None and holder.stdout.readline() == "held\n"
        line = serve_error(["--data-dir", str(data)], capsys)
        assert f"{data}: the data dir is in use by swpc serve pid {holder.pid}" in line
        # it stopped before writing anything there: no store, no token, no CAN log
        assert sorted(p.name for p in data.iterdir()) == [".lock"]
    finally:
        assert holder.stdin is not None
        holder.stdin.close()
        holder.wait(10)


def test_serve_with_a_can_interface_that_cannot_be_opened_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    from services.store.locks import ChannelLock, DataDirLock

    channel = f"swpc{uuid.uuid4().hex[:8]}"  # no such interface (its lock is host-wide)
    monkeypatch.setenv("SWPC_TOKEN", TOKEN)
    monkeypatch.setenv("SWPC_CAN_INTERFACE", "socketcan")
    monkeypatch.setenv("SWPC_CAN_CHANNEL", channel)
    line = serve_error(["--data-dir", str(tmp_path)], capsys)
    # no such interface here (or no CAN in the kernel): python-can's reason, on one line
    assert f"cannot open CAN bus interface='socketcan' channel='{channel}': " in line
    # what it had taken is given back: the data dir's lock and the channel's
    DataDirLock(tmp_path).acquire().release()
    ChannelLock("socketcan", channel).acquire().release()


def test_serve_on_a_port_or_zenoh_endpoint_in_use_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    import socket

    monkeypatch.setenv("SWPC_TOKEN", TOKEN)
    monkeypatch.delenv("SWPC_CAN_INTERFACE", raising=False)
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        line = serve_error(["--data-dir", str(tmp_path / "a"), "--port", str(port)], capsys)
        assert f"cannot listen on 127.0.0.1:{port}: Address already in use" in line
        monkeypatch.setenv("SWPC_ZENOH_LISTEN", f'["tcp/127.0.0.1:{port}"]')
        line = serve_error(["--data-dir", str(tmp_path / "b")], capsys)
        assert f"cannot open the zenoh session (listen=['tcp/127.0.0.1:{port}']): " in line
        assert "Address already in use" in line and ".rs:" not in line
    from services.store.locks import DataDirLock

    DataDirLock(tmp_path / "b").acquire().release()
