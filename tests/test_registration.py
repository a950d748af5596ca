"""Registration layer: the robust rigid fit, the outlier filter, and the panoramic registration of
12 quadrants of a threaded hole (repetitive geometry: ICP's trap) against known transforms."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from scope3d.errors import InputError
from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import rotation_angle_between, rotvec_to_matrix
from scope3d.phantoms.scenes import build_scene
from scope3d.registration.outliers import OutlierOptions, statistical_inliers
from scope3d.registration.panorama import (PanoramaOptions, QuadrantCloud, loop_closure, register_quadrants,
                                           registration_errors, solve_panorama)
from scope3d.registration.rigid import fit_rigid, ransac_rigid

NOISE_MM = 0.01  # a sparse side-view reconstruction's point noise (~0.5 px at 5 mm range)


def _spin(deg):
    return Pose(rotvec_to_matrix([0.0, 0.0, np.deg2rad(deg)]), np.zeros(3))


def _quadrants(seed=0, n_features=6000, offset_mm=(0.2, -0.1), tilt_deg=1.0, k=12, step_deg=30.0,
               stage_errors=True):
    """Feature points on the true M8 thread, each with its own random 'SIFT' descriptor; quadrant q sees
    the features within ±30° of its view direction, displaced by the rotation stage model of a camera off
    and tilted from the axis (truth G_q = spin_q D spin_q^-1 takes the stacked frame to the world) after
    a small per-quadrant error — the stage's (angle 0.05°, axial re-positioning 0.01 mm, 1 sigma) with
    ``stage_errors``, else a general rigid one of the same size — with 0.01 mm noise and descriptor
    noise; 10 % of each quadrant's descriptors are swapped at random (wrong matches)."""
    rng = np.random.default_rng(seed)
    mesh = build_scene("thread").mesh.to_trimesh()
    pts, _ = trimesh.sample.sample_surface(mesh, 4 * n_features, seed=seed)
    pts = pts[(pts[:, 2] < -1.5) & (pts[:, 2] > -12.5)][:n_features]
    desc = rng.uniform(0, 100, (len(pts), 128)).astype(np.float32)
    mount = Pose(rotvec_to_matrix([np.deg2rad(tilt_deg), 0.0, 0.0]), [offset_mm[0], offset_mm[1], 0.0])
    truth, clouds = [], []
    ang = np.arctan2(pts[:, 1], pts[:, 0])
    for q in range(k):
        a = q * step_deg
        if stage_errors:
            rep = Pose(rotvec_to_matrix([0.0, 0.0, rng.normal(0, np.deg2rad(0.05))]), [0.0, 0.0, rng.normal(0, 0.01)])
        else:
            rep = Pose(rotvec_to_matrix(rng.normal(0, np.deg2rad(0.05), 3)), rng.normal(0, 0.01, 3))
        if q == 0:
            rep = Pose.identity()
        g = rep @ _spin(a) @ mount @ _spin(-a)  # world_from_stacked
        seen = np.abs(np.angle(np.exp(1j * (ang - np.deg2rad(a))))) < np.deg2rad(30.0)
        local = g.inverse().transform(pts[seen]) + rng.normal(0, NOISE_MM, (seen.sum(), 3))
        d = desc[seen] + rng.normal(0, 2.0, (seen.sum(), 128)).astype(np.float32)
        swap = rng.random(len(d)) < 0.1
        d[swap] = rng.uniform(0, 100, (swap.sum(), 128))
        truth.append(g)
        clouds.append(QuadrantCloud(q, a, local, d))
    return clouds, truth


def test_rigid_fit_and_ransac_recover_a_known_transform():
    rng = np.random.default_rng(1)
    src = rng.uniform(-5, 5, (200, 3))
    true = Pose(rotvec_to_matrix([0.1, -0.3, 0.5]), [1.0, 2.0, -0.5])
    dst = true.transform(src)
    exact = fit_rigid(src, dst)
    assert np.allclose(exact.rotation, true.rotation, atol=1e-10) and np.allclose(exact.translation, true.translation)
    noisy = dst + rng.normal(0, NOISE_MM, dst.shape)
    noisy[:60] += rng.uniform(-3, 3, (60, 3))  # 30 % gross outliers
    fit = ransac_rigid(src, noisy, seed=0)
    assert fit is not None and fit.inliers[60:].mean() > 0.95 and fit.inliers[:60].mean() < 0.1
    # 140 inliers of 0.01 mm noise: rotation good to ~0.01 mrad x sqrt(3) / (5 mm lever)
    assert np.rad2deg(rotation_angle_between(fit.target_from_source.rotation, true.rotation)) < 0.05
    with pytest.raises(ValueError):
        fit_rigid(src[:2], dst[:2])


