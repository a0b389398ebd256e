"""The live view's page in a real browser: Debian's headless Chromium driven by Selenium through the system
chromedriver (no browser download). During a short demo (5 simulated Crazyflies through cflib) the page draws
every drone, its table updates, the emergency stop asks for a confirmation, and "Land all" lands every drone.
A screenshot of the flight is taken; the test writes it in its own temporary folder, so that a test run leaves the
checkout as it found it. The README's picture is regenerated with

    LIVEVIEW_SCREENSHOT=results/liveview.png .venv/bin/python -m pytest tests/test_liveview_browser.py -k draws
"""
from __future__ import annotations

import os
import shutil
import threading
from pathlib import Path

import pytest

pytest.importorskip("cflib")
pytest.importorskip("aiohttp")

CHROMIUM = next((p for p in (shutil.which("chromium"), shutil.which("chromium-browser"), "/usr/bin/chromium")
                 if p and Path(p).is_file()), None)
CHROMEDRIVER = next((p for p in (shutil.which("chromedriver"), "/usr/bin/chromedriver")
                     if p and Path(p).is_file()), None)
if CHROMIUM is None or CHROMEDRIVER is None:
    pytest.skip("no chromium / chromedriver (apt-get install chromium chromium-driver)", allow_module_level=True)
webdriver = pytest.importorskip("selenium.webdriver")

from flight_fixtures import small_spec, wait_until, write_models  # noqa: E402
from groundstation.demo import DemoOptions, run_demo  # noqa: E402
from groundstation.liveview import LiveView  # noqa: E402
from test_liveview import post, tolerant_flight  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SCREENSHOT_ENV = "LIVEVIEW_SCREENSHOT"
"""Where the flight's screenshot goes (relative to the checkout); unset, the test's temporary folder."""
DOWN = {"landed", "lost"}
"""Statuses of a drone brought down: "lost" is one whose link timed out (its watchdog lands it), only seen when the
machine is so loaded that the ground station stalls."""


@pytest.fixture
def browser():
    from selenium.webdriver.chrome.service import Service
    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                "--window-size=1400,1300", "--disable-extensions"):
        opts.add_argument(arg)
    driver = webdriver.Chrome(service=Service(CHROMEDRIVER), options=opts)
    try:
        yield driver
    finally:
        driver.quit()


