"""The phantom lab through real scopes' lenses (issue 32): `scope3d phantom --lens fisheye-140|barrel-70`
renders each pixel's ray through the lens model, writes camera.json of that model, vignettes and masks the
circular field, and its boards calibrate back to the lens."""
from __future__ import annotations

import json

import numpy as np
import pytest

from scope3d.cli.main import main
from scope3d.io.camera_json import read_camera_json
from scope3d.phantoms import generate
from scope3d.phantoms.lenses import LENSES
from scope3d.phantoms.render import RenderOptions, render_frame
from scope3d.phantoms.scenes import build_scene

DISTORTING = ("fisheye-140", "barrel-70")


@pytest.mark.parametrize("lens", DISTORTING)
def test_every_pixel_sees_the_surface_along_its_ray_through_the_lens(lens):
    seq = generate("dome", lens=lens, size=(96, 96), n_frames=2)
    camera = seq.camera
    assert camera.model == LENSES[lens].model and seq.scene_info["camera"]["lens"] == lens
    for pose, depth in zip(seq.true_poses, seq.depths):
        pixels = camera.pixel_grid()[np.isfinite(depth)]
        assert len(pixels) > 1000
        rays = camera.unproject(pixels)
        z = depth[np.isfinite(depth)].astype(float)
        # the ray the lens model gives the pixel, cast again: it meets the surface at the true depth
        hits = seq.scene.caster.cast(np.broadcast_to(pose.centre, rays.shape), rays @ pose.rotation)
        assert hits.hit.all()
        along = z / rays[:, 2]  # distance along the ray to the stored z-depth
        # the depth map is float32: half an ulp, 2^-24 relative, scaled alike by 1 / cos(theta)
        np.testing.assert_array_less(np.abs(hits.distance_mm - along), 2.0**-23 * along)


def test_the_fisheye_sees_140_degrees_across_its_black_bordered_circular_field():
    seq = generate("dome", lens="fisheye-140", size=(96, 96), n_frames=1)
    camera = seq.camera
    radius = camera.mask_radius_px
    edge = camera.unproject(np.array([[camera.cx + radius, camera.cy], [camera.cx, camera.cy - radius]]))
    np.testing.assert_allclose(np.rad2deg(np.arccos(edge[:, 2])), 70.0, atol=1e-9)
    assert camera.max_half_angle_rad > np.deg2rad(70.0)  # no fold inside the field
    outside = ~camera.mask()
    assert outside.any() and np.all(seq.frames[0][outside] == 0) and np.all(np.isnan(seq.depths[0][outside]))


@pytest.mark.parametrize("lens", DISTORTING)
def test_vignetting_dims_each_pixel_by_its_lens_law(lens):
    scene = build_scene("dome")
    seq = generate("dome", lens=lens, size=(96, 96), n_frames=1)
    camera, pose = seq.camera, seq.true_poses[0]
    quiet = RenderOptions(read_noise=0.0, shot_noise=0.0, fluorescence_noise=0.0)
    flat = render_frame(scene, camera, pose, options=quiet)  # auto-exposed: 1 % of the pixels saturate
    dim = render_frame(scene, camera, pose, exposure=flat.exposure,
                       options=RenderOptions(read_noise=0.0, shot_noise=0.0, fluorescence_noise=0.0,
                                             vignetting=LENSES[lens].vignetting)).image.astype(float)
    cos_theta = camera.unproject(camera.pixel_grid().reshape(-1, 2))[:, 2].reshape(camera.height, camera.width)
    flat = flat.image.astype(float)
    unsaturated = camera.valid_mask() & np.all(flat < 255, axis=-1)
    assert unsaturated.sum() > 0.5 * camera.valid_mask().sum()
    expected = flat * (cos_theta ** LENSES[lens].vignetting)[..., None]
    # both images quantised to 8 bits: one grey level apart at most
    assert np.max(np.abs(dim - expected)[unsaturated]) <= 1.0
    # and the lens's vignetting is what generate renders by default
    assert seq.scene_info["render"]["vignetting"] == LENSES[lens].vignetting


@pytest.mark.parametrize("lens,model", [("fisheye-140", "fisheye"), ("barrel-70", "opencv")])
def test_boards_rendered_through_the_lens_calibrate_back_to_it(tmp_path, lens, model):
    data = tmp_path / "data"
    assert main(["phantom", "dome", "--lens", lens, "--boards", "15", "--size", "304x304", "--frames", "1",
                 "--out", str(data), "--no-progress"]) == 0
    truth = read_camera_json(data / "camera.json")
    scene = json.loads((data / "ground_truth" / "scene.json").read_text())
    assert scene["boards"]["calibrate"].endswith(f"--model {model}")
    boards = sorted((data / "boards").glob("board_*.png"))
    assert len(boards) == 15
    out = tmp_path / "cal"
    assert main(["calibrate", *map(str, boards), "--board", "9x6", "--square", "2", "--model", model,
                 "--out", str(out), "--no-progress"]) == 0
    fitted = read_camera_json(out / "camera.json")
    assert fitted.model == truth.model
    report = json.loads((out / "report.json").read_text())
    std = np.array([report["intrinsics"][n]["std"] for n in fitted.param_names])
    # every parameter within 4 of its sigmas (a 1-in-16000 event per parameter for an honest sigma)
    assert np.all(np.abs(fitted.params - truth.params) < 4 * std), (fitted.params - truth.params) / std


def test_lens_refusals(tmp_path, capsys):
    assert main(["phantom", "dome", "--lens", "fisheye-140", "--fov", "90", "--out", str(tmp_path / "a")]) == 2
    assert "--fov sets the pinhole's field" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        main(["phantom", "dome", "--lens", "fisheye-200", "--out", str(tmp_path / "b")])
    assert exc.value.code == 2
    assert main(["phantom", "dome", "--raw-recording", "--lens", "barrel-70", "--out", str(tmp_path / "c")]) == 2
    assert "--lens and --boards apply to a dataset" in capsys.readouterr().err
    assert main(["phantom", "dome", "--boards", "-1", "--out", str(tmp_path / "d")]) == 2
    assert "number of board views must be zero or positive" in capsys.readouterr().err
    assert not any((tmp_path / name).exists() for name in "abcd")


def test_report_frusta_of_a_fisheye_stay_in_its_field():
    """The report's 3D view draws each camera to a z-depth: a fisheye's image corners lie past 90 deg, so its
    frustum's edges are cut where the lens sees, at most 75 deg from the axis (finite, in front)."""
    from scope3d.geometry.pose import Pose
    from scope3d.report.scene import camera_frusta

    camera = LENSES["fisheye-140"].camera(304, 304, fov_deg=53.0, mask_radius_px=150.0)
    segments = camera_frusta(camera, [Pose(np.eye(3), np.zeros(3))], 5.0)
    corners = segments[0::2, 1]  # centre -> corner edges
    assert np.all(np.isfinite(segments)) and np.allclose(corners[:, 2], 5.0)
    angle = np.arctan2(np.hypot(corners[:, 0], corners[:, 1]), corners[:, 2])
    assert np.all(angle <= np.deg2rad(75.0) + 1e-9) and np.all(angle > np.deg2rad(70.0))
