"""A wrong surface inside a map that is otherwise a cavity seen from inside (sfm.depth_consistency and the
panorama's self-check), on a constructed spiral in the bladder phantom's wall."""
from __future__ import annotations

import numpy as np

from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import look_at
from scope3d.geometry.sphere import fit_sphere
from scope3d.scene.tracks import Tracks
from scope3d.sensor.camera import Camera
from scope3d.sfm.cavity_mapping import CavityMap, CavityOptions
from scope3d.sfm.depth_consistency import MAX_INCONSISTENT_FRACTION, frame_depth_inconsistency, inconsistent_frames

SEMI_AXES = np.array([45.0, 38.0, 32.0])  # the bladder phantom's
CAMERA = Camera.from_fov(608, 608, 70.0)  # the phantom's frames
N_FRAMES = 36


def _spiral_map(seed: int = 3) -> tuple[Tracks, list[Pose]]:
    """The phantom's wall seen by a spiral of 36 views from within 8 mm of its centre, every wall point seen
    by two or more views observed in all of them: pixels with 0.15 px noise (the real keypoints' median
    error is 0.1 px), points 0.05 mm off the wall (a map at the noise of its keypoints)."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(6000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    wall = d / np.sqrt(((d / SEMI_AXES) ** 2).sum(axis=1, keepdims=True))
    k = np.arange(N_FRAMES)
    t = np.linspace(0.0, 4.0 * np.pi, N_FRAMES)
    centres = np.c_[8.0 * np.cos(t), 8.0 * np.sin(t), np.linspace(-6.0, 6.0, N_FRAMES)]
    polar = np.arccos(1.0 - 2.0 * (k + 0.5) / N_FRAMES)  # view directions spread evenly over the sphere
    azimuth = k * np.pi * (3.0 - np.sqrt(5.0))
    views = np.c_[np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth), np.cos(polar)]
    poses = [Pose.from_centre(look_at(c, c + v, up=(0.0, 0.0, 1.0) if abs(v[2]) < 0.9 else (1.0, 0.0, 0.0)), c)
             for c, v in zip(centres, views)]
    seen = []
    for pose in poses:
        px = CAMERA.project_world(pose, wall)
        seen.append(np.isfinite(px).all(axis=1) & (px >= 0).all(axis=1) & (px <= 607).all(axis=1))
    seen = np.array(seen)  # (frames, points); the inside of an ellipsoid hides none of its wall
    kept = np.flatnonzero(seen.sum(axis=0) >= 2)
    frame, point = np.nonzero(seen[:, kept])
    order = np.argsort(point, kind="stable")
    frame, point = frame[order], point[order]
    pixels = np.stack([CAMERA.project_world(poses[f], wall[kept[p]][None])[0] for f, p in zip(frame, point)])
    pixels += rng.normal(scale=0.15, size=pixels.shape)
    points = wall[kept] + rng.normal(scale=0.05, size=(len(kept), 3))
    tracks = Tracks(point, frame, np.arange(len(point)), pixels, np.zeros((len(kept), 3), np.uint8), points)
    return tracks, poses


def _with_wrong_surface(tracks: Tracks, frame: int, depth_mm: float = 6.0) -> Tracks:
    """Every other point the frame sees moved ``depth_mm`` towards the cavity's centre, its observations
    unchanged: the measured failure (the pale wet wall at a tenth of the vessels, planned poses, 2.5 mm
    mean: a quarter of the points 3-10 mm off the wall, median 6 mm inside it, among right ones in the same
    frames)."""
    ids = np.unique(tracks.track[tracks.frame == frame])[::2]
    points = tracks.points.copy()
    points[ids] -= depth_mm * points[ids] / np.linalg.norm(points[ids], axis=1, keepdims=True)
    return Tracks(tracks.track, tracks.frame, tracks.feature, tracks.pixels, tracks.colors, points)


def _cavity(tracks: Tracks, poses: list[Pose]) -> CavityMap:
    centre, radius = fit_sphere(tracks.points)
    return CavityMap(tracks, poses, centre, radius, np.ones(len(poses), bool), [], [], 0, [], False)


def test_a_right_map_has_every_frame_on_one_wall_and_a_wrong_surface_is_found_in_its_frames():
    tracks, poses = _spiral_map()
    registered = np.ones(N_FRAMES, bool)
    right = frame_depth_inconsistency(CAMERA, poses, tracks, registered)
    assert np.isfinite(right).all()  # every frame judged
    # 3 sigma of a 0.5 px noise on a 0.15 px one: only the wall's curvature across 8 neighbours is left
    assert inconsistent_frames(right) == [] and right.max() < MAX_INCONSISTENT_FRACTION / 2
    broken = frame_depth_inconsistency(CAMERA, poses, _with_wrong_surface(tracks, 10), registered)
    flagged = inconsistent_frames(broken)
    # half of frame 10's points off: about half of its observations disagree with their neighbours
    assert 10 in flagged and broken[10] > 0.3
    # frames sharing none of the moved points stay unflagged
    moved = np.unique(tracks.track[tracks.frame == 10])[::2]
    untouched = [j for j in range(N_FRAMES) if not np.isin(tracks.track[tracks.frame == j], moved).any()]
    assert untouched and not set(untouched) & set(flagged)
    # a frame not registered, or with too few points, is not judged
    registered[3] = False
    assert np.isnan(frame_depth_inconsistency(CAMERA, poses, tracks, registered)[3])


def test_the_self_check_warns_of_a_wrong_surface_inside_a_cavity_seen_from_inside():
    from scope3d.pipelines.panorama import self_check
    tracks, poses = _spiral_map()
    good = self_check(_cavity(tracks, poses), CavityOptions(), False, CAMERA)
    assert good["passed"] and good["warnings"] == [] and good["inconsistent_frames"] == []
    bad = self_check(_cavity(_with_wrong_surface(tracks, 10), poses), CavityOptions(), False, CAMERA)
    # the cameras are still inside the cavity: the map is written, with the warning naming the frames
    assert bad["passed"] and 10 in bad["inconsistent_frames"]
    assert len(bad["warnings"]) == 1 and "no single wall" in bad["warnings"][0] and "10" in bad["warnings"][0]
