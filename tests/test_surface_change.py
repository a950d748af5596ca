"""Change detection against the phantom lab's resection (issue 36): ``mvs.surface_change``.

The scene: the dome's survey flown as a 30 fps video at 320 x 240 along its first row (60 frames, 2 s, the
scope 15 mm above the plate moving 10 mm/s along +x from x = -10 mm), a pit of 3 mm radius and 1.5 mm depth
cut at 1 s (frame 30) into the wall under (0, 9) mm, 22 mm from the scope, in view all along. The map: the
plane-sweep points of three frames before the cut (4, 14, 24; 10 003 points, median sigma 0.07 mm, median
error 0.04 mm against the true surface). The new frames: the 30 after the cut, every fifth a reference.

Measured (2 shared cores, ~15 s for the six sweeps): noise factor 1.19; 209 points changed, every one
over the pit; recall 100 % of the observed points under which the wall moved 1 mm or more (131), 90 % of
those moved 0.5 mm or more (the threshold is 3 noise factors of a ~0.1 mm error, 0.36 mm); none of the 1343
observed points on the unchanged wall (before the neighbours' vote 1.8 % of them were flagged: the sweep's
depth errors have heavier tails than a Gaussian's 0.27 % beyond 3 sigma, but they are scattered). The
regions to map again: every one of their 6873 pixels in the six references sees the pit, and they cover
52 % of the pit's pixels where the wall moved 0.5 mm or more: the sweep keeps a depth only where the
texture has contrast (vessels and dots; 33 % of the pixels around the pit in frame 30), and the exposed
tissue is paler, so that the centre of the pit, with no vessel, is measured in no frame.
"""
from __future__ import annotations

import numpy as np
import pytest

from scope3d.mvs.plane_sweep import sweep
from scope3d.mvs.surface_change import SurfaceChangeOptions, detect_surface_change
from scope3d.phantoms import generate
from scope3d.phantoms.resection import Resection, wall_moved_mm
from scope3d.sensor.pose_tolerance import perturb_poses_uniform


@pytest.fixture(scope="module")
def resected():
    seq = generate("dome", seed=0, size=(320, 240), video_fps=30.0, n_frames=60,
                   resection=Resection(1.0, radius_mm=3.0, depth_mm=1.5, centre_xy_mm=(0.0, 9.0)))
    first = seq.scene_info["resection"]["first_frame"]
    options = SurfaceChangeOptions()
    poses = seq.true_poses
    points, sigma = [], []
    for r in (4, 14, 24):  # the map, from frames before the cut only
        sources = [r - 4, r + 4] if r + 4 < first else [r - 4, r - 8]
        m = sweep(seq.camera, seq.frames[r], poses[r], [seq.frames[s] for s in sources],
                  [poses[s] for s in sources], (10.0, 35.0), options=options.sweep)
        points.append(poses[r].inverse().transform(m.points_cam))
        ij = m.pixels.astype(int)
        sigma.append(m.sigma_mm[ij[:, 1], ij[:, 0]])
    points, sigma = np.concatenate(points), np.concatenate(sigma)
    after = list(range(first, len(seq)))
    change = detect_surface_change(seq.camera, points, sigma, [seq.frames[i] for i in after],
                                   [poses[i] for i in after], references=list(range(0, len(after), 5)),
                                   options=options)
    return seq, after, points, sigma, change


def _off_wall_before_mm(points: np.ndarray, truth: dict) -> np.ndarray:
    """Distance of each point from the dome's wall (sphere) or the plate (z = 0) before the cut."""
    c, radius = np.asarray(truth["sphere_centre_mm"]), truth["sphere_radius_mm"]
    in_cap = np.hypot(points[:, 0], points[:, 1]) < np.sqrt(radius ** 2 - c[2] ** 2)
    return np.where(in_cap, np.abs(np.linalg.norm(points - c, axis=1) - radius), np.abs(points[:, 2]))