def test_panorama_recovers_known_transforms_on_a_thread():
    clouds, truth = _quadrants()
    result = register_quadrants(clouds, seed=0)
    assert result.closed and result.loop_closure_deg is not None
    rot, off = registration_errors(result.world_from_stacked, truth, clouds)
    # the targets: 0.5° and 0.02 mm; with ~300 correspondences of 0.01 mm noise per pair the
    # solve does far better, so hold it to a fifth of the targets
    assert rot.max() < 0.1, rot
    assert off.max() < 0.02 / 5, off
    stacked_rot, stacked_off = registration_errors([Pose.identity()] * len(clouds), truth, clouds)
    assert stacked_off.max() > 5 * off.max()  # the stacked guess was really off


def test_free_pose_graph_and_translation_only_solves():
    clouds, truth = _quadrants(stage_errors=False)
    result = register_quadrants(clouds, options=PanoramaOptions(model="free"), seed=0)
    rot, off = registration_errors(result.world_from_stacked, truth, clouds)
    # six free unknowns per quadrant from ~300 correspondences per pair: within the 0.5°, 0.02 mm
    assert rot.max() < 0.5 and off.max() < 0.02, (rot, off)
    clouds, truth = _quadrants(tilt_deg=0.0, offset_mm=(0.25, 0.1), stage_errors=False)
    result = register_quadrants(clouds, options=PanoramaOptions(model="free", solve_rotations=False), seed=0)
    rot, off = registration_errors(result.world_from_stacked, truth, clouds)
    assert off.max() < 0.02  # offsets only: the 0.05° re-positioning twists remain (~0.005 mm at 6 mm)


def test_loop_closure_residual_measures_a_twisted_pair():
    clouds, truth = _quadrants()
    result = register_quadrants(clouds, seed=0)
    # each pair's rotation is good to ~0.04° (400 points of 0.017 mm combined noise over a 60° arc of
    # a 4 mm radius); twelve of them chained: ~0.04 sqrt(12) = 0.14°, and ~0.02 mm at the centroid
    assert result.loop_closure_deg < 0.3 and result.loop_closure_mm < 0.05
    # twist one pair's correspondences by 1° about the axis: the chained loop is off by that angle,
    # and the joint solve spreads it (no quadrant is off by the full degree)
    p = result.pairs[5]
    twist = Pose(rotvec_to_matrix([0.0, 0.0, np.deg2rad(1.0)]), np.zeros(3))
    p.points_j = twist.transform(p.points_j)
    p.i_from_j = p.i_from_j @ twist.inverse()
    deg, _ = loop_closure(result.pairs, clouds)
    assert abs(deg - 1.0) <= result.loop_closure_deg + 0.01
    poses, _ = solve_panorama(result.pairs, len(clouds))
    rot, _ = registration_errors(poses, truth, clouds)
    assert rot.max() < 0.5  # spread round the circle: well under the degree the chain piles up


def test_statistical_outlier_filter():
    rng = np.random.default_rng(2)
    u, v = rng.uniform(0, 10, (2, 5000))
    plane = np.stack([u, v, rng.normal(0, 0.01, 5000)], 1)
    far = rng.uniform(0, 10, (100, 3)) + [0, 0, 1.0]  # 2 % stray points 1-11 mm off the surface
    keep = statistical_inliers(np.concatenate([plane, far]), options=OutlierOptions(neighbours=30, n_sigmas=3.0))
    assert keep[:5000].mean() > 0.98 and keep[5000:].mean() < 0.05
    assert statistical_inliers(plane[:10]).all()


def test_errors_name_the_quadrant():
    clouds, _ = _quadrants(n_features=3000)
    bad = list(clouds)
    bad[7] = QuadrantCloud(7, 215.0, clouds[7].points, clouds[7].descriptors)
    with pytest.raises(InputError, match="quadrant 7.*inconsistent rotation"):
        register_quadrants(bad)
    lost = list(clouds)
    rng = np.random.default_rng(3)
    lost[5] = QuadrantCloud(5, 150.0, clouds[5].points, rng.uniform(0, 100, clouds[5].descriptors.shape))
    with pytest.raises(InputError, match="quadrants 4 and 5.*do not overlap"):
        register_quadrants(lost)


def test_views_at_the_same_advance_are_matched_when_first_views_differ():
    from scope3d.registration.panorama import match_quadrants

    rng = np.random.default_rng(5)
    n = 40
    shared = rng.uniform(0, 100, (n, 128)).astype(np.float32)  # the points seen from frame 1 in both quadrants

    def cloud(index):
        first = rng.uniform(0, 100, (n, 128)).astype(np.float32)  # first views: from elsewhere, unalike
        return QuadrantCloud(index, 30.0 * index, rng.normal(size=(n, 3)), first, None,
                             np.concatenate([np.arange(n), np.arange(n)]), np.repeat([0, 1], n),
                             np.concatenate([first, shared + rng.normal(0, 1, shared.shape).astype(np.float32)]))

    a, b = cloud(0), cloud(1)
    i, j = match_quadrants(a, b, 0.8)
    np.testing.assert_array_equal(i, np.arange(n))  # every point found, each with its own partner
    np.testing.assert_array_equal(j, np.arange(n))
    first_only = QuadrantCloud(1, 30.0, b.points, b.descriptors)  # no views kept: first views only
    assert len(match_quadrants(a, first_only, 0.8)[0]) == 0
