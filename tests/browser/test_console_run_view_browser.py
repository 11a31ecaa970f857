"""The console's Run view in a real browser, on a service of its own: Debian's Chromium,
headless, through Selenium (the rig: :mod:`tests.browser.browser_rig`).

``make test-browser`` (not part of ``make test``).  Against ``swpc serve`` on the
in-process simulator (the rig's ``service``: a separate process on a free loopback port),
in order on one service and one browser: the live view still draws a module's path after
a module that ended before any of its path reached the page (fed synthetic live events),
a planned protocol is shown before Start and then runs (the token entered first, as an
operator does from the header), and Abort in a tab without the token stops the run at the
first press.  Screenshots ``14-plan`` and ``18-forecast`` go to ``$SWPC_SCREENSHOTS``.
The operator's calibration from start to install, its check and its history:
:mod:`tests.browser.test_console_browser`.  No browser here: skipped, or a failure where
one is required (see the rig).
"""

from __future__ import annotations

import time
from typing import Any

import httpx
import pytest

from tests.browser.browser_rig import (
    TOKEN,
    browser,
    check_view,
    dialog_open,
    enter_token,
    go,
    press,
    service,
    severe_logs,
    shot,
    text,
    wait_for,
    wait_state,
)

assert browser and service  # the fixtures, imported for the tests below
from selenium.webdriver.common.by import By  # noqa: E402 - only with a browser at hand
from selenium.webdriver.remote.webdriver import WebDriver  # noqa: E402


@pytest.fixture
def token_entered(service: dict[str, Any], browser: WebDriver) -> None:
    """The page opened afresh with the token entered (in
    :mod:`tests.browser.test_console_browser` its first test enters it, at the first
    Start)."""
    enter_token(browser, service["url"], TOKEN)


# --------------------------------------------------------------------------- tests


def test_a_module_with_no_path_yet_then_the_next(
    service: dict[str, Any], browser: WebDriver
) -> None:
    """The page drew nothing more, for the rest of a run, once a module ended before any
    of its path had reached the page (a busy host): the next one began from a point that
    was not there.  Fed the same two ``live`` events, it now draws the second path."""
    d = browser
    d.get(service["url"] + "/#run")
    wait_for("the event stream", lambda: text(d, "link-state") == "live")
    drawn = d.execute_script(
        """
        const live = (points) => ({ nodes: [], can: null, run: null, spins: [],
          mocap: { age_s: 0.01, stale: false, pose: [0, 0, 0] },
          trail: { run: "synthetic", reset: false, points } });
        swpc.current = { id: "synthetic", state: "SPIN", module: 1, modules_total: 4 };
        swpc.trail = { run: "synthetic", chunks: [] };
        onLive(live([]));
        swpc.current.module = 2;
        onLive(live([[0, 0], [0.1, 0], [0.1, 0.1]]));
        return [swpc.trail.chunks.map((c) => c.points.length),
                document.querySelectorAll("#live-view polyline").length];
        """
    )
    assert drawn == [[0, 3], 1]
    assert severe_logs(d) == []


