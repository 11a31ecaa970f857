"""The rig of the browser tests (``test_console_*browser.py``, ``test_fleet_browser.py``):
Debian's Chromium, headless, through Selenium (the ``browser`` fixture, one per module, on
the module's ``service``: ``test_console_browser.py`` and ``test_console_run_view_browser.py``
take theirs from here, :func:`service`, ``swpc serve`` with the token :data:`TOKEN`),
screenshots to ``$SWPC_SCREENSHOTS``, and the console page's helpers: its views, its
token, its start form, and :func:`check_view`, which checks a view in every window of
:data:`WIDTHS` for what a tablet in a bright lab needs: no sideways scrolling, nothing
clipped or drawn over something else, and every piece of text at a WCAG contrast of 4.5:1
at least (the lowest found is left in :data:`state`).

No browser here (``/usr/bin/chromium`` and ``/usr/bin/chromedriver``, Debian's
``chromium`` and ``chromium-driver``): the modules that import this one are skipped with a
message, except where one is required (``SWPC_BROWSER_REQUIRED=1``, as ``.ci/run`` sets,
or ``CI`` set): a failure.
"""

from __future__ import annotations

import base64
import io
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from PIL import Image

from swpc_hw.files.kinematic_file import save_kinematics
from swpc_hw.robot.paper_robot import PAPER_NOMINAL
from swpc_hw.sensors.zenoh_session import free_tcp_endpoint

CHROMIUM = Path(os.environ.get("SWPC_CHROMIUM", "/usr/bin/chromium"))
CHROMEDRIVER = Path(os.environ.get("SWPC_CHROMEDRIVER", "/usr/bin/chromedriver"))
SHOTS = Path(os.environ.get("SWPC_SCREENSHOTS", ".cache/browser"))
TABLET = (820, 1180)  # CSS px: a tablet in portrait
FLAGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
    "--disable-dev-shm-usage",
]  # fmt: skip

if not (CHROMIUM.exists() and CHROMEDRIVER.exists()):
    why = (
        f"no browser: {CHROMIUM} and {CHROMEDRIVER} are needed "
        "(Debian: apt-get install chromium chromium-driver)"
    )
    if os.environ.get("SWPC_BROWSER_REQUIRED") == "1" or os.environ.get("CI"):
        pytest.fail(f"{why}; required here (SWPC_BROWSER_REQUIRED or CI)", pytrace=False)
    pytest.skip(why, allow_module_level=True)

from selenium import webdriver  # noqa: E402 - only with a browser at hand
from selenium.common.exceptions import StaleElementReferenceException  # noqa: E402
from selenium.webdriver.chrome.service import Service  # noqa: E402
from selenium.webdriver.common.by import By  # noqa: E402
from selenium.webdriver.common.keys import Keys  # noqa: E402
from selenium.webdriver.remote.webdriver import WebDriver  # noqa: E402

state: dict[str, Any] = {}  # what one step leaves for the next (the tests run in order)
TOKEN = "browser-token-4711"
"""The bearer token of the console's service (:func:`service`)."""


