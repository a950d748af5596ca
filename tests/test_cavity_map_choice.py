"""Which image-only cavity map to keep (sfm.cavity_map_choice.choose_map) and how far two maps disagree
(map_disagreement), on constructed maps of the bladder phantom's wall."""
from __future__ import annotations

import numpy as np

from scope3d.geometry.rotation import rotvec_to_matrix
from scope3d.scene.tracks import Tracks
from scope3d.geometry.pose import Pose
from scope3d.sensor.camera import Camera
from scope3d.sfm.cavity_map_choice import (SIGNIFICANT_SIGMAS, choose_map, explained_difference, map_disagreement,
                                           map_figures, spread_difference)
from scope3d.sfm.cavity_mapping import CavityOptions

SEMI_AXES = np.array([45.0, 38.0, 32.0])  # the bladder phantom's (~90 x 76 x 64 mm)
N_FRAMES = 36


def _wall(seed: int = 1, n: int = 4000) -> tuple[np.ndarray, np.ndarray]:
    """Points on the phantom's wall (n, 3) and the frame (n,) whose view holds each: the wall's directions
    cut into 36 sectors of longitude and height, as a spiral of 36 views sees it."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    points = d / np.sqrt(((d / SEMI_AXES) ** 2).sum(axis=1, keepdims=True))
    longitude = ((np.arctan2(d[:, 1], d[:, 0]) + np.pi) / (2 * np.pi) * 12).astype(int) % 12
    height = np.digitize(d[:, 2], [-1 / 3, 1 / 3])
    return points, 3 * longitude + height


def _tracks(points: np.ndarray, frame: np.ndarray) -> Tracks:
    """Each point seen by its frame and the next one (feature ids unique per point, as in one feature set)."""
    n = len(points)
    ids = np.arange(n)
    return Tracks(np.r_[ids, ids], np.r_[frame, (frame + 1) % N_FRAMES], np.r_[ids, ids], np.zeros((2 * n, 2)),
                  np.zeros((2 * n, 3), np.uint8), np.asarray(points, float))


def _figures(explained: int, frame_scatter: float = 0.0, seed: int = 0) -> dict:
    """A map's figures: ``explained`` observations over the 36 frames, each frame's count scattered by
    ``frame_scatter`` (0: the same in every frame)."""
    per_frame = explained / N_FRAMES + np.random.default_rng(seed).normal(scale=frame_scatter, size=N_FRAMES)
    per_frame += (explained - per_frame.sum()) / N_FRAMES
    return {"explained_observations": explained, "explained_per_frame": per_frame.tolist(), "cameras_off_centre": 0.05}


def _look(direction: np.ndarray, centre: np.ndarray) -> Pose:
    """A camera at ``centre`` whose optical axis is ``direction``."""
    z = direction / np.linalg.norm(direction)
    x = np.cross([0.0, 0.0, 1.0], z) if abs(z[2]) < 0.9 else np.cross([1.0, 0.0, 0.0], z)
    x /= np.linalg.norm(x)
    return Pose.from_centre(np.stack([x, np.cross(z, x), z]), centre)


def test_a_map_with_a_block_of_frames_turned_off_loses_to_one_that_explains_more():
    # a 36-view spiral inside the phantom's wall, 8 mm about its centre, 70 deg field at 256 px; every wall
    # point seen by the views whose field holds it
    camera = Camera(256, 256, 183.0, 183.0, 127.5, 127.5)
    t = np.linspace(0.0, 4.0 * np.pi, N_FRAMES)
    polar = np.linspace(0.35 * np.pi, 0.65 * np.pi, N_FRAMES)
    looks = np.c_[np.sin(polar) * np.cos(t), np.sin(polar) * np.sin(t), np.cos(polar)]
    centres = np.c_[8.0 * np.cos(t), 8.0 * np.sin(t), np.linspace(-6.0, 6.0, N_FRAMES)]
    truth = [_look(d, c) for d, c in zip(looks, centres)]
    points, _ = _wall(seed=7, n=3000)
    track, frame, pixels = [], [], []
    for k, pose in enumerate(truth):
        uv = camera.project_world(pose, points)
        seen = np.flatnonzero(np.all(np.isfinite(uv), axis=1) & np.all((uv >= 0) & (uv <= 255), axis=1))
        track.append(seen), frame.append(np.full(len(seen), k)), pixels.append(uv[seen])
    track, frame = np.concatenate(track), np.concatenate(frame)
    every = Tracks(track, frame, track, np.concatenate(pixels), np.zeros((len(track), 3), np.uint8),
                   np.zeros((len(points), 3)))
    options = CavityOptions()
    # the all-pair map: frames 27-35 turned together by 9 deg about the cavity's centre (the 256 px spiral's
    # measured failure: tracks within the block still agree, those across it do not); the chain's map:
    # every frame 0.3 deg off in its own way
    turn = rotvec_to_matrix(np.deg2rad([0.0, 0.0, 9.0]))
    block = [Pose.from_centre(p.rotation @ turn.T, turn @ p.centre) if k >= 27 else p for k, p in enumerate(truth)]
    rng = np.random.default_rng(8)
    wobbly = [Pose.from_centre(rotvec_to_matrix(np.deg2rad(rng.normal(scale=0.3, size=3))) @ p.rotation, p.centre)
              for p in truth]
    mapped = Tracks(np.arange(len(points)), np.zeros(len(points), int), np.arange(len(points)),
                    np.zeros((len(points), 2)), np.zeros((len(points), 3), np.uint8), points)
    all_pairs, chain, right = (map_figures(camera, every, mapped, poses, options.tracks, options.min_observations)
                              for poses in (block, wobbly, truth))
    # the turned block loses the observations of the tracks across it (frames 10-19 and 27-35 see the same
    # wall), more than the wobble loses
    assert all_pairs["explained_observations"] < chain["explained_observations"] < right["explained_observations"]
    use_chain, reason = choose_map(all_pairs, chain, (0.0, 1.0))
    assert use_chain and "explains more" in reason
    # the right map against either is kept
    assert not choose_map(right, chain, (0.0, 1.0))[0] and not choose_map(right, all_pairs, (0.0, 1.0))[0]


def test_a_bent_wall_loses_on_its_spread_a_slightly_wider_one_does_not():
    points, frame = _wall(seed=3, n=800)
    rng = np.random.default_rng(4)
    all_pairs = _tracks(points + rng.normal(scale=0.2, size=points.shape), frame)  # 0.2 mm: a good map
    # the chain's map 1.5 mm off by frames (each frame's wall moved together): the spreads differ by chance
    # in either direction, within the frames' scatter, and the data decide
    for seed in range(2):
        shift = np.random.default_rng(seed).normal(scale=1.5, size=(N_FRAMES, 3))
        chain = _tracks(points + shift[frame], frame)
        value, sigma = spread_difference(all_pairs, chain)
        assert abs(value) < SIGNIFICANT_SIGMAS * sigma
        assert not choose_map(_figures(10_000), _figures(9_000), (value, sigma))[0]
    # each frame's wall at its own distance from the centre (the measured failure at 256 px: a spread of
    # 0.22 against the chain's 0.04, and it explained 2.7 % more): with counts that differ within their
    # frames' scatter, the spread decides
    bent = _tracks(points * np.random.default_rng(5).uniform(0.7, 1.3, N_FRAMES)[frame, None], frame)
    excess = spread_difference(bent, all_pairs)
    close = _figures(10_000, frame_scatter=100.0, seed=1), _figures(9_800, frame_scatter=100.0, seed=2)
    assert abs(explained_difference(*close)[0]) < SIGNIFICANT_SIGMAS * explained_difference(*close)[1]
    use_chain, reason = choose_map(*close, excess)
    assert use_chain and "spreads more" in reason, (excess, reason)
    # the chain's map explaining more wins whatever the spreads, and so does an all-pair map explaining
    # significantly more (wet mucosa: 0.29 mm explaining 18 % more, its wall spreading 3.2 standard errors
    # more than a chain's 2.42 mm)
    assert choose_map(_figures(9_000), _figures(10_000), spread_difference(all_pairs, bent))[0]
    use_chain, reason = choose_map(_figures(10_000), _figures(8_500), excess)
    assert not use_chain and "all-pair map explains significantly more" in reason


def test_the_explained_difference_has_the_standard_error_of_a_sum_over_frames():
    # per-frame differences of scatter s: the total's standard error sqrt(36) s (within the sample's spread)
    for s in (10.0, 100.0):
        more, sigma = explained_difference(_figures(10_000, s, seed=3), _figures(10_000, s, seed=4))
        assert abs(more) < 1e-6 and 0.75 * 6 * np.sqrt(2) * s < sigma < 1.25 * 6 * np.sqrt(2) * s


def test_a_map_with_its_cameras_off_centre_loses_first():
    inside, outside = {**_figures(9_000)}, {**_figures(10_000), "cameras_off_centre": 0.97}
    assert choose_map(outside, inside, (0.0, 1.0))[0]
    assert not choose_map(inside, outside, (1.0, 0.01))[0]


def test_disagreement_is_zero_up_to_a_similarity_and_the_perturbation_otherwise():
    points, frame = _wall(seed=5)
    a = _tracks(points, frame)
    R = rotvec_to_matrix(np.array([0.3, -0.2, 0.5]))
    same = _tracks(2.5 * points @ R.T + [10.0, -4.0, 7.0], frame)
    d = map_disagreement(a, same)
    assert d["median"] < 1e-9 and d["p95"] < 1e-9 and d["n_common_points"] == len(points)
    # every point moved by 1 mm in a random direction: 1 mm over the wall's ~38 mm radius
    step = np.random.default_rng(6).normal(size=points.shape)
    step /= np.linalg.norm(step, axis=1, keepdims=True)
    moved = map_disagreement(a, _tracks(points + step, frame))
    radius = np.median(np.linalg.norm(points, axis=1))
    assert abs(moved["median"] * radius - 1.0) < 0.1 and abs(moved["p95"] * radius - 1.0) < 0.1
    # maps holding different points share none
    assert np.isnan(map_disagreement(a, _tracks(points, frame).subset(np.zeros(2 * len(points), bool)))["median"])


def test_self_check_warns_when_the_two_maps_disagree_by_more_than_half_the_radius():
    from scope3d.geometry.sphere import fit_sphere
    from scope3d.pipelines.panorama import self_check
    from scope3d.sfm.cavity_mapping import CavityMap
    points, frame = _wall(seed=9, n=500)
    tracks = _tracks(points, frame)
    poses = [Pose.from_centre(np.eye(3), c) for c in np.random.default_rng(10).normal(scale=5.0, size=(N_FRAMES, 3))]
    centre, radius = fit_sphere(points)
    # the other map: the same wall with a third of it moved by a whole radius (a cap-like failure)
    moved = points.copy()
    moved[frame < 12] += [radius, 0.0, 0.0]
    for other, warns in ((points + 0.3, False), (moved, True)):
        choice = {"kept": "all pairs", "reason": "test", "disagreement": map_disagreement(tracks, _tracks(other, frame))}
        cavity = CavityMap(tracks, poses, centre, radius, np.ones(N_FRAMES, bool), [], [], 0, [], False, {},
                           None, choice)
        check = self_check(cavity, CavityOptions(), scaled=False, camera=Camera.from_fov(608, 608, 70.0))
        # the disagreement's warning (this map's pixels are no views of its points: the frames' depth test,
        # tests/test_depth_consistency.py, has nothing to judge here)
        disagree = [w for w in check["warnings"] if "image-only maps disagree" in w]
        assert check["passed"] and bool(disagree) == warns and check["map_choice"] == choice
