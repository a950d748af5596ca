"""COLMAP text models: our writer read back by pycolmap and by our reader; reader errors; import."""
from pathlib import Path

import numpy as np
import pycolmap  # the reference reader; a declared "peers" dependency, installed in CI
import pytest

from scope3d.cli.main import main
from scope3d.errors import InputError
from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import look_at, rotation_angle_between
from scope3d.io.colmap import SparseModel, import_colmap, read_colmap_text, write_colmap_text
from scope3d.io.dataset import load_dataset
from scope3d.io.images import write_image
from scope3d.sensor.camera import Camera


def _model(seed=0) -> SparseModel:
    """4 cameras on a ring 80 mm around 30 points near the origin; every point seen by 2-4 images."""
    rng = np.random.default_rng(seed)
    cameras = [
        Camera(64, 48, 60.0, 60.0, 31.7, 23.2, k1=-0.12, k2=0.03),   # fx == fy -> RADIAL
        Camera(64, 48, 58.0, 61.5, 32.1, 24.4, k1=0.05, k2=-0.01),   # fx != fy -> OPENCV
    ]
    poses = []
    for j in range(4):
        centre = 80.0 * np.array([np.cos(0.4 * j), 0.1, np.sin(0.4 * j)])
        poses.append(Pose.from_centre(look_at(centre, np.zeros(3)), centre))
    image_cameras = np.array([0, 1, 0, 1])
    points = rng.uniform(-5, 5, (30, 3))
    obs_img, obs_pt, obs_px = [], [], []
    for i, p in enumerate(points):
        seen_by = rng.choice(4, size=rng.integers(2, 5), replace=False)
        for j in sorted(seen_by):
            obs_img.append(j)
            obs_pt.append(i)
            obs_px.append(cameras[image_cameras[j]].project_world(poses[j], p[None])[0])
    errors = rng.uniform(0.1, 1.0, 30)
    errors[3] = np.nan
    return SparseModel.from_observations(
        cameras, [f"img_{j:02d}.png" for j in range(4)], poses, points, obs_img, obs_pt, obs_px,
        image_cameras=image_cameras, colors=rng.integers(0, 256, (30, 3)), errors=errors,
    )


def _same_camera(a: Camera, b: Camera) -> None:
    # The +-0.5 px shift of the principal point may cost one rounding (1e-14 px).
    assert (a.width, a.height, a.mask_radius_px) == (b.width, b.height, b.mask_radius_px)
    np.testing.assert_allclose(a.intrinsics, b.intrinsics, rtol=0, atol=1e-12)


def test_pycolmap_reads_our_model(tmp_path):
    model = _model()
    write_colmap_text(model, tmp_path / "sparse")
    rec = pycolmap.Reconstruction(str(tmp_path / "sparse"))
    assert (rec.num_cameras(), rec.num_images(), rec.num_points3D()) == (2, 4, 30)
    assert [rec.cameras[i].model.name for i in (1, 2)] == ["RADIAL", "OPENCV"]
    np.testing.assert_allclose(rec.cameras[1].params, [60.0, 32.2, 23.7, -0.12, 0.03])
    np.testing.assert_allclose(rec.cameras[2].params, [58.0, 61.5, 32.6, 24.9, 0.05, -0.01, 0, 0])
    for j in range(4):
        image = rec.images[j + 1]
        assert image.name == model.image_names[j] and image.camera_id == model.image_cameras[j] + 1
        np.testing.assert_allclose(image.cam_from_world().matrix(), model.poses[j].matrix[:3], atol=1e-12)
    for i in range(30):
        point = rec.points3D[i + 1]
        np.testing.assert_allclose(point.xyz, model.points3d[i], atol=1e-12)
        np.testing.assert_array_equal(point.color, model.colors[i])
        assert point.error == pytest.approx(-1.0 if i == 3 else model.errors[i])
        track = sorted((e.image_id - 1, e.point2D_idx) for e in point.track.elements)
        assert track == sorted(map(tuple, model.tracks[i].tolist()))


def test_pycolmap_projects_like_scope3d_up_to_the_half_pixel(tmp_path):
    """COLMAP's pixel origin is the image corner, ours the top-left pixel's centre: +0.5 px exactly."""
    model = _model()
    write_colmap_text(model, tmp_path / "sparse")
    rec = pycolmap.Reconstruction(str(tmp_path / "sparse"))
    for j in range(4):
        image = rec.images[j + 1]
        ours = model.cameras[model.image_cameras[j]].project_world(model.poses[j], model.points3d)
        for i in range(0, 30, 7):
            np.testing.assert_allclose(image.project_point(model.points3d[i]), ours[i] + 0.5, atol=1e-9)
        # the stored keypoints are where the points project, in COLMAP's convention
        for k, p2d in enumerate(image.points2D):
            assert p2d.has_point3D()
            np.testing.assert_allclose(p2d.xy, image.project_point(rec.points3D[p2d.point3D_id].xyz), atol=1e-9)


