"""The textured wall (mvs.texturing) against the bladder phantom's truth, and its OBJ files."""
from __future__ import annotations

import numpy as np
import pytest

from scope3d.errors import InputError
from scope3d.geometry.similarity import Similarity
from scope3d.io.dataset import load_dataset
from scope3d.io.obj import read_textured_obj, write_textured_obj
from scope3d.metrology.texture_evaluation import TextureEvaluationOptions, textured_errors
from scope3d.mvs.texturing import TexturedMesh, TextureOptions, texture_mesh
from scope3d.phantoms import generate, write
from scope3d.phantoms.scenes import build_scene

IDENTITY = Similarity(1.0, np.eye(3), np.zeros(3), np.zeros(3))
# fewer points and patches than the benchmark: the test's budget (a few seconds)
EVALUATION = TextureEvaluationOptions(n_points=20_000, n_patches=60, patch_texels=32)


@pytest.fixture(scope="module")
def true_texture(tmp_path_factory):
    """The 12-frame bladder spiral at 128 px textured from its TRUE poses onto its TRUE wall: what is under
    test is the texturing alone."""
    root = tmp_path_factory.mktemp("texturing") / "bladder"
    write(generate("bladder", size=(128, 128), n_frames=12), root)
    ds = load_dataset(root)
    wall = ds.ground_truth.surface()
    return ds, wall, texture_mesh(wall, np.zeros(3), ds.camera, ds.ground_truth.poses, ds.frame,
                                  options=TextureOptions())


def test_texture_matches_the_true_albedo_where_the_frames_saw_the_wall(true_texture):
    ds, wall, textured = true_texture
    # 12 frames of one spiral see most of the wall, not its poles
    assert 0.5 < textured.textured_fraction < 1.0
    # the default texel is the frames' own footprint: ~30 mm / 91 px focal
    assert 0.2 < textured.texel_mm < 0.6
    result = textured_errors(textured, IDENTITY, wall, np.zeros(3), build_scene("bladder").albedo, options=EVALUATION)
    colour, shift = result["colour_error"], result["misregistration_mm"]
    # the sensor's noise (2 grey levels read noise + 2 % shot noise at full scale) and the specular glint the
    # Lambertian correction leaves (6 % of white at normal incidence) bound the mean error at ~8 %
    assert colour["mean_fraction"] < 0.08
    assert colour["luminance_correlation"] > 0.95
    # true poses and wall: what is left is bilinear sampling and phase correlation's sub-texel accuracy
    # (~0.1 texel); 0.3 texel allows for the 128 px frames' aliasing
    assert shift["n"] >= 10
    assert shift["median"] < 0.3 * result["texel_mm"]


def test_the_misregistration_measure_sees_a_shifted_texture(true_texture):
    """The check can fail: the same atlas moved by 3 texels is measured ~3 texels off."""
    ds, wall, textured = true_texture
    moved = TexturedMesh(textured.mesh, textured.uv, textured.face_uv, np.roll(textured.image, 3, axis=1),
                         textured.texel_mm, textured.face_frame, textured.textured_fraction, textured.gains)
    result = textured_errors(moved, IDENTITY, wall, np.zeros(3), build_scene("bladder").albedo, options=EVALUATION)
    # texel_mm is a texel's size at a cell's centre on a wall at the median distance; off the centre (the
    # tangent-adjusted cube map) and on nearer walls texels are smaller, down to ~0.5 of it: 3 texels are
    # 1.5-3 texel_mm on the wall
    assert 1.5 * result["texel_mm"] < result["misregistration_mm"]["median"] < 3.0 * result["texel_mm"]


def test_obj_files_round_trip_and_bad_faces_are_refused(true_texture, tmp_path):
    _, _, textured = true_texture
    paths = write_textured_obj(tmp_path / "wall.obj", textured.mesh.vertices, textured.mesh.faces, textured.uv,
                               textured.face_uv, textured.image)
    assert [p.name for p in paths] == ["wall.obj", "wall.mtl", "wall.png"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["wall.mtl", "wall.obj", "wall.png"]  # no temporaries
    v, f, uv, fuv, image = read_textured_obj(paths[0])
    assert np.abs(v - textured.mesh.vertices).max() < 1e-6  # written to 1e-6 mm
    assert np.array_equal(f, textured.mesh.faces) and np.array_equal(fuv, textured.face_uv)
    assert np.abs(uv - textured.uv).max() < 1e-7 and np.array_equal(image, textured.image)
    import trimesh  # a user's tool opens it with its texture

    loaded = trimesh.load(paths[0], process=False)
    assert loaded.visual.kind == "texture" and loaded.visual.material.image.size == image.shape[1::-1]
    bad = tmp_path / "quad.obj"
    bad.write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nf 1/1 2/1 3/1 4/1\n")
    with pytest.raises(InputError, match="quad.obj: line 6"):
        read_textured_obj(bad)


def test_options_are_validated():
    with pytest.raises(ValueError):
        TextureOptions(texel_mm=0)
    with pytest.raises(ValueError):
        TextureOptions(min_cos=1.0)


def test_a_frame_with_no_texel_to_give_is_sampled_as_nothing():
    """Found on an unseen wet cavity (shape seed 11, images only): a frame that sees a face but none of its
    texels reached cv2.remap with an empty map, which OpenCV refuses with an assertion."""
    from scope3d.mvs.texturing import sample_image

    image = np.zeros((8, 8, 3), np.uint8)
    assert sample_image(image, np.zeros((0, 2), np.float32)).shape == (0, 3)


def test_every_texel_inside_a_face_belongs_to_that_face():
    """The ID-buffer rasteriser: OpenCV's fill also takes texels an edge only grazes; deepest_faces gives each
    texel whose centre lies inside a face to that face (on this random triangulation the raw fill gives 21 % of these texels to a neighbour)."""
    from scipy.spatial import Delaunay

    from scope3d.mvs.texturing import deepest_faces, face_neighbours, rasterise

    rng = np.random.default_rng(4)
    tri = Delaunay(rng.uniform(3, 57, size=(60, 2)))
    corners = tri.points[tri.simplices]
    faces = np.arange(len(tri.simplices))
    owner = rasterise(corners, faces, 60, 60, gutter_px=2)
    index = np.flatnonzero(owner >= 0)
    face, bary = deepest_faces(corners, owner[index], index, 60, face_neighbours(tri.simplices),
                               np.ones(len(faces), bool))
    centres = np.stack([index % 60, index // 60], axis=1).astype(float)
    truth = tri.find_simplex(centres, tol=-1e-6)  # -1: outside, or within 1e-6 of an edge (either face is right)
    inside = truth >= 0
    assert inside.sum() > 1500
    assert np.array_equal(face[inside], truth[inside])
    assert np.all(bary[inside] >= -1e-9)
    assert np.mean(owner[index][inside] != truth[inside]) > 0.01  # the raw fill alone would fail the check