@pytest.fixture(scope="module")
def browser(service: dict[str, Any]) -> Iterator[WebDriver]:
    opts = webdriver.ChromeOptions()
    opts.binary_location = str(CHROMIUM)
    for flag in FLAGS:
        opts.add_argument(flag)
    profile = tempfile.mkdtemp(prefix="swpc-chromium-")
    opts.add_argument(f"--user-data-dir={profile}")
    opts.add_argument(f"--window-size={TABLET[0]},{TABLET[1]}")
    opts.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    svc = Service(str(CHROMEDRIVER))
    driver = webdriver.Chrome(options=opts, service=svc)
    try:
        driver.set_window_size(*TABLET)
        yield driver
    finally:
        driver.quit()
        proc = svc.process
        if proc is not None and proc.poll() is None:  # chromedriver, by its PID
            proc.kill()
            proc.wait()
        shutil.rmtree(profile, ignore_errors=True)


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    """``swpc serve`` with a kinematic file in force: the nominal design (the console's
    tests, one per module that imports it: a separate process on a free loopback port, on
    the in-process simulator, with the token :data:`TOKEN`)."""
    data: Path = tmp_path_factory.mktemp("console")
    kin = data / "kinematics.yaml"
    save_kinematics(kin, PAPER_NOMINAL, created="2026-01-01T00:00:00Z")
    port = int(free_tcp_endpoint().rsplit(":", 1)[1])
    env = dict(os.environ, SWPC_TOKEN=TOKEN, SWPC_DATA_DIR=str(data), SWPC_PORT=str(port))
    for key in ("SWPC_CAN_INTERFACE", "SWPC_TIME_SCALE", "SWPC_ROBOT_CONFIG"):
        env.pop(key, None)
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
                if not httpx.get(f"{url}/health", timeout=2).json()["mocap_stale"]:
                    break
            except httpx.TransportError:
                pass
            assert proc.poll() is None, (data / "service.log").read_text()
            assert time.monotonic() < deadline, "service did not start"
            time.sleep(0.2)
        yield {"url": url, "data": data, "kin": kin}
    finally:
        proc.terminate()  # by its PID
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        log.close()


# ------------------------------------------------------------------------- helpers


def wait_for(what: str, cond: Callable[[], Any], timeout: float = 60.0) -> Any:
    deadline = time.monotonic() + timeout
    while True:
        try:
            got = cond()
        except StaleElementReferenceException:
            got = None
        if got:
            return got
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.05)


def text(d: WebDriver, elem_id: str) -> str:
    return str(d.find_element(By.ID, elem_id).text)


def shot(d: WebDriver, name: str) -> Path:
    """A screenshot of the whole page (not only the window) as ``<SHOTS>/<name>.png``."""
    SHOTS.mkdir(parents=True, exist_ok=True)
    m = d.execute_cdp_cmd("Page.getLayoutMetrics", {})
    size = m["cssContentSize"]
    clip = {"x": 0, "y": 0, "width": size["width"], "height": min(size["height"], 5000), "scale": 1}
    png = d.execute_cdp_cmd(
        "Page.captureScreenshot", {"format": "png", "captureBeyondViewport": True, "clip": clip}
    )
    path = SHOTS / f"{name}.png"
    # 256 colours: a third of the size, the page's flat colours unchanged to the eye
    image = Image.open(io.BytesIO(base64.b64decode(png["data"]))).convert("RGB")
    image.quantize(256, method=Image.Quantize.MEDIANCUT).save(path, optimize=True)
    return path


def css(d: WebDriver, selector: str) -> list[Any]:
    return list(d.find_elements(By.CSS_SELECTOR, selector))


def dialog_open(d: WebDriver, elem_id: str) -> bool:
    return d.find_element(By.ID, elem_id).get_attribute("open") is not None


def go(d: WebDriver, view: str) -> None:
    d.find_element(By.CSS_SELECTOR, f'nav a[data-view="{view}"]').click()
    wait_for(f"view {view}", lambda: d.find_element(By.ID, f"view-{view}").is_displayed())


def enter_token(d: WebDriver, url: str, token: str = TOKEN) -> None:
    """Open the console at ``url`` afresh and enter ``token`` as an operator does: the
    header's token button, then the token typed into its dialog and Enter'd (kept in the
    tab's ``sessionStorage`` from then on)."""
    d.get(url + "/")
    wait_for("the event stream", lambda: text(d, "link-state") == "live")
    d.find_element(By.ID, "token-button").click()
    wait_for("the token dialog", lambda: dialog_open(d, "token-dialog"))
    d.find_element(By.ID, "token-input").send_keys(token + Keys.ENTER)
    wait_for("the token set", lambda: text(d, "token-button") == "Token set ✓")


def press(d: WebDriver, elem_id: str) -> None:
    """Click a control in the middle of the window: the sticky abort bar is at its top
    while a run goes (an operator scrolls it there too)."""
    e = d.find_element(By.ID, elem_id)
    d.execute_script("arguments[0].scrollIntoView({block: 'center'})", e)
    e.click()


