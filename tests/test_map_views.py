"""More views of the same object must give the map more points, not fewer.

Tracks are the connected components of the pairwise matches, and a track holding two features of one frame
is dropped whole (:func:`scope3d.feature.tracks.build_tracks`). Every pair adds a few wrong matches that can glue
two tracks together, so with a fixed number of partners per frame the loss grows with the density of
views (on a dense ring the partners all see the same points). The ``photograph`` preset therefore keeps
one partner per direction of camera motion (:class:`scope3d.feature.pairs.PairOptions`). The checks follow from
that geometry, not from tuning:

* pair selection: on a ring each view is paired with its two neighbours only, on a raster with its four
  neighbours, whatever the spacing;
* on a rendered ring sub-sampled 1 in 3, the 12 views are also in the 36-view ring, where their partners
  are three times closer (7 instead of 21 deg): SIFT repeats better at smaller viewpoint changes, so each
  view's observations cannot fall, and the points grow;
* the pairs of a ring form one cycle, so a track can hold two features of a frame only by wrapping round
  the whole ring: matched features lost to inconsistent tracks stay below 1 %.
"""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from scope3d import phantoms
from scope3d.feature.depth_prior import DepthPrior
from scope3d.feature.pairs import PairOptions, select_pairs
from scope3d.feature.tracks import build_tracks
from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import rotvec_to_matrix
from scope3d.io.dataset import load_dataset, write_dataset
from scope3d.phantoms.trajectories import ring_poses
from scope3d.pipelines.surgical_map import MAP_PRESETS, run
from scope3d.sensor.camera import Camera
from scope3d.sensor.pose_tolerance import MICRO_STAGE, MeasuredPose

RING_VIEWS = 36
RING_SIZE_PX = 200


def _pair_set(pairs) -> set:
    return {(i, j) for i, j, _ in pairs}


@pytest.mark.parametrize("n", [8, 12, 24, 48])
def test_one_partner_per_direction_pairs_ring_neighbours(n):
    # 8 views are 45 deg apart, beyond the preset's 35 deg view-angle limit: the limit must not isolate a
    # view (before issue 34 it left the sparse ring without pairs), its neighbours on either side are kept
    camera = Camera.from_fov(640, 480, 24.0)
    poses = ring_poses(n, tilt_deg=90.0, distance_mm=560.0)
    depth = DepthPrior(500.0, 620.0)
    pairs = select_pairs(camera, poses, depth, options=MAP_PRESETS["photograph"].pairs)
    assert _pair_set(pairs) == {tuple(sorted((k, (k + 1) % n))) for k in range(n)}


def test_one_partner_per_direction_pairs_grid_neighbours():
    traj = phantoms.grid_trajectory(5, 6)  # 5 mm apart, 15 mm above the plate, serpentine order
    camera = Camera.from_fov(608, 608, 53.0)
    options = PairOptions(max_pairs_per_frame=0, max_pairs_per_direction=1)
    pairs = select_pairs(camera, traj.poses, DepthPrior(10.0, 25.0), options=options)
    centres = np.stack([p.centre for p in traj.poses])
    d = np.linalg.norm(centres[:, None] - centres[None], axis=2)
    neighbours = {(i, j) for i in range(len(d)) for j in range(i + 1, len(d)) if abs(d[i, j] - 5.0) < 1e-6}
    assert _pair_set(pairs) == neighbours


def test_a_second_view_from_the_same_place_is_paired_without_displacing_the_neighbours():
    camera = Camera.from_fov(640, 480, 24.0)
    poses = ring_poses(12, tilt_deg=90.0, distance_mm=560.0)
    # Middlebury's ring holds one viewpoint twice, the camera turned 180 deg about its optical axis: the
    # two are paired (the same-place class), and each keeps its neighbours on either side
    turned = rotvec_to_matrix(np.array([0.0, 0.0, np.pi])) @ poses[0].rotation
    poses.append(Pose.from_centre(turned, poses[0].centre))
    pairs = _pair_set(select_pairs(camera, poses, DepthPrior(500.0, 620.0), options=MAP_PRESETS["photograph"].pairs))
    ring = {tuple(sorted((k, (k + 1) % 12))) for k in range(12)}
    assert pairs == ring | {(0, 12), (1, 12), (11, 12)}


