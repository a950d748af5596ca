"""Change detection against the phantom lab's resection (issue 36): ``mvs.surface_change``.

The scene: the dome's survey flown as a 30 fps video at 320 x 240 along its first row (60 frames, 2 s, the
scope 15 mm above the plate moving 10 mm/s along +x from x = -10 mm), a pit of 3 mm radius and 1.5 mm depth
cut at 1 s (frame 30) into the wall under (0, 9) mm, 22 mm from the scope, in view all along. The map: the
plane-sweep points of three frames before the cut (4, 14, 24; 10 003 points, median sigma 0.07 mm, median
error 0.04 mm against the true surface). The new frames: the 30 after the cut, every fifth a reference.

Measured (2 shared cores, ~15 s for the six sweeps): noise factor 1.19; 300 points flagged; recall 100 % of
the observed points under which the wall moved 1 mm or more (162), 91 % of those moved 0.5 mm or more (the
threshold is 3 noise factors of a ~0.1 mm error, 0.36 mm); of the flagged points 83 % lie over the pit and
92 % lie over it or were off the true surface before by more than three times the map's sigma (points whose
images never agreed with the map: dropping them is right); 1.8 % of the observed points on the unchanged
wall are flagged (the sweep's depth errors have heavier tails than a Gaussian's 0.27 % beyond 3 sigma).
The regions to map again: of their pixels, 92, 92, 81, 75, 29 and 32 % see the pit in the six references
(the pit moves to the field's edge in the last two, where isolated blocks of wrong sweep depths outnumber
the pit's few kept pixels), 77 % over all six; they cover only part of the pit, where the sweep kept a depth
(the exposed tissue's paler texture has less contrast).
"""
from __future__ import annotations

import numpy as np
import pytest

from scope3d.mvs.plane_sweep import sweep
from scope3d.mvs.surface_change import SurfaceChangeOptions, detect_surface_change
from scope3d.phantoms import generate
from scope3d.phantoms.resection import Resection, wall_moved_mm


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
    # what is flagged lies over the pit, or is a map point that was off the wall before by more than its
    # own 3 sigma; the sweep's heavier-than-Gaussian tail makes the rest (a Gaussian: 0.27 %)
    explained = (moved > 0) | (_off_wall_before_mm(points, truth) > 3.0 * sigma)
    assert change.changed.sum() > 100 and explained[change.changed].mean() >= 0.85
    unchanged = judged & (moved == 0) & ~explained
    assert unchanged.sum() > 500 and change.changed[unchanged].mean() <= 0.05
    # a point no new frame observed is never dropped
    assert not np.any(change.changed & (change.n_views < 2))


def test_the_region_to_map_again_is_the_pit(resected):
    seq, after, points, sigma, change = resected
    truth = seq.scene_info["resection"]
    over_pit, flagged = 0, 0
    for r, region in zip(change.references, change.regions):
        frame = after[r]
        depth = seq.depths[frame]
        v, u = np.nonzero(region & np.isfinite(depth))
        if len(u) == 0:
            continue
        # the flagged pixels' true points (on the wall as it is now) lie over the pit
        world = seq.true_poses[frame].inverse().transform(seq.camera.unproject(np.stack([u, v], 1).astype(float),
                                                                                depth[v, u]))
        over_pit += int(np.sum(wall_moved_mm(world, truth) > 0))
        flagged += len(u)
    # most of what the region says changed did: the majority of its pixels see the pit
    assert flagged > 500 and over_pit / flagged > 0.5