def test_our_reader_round_trips_our_writer(tmp_path):
    model = _model()
    write_colmap_text(model, tmp_path / "sparse")
    back = read_colmap_text(tmp_path / "sparse")
    assert back.image_names == model.image_names
    for a, b in zip(back.cameras, model.cameras, strict=True):
        _same_camera(a, b)
    np.testing.assert_array_equal(back.image_cameras, model.image_cameras)
    for a, b in zip(back.poses, model.poses):
        np.testing.assert_allclose(a.matrix, b.matrix, atol=1e-12)
    np.testing.assert_array_equal(back.points3d, model.points3d)
    np.testing.assert_array_equal(back.colors, model.colors)
    np.testing.assert_array_equal(back.errors, model.errors)  # NaN stays NaN
    for a, b in zip(back.observations(), model.observations()):
        np.testing.assert_allclose(a, b, atol=1e-12)


def test_reader_reads_pycolmap_output(tmp_path):
    write_colmap_text(_model(), tmp_path / "ours")
    rec = pycolmap.Reconstruction(str(tmp_path / "ours"))
    (tmp_path / "theirs").mkdir()
    rec.write_text(str(tmp_path / "theirs"))
    a, b = read_colmap_text(tmp_path / "ours"), read_colmap_text(tmp_path / "theirs")
    assert a.image_names == b.image_names
    for x, y in zip(a.cameras, b.cameras, strict=True):
        _same_camera(x, y)
    np.testing.assert_allclose(a.points3d, b.points3d)
    for x, y in zip(a.observations(), b.observations()):
        np.testing.assert_allclose(np.sort(x, axis=0), np.sort(y, axis=0), atol=1e-12)


def test_model_scale_converts_to_mm(tmp_path):
    write_colmap_text(_model(), tmp_path / "m")
    back = read_colmap_text(tmp_path / "m", length_scale_to_mm=1000.0)
    np.testing.assert_allclose(back.points3d, 1000.0 * _model().points3d)
    np.testing.assert_allclose(back.poses[2].centre, 1000.0 * _model().poses[2].centre)


def test_sparse_model_rejects_inconsistent_tracks():
    cam = Camera(10, 10, 5.0, 5.0, 4.5, 4.5)
    with pytest.raises(ValueError, match="does not exist"):
        SparseModel([cam], ["a.png"], [Pose.identity()], points3d=[[0, 0, 1]], tracks=[[[0, 0]]])
    with pytest.raises(ValueError, match="two tracks"):
        SparseModel([cam], ["a.png"], [Pose.identity()], points3d=[[0, 0, 1], [0, 0, 2]],
                    keypoints=[[[1, 1]]], tracks=[[[0, 0]], [[0, 0]]])


# --- reader errors: file and line ------------------------------------------------------------------


@pytest.fixture
def sparse(tmp_path):
    return write_colmap_text(_model(), tmp_path / "sparse")


def _replace_line(path: Path, number: int, text: str) -> None:
    lines = path.read_text().splitlines()
    lines[number - 1] = text
    path.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize(
    "file, line, text, fragments",
    [
        ("cameras.txt", 4, "1 SIMPLE_RADIAL_FISHEYE 64 48 60 32 24 0.1", ["cameras.txt line 4", "not supported"]),
        ("cameras.txt", 5, "2 OPENCV 64 48 58 61 32 24 0.05 0 nan 0", ["cameras.txt line 5", "NaN"]),
        ("cameras.txt", 4, "1 RADIAL 64 48 60 32 24 0.1", ["cameras.txt line 4", "5 parameters, found 4"]),
        ("images.txt", 5, "1 1.1 0 0 0 0 0 0 1 img_00.png", ["images.txt line 5", "not unit"]),
        ("images.txt", 5, "1 0 0 0 0 0 0 0 1 img_00.png", ["images.txt line 5", "not unit", "norm 0"]),
        # beyond the rounding of a quaternion printed to 3 or more digits (norm within 1e-3 of 1)
        ("images.txt", 7, "2 1.002 0 0 0 0 0 0 2 img_01.png", ["images.txt line 7", "not unit", "1.002"]),
        ("images.txt", 5, "1 1 0 0 0 0 nan 0 1 img_00.png", ["images.txt line 5", "NaN"]),
        ("images.txt", 5, "1 1 0 0 0 0 0 0 7 img_00.png", ["images.txt line 5", "camera 7"]),
        ("images.txt", 6, "1.5 2.5", ["images.txt line 6", "triples"]),
        ("points3D.txt", 4, "1 0 0 0 1 2 3 0.5 9 0", ["points3D.txt line 4", "image 9"]),
        ("points3D.txt", 4, "1 0 0 0 1 2 3 0.5 1 999", ["points3D.txt line 4", "2D point 999"]),
    ],
)
def test_reader_errors_name_file_and_line(sparse, file, line, text, fragments):
    _replace_line(sparse / file, line, text)
    with pytest.raises(InputError) as info:
        read_colmap_text(sparse)
    for f in fragments:
        assert f in str(info.value), str(info.value)