@pytest.mark.usefixtures("token_entered")
def test_the_plan_is_shown_before_start_and_runs(
    service: dict[str, Any], browser: WebDriver
) -> None:
    """Ticking "Plan the protocol" shows the plan (docs/plan.md) before Start: its angles,
    sweep, predicted robot time and targets; Start then runs it."""
    d = browser
    go(d, "run")
    d.find_element(By.ID, "f-plan").click()
    assert text(d, "plan-text").startswith(("Planning", "Planned"))
    planned = wait_for(
        "the plan on the page", lambda: (t := text(d, "plan-text")).startswith("Planned") and t,
        timeout=600,
    )  # fmt: skip
    with httpx.Client(base_url=service["url"], timeout=10.0) as http:
        plan = http.get("/plan").json()
    assert f"{plan['robot_time_s']:.1f} s of robot time (predicted)" in planned
    assert f"{plan['protocol']['sweep_deg']:g} deg sweeps" in planned
    assert "Targets: position 0.5 mm, beta 0.2 deg, radius 0.2 mm; the square path within " \
        "0.5 mm, 0.016 deg" in planned
    # the form's own protocol settings are not used: greyed out, not left looking in force
    assert d.find_element(By.ID, "f-sweep").get_attribute("disabled") is not None
    assert d.find_element(By.ID, "f-angles").get_attribute("disabled") is not None
    check_view(d, "run, planned")
    shot(d, "14-plan")
    before = text(d, "run-id")
    d.find_element(By.ID, "start").click()
    run_id = wait_for("the new run on the page", lambda: (t := text(d, "run-id")) != before and t)
    assert text(d, "start-error") == ""
    # during a spin: the std devs forecast from the data so far, against the targets
    wait_for(
        "a spin judged by its forecast",
        lambda: "This spin ends once" in text(d, "forecast-note"), timeout=120,
    )  # fmt: skip
    wait_for(  # its rows are drawn anew at every live update: read until not stale
        "the forecast's rows",
        lambda: "mm" in text(d, "forecast-position") and "°" in text(d, "forecast-beta"),
    )  # fmt: skip
    assert text(d, "run-sweep").endswith("°")  # no "of 360°": the forecast ends the spin
    # the forecast table whole in every window (issue 45 item 6: it scrolled sideways and
    # its last column was cut at 800 px)
    check_view(d, "run, forecast")
    shot(d, "18-forecast")
    assert wait_state(d, {"DONE", "FAILED", "ABORTED"}, timeout=300) == "DONE"
    with httpx.Client(base_url=service["url"], timeout=10.0) as http:
        st = http.get(f"/calibrations/{run_id}").json()
    assert st["segments"] == 4 * len(plan["protocol"]["angles_deg"])
    # the forecast ends spins early: within the plan's predicted robot time (142 s; the
    # sequential runs through the service took 119-127 s, docs/figures.md)
    assert st["elapsed_s"] < plan["robot_time_s"]
    f = st["forecast"]  # the last judgement, as the page shows it
    wait_for("the last forecast", lambda: "After 8 spins" in text(d, "forecast-note"))
    row = wait_for("the radius row", lambda: text(d, "forecast-radius"))
    shown = [float(w) for w in row.split() if w.replace(".", "", 1).isdigit()]
    assert shown[0] == pytest.approx(f["radius_mm"], rel=5e-3), row  # forecast, target
    assert shown[1] == pytest.approx(f["targets"]["radius_mm"], rel=5e-3), row
    assert f["ratio"] <= 1.0
    d.find_element(By.ID, "f-plan").click()  # as the other tests left it
    assert text(d, "plan-text") == ""
    assert d.find_element(By.ID, "f-sweep").get_attribute("disabled") is None


def test_an_abort_from_a_tab_without_the_token_stops_at_the_first_press(
    service: dict[str, Any], browser: WebDriver
) -> None:
    """Issue 45, item 1: in a tab without the token, Abort opened the token dialog while
    the robot went on spinning (still spinning 3 s later), and Cancel let the run go on.
    Now the first press stops it: no dialog, the run ABORTED."""
    d = browser
    r = httpx.post(f"{service['url']}/calibrations", headers={"Authorization": f"Bearer {TOKEN}"},
                   json={"overrides": {"protocol": {"sweep_deg": 1440}}}, timeout=30)  # fmt: skip
    assert r.status_code == 202, r.text
    run_id = r.json()["id"]
    first = d.current_window_handle
    d.switch_to.new_window("tab")  # a tab of its own: no token in its sessionStorage
    try:
        d.get(service["url"] + "/")
        assert d.execute_script("return sessionStorage.getItem('swpc-token')") is None
        wait_for("the spin, in this tab", lambda: text(d, "run-state") == "SPIN", timeout=120)
        t = time.monotonic()
        press(d, "abort")
        assert wait_state(d, {"ABORTED", "FAILED", "DONE"}, timeout=30) == "ABORTED"
        took = time.monotonic() - t
        assert not dialog_open(d, "token-dialog")
        assert "aborted by the operator" in text(d, "run-reason")
        st = httpx.get(f"{service['url']}/calibrations/{run_id}", timeout=10).json()
        assert st["state"] == "ABORTED", st
        print(f"\nabort from a tab without the token: ABORTED on the page {took:.2f} s after "
              "the press")  # fmt: skip
    finally:
        d.close()
        d.switch_to.window(first)
