"""The console's Drives view in a real browser (Debian's Chromium, headless, through
Selenium; the rig: :mod:`tests.browser.browser_rig`).

The service runs in this process (on the in-process simulator, behind the real HTTP
server) so that the test can reach into the virtual robot: it opens the view before any
run (each module axis on its configured node, liveness unknown), watches the same table
turn alive as a run brings the drives up (the page's live events, no reload), then injects
a fault on module 2's wheel and reads it on the page: the row stands out, the error named.
Every state is checked at the rig's four windows for layout and contrast; screenshots
``19-drives`` (a run) and ``20-drives-fault`` go to ``$SWPC_SCREENSHOTS``.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from pydantic import SecretStr

from firmware_protocol.codec import Axis, ErrorFlag
from services.config.settings import ServiceSettings
from services.http.app import create_app
from tests.browser.browser_rig import browser, check_view, severe_logs, shot, text, wait_for
from tests.service_rig import SHORT, TOKEN, served, start, wait_spinning

assert browser  # the fixture, imported for the tests below
from selenium.webdriver.common.by import By  # noqa: E402 - only with a browser at hand
from selenium.webdriver.remote.webdriver import WebDriver  # noqa: E402


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    """The service on the in-process simulator behind the real server, in this process."""
    data: Path = tmp_path_factory.mktemp("drives")
    app = create_app(ServiceSettings(data_dir=data, token=SecretStr(TOKEN)))
    with served(app) as (_srv, port):
        yield {"url": f"http://127.0.0.1:{port}", "rt": app.state.runtime}


TABLE_JS = """
return [...document.querySelectorAll("#drive-rows tr[data-axis]")].map((r) =>
  [r.dataset.axis, r.className, [...r.querySelectorAll("th, td")].map((c) => c.innerText.trim())]);
"""


def table(d: WebDriver) -> dict[str, list[str]]:
    """The Drives table as shown: ``"<module>.<axis>"`` -> its cells' text, read at once
    (the page draws it anew at every live update)."""
    return {axis: cells for axis, _cls, cells in d.execute_script(TABLE_JS)}


def standing_out(d: WebDriver) -> list[str]:
    """The rows drawn to stand out (class ``bad``)."""
    return [axis for axis, cls, _cells in d.execute_script(TABLE_JS) if "bad" in cls.split()]


def test_the_drives_view_idle_alive_and_a_fault(
    service: dict[str, Any], browser: WebDriver
) -> None:
    d, url, rt = browser, service["url"], service["rt"]
    d.get(url + "/#drives")
    wait_for("the event stream", lambda: text(d, "link-state") == "live")
    rows = wait_for("the drives' rows", lambda: len(t := table(d)) == 8 and t)
    # before any run: each axis on the node the robot config gives its module (swpc's
    # dual-axis controllers: nodes 1..4), liveness unknown (the simulator's time stands
    # still between runs), as GET /drives says
    doc = httpx.get(url + "/drives", timeout=10).json()
    assert list(rows) == [f"{a['module']}.{a['axis']}" for a in doc["axes"]]
    assert [r[:3] for r in rows.values()] == [
        [f"{m} {axis}", str(m), "unknown"] for m in (1, 2, 3, 4) for axis in ("steer", "wheel")
    ]
    assert all(r[6] == "none" for r in rows.values())
    assert d.find_element(By.ID, "drv-unwatched").is_displayed()
    summary = text(d, "drv-summary")
    assert summary == (
        f"swpc drives on virtual:{rt.can_channel} · driver inactive · 8 axes: liveness "
        "unknown · no fault"
    )
    assert "swpc drives scan" in text(d, "view-drives")
    check_view(d, "drives, idle")

    # a run brings the drives up: the same table turns alive, pushed to the page
    with httpx.Client(base_url=url, timeout=30) as http:
        run_id = start(http, SHORT)  # type: ignore[arg-type]
        wait_spinning(http, run_id, guard=120)  # type: ignore[arg-type]

    def all_alive() -> dict[str, list[str]] | None:
        t = table(d)
        return t if t and all(r[2] == "yes" and r[4] == "ENABLED" for r in t.values()) else None

    rows = wait_for("every drive alive and enabled on the page", all_alive, timeout=60)
    ages = [int(r[3].split(" ms ago")[0]) for r in rows.values()]
    loss_ms = 1000 * rt.drives.config.loss_after_s
    assert all(0 <= a < loss_ms for a in ages), (ages, loss_ms)
    assert [rows[f"{m}.steer"][7] for m in (1, 2, 3, 4)] == ["yes"] * 4  # homed
    assert [rows[f"{m}.wheel"][7] for m in (1, 2, 3, 4)] == ["n/a"] * 4
    # spinning about module 1: its wheel held, the others' driven by torque
    assert [rows[f"{m}.wheel"][5] for m in (1, 2, 3, 4)] == ["HOLD"] + ["TORQUE"] * 3
    assert not d.find_element(By.ID, "drv-unwatched").is_displayed()
    assert "driver active · 8 axes: 8 alive · no fault" in text(d, "drv-summary")
    check_view(d, "drives, a run")
    shot(d, "19-drives")
    print(f"\ndrives view during a run: heartbeat ages {min(ages)}-{max(ages)} ms")

    # a drive's fault: its row stands out, the error named; the run stopped on it
    rt.simulator.inject_fault(2, Axis.WHEEL, ErrorFlag.OVER_TEMPERATURE)
    wait_for("the fault on the page", lambda: standing_out(d) == ["2.wheel"], timeout=60)
    rows = table(d)
    assert rows["2.wheel"][6] == "FAULT: OVER_TEMPERATURE (0x0080)"
    assert rows["2.wheel"][4] == "FAULT"
    assert all(r[6] == "none" for k, r in rows.items() if k != "2.wheel")
    wait_for("the stop on the page", lambda: "driver inactive" in text(d, "drv-summary"))
    assert "· 1 in fault · last stopped on: module 2 (node 2) axis 1 (wheel): fault " \
        "OVER_TEMPERATURE" in text(d, "drv-summary")
    state = wait_for("the run's end", lambda: (st := httpx.get(
        f"{url}/calibrations/{run_id}", timeout=10).json())["state"] == "FAILED" and st)
    assert "OVER_TEMPERATURE" in state["reason"], state
    background = d.execute_script(
        "return getComputedStyle(document.querySelector('tr[data-axis=\"2.wheel\"]'))"
        ".backgroundColor"
    )
    assert background == "rgb(253, 231, 234)"
    check_view(d, "drives, a fault")
    shot(d, "20-drives-fault")
    assert severe_logs(d) == []