def test_reader_needs_cameras_and_images_but_not_points(sparse):
    (sparse / "points3D.txt").unlink()
    assert len(read_colmap_text(sparse).points3d) == 0
    (sparse / "images.txt").unlink()
    with pytest.raises(InputError, match="images.txt: file is missing"):
        read_colmap_text(sparse)


def test_reader_can_skip_the_points(sparse):
    full = read_colmap_text(sparse)
    _replace_line(sparse / "points3D.txt", 4, "1 0 0 0 1 2 3 0.5 9 0")  # a broken point is not even read
    cameras_only = read_colmap_text(sparse, points=False)
    assert len(cameras_only.points3d) == 0 and cameras_only.image_names == full.image_names
    for a, b in zip(cameras_only.poses, full.poses):
        np.testing.assert_array_equal(a.rotation, b.rotation)
        np.testing.assert_array_equal(a.translation, b.translation)
    assert cameras_only.cameras[0] == full.cameras[0]


# --- import into a dataset -------------------------------------------------------------------------


def _colmap_set(tmp_path):
    """One shared camera, images in a sub-folder, one of them a JPEG."""
    rng = np.random.default_rng(3)
    model = _model()
    cam = model.cameras[0]
    names = ["seq/a.png", "seq/b.png", "seq/c.jpg", "seq/d.png"]
    model = SparseModel([cam], names, model.poses, None, model.points3d, model.colors, model.errors,
                        model.keypoints, model.tracks)
    write_colmap_text(model, tmp_path / "sparse")
    for name in names:
        write_image(tmp_path / "images" / name, rng.integers(0, 255, (48, 64, 3), dtype=np.uint8))
    return model


def test_import_colmap(tmp_path):
    model = _colmap_set(tmp_path)
    import_colmap(tmp_path / "sparse", tmp_path / "images", tmp_path / "ds")
    ds = load_dataset(tmp_path / "ds", check_images=True)
    assert ds.names == ["seq_a.png", "seq_b.png", "seq_c.png", "seq_d.png"]
    _same_camera(ds.camera, model.cameras[0])
    assert all(m.tolerance.is_exact for m in ds.poses)
    for got, want in zip(ds.poses, model.poses):
        np.testing.assert_allclose(got.pose.matrix, want.matrix, atol=1e-9)
    assert (tmp_path / "ds" / "frames" / "seq_a.png").read_bytes() == (tmp_path / "images/seq/a.png").read_bytes()
    assert ds.metadata["source"]["format"] == "colmap-text"


