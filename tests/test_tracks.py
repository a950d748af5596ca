"""Tracks: connected components of the matches, exact multi-view triangulation, filters."""
from __future__ import annotations

import numpy as np
import pytest

from scope3d.estimators.triangulation import (
    TrackOptions,
    reprojection_errors,
    triangulate_observations,
    triangulate_tracks,
)
from scope3d.feature.detection import Features
from scope3d.feature.matching import PairMatches
from scope3d.feature.tracks import build_tracks
from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import look_at
from scope3d.scene.tracks import Tracks
from scope3d.sensor.camera import Camera

CAM = Camera.from_fov(608, 608, 70.0, k1=-0.12, k2=0.02, mask_radius_px=300.0)


def _scene(n=300, seed=0):
    rng = np.random.default_rng(seed)
    X = rng.uniform([-6, -6, -4], [6, 6, 2], (n, 3))
    poses = [Pose.from_centre(look_at(np.array([x, y, 15.0]), np.array([0.0, 0.0, -2.0])), [x, y, 15.0])
             for x in (-5.0, 0.0, 5.0) for y in (-2.5, 2.5)]
    return X, poses


def _tracks_from(X, poses, noise_px=0.0, seed=1):
    rng = np.random.default_rng(seed)
    m = len(poses)
    track = np.repeat(np.arange(len(X)), m)
    frame = np.tile(np.arange(m), len(X))
    px = np.stack([CAM.project_world(p, X) for p in poses], axis=1).reshape(-1, 2)
    px = px + rng.normal(0, noise_px, px.shape) if noise_px else px
    return Tracks(track, frame, np.arange(len(track)), px, np.zeros((len(X), 3), np.uint8))


@pytest.mark.parametrize("method", ["midpoint", "dlt"])
def test_triangulation_is_exact_on_noise_free_data_with_distortion(method):
    X, poses = _scene()
    t = _tracks_from(X, poses)
    Y = triangulate_observations(CAM, poses, t.track, t.frame, t.pixels, len(X), method)
    np.testing.assert_allclose(Y, X, atol=1e-9)


# an equidistant fisheye that sees 200 deg across (100 deg from its axis at the circle's edge)
WIDE = Camera.from_params(608, 608, "OPENCV_FISHEYE", [170.0, 170.0, 303.5, 303.5, 0.0, 0.0, 0.0, 0.0],
                          mask_radius_px=300.0)


@pytest.mark.parametrize("method", ["midpoint", "dlt"])
def test_points_seen_past_90_deg_from_the_axis_triangulate(method):
    # the cameras look down -z; the points lie beside and slightly behind them, 95-100 deg off their axes
    poses = [Pose.from_centre(look_at(np.array([x, 0.0, 0.0]), np.array([x, 0.0, -10.0])), [x, 0.0, 0.0])
             for x in (-3.0, 0.0, 3.0)]
    X = np.array([[0.0, 20.0, 2.0], [4.0, -20.0, 3.0], [-2.0, 15.0, 2.5]])
    angle = np.degrees(np.stack([WIDE.lens.half_angle(p.transform(X)) for p in poses]))
    assert angle.min() > 95.0 and angle.max() < 100.0
    m = len(poses)
    track, frame = np.repeat(np.arange(len(X)), m), np.tile(np.arange(m), len(X))
    px = np.stack([WIDE.project_world(p, X) for p in poses], axis=1).reshape(-1, 2)
    assert np.all(np.isfinite(px)) and np.all(WIDE.in_image(px))
    np.testing.assert_allclose(triangulate_observations(WIDE, poses, track, frame, px, len(X), method), X, atol=1e-9)
    # and the filters keep them: in front along their rays although behind the camera planes (z < 0)
    t = Tracks(track, frame, np.arange(len(track)), px, np.zeros((len(X), 3), np.uint8))
    out = triangulate_tracks(WIDE, poses, t, TrackOptions(method=method))
    assert out.n_tracks == len(X) and reprojection_errors(WIDE, poses, out).max() < 1e-6


def test_triangulate_tracks_keeps_everything_good_and_reprojects_to_zero():
    X, poses = _scene()
    out = triangulate_tracks(CAM, poses, _tracks_from(X, poses))
    assert out.n_tracks == len(X)
    assert reprojection_errors(CAM, poses, out).max() < 1e-6


def test_a_wrong_observation_is_dropped_and_the_point_recovered():
    X, poses = _scene(n=20)
    t = _tracks_from(X, poses)
    t.pixels[0] += [25.0, -10.0]  # point 0 in frame 0: a wrong match
    out = triangulate_tracks(CAM, poses, t, TrackOptions(max_reprojection_error_px=2.0))
    assert out.n_observations == t.n_observations - 1
    np.testing.assert_allclose(out.points[0], X[0], atol=1e-9)


