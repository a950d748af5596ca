"""report.html: every job writes one; it is self-contained; its 3D view holds the run's geometry (thinned
deterministically), the cameras' frusta and colourings that agree with the run's own figures. The page
in a real browser: tests/test_report_browser.py."""
from __future__ import annotations

import base64
import json
import re

import numpy as np
import pytest

from scope3d import phantoms
from scope3d.cli.main import main
from scope3d.io.ply import read_ply
from scope3d.report import ReportOptions, build_page, write_report
from scope3d.report.html import read_report_json
from scope3d.report.scene import gather_scene, scene_payload

MAP_FRAMES = 12  # the frames of conftest's small_dome_map


@pytest.fixture(scope="module")
def map_run(small_dome_map):
    return small_dome_map


@pytest.fixture(scope="module")
def axial_run(tmp_path_factory):
    seq = phantoms.generate("thread", "axial", seed=0, n_frames=4, size=(160, 160))
    dataset = phantoms.write(seq, tmp_path_factory.mktemp("thread") / "thread")
    return dataset, tmp_path_factory.mktemp("axial") / "run"


def _payload(page: str) -> dict:
    match = re.search(r'<script type="application/json" id="scene-data">(.*?)</script>', page, re.S)
    return json.loads(match.group(1).replace("<\\/", "</"))


def test_map_job_writes_a_self_contained_page(map_run):
    page = (map_run / "report.html").read_text()
    # nothing fetched at view time: no external scripts, styles or images, a CSP forbidding any
    assert not re.search(r'<(script|img|link|iframe)[^>]+(src|href)="(?!data:)', page)
    assert "default-src 'none'" in page
    assert not re.search(r'<a [^>]*href="https?:', page)
    # every picture of the run is inlined, every PLY is linked
    pngs = sorted(p.name for p in map_run.glob("*.png"))
    assert pngs and page.count("data:image/png;base64,") == len(pngs)
    for ply in map_run.glob("*.ply"):
        assert f'href="{ply.name}"' in page
    report = read_report_json(map_run)
    rows = re.search(r'<table id="targets">.*?<tbody>(.*?)</tbody>', page, re.S).group(1)
    assert report["targets"] and rows.count("<tr>") == len(report["targets"])


def test_the_view_holds_the_run_geometry_and_one_frustum_per_camera(map_run):
    report = read_report_json(map_run)
    scene = gather_scene(map_run, report, ReportOptions())
    names = [layer.name for layer in scene.layers]
    assert names == ["mesh.ply", "points.ply"]
    points = read_ply(map_run / "points.ply").points
    np.testing.assert_array_equal(scene.layers[1].positions, points)
    # 8 segments a camera (4 edges to the corners, 4 around the far rectangle), apex at each centre
    assert scene.frusta.shape == (8 * MAP_FRAMES, 2, 3)
    np.testing.assert_allclose(scene.frusta[0::8, 0], scene.trajectory, atol=1e-9)
    # colourings: height and error for both, texture (reflectance) and texture + fluorescence for the mesh
    assert set(scene.layers[0].colours) == {"height", "error", "texture", "multimodal"}
    assert set(scene.layers[1].colours) == {"height", "error", "texture"}


def test_error_colouring_measures_what_the_map_reports(map_run):
    """The view's per-point errors are distances to the true surface; on the sparse points they are the
    map's own "direct" figure, measured on a sampling of the truth (both sample it at the evaluation's
    step, so they agree to a fraction of it)."""
    report = read_report_json(map_run)
    scene = gather_scene(map_run, report, ReportOptions())
    errors = scene.layers[1].error_mm
    assert errors.mean() == pytest.approx(report["surface_error_mm"]["direct"]["mean"], abs=0.01)
    # the mesh is interpolated between the points: its median error stays within the points' p95
    assert np.median(scene.layers[0].error_mm) < report["surface_error_mm"]["direct"]["p95"]


def test_large_clouds_are_thinned_deterministically(map_run, tmp_path):
    options = ReportOptions(max_points=100, seed=3)
    first, second = build_page(map_run, options), build_page(map_run, options)
    assert first == second
    payload = _payload(first)
    counts = {layer["name"]: layer["count"] for layer in payload["layers"]}
    assert counts == {"mesh.ply": 100, "points.ply": 100}
    mesh = payload["layers"][0]
    assert mesh["faces"] is None and mesh["file_count"] > 100  # drawn as a thinned cloud of its vertices
    positions = np.frombuffer(base64.b64decode(mesh["positions"]), "<f4").reshape(-1, 3)
    truth = read_ply(map_run / "mesh.ply").vertices - np.array(payload["centre_mm"])
    # every drawn vertex is one of the file's (float32 rounding: 1e-5 mm at this scale)
    distances = np.min(np.linalg.norm(truth[None] - positions[:, None], axis=2), axis=1)
    assert distances.max() < 1e-5
    assert "100 of" in first and "seed 3" in first
    other = _payload(build_page(map_run, ReportOptions(max_points=100, seed=4)))
    assert other["layers"][0]["positions"] != mesh["positions"]


def test_axial_job_writes_a_page_and_json_on_stdout(axial_run, capsys):
    dataset, out = axial_run
    assert main(["axial", str(dataset), "--out", str(out), "--frames", "1", "2", "--json", "--quiet"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed == json.loads((out / "report.json").read_text())
    payload = _payload((out / "report.html").read_text())
    assert [layer["name"] for layer in payload["layers"]] == ["mesh.ply", "cloud.ply"]
    # no sparse model: the frusta come from the dataset's measured poses, one per frame
    assert len(np.frombuffer(base64.b64decode(payload["frusta"]), "<f4")) == 4 * 8 * 2 * 3


def test_report_command_and_bad_input(map_run, tmp_path, capsys):
    (map_run / "report.html").unlink()
    assert main(["report", str(map_run)]) == 0
    assert (map_run / "report.html").is_file()
    assert main(["report", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("scope3d report: error:") and "report.json" in err and err.count("\n") == 1
    (tmp_path / "report.json").write_text("{not json")
    assert main(["report", str(tmp_path)]) == 2
    assert not (tmp_path / "report.html").exists()


def test_the_page_is_written_even_without_its_dataset(map_run, tmp_path):
    """A run folder copied elsewhere, its dataset gone: the page has no frusta and no error colouring,
    and says why."""
    import shutil

    copy = tmp_path / "run"
    shutil.copytree(map_run, copy, ignore=shutil.ignore_patterns("sparse"))
    report = read_report_json(copy)
    report["dataset"] = str(tmp_path / "moved-away")
    (copy / "report.json").write_text(json.dumps(report))
    page = write_report(copy).read_text()
    payload = _payload(page)
    assert payload["frusta"] is None
    assert all("error" not in layer["colours"] for layer in payload["layers"])
    assert "not found" in page


def test_scene_payload_round_trips(map_run):
    report = read_report_json(map_run)
    scene = gather_scene(map_run, report, ReportOptions())
    payload = json.loads(json.dumps(scene_payload(scene)))
    centre = np.array(payload["centre_mm"])
    for layer, drawn in zip(scene.layers, payload["layers"]):
        positions = np.frombuffer(base64.b64decode(drawn["positions"]), "<f4").reshape(-1, 3)
        np.testing.assert_allclose(positions + centre, layer.positions, atol=1e-5)
        for mode, colours in layer.colours.items():
            assert np.frombuffer(base64.b64decode(drawn["colours"][mode]), np.uint8).tobytes() == colours.tobytes()
    assert len(payload["targets"]) == len(report["targets"])