def test_the_resected_points_are_found_and_the_rest_kept(resected):
    seq, _, points, sigma, change = resected
    truth = seq.scene_info["resection"]
    moved = wall_moved_mm(points, truth)
    judged = change.n_views >= 2
    # the threshold is 3 noise factors of hypot(sweep sigma, map sigma): about 0.36 mm here; a wall moved
    # by 1 mm or more is beyond it by 2.8 times and more, whatever the noise's tail
    threshold = 3.0 * change.noise_factor * float(np.median(np.hypot(sigma, sigma)))
    deep = judged & (moved >= 2.8 * threshold)
    assert deep.sum() > 100
    assert change.changed[deep].mean() >= 0.95
    # what is changed lies over the pit, or is a map point that was off the wall before by more than its
    # own 3 sigma (its images never agreed with it); on the unchanged wall a point is dropped less often
    # than a Gaussian's 3-sigma rate, the single test the neighbours' vote only makes rarer
    explained = (moved > 0) | (_off_wall_before_mm(points, truth) > 3.0 * sigma)
    assert change.changed.sum() > 100 and explained[change.changed].mean() >= 0.95
    unchanged = judged & (moved == 0) & ~explained
    assert unchanged.sum() > 500 and change.changed[unchanged].mean() <= 0.0027
    # a point no new frame observed is never dropped
    assert not np.any(change.changed & (change.n_views < 2))


def test_the_region_to_map_again_is_the_pit(resected):
    seq, after, points, sigma, change = resected
    truth = seq.scene_info["resection"]
    over_pit, flagged, deep, deep_found = 0, 0, 0, 0
    for r, region in zip(change.references, change.regions):
        frame = after[r]
        depth = seq.depths[frame]
        v, u = np.nonzero(np.isfinite(depth))
        # every pixel's true point, on the wall as it is now
        world = seq.true_poses[frame].inverse().transform(seq.camera.unproject(np.stack([u, v], 1).astype(float),
                                                                                depth[v, u]))
        moved = wall_moved_mm(world, truth)
        inside = region[v, u]
        over_pit += int(np.sum(moved[inside] > 0))
        flagged += int(inside.sum())
        deep += int(np.sum(moved >= 0.5))
        deep_found += int(np.sum(inside & (moved >= 0.5)))
    # the region holds what changed and nothing else: its pixels see the pit (its footprint reaches two
    # map spacings, 0.2 mm, beyond a changed point: outside the pit only at the rim, where the wall moved
    # by less than the threshold and no point is found)
    assert flagged > 1000 and over_pit / flagged >= 0.95
    # and a part of the pit at least as large as the sweep measures there (33 % of the pixels around it)
    assert deep_found / deep >= 0.33


def test_pose_errors_blind_it_rather_than_drop_unchanged_tissue(resected):
    """Poses of the new frames off by up to +-0.05 mm and +-0.025 deg per axis, independently per frame
    (measured: noise factor 4.2 instead of 1.2, 40 points changed, all over the pit, 39 % of those moved 1 mm
    or more; at +-0.1 mm the factor is 7.1 and nothing is found): the sweep's depths are then off by more
    than their modelled error, the measured noise factor grows with them, and the threshold with it: what
    is lost is recall, not the unchanged wall."""
    seq, after, points, sigma, clean = resected
    noisy = [m.pose for m in perturb_poses_uniform([seq.true_poses[i] for i in after], 0.05, np.deg2rad(0.025),
                                                    seed=3)]
    change = detect_surface_change(seq.camera, points, sigma, [seq.frames[i] for i in after], noisy,
                                   references=clean.references)
    assert change.noise_factor > 2.0 * clean.noise_factor
    moved = wall_moved_mm(points, seq.scene_info["resection"])
    assert change.changed.sum() > 10 and np.all(moved[change.changed] > 0)
    assert change.changed.sum() < clean.changed.sum()
