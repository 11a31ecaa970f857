"""The fleet page in a real browser (headless Chromium through Selenium), as
``test_console_browser.py``: ``swpc fleet`` as the router on loopback, five simulated
robots (each a process with a real service runtime and the real publisher,
:mod:`tests.browser.fleet_robot`), one of them killed (SIGKILL): the page shows five
robots, one stale.  Screenshots to ``$SWPC_SCREENSHOTS`` (``fleet.png``,
``fleet-stale.png``); the JSON the page showed and the time from the kill to "stale" to
``fleet.json`` beside them.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from swpc_hw.sensors.zenoh_session import free_tcp_endpoint
from tests.browser.browser_rig import SHOTS, browser, check_view, shot, wait_for

assert browser  # the fixture, imported for the tests below
from selenium.webdriver.common.by import By  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
ROBOTS = [f"robot{i}" for i in range(1, 6)]


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    """``swpc fleet`` as the router (the shipped fleet-router.json5 on a loopback port),
    and five robots publishing through it."""
    data: Path = tmp_path_factory.mktemp("fleet")
    ep = free_tcp_endpoint()
    port = int(free_tcp_endpoint().rsplit(":", 1)[1])
    env = {k: v for k, v in os.environ.items() if not k.startswith("SWPC_")}
    logs = []
    procs: dict[str, subprocess.Popen[bytes]] = {}
    try:
        log = (data / "fleet.log").open("w")
        logs.append(log)
        procs["fleet"] = subprocess.Popen(
            [sys.executable, "-m", "services.cli", "fleet", "--port", str(port),
             "--data-dir", str(data / "store"), "--zenoh-mode", "router",
             "--zenoh-config", str(ROOT / "deploy/zenoh/fleet-router.json5"),
             "--zenoh-listen", ep, "--log-level", "warning"],
            env=env, stdout=log, stderr=subprocess.STDOUT, cwd=ROOT,
        )  # fmt: skip
        for k, name in enumerate(ROBOTS, start=1):
            log = (data / f"{name}.log").open("w")
            logs.append(log)
            procs[name] = subprocess.Popen(
                [sys.executable, "-m", "tests.browser.fleet_robot", str(data / name), name,
                 str(k), ep],
                env=env, stdout=log, stderr=subprocess.STDOUT, cwd=ROOT,
            )  # fmt: skip
        url = f"http://127.0.0.1:{port}"

        def live() -> bool:
            try:
                got = httpx.get(f"{url}/robots", timeout=2).json()
            except httpx.TransportError:
                got = []
            for name, p in procs.items():
                assert p.poll() is None, (data / f"{name}.log").read_text()
            return len(got) == 5 and all(r["status"] == "live" for r in got)

        wait_for("five robots live", live, timeout=120)
        yield {"url": url, "procs": procs}
    finally:
        for p in procs.values():  # each by its PID
            if p.poll() is None:
                p.terminate()
        for p in procs.values():
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        for log in logs:
            log.close()


def statuses(d: Any) -> dict[str, str]:
    out = {}
    for row in d.find_elements(By.CSS_SELECTOR, "#robot-rows tr[data-robot]"):
        chip = row.find_element(By.CSS_SELECTOR, "[data-status]")
        out[str(row.get_attribute("data-robot"))] = str(chip.get_attribute("data-status"))
    return out


def test_the_fleet_page_shows_five_robots_then_one_stale(
    service: dict[str, Any], browser: Any
) -> None:
    d = browser
    d.get(f"{service['url']}/#robot3")
    wait_for("five live rows", lambda: statuses(d) == dict.fromkeys(ROBOTS, "live"))
    drift_rows = "#drift-rows tr"
    wait_for("robot3's drift", lambda: len(d.find_elements(By.CSS_SELECTOR, drift_rows)) == 20)
    assert "robot3" in d.find_element(By.ID, "drift-robot").text
    row3 = d.find_element(By.CSS_SELECTOR, 'tr[data-robot="robot3"]').text
    assert "module 2 beta +2.000 deg" in row3
    # each robot's row links to its own console (issue 45 item 8)
    link = d.find_element(By.CSS_SELECTOR, 'tr[data-robot="robot3"] a.console-link')
    assert link.get_attribute("href") == "http://robot3.lab.invalid:8080/"
    before = httpx.get(f"{service['url']}/robots").json()
    # nothing clipped or scrolling sideways in any window, 800 px included (issue 45 item 8)
    check_view(d, "fleet")
    shot(d, "fleet")

    t0 = time.monotonic()
    service["procs"]["robot1"].send_signal(signal.SIGKILL)
    wait_for(
        "robot1 stale in the JSON",
        lambda: httpx.get(f"{service['url']}/robots/robot1").json()["status"] == "stale",
    )
    kill_to_stale = time.monotonic() - t0
    wait_for("robot1 stale on the page", lambda: statuses(d).get("robot1") == "stale")
    kill_to_page = time.monotonic() - t0
    got = statuses(d)
    assert got == {**dict.fromkeys(ROBOTS, "live"), "robot1": "stale"}
    row1 = d.find_element(By.CSS_SELECTOR, 'tr[data-robot="robot1"]').text
    assert "liveliness token" in row1
    # its health is its last word, not a state now
    assert "unknown now (last said " in row1, row1
    live = d.find_element(By.CSS_SELECTOR, 'tr[data-robot="robot2"]').text
    assert "unknown now" not in live, live
    assert "4 live, 1 stale" in d.find_element(By.ID, "fleet-counts").text
    shot(d, "fleet-stale")
    after = httpx.get(f"{service['url']}/robots").json()
    SHOTS.mkdir(parents=True, exist_ok=True)
    (SHOTS / "fleet.json").write_text(json.dumps({
        "kill_to_stale_json_s": round(kill_to_stale, 4),
        "kill_to_stale_page_s": round(kill_to_page, 3),
        "robots_before": before, "robots_after_kill": after,
    }, indent=1) + "\n")  # fmt: skip
    print(f"\nfleet page: robot1 stale {kill_to_stale * 1000:.0f} ms after SIGKILL (JSON), "
          f"{kill_to_page:.2f} s on the page")
