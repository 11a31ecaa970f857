"""The console's Commission view in a real browser (Debian's Chromium, headless, through
Selenium; the rig: :mod:`tests.browser.browser_rig`).

The service runs in this process on the in-process simulator, its hidden truth miswired
(module 2's wheel mounted the other way round), on a robot config file of the operator's.
An operator opens the view, reads what a commissioning needs, starts it (the token typed
in), follows it on the page, reads the finding and the corrected config as a difference,
and accepts it: the file is written only then, the one it replaced kept beside it.  Every
state is checked at the rig's windows for layout and contrast; screenshots
``21-commission`` (the report) and ``22-commission-accepted`` go to ``$SWPC_SCREENSHOTS``.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml
from pydantic import SecretStr

from services.config.settings import ServiceSettings
from services.http.app import create_app
from tests.browser.browser_rig import (
    browser,
    check_view,
    dialog_open,
    go,
    press,
    severe_logs,
    shot,
    text,
    wait_for,
)
from tests.service_rig import TOKEN, served

assert browser  # the fixture, imported for the tests below
from selenium.webdriver.common.by import By  # noqa: E402 - only with a browser at hand
from selenium.webdriver.common.keys import Keys  # noqa: E402
from selenium.webdriver.remote.webdriver import WebDriver  # noqa: E402

CONFIG = "robot: swpc\nlimits:\n  spin_torque: 0.6\n"


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    """The service on a simulator whose module 2 wheel turns the other way round."""
    work: Path = tmp_path_factory.mktemp("commission")
    (work / "wiring.yaml").write_text(
        yaml.safe_dump({"inverted": [{"module": 2, "axis": "wheel"}]})
    )
    robot, built = work / "robot.yaml", work / "built.yaml"
    robot.write_text(CONFIG)
    built.write_text(CONFIG)
    settings = ServiceSettings(
        data_dir=work / "data", token=SecretStr(TOKEN), robot_config=robot,
        sim_wiring=work / "wiring.yaml", sim_robot_config=built,
    )  # fmt: skip
    app = create_app(settings)
    with served(app) as (_srv, port):
        yield {"url": f"http://127.0.0.1:{port}", "robot": robot}


MODULE_ROWS_JS = """
return [...document.querySelectorAll("#com-module-rows tr")].map((r) =>
  [...r.querySelectorAll("th, td")].map((c) => c.innerText.trim()));
"""


def test_commission_a_miswired_robot_from_the_console_and_accept_the_fix(
    service: dict[str, Any], browser: WebDriver
) -> None:
    d, robot = browser, service["robot"]
    d.get(service["url"] + "/#run")
    wait_for("the event stream", lambda: text(d, "link-state") == "live")
    go(d, "commission")
    # what it needs, before anything moves
    intro = text(d, "view-commission")
    assert "on the floor" in intro and "motion capture" in intro and "Nothing is written" in intro
    assert d.find_element(By.ID, "com-empty").is_displayed()
    check_view(d, "commission, before")

    press(d, "com-start")  # no token yet: asked for, typed in
    wait_for("the token dialog", lambda: dialog_open(d, "token-dialog"))
    d.switch_to.active_element.send_keys(TOKEN + Keys.ENTER)
    run_id = wait_for("the commissioning on the page", lambda: text(d, "com-id"))
    assert d.current_url.endswith("#commission/" + run_id)
    wait_for("its progress", lambda: "module" in text(d, "com-state"), timeout=120)
    assert d.find_element(By.ID, "abort").is_displayed()  # the abort bar, as for any run
    verdict = wait_for("the report", lambda: "right" in (v := text(d, "com-verdict")) and v,
                       timeout=300)  # fmt: skip
    assert verdict == "Not right: 1 finding(s), 0 not known", verdict
    findings = text(d, "com-findings")
    assert "module 2's wheel rolls backwards" in findings and "polarity -1" in findings
    rows = d.execute_script(MODULE_ROWS_JS)
    assert [r[0] for r in rows] == ["1", "2", "3", "4"]
    assert [r[5] for r in rows] == ["as configured", "reversed", "as configured", "as configured"]
    assert [r[1] for r in rows] == ["1", "2", "3", "4"]  # each module's drives its own
    diff = text(d, "com-diff")
    assert "+polarity:" in diff and "wheel: -1" in diff, diff
    assert d.find_element(By.CSS_SELECTOR, "#com-diff span.add").is_displayed()
    assert robot.read_text() == CONFIG  # nothing written before the operator accepts
    check_view(d, "commission, the report")
    shot(d, "21-commission")

    press(d, "com-accept")  # asks first; cancel writes nothing
    wait_for("the confirmation", lambda: dialog_open(d, "confirm-dialog"))
    d.find_element(By.ID, "confirm-cancel").click()
    assert robot.read_text() == CONFIG
    press(d, "com-accept")
    wait_for("the confirmation", lambda: dialog_open(d, "confirm-dialog"))
    d.find_element(By.ID, "confirm-ok").click()
    accepted = wait_for("the answer", lambda: text(d, "com-accepted"))
    assert accepted.startswith(f"Written to {robot}"), accepted
    assert "In force now: commission again" in accepted  # polarity only: no restart
    doc = yaml.safe_load(robot.read_text())
    assert doc["polarity"] == {2: {"wheel": -1}} and doc["limits"] == {"spin_torque": 0.6}
    backups = sorted(robot.parent.glob("robot.yaml.*.bak"))
    assert [b.read_text() for b in backups] == [CONFIG]
    check_view(d, "commission, accepted")
    shot(d, "22-commission-accepted")
    assert severe_logs(d) == []
