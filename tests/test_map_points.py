"""The map's points for localization: one real descriptor per track, written and read back, bad files refused."""
from __future__ import annotations

import numpy as np
import pytest

from scope3d.errors import InputError
from scope3d.feature.detection import Features
from scope3d.feature.tracks import track_descriptors
from scope3d.io.map_points import MapPoints, read_map_points, write_map_points
from scope3d.scene.tracks import Tracks


def _features(descriptors: np.ndarray) -> Features:
    n = len(descriptors)
    return Features(np.zeros((n, 2)), descriptors.astype(np.float32), np.ones(n, np.float32), np.zeros((n, 3), np.uint8))


def test_track_descriptor_is_the_observation_nearest_the_mean():
    rng = np.random.default_rng(0)
    base = rng.uniform(0, 100, (2, 128))
    # track 0: three observations, the middle one is the mean exactly; track 1: two, an outlier and a typical one
    f0 = _features(np.stack([base[0] + 5, base[1] + 40]))
    f1 = _features(np.stack([base[0], base[1] + 1]))
    f2 = _features(np.stack([base[0] - 5]))
    tracks = Tracks(np.array([0, 0, 0, 1, 1]), np.array([0, 1, 2, 0, 1]), np.array([0, 0, 0, 1, 1]),
                    np.zeros((5, 2)), np.zeros((2, 3), np.uint8))
    d = track_descriptors([f0, f1, f2], tracks)
    assert d.shape == (2, 128) and d.dtype == np.float32
    np.testing.assert_allclose(d[0], base[0], rtol=1e-6)
    # mean of track 1 is base + 20.5: equidistant from +40 and +1 -> both 19.5 off; the tie goes to either,
    # but the descriptor must be one that an image showed
    assert any(np.allclose(d[1], base[1] + k, rtol=1e-6) for k in (1, 40))


def test_map_points_round_trip_and_refusals(tmp_path):
    rng = np.random.default_rng(1)
    pts = MapPoints(rng.normal(size=(5, 3)), rng.uniform(0, 200, (5, 128)).astype(np.float32),
                    np.array([2, 3, 2, 4, 2], np.int32), np.zeros((5, 3), np.uint8))
    write_map_points(tmp_path / "map_points.npz", pts)
    back = read_map_points(tmp_path)  # a folder holding the file works too
    np.testing.assert_array_equal(back.xyz_mm, pts.xyz_mm)
    np.testing.assert_array_equal(back.descriptors, pts.descriptors)
    with pytest.raises(InputError, match="no map points"):
        read_map_points(tmp_path / "elsewhere")
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    with pytest.raises(InputError, match="bad.npz"):
        read_map_points(tmp_path / "bad.npz")
    np.savez(tmp_path / "short.npz", xyz_mm=pts.xyz_mm)
    with pytest.raises(InputError, match="missing array"):
        read_map_points(tmp_path / "short.npz")


def test_observation_descriptors_round_trip_and_old_files_still_read(tmp_path):
    rng = np.random.default_rng(2)
    obs = rng.uniform(0, 200, (7, 128)).astype(np.float32)
    pts = MapPoints(rng.normal(size=(3, 3)), obs[:3], np.array([2, 3, 2], np.int32), np.zeros((3, 3), np.uint8),
                    obs, np.array([0, 0, 1, 1, 1, 2, 2]))
    write_map_points(tmp_path / "map_points.npz", pts)
    back = read_map_points(tmp_path)
    np.testing.assert_array_equal(back.observation_descriptors, obs)
    np.testing.assert_array_equal(back.observation_point, pts.observation_point)
    # a map written before the optional arrays existed is read as before: representatives only
    write_map_points(tmp_path / "old.npz", MapPoints(pts.xyz_mm, pts.descriptors, pts.n_observations, pts.colors))
    assert read_map_points(tmp_path / "old.npz").observation_point is None
    # an observation pointing past the points, or one array without the other, is refused in one line
    arrays = dict(np.load(tmp_path / "map_points.npz"))
    np.savez(tmp_path / "past.npz", **(arrays | {"observation_point": np.array([0, 0, 1, 1, 1, 2, 3], np.int32)}))
    with pytest.raises(InputError, match="past.npz.*index"):
        read_map_points(tmp_path / "past.npz")
    np.savez(tmp_path / "half.npz", **{k: v for k, v in arrays.items() if k != "observation_descriptors"})
    with pytest.raises(InputError, match="half.npz"):
        read_map_points(tmp_path / "half.npz")