def test_bad_pair_options():
    with pytest.raises(ValueError):
        PairOptions(max_pairs_per_direction=-1)


@pytest.fixture(scope="module")
def dome_ring(tmp_path_factory):
    """The dome phantom from a ring of 36 views (40 deg off its axis, 25 mm from the middle of the
    cavity), and every third view of it."""
    scene = phantoms.build_scene("dome")
    camera = Camera.from_fov(RING_SIZE_PX, RING_SIZE_PX, scene.fov_deg)
    poses = ring_poses(RING_VIEWS, tilt_deg=40.0, distance_mm=25.0, target=(0.0, 0.0, -5.0))
    exposure = phantoms.sequence_exposure(scene, camera, poses)
    frames = [phantoms.render_frame(scene, camera, p, seed=0, frame_index=i, exposure=exposure).image
              for i, p in enumerate(poses)]
    root = tmp_path_factory.mktemp("ring")
    measured = [MeasuredPose(p, MICRO_STAGE) for p in poses]
    names = [f"{i:04d}.png" for i in range(RING_VIEWS)]
    dense = write_dataset(root / "dense", camera, frames, measured, names=names)
    sparse = write_dataset(root / "sparse", camera, frames[::3], measured[::3], names=names[::3])
    return load_dataset(sparse), load_dataset(dense)


def _consistent_fraction(result) -> float:
    """Fraction of the features matched in some pair that build_tracks keeps (not in an inconsistent track)."""
    matched = set()
    for m in result.matching.matches:
        matched.update((m.i, int(k)) for k in m.idx_i)
        matched.update((m.j, int(k)) for k in m.idx_j)
    return build_tracks(result.features, result.matching.matches).n_observations / len(matched)


def test_points_grow_with_views_on_a_ring(dome_ring, tmp_path):
    options = replace(MAP_PRESETS["photograph"], figures=False)
    sparse, dense = (run(options, ds, tmp_path / f"map{len(ds)}") for ds in dome_ring)
    few, many = sparse.report, dense.report
    assert many["n_points"] > few["n_points"]
    assert many["n_observations"] / many["n_frames"] >= few["n_observations"] / few["n_frames"]
    assert _consistent_fraction(dense) >= 0.99


def test_a_ring_of_8_views_maps_more_points_than_colmap_with_no_worse_reprojection(tmp_path):
    """Issue 34's target beside its peer in the same run: the dome phantom seen from bench_map_views.py's
    ring of 8 views (320 px, exact poses), mapped with the ``photograph`` preset and by COLMAP's known-pose
    triangulation (pycolmap: SIFT, exhaustive matching, ``triangulate_points`` at the same poses), as the
    benchmark runs them: at least 1.3x COLMAP's points, a mean reprojection error no worse. With OpenCV's
    SIFT contrast threshold (0.04) the map found 820 features a frame where COLMAP finds ~2,000, and kept
    0.70x its points."""
    import importlib
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    try:
        bench = importlib.import_module("bench_map_views")
    finally:
        sys.path.pop(0)
    ds = load_dataset(bench.render_dome_ring(8, tmp_path / "ring"))
    ours = run(bench.PHOTOGRAPH, ds, tmp_path / "map").report
    colmap = bench.colmap_run(ds, tmp_path / "colmap", 1)
    assert ours["n_points"] >= 1.3 * colmap["n_points"], (ours["n_points"], colmap["n_points"])
    assert ours["mean_reprojection_error_px"] <= colmap["mean_reprojection_error_px"]