def test_import_colmap_with_rounded_quaternions(tmp_path):
    """images.txt printed to 7 significant digits, one quaternion to 4: imported within the rounding.

    A quaternion printed to d digits is q + e with |e| <= sqrt(4) 0.5e-d = 1e-d. Normalised, it is at
    most asin(|e| / (1 - |e|)) from q on the unit sphere, and rotation angles are twice that.
    """
    model = _colmap_set(tmp_path)
    images_txt = tmp_path / "sparse" / "images.txt"
    lines = images_txt.read_text().splitlines()
    pose_lines = range(4, len(lines), 2)  # after 4 comment lines, a pose line then its 2D points
    coarse, digits = 6, {}
    for i in pose_lines:
        digits[i] = 4 if i == coarse else 7
        tokens = lines[i].split()
        tokens[1:8] = [f"{float(v):.{digits[i]}g}" for v in tokens[1:8]]
        lines[i] = " ".join(tokens)
    images_txt.write_text("\n".join(lines) + "\n")

    import_colmap(tmp_path / "sparse", tmp_path / "images", tmp_path / "ds")
    ds = load_dataset(tmp_path / "ds")
    for i, got, want in zip(pose_lines, ds.poses, model.poses, strict=True):
        e = 10.0 ** -digits[i]
        assert rotation_angle_between(got.pose.rotation, want.rotation) <= 2 * np.arcsin(e / (1 - e))
        # atol: poses.csv keeps 12 digits of the ~80 mm centre, so a zero component comes back as ~1e-11
        np.testing.assert_allclose(got.pose.translation, want.translation, rtol=0.5 * 10.0 ** (1 - digits[i]),
                                   atol=1e-9)
    # Provenance: the largest normalisation is the coarse line's, |q + e| - 1 = q.e to first order
    # (second order: |e|^2); the 7-digit lines' are below 1e-7.
    qx, qy, qz, qw = model.poses[(coarse - 4) // 2].quaternion
    q = np.array([qw, qx, qy, qz])
    e = np.array(lines[coarse].split()[1:5], float) - q
    recorded = ds.metadata["source"]["quaternion_normalised_max"]
    assert abs(q @ e) > 10 * 1e-7 and abs(recorded - abs(q @ e)) <= e @ e, (recorded, q @ e)


def test_cli_import_colmap_with_tolerance(tmp_path, capsys):
    _colmap_set(tmp_path)
    code = main(["import", "colmap", str(tmp_path / "sparse"), str(tmp_path / "images"),
                 "--out", str(tmp_path / "ds"), "--tolerance", "0.5", "--tolerance-deg", "0.2"])
    assert code == 0, capsys.readouterr().err
    ds = load_dataset(tmp_path / "ds")
    np.testing.assert_allclose(ds.poses[0].tolerance.position_mm, 0.5)
    np.testing.assert_allclose(ds.poses[0].tolerance.orientation_deg, 0.2)


def test_import_colmap_with_a_missing_image_writes_nothing(tmp_path, capsys):
    _colmap_set(tmp_path)
    (tmp_path / "images" / "seq" / "d.png").unlink()
    code = main(["import", "colmap", str(tmp_path / "sparse"), str(tmp_path / "images"), "--out", str(tmp_path / "ds")])
    err = capsys.readouterr().err
    assert code == 2 and "images.txt" in err and "seq/d.png" in err and err.count("\n") == 1
    assert not (tmp_path / "ds").exists()


def test_import_colmap_refuses_two_different_cameras(tmp_path):
    write_colmap_text(_model(), tmp_path / "sparse")
    with pytest.raises(InputError, match="2 different cameras"):
        import_colmap(tmp_path / "sparse", tmp_path, tmp_path / "ds")


@pytest.mark.parametrize("shift_px, accepted", [(0.002, True), (0.05, False)])
def test_import_colmap_takes_cameras_differing_by_the_rounding_of_k_as_one(tmp_path, shift_px, accepted):
    """Per-image cameras of one physical camera, each K from a decomposed projection matrix, differ by
    rounding: principal points 0.002 px apart in x and y move every pixel by 0.002 sqrt(2) = 0.0028 px, under
    SAME_CALIBRATION_PX (one camera, the first one's K, the shift recorded); 0.05 px apart is another camera,
    refused in one line naming cameras.txt (issue 34)."""
    from scope3d.sensor.camera import SAME_CALIBRATION_PX

    model = _colmap_set(tmp_path)
    cam = model.cameras[0]
    twin = Camera(cam.width, cam.height, cam.fx, cam.fy, cam.cx + shift_px, cam.cy - shift_px, cam.k1, cam.k2)
    model = SparseModel([cam, twin], model.image_names, model.poses, np.array([0, 1, 0, 1]), model.points3d,
                        model.colors, model.errors, model.keypoints, model.tracks)
    write_colmap_text(model, tmp_path / "sparse")
    if not accepted:
        with pytest.raises(InputError, match=r"cameras.txt: camera #2 \(in the file's order\) differs from #1 .*K by 0.0707 px") as info:
            import_colmap(tmp_path / "sparse", tmp_path / "images", tmp_path / "ds")
        assert "\n" not in str(info.value) and not (tmp_path / "ds").exists()
        return
    ds = load_dataset(import_colmap(tmp_path / "sparse", tmp_path / "images", tmp_path / "ds"))
    _same_camera(ds.camera, cam)
    recorded = ds.metadata["source"]["camera_k_shift_max_px"]
    assert recorded == pytest.approx(shift_px * np.sqrt(2.0), rel=1e-9) and recorded < SAME_CALIBRATION_PX
