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
# Waits below end when the page gets there; this only ends a page that never does. Nothing is timed: a
# deadline near the page's real time (30 s for SwiftShader's first frame) is a speed limit that a loaded
# machine can miss (issue 31).
HANG_S = 600.0


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
    _wait_for(lambda: browser.execute_script("return document.body.getAttribute('data-viewer')") is not None,
              "the viewer never drew a frame")


def _wait_for(condition, what: str) -> None:
    deadline = time.monotonic() + HANG_S
    while not condition():
        assert time.monotonic() < deadline, what
        time.sleep(0.1)


def _drawn(browser) -> None:
    """Return once the page has drawn what the last action asked for: the viewer redraws on the next
    animation frame (requestAnimationFrame), so two frames requested now run after that draw, whatever
    the machine's speed (a fixed 0.5 s pause is a guess that a loaded machine's draw can outlast)."""
    browser.set_script_timeout(HANG_S)
    browser.execute_async_script("var done = arguments[arguments.length - 1];"
                                 "requestAnimationFrame(function () { requestAnimationFrame(done); });")


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
    requests, errors = [], []

    def both_seen():
        requests.extend(_requests(browser))
        errors.extend(_console_errors(browser))
        return "http://127.0.0.1:9/x.png" in requests and any("boom" in entry["message"] for entry in errors)

    _wait_for(both_seen, f"requests {requests}, console errors {errors}")


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
    _drawn(browser)
    error = _canvas_pixels(browser)
    assert np.mean(np.any(height != error, axis=2)) > 0.02
    assert browser.find_element("css selector", ".colour-scale[data-mode=error]").is_displayed()
    assert not browser.find_element("css selector", ".colour-scale[data-mode=height]").is_displayed()
    for box in browser.find_elements("css selector", "input[data-layer]"):
        box.click()
    browser.find_element("id", "show-frusta").click()
    browser.find_element("id", "show-targets").click()
    _drawn(browser)
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


@pytest.fixture(scope="module")
def panorama_run(tmp_path_factory):
    """A panorama run folder drawn from the truth of a small bladder phantom (what is under test is the
    page's explorer and texture, not the reconstruction): the true wall as mesh.ply and, textured from the
    frames, as wall.obj, the true cameras as sparse/."""
    from scope3d.io.colmap import SparseModel, write_colmap_text
    from scope3d.io.dataset import load_dataset
    from scope3d.io.obj import write_textured_obj
    from scope3d.io.ply import write_ply
    from scope3d.mvs.texturing import texture_mesh
    from scope3d.phantoms import generate, write
    from scope3d.report import write_report

    root = tmp_path_factory.mktemp("explorer")
    write(generate("bladder", size=(128, 128), n_frames=12), root / "bladder")
    dataset = load_dataset(root / "bladder")
    run = root / "run"
    run.mkdir()
    write_ply(run / "mesh.ply", dataset.ground_truth.surface())
    textured = texture_mesh(dataset.ground_truth.surface(), np.zeros(3), dataset.camera, dataset.ground_truth.poses,
                            dataset.frame)
    write_textured_obj(run / "wall.obj", textured.mesh.vertices, textured.mesh.faces, textured.uv, textured.face_uv,
                       textured.image)
    write_colmap_text(SparseModel([dataset.camera], dataset.names, dataset.ground_truth.poses, points3d=np.zeros((0, 3))),
                      run / "sparse")
    (run / "report.json").write_text(json.dumps({"job": "panorama", "dataset": str(root / "bladder")}))
    write_report(run)
    return run, dataset


def _truly_seeing(dataset, point: np.ndarray, margin_px: float) -> set[str]:
    """Frames whose true camera sees ``point`` (mm, on the true wall): inside the image (and its circular
    field) by ``margin_px`` (negative: outside by up to that much), and nothing of the wall in between
    (a ray cast from the camera's centre first meets the wall at the point)."""
    import trimesh

    mesh = dataset.ground_truth.surface()
    caster = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    seen = set()
    for name, pose in zip(dataset.names, dataset.ground_truth.poses):
        uv = dataset.camera.project_world(pose, point[None])
        if not dataset.camera.in_image(uv, margin_px=margin_px)[0]:
            continue
        ray = point - pose.centre
        distance = np.linalg.norm(ray)
        hits, _, _ = caster.ray.intersects_location([pose.centre], [ray / distance])
        first = np.linalg.norm(hits - pose.centre, axis=1).min() if len(hits) else np.inf
        if first > distance - 0.01:  # 0.01 mm: the float32 the page holds positions in, at ~50 mm
            seen.add(name)
    return seen