def test_noise_gives_sub_pixel_errors_and_depth_error_of_the_expected_size():
    X, poses = _scene(n=500)
    sigma = 0.5
    out = triangulate_tracks(CAM, poses, _tracks_from(X, poses, noise_px=sigma))
    # 2-D residuals of a 3-parameter fit to 6 views x 2 coordinates: RMS = sigma sqrt(2 (1 - 3/12))
    rms = np.sqrt(np.mean(reprojection_errors(CAM, poses, out) ** 2))
    assert rms < sigma * np.sqrt(2.0)
    # 6 views, baselines 5-10 mm at ~15-19 mm: sigma_z ~ z^2 sigma / (f b) / sqrt(6) < 0.1 mm
    err = np.linalg.norm(out.points - X, axis=1)
    assert np.median(err) < 0.1


def _down_looking(x: float, y: float = 0.0, z: float = 15.0) -> Pose:
    """A camera at (x, y, z) mm looking straight down the world -z axis."""
    return Pose.from_centre(look_at(np.array([x, y, z]), np.array([x, y, z - 10.0])), [x, y, z])


def _observe(poses, X, frames_of_track):
    """Noise-free observations of points ``X`` (n, 3) in the given frames, one list of frame indices per point.

    A point behind a camera is given the pixel of its own viewing ray (the mirror of the point through the
    centre projects there): such an observation is geometrically consistent with the point, with zero
    reprojection error along the ray, so only the cheirality check can tell it is wrong."""
    track, frame, px = [], [], []
    for k, frames in enumerate(frames_of_track):
        for f in frames:
            p_cam = poses[f].transform(X[k:k + 1])
            if p_cam[0, 2] < 0:
                p_cam = -p_cam
            track.append(k)
            frame.append(f)
            px.append(CAM.project(p_cam)[0])
    track, frame = np.array(track), np.array(frame)
    assert np.all(CAM.in_image(np.array(px))), "a synthetic observation left the image"
    return Tracks(track, frame, np.arange(len(track)), np.array(px), np.zeros((len(X), 3), np.uint8))


def test_cheirality_and_angle_filters():
    X, poses = _scene(n=10)
    t = _tracks_from(X, poses[:2])
    # two identical cameras: zero parallax, every track must go
    same = [poses[0], poses[0]]
    t_same = Tracks(t.track, t.frame, t.feature, np.concatenate([CAM.project_world(poses[0], X)] * 2)[
        np.argsort(np.r_[np.arange(10) * 2, np.arange(10) * 2 + 1])], t.colors)
    assert triangulate_tracks(CAM, same, t_same, TrackOptions(min_angle_deg=1.0)).n_tracks == 0

    # cheirality. Cameras 0 and 1 look down from z = 15 mm, 5 mm apart; camera 2 looks down from z = -30 mm,
    # under the scene, so everything at z > -30 mm is behind it.
    cams = [_down_looking(-2.5), _down_looking(2.5), _down_looking(0.0, z=-30.0)]
    pts = np.array([
        [0.3, 0.2, 0.0],    # 0: in front of 0 and 1 (15 mm deep): kept whole
        [0.3, 0.2, 30.0],   # 1: 15 mm *behind* 0 and 1 (their rays meet above them): must go
        [-0.4, 0.5, -2.0],  # 2: in front of 0 and 1, behind 2: the point stays, its view in 2 must go
    ])
    obs = _observe(cams, pts, [[0, 1], [0, 1], [0, 1, 2]])
    # the point behind cameras 0 and 1 is what their rays give (exact triangulation, zero reprojection error,
    # a 19 deg triangulation angle): neither the reprojection gate nor the angle filter can reject it
    behind = triangulate_observations(CAM, cams, obs.track, obs.frame, obs.pixels, 3)
    np.testing.assert_allclose(behind, pts, atol=1e-9)
    options = TrackOptions(max_reprojection_error_px=2.0, min_angle_deg=1.0)
    out = triangulate_tracks(CAM, cams, obs, options)
    assert out.n_tracks == 2
    np.testing.assert_allclose(out.points, pts[[0, 2]], atol=1e-9)
    assert out.lengths().tolist() == [2, 2]
    assert 2 not in out.frame.tolist()  # the observation in the camera the point is behind is dropped
    depth = np.einsum("mi,mi->m", np.stack([c.rotation[2] for c in cams])[out.frame], out.points[out.track]) \
        + np.stack([c.translation[2] for c in cams])[out.frame]
    assert np.all(depth > 0)

    # triangulation angle: two cameras 0.5 mm apart and points on their bisecting plane at a distance rho
    # from the baseline, where the two rays meet at exactly 2 atan(0.25 / rho). Noise-free data triangulate
    # exactly (first test), so the angle is known to ~1e-9 relative and points 1 % either side of the
    # threshold are decided by the filter alone.
    pair = [_down_looking(-0.25), _down_looking(0.25)]
    threshold_deg = 1.0
    angles_deg = np.array([0.99, 1.01, 0.5, 2.0]) * threshold_deg
    rho = 0.25 / np.tan(np.radians(angles_deg) / 2.0)
    pts = np.column_stack([np.zeros(4), np.linspace(-0.5, 0.5, 4), 15.0 - rho])
    obs = _observe(pair, pts, [[0, 1]] * 4)
    out = triangulate_tracks(CAM, pair, obs, TrackOptions(min_angle_deg=threshold_deg))
    np.testing.assert_allclose(out.points, pts[angles_deg > threshold_deg], atol=1e-6)
    # and nothing else rejected them: without the angle filter all four are kept
    assert triangulate_tracks(CAM, pair, obs, TrackOptions(min_angle_deg=0.0)).n_tracks == 4


