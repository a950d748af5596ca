"""2-D mosaic (registration.mosaic, ``scope3d mosaic``): global alignment against the true plane mapping."""
from __future__ import annotations

import json

import numpy as np
import pytest

from scope3d.cli.main import main
from scope3d.io.dataset import write_dataset
from scope3d.phantoms import generate, write
from scope3d.registration.mosaic import FrameLink, align_globally, frame_pixels, rectified_pixels
from scope3d.sensor.camera import Camera


@pytest.fixture(scope="module")
def sheet(tmp_path_factory):
    seq = generate("sheet", "grid5x6", size=(160, 160), n_frames=12)
    root = tmp_path_factory.mktemp("mosaic") / "sheet"
    write(seq, root)
    return seq, root


def test_mosaic_of_a_plane_matches_the_true_frame_to_mosaic_mapping(sheet, tmp_path):
    _, root = sheet
    assert main(["mosaic", str(root), "--out", str(tmp_path / "m"), "--no-progress"]) == 0
    report = json.loads((tmp_path / "m" / "report.json").read_text())
    assert report["n_registered"] == report["n_frames"] == 12
    # SIFT keypoints on these renders are good to ~0.3-0.5 px; frames up to 3 links from the reference
    # frame gather a random walk of that (sqrt(3) x 0.5 px), so 1 px mean and 2 px p95 bound a correct
    # global alignment, while a wrong pair or a chained drift would put frames off by tens of pixels.
    assert report["alignment_error_px"]["mean"] < 1.0
    assert report["alignment_error_px"]["p95"] < 2.0
    # A 2 x 6 raster with 2/3 overlap sweeps its hull with no holes but the rounded field's corners.
    assert report["coverage_fraction"] > 0.9
    for name in ("mosaic.png", "mosaic_path.png", "coverage.png"):
        assert (tmp_path / "m" / name).stat().st_size > 0


@pytest.mark.parametrize("lens", ["fisheye-140", "barrel-70"])
def test_mosaic_through_a_distorting_lens_matches_the_true_mapping_in_the_frames_own_pixels(lens, tmp_path):
    seq = generate("sheet", "grid5x6", size=(160, 160), n_frames=12, lens=lens)
    write(seq, tmp_path / "sheet")
    assert main(["mosaic", str(tmp_path / "sheet"), "--out", str(tmp_path / "m"), "--no-progress"]) == 0
    report = json.loads((tmp_path / "m" / "report.json").read_text())
    assert report["n_registered"] == report["n_frames"] == 12
    # the same bounds as the pinhole's, in each frame's own pixels, where SIFT's 0.3-0.5 px holds whatever
    # the lens (a rectified pixel of the fisheye's rim stands for up to 8.5 of its own)
    err = report["alignment_error_frame_px"]
    assert err["mean"] < 1.0 and err["p95"] < 2.0
    assert report["coverage_fraction"] > 0.9
    assert (tmp_path / "m" / "mosaic.png").stat().st_size > 0


def test_the_radial_path_of_the_mosaic_is_the_undistorted_pinhole_pixel():
    # rectified pixels of a pinhole without distortion are its own pixels; a fisheye's ray past 90 deg has none
    camera = generate("sheet", "grid5x6", size=(160, 160), n_frames=2).camera
    px = np.array([[3.0, 7.0], [80.0, 90.0], [150.0, 12.0]])
    np.testing.assert_allclose(rectified_pixels(camera, px), px, atol=1e-9)
    fisheye = Camera.from_params(200, 200, "OPENCV_FISHEYE", [60.0, 60.0, 99.5, 99.5, 0.0, 0.0, 0.0, 0.0])
    rays = np.array([[np.sin(a), 0.0, np.cos(a)] for a in np.deg2rad([10.0, 60.0, 95.0])])
    rect = rectified_pixels(fisheye, fisheye.project(rays))
    np.testing.assert_allclose(rect[:2, 0], 99.5 + 60.0 * np.tan(np.deg2rad([10.0, 60.0])), atol=1e-6)
    assert np.all(np.isnan(rect[2]))
    np.testing.assert_allclose(frame_pixels(fisheye, rect[:2]), fisheye.project(rays[:2]), atol=1e-6)


def test_mosaic_refuses_frames_without_overlap(sheet, tmp_path, capsys):
    seq, _ = sheet
    blank = np.full_like(seq.frames[0], 128)
    write_dataset(tmp_path / "ds", seq.camera, [seq.frames[0], blank], seq.measured_poses[:2], names=["a.png", "b.png"])
    assert main(["mosaic", str(tmp_path / "ds"), "--out", str(tmp_path / "m"), "--no-progress"]) == 2
    assert "without overlap" in capsys.readouterr().err
    assert not (tmp_path / "m").exists()
    with pytest.raises(ValueError, match="overlaps"):
        align_globally(3, [FrameLink(1, 2, np.zeros((20, 2)), np.zeros((20, 2)))], [(10, 10)] * 3)