def set_field(d: WebDriver, elem_id: str, value: str) -> None:
    e = d.find_element(By.ID, elem_id)
    e.clear()
    e.send_keys(value)


def start_run(d: WebDriver, **fields: str) -> str:
    """Fill the start form and press Start; returns the new run's id (from the page)."""
    go(d, "run")
    details = d.find_element(By.CSS_SELECTOR, "#start-form details")
    if not details.get_attribute("open"):
        details.find_element(By.TAG_NAME, "summary").click()
    ids = {
        "sweep": "f-sweep",
        "settle": "f-settle",
        "stop": "f-stop",
        "align": "f-align",
        "resteer": "f-resteer",
        "angles": "f-angles",
    }
    for k, v in fields.items():
        if k == "install":
            d.find_element(By.CSS_SELECTOR, f'#f-install option[value="{v}"]').click()
        else:
            set_field(d, ids[k], v)
    before = text(d, "run-id")
    d.find_element(By.ID, "start").click()
    run_id = wait_for(
        "the new run on the page",
        lambda: ((t := text(d, "run-id")) != before and t) or text(d, "start-error"),
    )
    assert text(d, "start-error") == ""
    return str(run_id)


def wait_state(d: WebDriver, states: set[str], timeout: float = 180.0) -> str:
    return str(
        wait_for(f"state in {states}", lambda: (s := text(d, "run-state")) in states and s, timeout)
    )


def severe_logs(d: WebDriver) -> list[str]:
    return [e["message"] for e in d.get_log("browser") if e["level"] == "SEVERE"]


# WCAG 2 contrast of every visible piece of text against the background it is drawn on
# (background colours composited up the tree; disabled controls are exempt, as in WCAG)
CONTRAST_JS = """
const lin = (v) => { v /= 255; return v <= 0.03928 ? v / 12.92 : ((v + 0.055) / 1.055) ** 2.4; };
const lum = (c) => 0.2126 * lin(c[0]) + 0.7152 * lin(c[1]) + 0.0722 * lin(c[2]);
const rgba = (s) => {
  const p = s.match(/[\\d.]+/g).map(Number);
  return [p[0], p[1], p[2], p.length > 3 ? p[3] : 1];
};
const over = (top, under) => under.map((u, i) => top[i] * top[3] + u * (1 - top[3]));
function background(el) {
  const layers = [];
  for (let e = el; e; e = e.parentElement) {
    const c = rgba(getComputedStyle(e).backgroundColor);
    if (c[3] > 0) { layers.push(c); if (c[3] >= 1) break; }
  }
  return layers.reverse().reduce((under, top) => over(top, under), [255, 255, 255]);
}
const out = [];
for (const el of document.querySelectorAll("body *")) {
  if (el.closest("svg, [disabled], dialog:not([open])")) continue;
  const own = [...el.childNodes].some((n) => n.nodeType === 3 && n.textContent.trim());
  const shown = el.getClientRects().length && getComputedStyle(el).visibility === "visible";
  if (!own || !shown) continue;
  const bg = background(el), fg = over(rgba(getComputedStyle(el).color), bg);
  const [a, b] = [lum(fg), lum(bg)].sort((x, y) => y - x);
  const what = el.tagName + (el.id ? "#" + el.id : "") + " " + el.textContent.trim().slice(0, 30);
  out.push([(a + 0.05) / (b + 0.05), what]);
}
return out;
"""


