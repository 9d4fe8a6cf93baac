"""The live view in a real browser: 50 simulated walkers move on /view, whose ellipses are the
API's tracks, drawn from the service's own origin only, without a console error, smoothly.

A real ``vlp serve`` runs with the demo room; ``vlp demo walkers`` posts 50 walkers through
the public API; headless Debian Chromium (as in ``test_swagger_ui.py``) opens ``/view``,
enters the key once, and the test reads the drawing back from the page.
"""

from __future__ import annotations

import math
import signal
import statistics
import subprocess
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from selenium import webdriver
from selenium.webdriver.chrome.service import Service
from selenium.webdriver.common.by import By
from selenium.webdriver.remote.webdriver import WebDriver
from selenium.webdriver.support.ui import WebDriverWait

from app.client import VLPClient
from tests.live_server import TERMINAL_KEY, VLP, LiveServer, live_server, server_env

from .test_swagger_ui import _FLAGS, CHROMEDRIVER, CHROMIUM, REPO

pytestmark = pytest.mark.slow

WALKERS = 50
WAIT_S = 120.0
FRAMES_PER_S = 20


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[LiveServer, str]]:
    with live_server(tmp_path_factory.mktemp("view"), VLP_DEMO="1") as live:
        with VLPClient(live.url, api_key=TERMINAL_KEY) as client:
            room_id = client.list_rooms().items[0].id
            client.wait_for_room(room_id, timeout_s=WAIT_S)
        yield live, room_id


@pytest.fixture(scope="module")
def browser(tmp_path_factory: pytest.TempPathFactory) -> Iterator[WebDriver]:
    if not (CHROMIUM.exists() and CHROMEDRIVER.exists()):
        subprocess.run([str(REPO / "scripts" / "ensure-chromium.sh")], check=True, timeout=900)
    options = webdriver.ChromeOptions()
    options.binary_location = str(CHROMIUM)
    for flag in _FLAGS:
        options.add_argument(
            flag if not flag.startswith("--window-size") else "--window-size=1400,1000"
        )
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    profile = tempfile.mkdtemp(dir=tmp_path_factory.mktemp("chromium"))
    options.add_argument(f"--user-data-dir={profile}")
    driver = webdriver.Chrome(service=Service(str(CHROMEDRIVER)), options=options)
    try:
        yield driver
    finally:
        driver.quit()


def _walkers(live: LiveServer, room_id: str) -> subprocess.Popen[bytes]:
    """Walkers posting until they are stopped (Ctrl-C: SIGINT), not for a fixed time the
    test would race."""
    command = [
        str(VLP),
        "demo",
        "walkers",
        "--count",
        str(WALKERS),
        "--room",
        room_id,
        "--seed",
        "5",
        "--url",
        live.url,
        "--key",
        TERMINAL_KEY,
        "--json",
    ]
    return subprocess.Popen(
        command, env=server_env(live.data_dir), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )


def _semi_axes(covariance: list[list[float]]) -> list[float]:
    eigenvalues = np.linalg.eigvalsh(np.array(covariance))
    return sorted(2.448 * math.sqrt(max(value, 0.0)) for value in eigenvalues)


def _drawn(driver: WebDriver) -> dict[str, dict[str, float]]:
    ellipses: list[dict[str, Any]] = driver.execute_script(
        "return [...document.querySelectorAll('#ellipses ellipse')].map(e => ({"
        "id: e.dataset.trackId, cx: +e.getAttribute('cx'), cy: +e.getAttribute('cy'),"
        "rx: +e.getAttribute('rx'), ry: +e.getAttribute('ry')}))"
    )
    return {e["id"]: e for e in ellipses}


def test_walkers_move_on_the_live_view(
    server: tuple[LiveServer, str], browser: WebDriver, tmp_path: Path
) -> None:
    live, room_id = server
    walkers = _walkers(live, room_id)
    try:
        browser.get(f"{live.url}/view")
        field = WebDriverWait(browser, WAIT_S).until(lambda d: d.find_element(By.ID, "key-input"))
        field.send_keys(TERMINAL_KEY)
        browser.find_element(By.CSS_SELECTOR, "#key-form button").click()
        WebDriverWait(browser, WAIT_S).until(lambda d: len(_drawn(d)) >= WALKERS)
        # Frames per second while 50 tracks move (the page counts its animation frames).
        readings = []
        for _ in range(5):
            time.sleep(1.05)
            readings.append(int(browser.execute_script("return window.vlpView.fps()")))
        events_before = int(browser.execute_script("return window.vlpView.events()"))
        assert statistics.median(readings) >= FRAMES_PER_S, readings
        browser.find_element(By.ID, "show-raw").click()
        # The page goes on receiving the walkers' updates.
        WebDriverWait(browser, WAIT_S).until(
            lambda d: int(d.execute_script("return window.vlpView.events()")) > events_before
        )
        walkers.send_signal(signal.SIGINT)
        assert walkers.wait(timeout=WAIT_S) == 0
    finally:
        if walkers.poll() is None:
            walkers.terminate()
            walkers.wait(timeout=30)

    with VLPClient(live.url, api_key=TERMINAL_KEY) as client:
        tracks = {t.id: t for t in client.list_tracks(room_id, limit=1000).items}
    assert len(tracks) == WALKERS

    def caught_up(driver: WebDriver) -> bool:
        shown = {
            t["id"]: t["updates"] for t in driver.execute_script("return window.vlpView.tracks()")
        }
        return all(shown.get(i) == t.updates for i, t in tracks.items())

    WebDriverWait(browser, WAIT_S).until(caught_up)
    drawn = _drawn(browser)
    width = 4.0  # the demo room: SVG y runs down from its far wall
    for track_id, track in tracks.items():
        ellipse = drawn[track_id]
        assert ellipse["cx"] == pytest.approx(track.x, abs=1e-9)
        assert ellipse["cy"] == pytest.approx(width - track.y, abs=1e-9)
        assert sorted((ellipse["rx"], ellipse["ry"])) == pytest.approx(
            _semi_axes(track.covariance), rel=1e-6, abs=1e-9
        )
    raws = browser.execute_script(
        "return document.querySelectorAll('#raws path:not(.hidden)').length"
    )
    assert raws == WALKERS

    loaded = browser.execute_script(
        "return performance.getEntriesByType('resource').map(entry => entry.name)"
    )
    assert any(url.endswith("/tracking/accuracy") for url in loaded)
    outside = [url for url in loaded if not url.startswith(live.url + "/")]
    assert not outside, outside
    log: list[dict[str, Any]] = browser.get_log("browser")  # type: ignore[attr-defined]  # Chrome only
    errors = [entry for entry in log if entry["level"] == "SEVERE"]
    assert not errors, errors
    browser.save_screenshot(str(tmp_path / "live-view.png"))
    assert (tmp_path / "live-view.png").stat().st_size > 10_000
