"""The coarse pass (scope3d.sfm.coarse_poses) on a small rendered dome with robot-grade poses."""
from __future__ import annotations

import numpy as np
import pytest

from scope3d import phantoms
from scope3d.io.dataset import load_dataset
from scope3d.pipelines.surgical_map import MapOptions, detect_features
from scope3d.sfm.coarse_poses import CoarseOptions, coarse_poses


@pytest.fixture(scope="module")
def robot_dome(tmp_path_factory):
    """30 frames at 320 px, centres off by up to +-3 mm per axis and +-1.5 deg (the phantom lab's
    cable-driven arm), and their SIFT features."""
    seq = phantoms.generate("dome", "grid5x6", size=(320, 320), seed=7, pose_noise_mm=3.0)
    ds = load_dataset(phantoms.write(seq, tmp_path_factory.mktemp("coarse") / "dome"))
    return ds, detect_features(MapOptions(), ds, [ds.frame(k) for k in range(len(ds))])


def _degrees(result, n):
    return np.bincount(np.array([(m.i, m.j) for m in result.matches]).ravel(), minlength=n)


def test_staged_verification_tries_fewer_pairs_and_places_every_frame(robot_dome):
    ds, features = robot_dome
    n = len(ds)
    every = coarse_poses(ds.camera, features, ds.poses, options=CoarseOptions(stop_when_placed=False))
    staged = coarse_poses(ds.camera, features, ds.poses, options=CoarseOptions(stop_when_placed=True))
    assert staged.n_tried < every.n_tried
    assert staged.n_groups == 1 == every.n_groups
    # a frame the pairs of every rank tie to three or more partners is tied to at least three when
    # verification stops at min_pairs_per_frame (the reinforce rounds try more where fewer verify)
    want = np.minimum(_degrees(every, n), CoarseOptions().min_pairs_per_frame)
    assert np.all(_degrees(staged, n) >= want)
    # both bring the cameras closer to the truth than the arm reported them (the pass's purpose)
    truth = np.stack([p.centre for p in ds.ground_truth.poses])
    measured = np.linalg.norm(np.stack([m.pose.centre for m in ds.poses]) - truth, axis=1).mean()
    for result in (every, staged):
        error = np.linalg.norm(np.stack([p.centre for p in result.poses]) - truth, axis=1).mean()
        assert error < 0.5 * measured