def test_build_tracks_joins_chains_and_drops_inconsistent_components():
    feats = [Features(np.zeros((5, 2)), np.zeros((5, 128), np.float32), np.ones(5, np.float32),
                      np.full((5, 3), 100, np.uint8)) for _ in range(3)]
    a = np.array
    matches = [
        PairMatches(0, 1, a([0, 1, 2]), a([0, 1, 2])),
        PairMatches(1, 2, a([0, 1]), a([3, 4])),
        # frame-0 feature 2 -> frame-2 feature 3, which is already tied to frame-0 feature 0: conflict
        PairMatches(0, 2, a([2]), a([3])),
    ]
    t = build_tracks(feats, matches)
    lengths = t.lengths()
    # (0:1, 1:1, 2:4) survives as a 3-track; the component {0:0, 1:0, 2:3, 0:2, 1:2} has two frame-0 features
    assert t.n_tracks == 1 and lengths.tolist() == [3]
    assert sorted(zip(t.frame.tolist(), t.feature.tolist())) == [(0, 1), (1, 1), (2, 4)]
    assert t.colors.tolist() == [[100, 100, 100]]


def test_split_inconsistent_keeps_both_tracks_a_wrong_match_glued():
    # two points, A (feature 0 in every frame) and B (feature 1), seen in 3 frames; one wrong match ties A in
    # frame 0 to B in frame 2: dropped whole, the component loses both points; split, the wrong match, the
    # least similar link, is refused and both tracks come back whole
    rng = np.random.default_rng(0)
    desc_a, desc_b = rng.uniform(0, 50, (2, 128)).astype(np.float32)
    feats = [Features(np.zeros((2, 2)), np.stack([desc_a, desc_b]) + rng.normal(0, 1, (2, 128)).astype(np.float32),
                      np.ones(2, np.float32), np.full((2, 3), 100, np.uint8)) for _ in range(3)]
    a = np.array
    matches = [PairMatches(0, 1, a([0, 1]), a([0, 1])), PairMatches(1, 2, a([0, 1]), a([0, 1])),
               PairMatches(0, 2, a([0, 1, 0]), a([0, 1, 1]))]  # the last: frame 0's A -> frame 2's B, wrong
    assert build_tracks(feats, matches).n_tracks == 0
    t = build_tracks(feats, matches, split_inconsistent=True)
    assert t.n_tracks == 2 and t.lengths().tolist() == [3, 3]
    assert sorted(tuple(np.unique(t.feature[t.track == k])) for k in range(2)) == [(0,), (1,)]


def test_strongest_keeps_the_longest_then_the_highest_priority():
    a = np.array
    # tracks 0 (3 views), 1, 2, 3 (2 views each)
    t = Tracks(a([0, 0, 0, 1, 1, 2, 2, 3, 3]), a([0, 1, 2, 0, 1, 1, 2, 0, 2]), a(range(9)), np.zeros((9, 2)),
               np.zeros((4, 3), np.uint8))
    assert sorted(np.unique(t.feature[np.isin(t.track, [0, 1])]).tolist()) == \
        sorted(t.strongest(2).feature.tolist())  # without a priority: the lowest id among the ties
    # with one: the three-view track, then the two-view track of the highest priority (track 2)
    kept = t.strongest(2, priority=a([0.0, 1.0, 5.0, 2.0]))
    assert sorted(kept.feature.tolist()) == [0, 1, 2, 5, 6]
    assert t.strongest(4, priority=a([0.0, 1.0, 5.0, 2.0])) is t


def test_build_tracks_with_no_matches_is_empty():
    feats = [Features.empty(), Features.empty()]
    assert build_tracks(feats, []).n_tracks == 0


def test_bad_inputs():
    X, poses = _scene(n=5)
    t = _tracks_from(X, poses)
    with pytest.raises(ValueError, match="poses"):
        triangulate_tracks(CAM, poses[:2], t)
    with pytest.raises(ValueError):
        TrackOptions(method="svd")
    with pytest.raises(ValueError):
        TrackOptions(min_track_length=1)
