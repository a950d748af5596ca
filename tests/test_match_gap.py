"""A gap along the circle between neighbour quadrants' matched points moves every quadrant radially in the
joint solve (registration.panorama.pairs_drawn_apart, joint_solve): the diameter bias the match-gap
systematic term of pipelines.thread_scan propagates."""
from __future__ import annotations

import numpy as np
import pytest

from scope3d.geometry.pose import Pose
from scope3d.registration.panorama import PairRegistration, PanoramaOptions, joint_solve, pairs_drawn_apart


def _exact_pairs(radius=3.6, step_deg=30.0, k=12, seed=0):
    """Correspondences of k quadrants already in place (stacked = true), on the wall where neighbours
    overlap: half a step from each quadrant's centre, at heights over 4 mm."""
    rng = np.random.default_rng(seed)
    pairs = []
    for i in range(k):
        j = (i + 1) % k
        angle = np.deg2rad(step_deg * (i + 0.5)) + rng.normal(0.0, np.deg2rad(1.0), 80)
        points = np.c_[radius * np.cos(angle), radius * np.sin(angle), rng.uniform(-6.0, -2.0, 80)]
        pairs.append(PairRegistration(i, j, Pose.identity(), points, points.copy(), 80, 0.0, 0.0))
    return pairs


def test_a_gap_between_matched_points_shrinks_every_quadrant_radially():
    pairs, gap = _exact_pairs(), 0.003
    angles = [30.0 * q for q in range(12)]
    options = PanoramaOptions()  # the stage model: one mount error for every quadrant
    exact = joint_solve(pairs, angles, options=options)[0]
    drawn = joint_solve(pairs_drawn_apart(pairs, gap), angles, options=options)[0]
    for q in range(12):  # each quadrant's centre of view on the wall, moved by the re-solved placement
        centre = 3.6 * np.array([np.cos(np.deg2rad(30.0 * q)), np.sin(np.deg2rad(30.0 * q)), -4.0 / 3.6])
        move = drawn[q].transform(centre[None])[0] - exact[q].transform(centre[None])[0]
        radial = move[:2] @ centre[:2] / np.linalg.norm(centre[:2])
        # the gap closes by a common inward shift d with 2 d sin(15°) = gap (every quadrant alike, up to
        # the solve's gauge: a common rotation and axial shift); 5 %: the points' 1° scatter about 15°
        assert radial == pytest.approx(-gap / (2 * np.sin(np.deg2rad(15.0))), rel=0.05)