def test_page_draws_the_swarm_updates_and_lands_it(browser, tmp_path):
    from selenium.webdriver.common.by import By
    models = write_models(tmp_path / "models", small_spec(), seed=3)
    screenshot = ROOT / os.environ[SCREENSHOT_ENV] if os.environ.get(SCREENSHOT_ENV) else tmp_path / "liveview.png"
    box: dict = {}
    with LiveView(port=0) as view:
        def fly():
            try:
                box["result"] = run_demo(DemoOptions(duration=40.0, models=str(models), seed=6,
                                                     flight=str(tolerant_flight(tmp_path))), view=view)
            except BaseException as exc:  # handed to the test
                box["error"] = exc

        thread = threading.Thread(target=fly, name="demo", daemon=True)
        thread.start()
        try:
            browser.get(view.url)
            canvas = browser.find_element(By.ID, "arena")

            def statuses() -> list[str]:
                return [tr.get_attribute("data-status") for tr in browser.find_elements(By.CSS_SELECTOR,
                                                                                       "#drones tbody tr")]

            assert wait_until(lambda: statuses() == ["flying"] * 5 and canvas.get_attribute("data-drones") == "5",
                              timeout=60, period=0.2), (statuses(), box.get("error"))
            # the table updates: the positions change from one second to the next, frames keep coming
            cell = "#drones tbody tr[data-drone='cf0'] td:nth-child(10)"
            first, frames = browser.find_element(By.CSS_SELECTOR, cell).text, int(canvas.get_attribute("data-frames"))
            assert wait_until(lambda: browser.find_element(By.CSS_SELECTOR, cell).text != first, timeout=5,
                              period=0.1)
            assert wait_until(lambda: int(canvas.get_attribute("data-frames")) >= frames + 10, timeout=5, period=0.1)
            roles = {tr.find_elements(By.TAG_NAME, "td")[1].text
                     for tr in browser.find_elements(By.CSS_SELECTOR, "#drones tbody tr")}
            # "-": a drone whose actor was handed on (a role repair: on a loaded machine a link can time out)
            assert roles <= {"pursuer", "scout", "evader", "-"} and roles - {"-"}
            assert browser.find_elements(By.CSS_SELECTOR, "#metrics tr[data-metric='mean_avg_dist']")
            assert browser.find_elements(By.CSS_SELECTOR, "#events li")  # mission_start, roles_assigned, ...
            # the emergency stop asks first; cancel leaves everyone flying
            confirm = browser.find_element(By.ID, "estop-confirm")
            assert not confirm.is_displayed()
            browser.find_element(By.ID, "estop").click()
            assert wait_until(confirm.is_displayed, timeout=2, period=0.05)
            browser.find_element(By.ID, "estop-no").click()
            assert wait_until(lambda: not confirm.is_displayed(), timeout=2, period=0.05)
            screenshot.parent.mkdir(parents=True, exist_ok=True)
            assert browser.save_screenshot(str(screenshot))
            assert "stopped" not in statuses()  # cancelled: nothing was stopped
            # land all from the page
            browser.find_element(By.ID, "land-all").click()
            # every drone lands; one whose link timed out on a loaded machine ("lost") comes down on its watchdog
            assert wait_until(lambda: set(statuses()) <= DOWN, timeout=30, period=0.2), statuses()
            assert "landed" in statuses()
            thread.join(timeout=60)
            assert "error" not in box, box.get("error")
            assert box["result"]["landed"] == 5 and set(box["result"]["final_status"].values()) <= DOWN
            # the flight is over: the buttons are off
            assert wait_until(lambda: not browser.find_element(By.ID, "land-all").is_enabled(), timeout=5, period=0.1)
        finally:
            if thread.is_alive():
                post(view, "/api/land_all")
                thread.join(timeout=60)
    assert screenshot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_replay_bar_pauses_and_seeks(browser):
    """A made-up 10 s log of 3 drones circling, played into the page: its replay bar pauses and seeks, and the
    page shows no flight controls."""
    import math

    from selenium.webdriver.common.by import By

    from groundstation.liveview import scene
    from groundstation.positioning import AnchorLayout
    from groundstation.replay import ReplaySource
    from groundstation.safety import FenceConfig
    from runtime.spec import SwarmSpec
    rows = [{"t": 0.0, "event": "scene", "drone": None, "detail": "",
             "scene": scene(FenceConfig(), AnchorLayout(), SwarmSpec())}]
    roles = ("pursuer", "scout", "evader")
    for k in range(101):
        t = round(k * 0.1, 4)
        for i, role in enumerate(roles):
            a = 0.3 * t + 2 * math.pi * i / 3
            rows.append({"t": t, "drone": f"cf{i}", "role": role, "actor": f"{role}_0",
                         "state": "flying" if k < 100 else "landed", "position": [math.cos(a), math.sin(a), 0.6],
                         "setpoint": [0.0, 0.0, 0.0], "battery": 3.9, "link_quality": 1.0, "telemetry_age": 0.01})
    source = ReplaySource(rows, speed=1.0)
    with LiveView(port=0) as view:
        view.attach(source)
        browser.get(view.url)
        canvas = browser.find_element(By.ID, "arena")
        assert wait_until(lambda: canvas.get_attribute("data-drones") == "3", timeout=20, period=0.1)
        assert browser.find_element(By.ID, "replay").is_displayed()
        assert not browser.find_element(By.ID, "land-all").is_displayed()
        browser.find_element(By.ID, "replay-pause").click()
        assert wait_until(lambda: source.paused, timeout=5, period=0.05)
        assert wait_until(lambda: browser.find_element(By.ID, "replay-pause").text == "Play", timeout=5, period=0.05)
        browser.execute_script("const s = document.getElementById('replay-seek'); s.value = 7.5;"
                               "s.dispatchEvent(new Event('change'));")
        assert wait_until(lambda: browser.find_element(By.ID, "replay-time").text.startswith("7.5 /"), timeout=5,
                          period=0.05)
        cell = browser.find_element(By.CSS_SELECTOR, "#drones tbody tr[data-drone='cf0'] td:nth-child(10)").text
        x, y = math.cos(0.3 * 7.5), math.sin(0.3 * 7.5)
        assert cell == f"({x:.2f}, {y:.2f}, 0.60)"
        browser.execute_script("const s = document.getElementById('replay-seek'); s.value = 10;"
                               "s.dispatchEvent(new Event('change'));")
        assert wait_until(lambda: [tr.get_attribute("data-status") for tr in browser.find_elements(
            By.CSS_SELECTOR, "#drones tbody tr")] == ["landed"] * 3, timeout=5, period=0.05)