# What is cut off or drawn over something else, at the window's size: every visible box
# that clips what it holds (overflow other than visible, or text-overflow: ellipsis) and
# holds more than it shows (scrollWidth over clientWidth), and every two visible boxes of
# the layout (not inline text runs, not taken out of the flow) side by side under one
# parent that overlap.  Form fields, SVG drawings and screen-reader-only text are left out.
LAYOUT_JS = """
const cls = (e) => (typeof e.className === "string" && e.className.trim()
  ? "." + e.className.trim().replace(/\\s+/g, ".") : "");
const name = (e) => e.tagName.toLowerCase() + (e.id ? "#" + e.id : "") + cls(e) +
  " '" + e.textContent.trim().replace(/\\s+/g, " ").slice(0, 40) + "'";
const shown = (e) => e.getClientRects().length > 0 && getComputedStyle(e).visibility === "visible";
const skip = (e) => e.closest("svg, .sr-only, input, select, textarea, dialog:not([open])");
const clipped = [], overlaps = [];
for (const e of document.querySelectorAll("body *")) {
  if (skip(e) || !shown(e)) continue;
  const cs = getComputedStyle(e);
  const clips = cs.overflowX !== "visible" || cs.textOverflow === "ellipsis";
  if (clips && e.scrollWidth > e.clientWidth + 1) {
    clipped.push(`${name(e)}: ${e.scrollWidth} px in ${e.clientWidth} px`);
  }
  const kids = [...e.children].filter((k) => !skip(k) && shown(k) &&
    getComputedStyle(k).display !== "inline" &&
    !["absolute", "fixed"].includes(getComputedStyle(k).position));
  const boxes = kids.map((k) => k.getBoundingClientRect());
  for (let i = 0; i < kids.length; i++) {
    for (let j = i + 1; j < kids.length; j++) {
      const a = boxes[i], b = boxes[j];
      const w = Math.min(a.right, b.right) - Math.max(a.left, b.left);
      const h = Math.min(a.bottom, b.bottom) - Math.max(a.top, b.top);
      if (w > 1 && h > 1) {
        overlaps.push(`${name(kids[i])} and ${name(kids[j])}: ${w.toFixed(0)}x${h.toFixed(0)} px`);
      }
    }
  }
}
return [clipped, overlaps];
"""

WIDTHS = [TABLET, (1280, 900), (1920, 1080), (800, 1200)]
"""The windows every view is checked in (CSS px): a tablet in portrait, two desktops, a
narrow window."""


def set_window(d: WebDriver, size: tuple[int, int]) -> None:
    """The page's viewport at exactly ``size`` CSS px (device metrics, no window chrome)."""
    d.execute_cdp_cmd(
        "Emulation.setDeviceMetricsOverride",
        {"width": size[0], "height": size[1], "deviceScaleFactor": 1, "mobile": False},
    )
    wait_for(f"a {size[0]} px window", lambda: d.execute_script("return innerWidth") == size[0])


def layout_problems(d: WebDriver) -> list[str]:
    """What is scrolled sideways, clipped or drawn over something else, at this size."""
    width = d.execute_script("return [document.documentElement.scrollWidth, innerWidth]")
    out = [] if width[0] <= width[1] else [f"page {width[0]} px wide in {width[1]} px"]
    clipped, overlaps = d.execute_script(LAYOUT_JS)
    return out + [f"clipped: {c}" for c in clipped] + [f"overlapping: {o}" for o in overlaps]


def check_view(d: WebDriver, view: str, shots: str | None = None) -> None:
    """In every window of :data:`WIDTHS`: nothing scrolls sideways, nothing is clipped
    or overlaps (:data:`LAYOUT_JS`), every text's contrast is 4.5:1 at least; with
    ``shots``, a screenshot ``<shots>-<width>`` at each desktop width (the tablet's is
    the caller's).  The window is the tablet's again afterwards."""
    found: dict[str, list[str]] = {}
    try:
        for size in WIDTHS:
            set_window(d, size)
            problems = layout_problems(d)
            contrast = d.execute_script(CONTRAST_JS)
            assert contrast, view
            worst = min(contrast)
            state["contrast"] = min(state.get("contrast", (99.0, ""))[0], worst[0]), worst[1]
            problems += [f"contrast {r:.2f} under 4.5: {what}" for r, what in contrast if r < 4.5]
            if problems:
                found[f"{size[0]}x{size[1]}"] = problems
            if shots and size != TABLET:
                shot(d, f"{shots}-{size[0]}")
    finally:
        set_window(d, TABLET)
    assert not found, f"{view}: " + json.dumps(found, indent=1)