def test_clicking_the_panorama_lists_the_frames_that_really_see_the_spot(browser, panorama_run):
    """Seen from inside the cavity, a click on the wall lists exactly the frames whose TRUE camera sees that
    spot (ray cast against the true wall), each with its picture and the spot's pixel."""
    from selenium.webdriver.common.action_chains import ActionChains

    run, dataset = panorama_run
    _open(browser, run / "report.html")
    assert browser.find_element("id", "inside-view").is_selected()
    assert _console_errors(browser) == []
    canvas = browser.find_element("id", "view")
    pixels = _canvas_pixels(browser)
    height, width = pixels.shape[:2]
    css_w, css_h = canvas.size["width"], canvas.size["height"]
    checked = 0
    for fx, fy in [(fx, fy) for fy in (0.1, 0.3, 0.5, 0.7, 0.9) for fx in (0.1, 0.3, 0.5, 0.7, 0.9)]:
        if not np.any(np.abs(pixels[int(fy * height), int(fx * width)].astype(int) - BACKGROUND_RGB) > 12):
            continue  # no wall drawn there
        ActionChains(browser).move_to_element_with_offset(canvas, (fx - 0.5) * css_w, (fy - 0.5) * css_h) \
            .click().perform()
        picked = json.loads(browser.execute_script("return document.body.getAttribute('data-picked')"))
        assert picked is not None, "a click on the drawn wall picked nothing"
        point = np.array(picked["point_mm"])
        listed = set(picked["frames"])
        # within 1 px of the image's edge a float32 position may fall either side: those frames may go
        # either way; every other frame must be listed if and only if its true camera sees the spot
        assert _truly_seeing(dataset, point, 1.0) <= listed <= _truly_seeing(dataset, point, -1.0)
        pictures = browser.find_elements("css selector", "#explorer-frames figure img")
        assert len(pictures) == len(listed)
        for name, uv in zip(picked["frames"], picked["pixels"]):
            k = dataset.names.index(name)
            truth = dataset.camera.project_world(dataset.ground_truth.poses[k], point[None])[0]
            assert np.linalg.norm(np.array(uv) - truth) < 0.05  # float32 positions: ~1e-5 mm at 50 mm
        checked += len(listed) >= 2
    assert checked >= 2, "fewer than two clicks found a spot seen by two frames or more"


def test_the_panorama_wall_is_drawn_with_its_texture(browser, panorama_run):
    """The textured wall (wall.obj, drawn instead of mesh.ply) is what "texture" shows: its atlas decoded
    and drawn (the tissue's colours, the atlas's), unlike the height colouring."""
    run, _ = panorama_run
    _open(browser, run / "report.html")
    _wait_for(lambda: browser.execute_script("return document.body.getAttribute('data-textures-loaded')") == "1",
              "the atlas was never uploaded")
    _drawn(browser)  # the redraw the upload asked for
    assert browser.find_element("css selector", "input[name=colouring][value=texture]").is_selected()
    assert "wall.obj" in browser.find_element("id", "view-section").text
    assert "mesh.ply" not in browser.find_element("id", "view-section").text  # the same wall, once
    browser.find_element("id", "show-frusta").click()  # the wall alone: no frusta's lines
    _drawn(browser)
    textured = _canvas_pixels(browser).astype(float)
    browser.find_element("css selector", "input[name=colouring][value=height]").click()
    _drawn(browser)
    height = _canvas_pixels(browser).astype(float)
    drawn = np.any(np.abs(textured - BACKGROUND_RGB) > 12, axis=2)
    assert drawn.mean() > 0.5  # seen from inside, the wall fills the view
    # the phantom's mucosa (albedo 0.90, 0.66, 0.58) and its vessels are mostly red-dominant (some are blue);
    # turbo's scale is not. The wall no frame saw is grey (R = G = B), left out.
    grey = (np.abs(textured[..., 0] - textured[..., 1]) < 8) & (np.abs(textured[..., 1] - textured[..., 2]) < 8)
    red = (textured[..., 0] > textured[..., 1]) & (textured[..., 0] > textured[..., 2])
    assert (drawn & ~grey).mean() > 0.3
    assert red[drawn & ~grey].mean() > 0.8
    # the colours drawn are the atlas's: their chromaticity (r, g over r + g + b: the viewer's shading scales
    # all three alike) has the atlas's median within 0.02; the height colouring's is elsewhere
    atlas = cv2.imread(str(run / "wall.png"))[..., ::-1].astype(float).reshape(-1, 3)
    atlas = atlas[np.abs(atlas - 128).max(axis=1) > 8]  # the texels frames filled (unseen ones are grey 128)

    def chroma(rgb):
        return np.median(rgb[:, :2] / np.maximum(rgb.sum(axis=1, keepdims=True), 1), axis=0)
    assert np.abs(chroma(textured[drawn & ~grey]) - chroma(atlas)).max() < 0.02
    assert np.abs(chroma(height[drawn]) - chroma(atlas)).max() > 0.05
