"""report.html in a real browser: Debian's chromium driven by chromedriver through selenium (``make test``
installs both with apt-get; no browser build is ever downloaded). Headless, no GPU: WebGL runs on
SwiftShader, Chromium's CPU renderer, which recent Chromium enables only when asked
(--use-angle=swiftshader --enable-unsafe-swiftshader; see docs/report.md)."""
from __future__ import annotations

import json
import time
from pathlib import Path

import cv2
import numpy as np
import pytest


CHROMIUM = Path("/usr/bin/chromium")
CHROMEDRIVER = Path("/usr/bin/chromedriver")
BROWSER_FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync",
                 "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--window-size=1280,1600")
# The viewer clears to rgb(0.07, 0.08, 0.1) * 255.
BACKGROUND_RGB = np.array([18, 20, 26])


@pytest.fixture(scope="module")
def run_dir(small_dome_map):
    return small_dome_map


@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    if not (CHROMIUM.is_file() and CHROMEDRIVER.is_file()):
        pytest.fail("chromium and chromium-driver are missing: `make test` installs them "
                    "(apt-get install chromium chromium-driver)")
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = str(CHROMIUM)
    for flag in BROWSER_FLAGS:
        options.add_argument(flag)
    options.add_argument(f"--user-data-dir={tmp_path_factory.mktemp('chromium-profile')}")
    options.set_capability("goog:loggingPrefs", {"browser": "ALL", "performance": "ALL"})
    # an explicit driver path: selenium's manager then looks nothing up and downloads nothing
    driver = webdriver.Chrome(service=Service(executable_path=str(CHROMEDRIVER)), options=options)
    try:
        yield driver
    finally:
        driver.quit()


def _open(browser, page: Path) -> None:
    browser.get_log("performance")  # drop what the browser's own start page requested (chrome://...)
    browser.get_log("browser")
    browser.get(page.resolve().as_uri())
    deadline = time.monotonic() + 30  # SwiftShader's first frame on a loaded 2-core machine
    while browser.execute_script("return document.body.getAttribute('data-viewer')") is None:
        if time.monotonic() > deadline:
            raise AssertionError("the viewer never drew a frame")
        time.sleep(0.1)


def _console_errors(browser) -> list[dict]:
    return [entry for entry in browser.get_log("browser") if entry["level"] == "SEVERE"]


def _requests(browser) -> list[str]:
    """URLs the page asked for since the last call (Chromium's network events)."""
    urls = []
    for entry in browser.get_log("performance"):
        message = json.loads(entry["message"])["message"]
        if message["method"] == "Network.requestWillBeSent":
            urls.append(message["params"]["request"]["url"])
    return urls


def test_the_checks_see_a_network_request_and_a_console_error(browser, tmp_path):
    """The offline checks below can fail: a page asking a (closed) loopback port for an image and logging
    an error is caught by both."""
    page = tmp_path / "leaky.html"
    page.write_text('<!DOCTYPE html><html><body data-viewer="ready"><img src="http://127.0.0.1:9/x.png">'
                    '<script>console.error("boom")</script></body></html>')
    _open(browser, page)
    time.sleep(0.5)
    assert "http://127.0.0.1:9/x.png" in _requests(browser)
    assert any("boom" in entry["message"] for entry in _console_errors(browser))


def _canvas_pixels(browser) -> np.ndarray:
    png = browser.find_element("id", "view").screenshot_as_png
    bgr = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    return bgr[..., ::-1]


def test_page_loads_offline_and_draws(browser, run_dir):
    _open(browser, run_dir / "report.html")
    assert browser.execute_script("return document.body.getAttribute('data-viewer')") == "ready"
    assert browser.execute_script("return document.body.getAttribute('data-layers-drawn')") == "2"
    assert _console_errors(browser) == []
    requests = _requests(browser)
    assert requests, "the performance log saw no request at all (not even the page itself)"
    assert [url for url in requests if not url.startswith(("file:", "data:"))] == []

    pixels = _canvas_pixels(browser)
    drawn = np.any(np.abs(pixels.astype(int) - BACKGROUND_RGB) > 12, axis=2)
    # the dome mesh, points, frusta and targets cover a good part of the view; a blank (or failed) WebGL
    # canvas is all background
    assert drawn.mean() > 0.05
    assert len(np.unique(pixels[drawn].reshape(-1, 3) // 16, axis=0)) > 20  # a colour scale, not one flat colour


def test_targets_table_has_one_row_per_target(browser, run_dir):
    _open(browser, run_dir / "report.html")
    report = json.loads((run_dir / "report.json").read_text())
    rows = browser.find_elements("css selector", "#targets tbody tr")
    assert report["targets"] and len(rows) == len(report["targets"])
    labels = [row.find_elements("css selector", "td")[0].text for row in rows]
    assert labels == [str(t["label"]) for t in report["targets"]]


def test_colouring_and_layer_controls_change_the_view(browser, run_dir):
    _open(browser, run_dir / "report.html")
    height = _canvas_pixels(browser)
    browser.find_element("css selector", "input[name=colouring][value=error]").click()
    time.sleep(0.5)
    error = _canvas_pixels(browser)
    assert np.mean(np.any(height != error, axis=2)) > 0.02
    assert browser.find_element("css selector", ".colour-scale[data-mode=error]").is_displayed()
    assert not browser.find_element("css selector", ".colour-scale[data-mode=height]").is_displayed()
    for box in browser.find_elements("css selector", "input[data-layer]"):
        box.click()
    browser.find_element("id", "show-frusta").click()
    browser.find_element("id", "show-targets").click()
    time.sleep(0.5)
    empty = _canvas_pixels(browser)
    assert np.mean(np.any(np.abs(empty.astype(int) - BACKGROUND_RGB) > 12, axis=2)) < 0.001


def test_a_run_without_geometry_still_loads_cleanly(browser, tmp_path):
    """A report.json and nothing else (a job that failed before writing its clouds): the page says so
    and the viewer draws an empty scene without a script error."""
    from scope3d.report import write_report

    (tmp_path / "report.json").write_text(json.dumps({"n_points": 0, "time_s": 0.5}))
    page = write_report(tmp_path)
    _open(browser, page)
    assert _console_errors(browser) == []
    assert browser.execute_script("return document.body.getAttribute('data-layers-drawn')") == "0"
    assert "no cloud or mesh" in browser.find_element("id", "view-section").text
