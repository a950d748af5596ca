"""Pair selection from poses, feature position prediction, guided vs exhaustive matching on a rendered pair."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from scope3d import phantoms
from scope3d.feature.depth_prior import DepthPrior, predict_segments, window_radius_px
from scope3d.feature.detection import detect
from scope3d.feature.matching import (
    MatchOptions,
    _ratio_select_grouped,
    best_two_per_query,
    match_exhaustive,
    match_guided,
    match_pairs,
    pair_squared_distances,
    two_nearest,
)
from scope3d.feature.pairs import PairOptions, frame_overlap, select_pairs
from scope3d.geometry.pose import Pose
from scope3d.metrology.evaluation import true_match_error_px
from scope3d.sensor.pose_tolerance import OPTICAL_TRACKER, PoseTolerance
from scope3d.sfm.depth_priors import estimate_depth_prior

CORRECT_PX = 3.0  # a match is correct when the true depth sends its keypoint within 3 px of its partner
SIFT_SIGMA_PX = 0.5  # SIFT keypoint localisation, per coordinate (MatchOptions: "good to ~0.5 px")


@pytest.fixture(scope="module")
def pair():
    seq = phantoms.generate("dome", "grid5x6", size=(400, 400), seed=0, n_frames=3)
    feats = [detect(f, seq.camera) for f in seq.frames]
    return seq, feats


def _correct(seq, feats, m):
    err = true_match_error_px(seq.camera, seq.true_poses[m.i], seq.true_poses[m.j], seq.depths[m.i],
                              feats[m.i].keypoints[m.idx_i], feats[m.j].keypoints[m.idx_j])
    return int(np.sum(err < CORRECT_PX)), err


def test_guided_finds_at_least_as_many_correct_matches_as_exhaustive(pair):
    seq, feats = pair
    depth = DepthPrior(12.0, 28.0)
    for i, j in ((0, 1), (1, 2), (0, 2)):
        # the wide pair (0, 2) sits at the 15-match gate at 400 px (a few renders more or less texture
        # drop it whole either way): compare the matchers there before the gate
        options = MatchOptions(min_matches=0) if (i, j) == (0, 2) else MatchOptions()
        g = match_guided(seq.camera, feats[i], feats[j], seq.measured_poses[i], seq.measured_poses[j], depth,
                         options=options,
                         i=i, j=j)
        e = match_exhaustive(seq.camera, feats[i], feats[j], options, i=i, j=j)
        good_g, err_g = _correct(seq, feats, g)
        good_e, err_e = _correct(seq, feats, e)
        assert good_g >= good_e and good_g > 0, (i, j, good_g, good_e)
        # and are as often right: a wrong match along the epipolar line passes RANSAC either way, the
        # window only ever removes candidates (precision within 5 points of the exhaustive one)
        if len(e):
            assert np.mean(err_g < CORRECT_PX) >= np.mean(err_e < CORRECT_PX) - 0.05
        assert g.n_candidates < len(feats[i]) * len(feats[j]) / 10  # the window does restrict the search


def test_prediction_contains_the_true_position(pair):
    seq, feats = pair
    cam, depth = seq.camera, DepthPrior(12.0, 28.0)
    kp = feats[0].keypoints
    p0, p1 = predict_segments(cam, seq.true_poses[0], seq.true_poses[1], kp, depth)
    z = seq.depths[0][np.rint(kp[:, 1]).astype(int), np.rint(kp[:, 0]).astype(int)]
    truth = cam.project_world(seq.true_poses[1], (cam.unproject(kp, z) - seq.true_poses[0].translation) @ seq.true_poses[0].rotation)
    ok = np.isfinite(truth).all(axis=1) & np.isfinite(z)
    d = p1[ok] - p0[ok]
    t = np.clip(np.einsum("ij,ij->i", truth[ok] - p0[ok], d) / np.einsum("ij,ij->i", d, d), 0, 1)
    dist = np.linalg.norm(truth[ok] - (p0[ok] + t[:, None] * d), axis=1)
    assert dist.max() < 1e-6  # exact poses, depth inside the prior: the truth lies on the segment


def test_homography_limit_when_the_depth_range_is_thin(pair):
    seq, feats = pair
    p0, p1 = predict_segments(seq.camera, seq.true_poses[0], seq.true_poses[1], feats[0].keypoints, DepthPrior(20.0, 20.0))
    np.testing.assert_allclose(p0, p1)


def test_window_radius_follows_the_tolerance():
    from scope3d.sensor.camera import Camera

    cam = Camera.from_fov(608, 608, 53.0)
    depth = DepthPrior(15.0, 25.0)
    exact = window_radius_px(cam, PoseTolerance.exact(), PoseTolerance.exact(), depth, 4.0)
    assert exact == pytest.approx(4.0)
    tracker = window_radius_px(cam, OPTICAL_TRACKER, OPTICAL_TRACKER, depth, 4.0)
    dp = 2 * np.linalg.norm(OPTICAL_TRACKER.position_mm)
    dw = 2 * np.linalg.norm(OPTICAL_TRACKER.orientation_rad)
    assert tracker == pytest.approx(4.0 + cam.fx * dp / 15.0 + cam.fx * dw)
    assert window_radius_px(cam, PoseTolerance.unknown(), PoseTolerance.exact(), depth, 4.0) == np.inf


def test_loose_poses_fall_back_to_exhaustive(pair):
    seq, feats = pair
    loose = [type(m)(m.pose, PoseTolerance.unknown()) for m in seq.measured_poses]
    m = match_guided(seq.camera, feats[0], feats[1], loose[0], loose[1], DepthPrior(12.0, 28.0))
    assert m.method == "guided->exhaustive" and len(m) > 0


def test_overlap_and_pair_selection(pair):
    seq, _ = pair
    depth = DepthPrior(15.0, 25.0)
    ov = frame_overlap(seq.camera, seq.true_poses, depth)
    assert np.allclose(np.diag(ov), 1.0) and np.allclose(ov, ov.T)
    # neighbours 5 mm apart overlap more than frames 10 mm apart
    assert ov[0, 1] > ov[0, 2] > 0
    pairs = select_pairs(seq.camera, seq.true_poses, depth, options=PairOptions(min_overlap=0.0, max_pairs_per_frame=1))
    assert {(i, j) for i, j, _ in pairs} == {(0, 1), (1, 2)}


def test_depth_prior_estimate_brackets_the_true_depths(pair):
    seq, feats = pair
    prior = estimate_depth_prior(seq.camera, feats, seq.measured_poses)
    # the prior comes from matched features: it must bracket the true depth of those features
    kp = feats[0].keypoints
    z = seq.depths[0][np.rint(kp[:, 1]).astype(int), np.rint(kp[:, 0]).astype(int)]
    lo, hi = np.nanpercentile(z, [10, 90])
    assert prior.near_mm <= lo and prior.far_mm >= hi


def test_guided_batches_match_as_one(pair, monkeypatch):
    """match_pairs matches guided pairs in batches, each with only its own frames (to bound memory): a
    pair's matches must not depend on the batch it falls in (one pair per batch against all in one)."""
    import scope3d.feature.matching as matching

    seq, feats = pair
    pairs = [(0, 2, 1.0), (0, 1, 1.0), (1, 2, 1.0)]
    together = match_pairs(seq.camera, feats, seq.measured_poses, pairs, DepthPrior(12.0, 28.0))
    monkeypatch.setattr(matching, "_GUIDED_PAIRS_PER_BATCH", 1)
    alone = match_pairs(seq.camera, feats, seq.measured_poses, pairs, DepthPrior(12.0, 28.0))
    assert [(m.i, m.j) for m in alone] == [(0, 2), (0, 1), (1, 2)]
    assert sum(len(m) for m in alone) > 0
    for a, b in zip(alone, together):
        assert (a.i, a.j, a.n_putative, a.n_candidates) == (b.i, b.j, b.n_putative, b.n_candidates)
        np.testing.assert_array_equal(a.idx_i, b.idx_i)
        np.testing.assert_array_equal(a.idx_j, b.idx_j)


def test_candidate_search_in_chunks_finds_the_same_candidates(pair, monkeypatch):
    """match_guided_many searches segment samples in chunks of bounded tree hits (to bound memory at
    wide windows): the candidates, hence the matches, must not depend on the chunk size (one sample per
    chunk against the default). A tracker's tolerance gives windows of tens of px, several samples each."""
    import scope3d.feature.matching as matching

    seq, feats = pair
    tracker = [replace(m, tolerance=OPTICAL_TRACKER) for m in seq.measured_poses]
    pairs = [(0, 1, 1.0), (1, 2, 1.0), (0, 2, 1.0)]
    whole = match_pairs(seq.camera, feats, tracker, pairs, DepthPrior(12.0, 28.0))
    monkeypatch.setattr(matching, "_CANDIDATE_HITS_PER_CHUNK", 1)
    chunked = match_pairs(seq.camera, feats, tracker, pairs, DepthPrior(12.0, 28.0))
    assert sum(m.n_candidates for m in whole) > 0 and sum(len(m) for m in whole) > 0
    for a, b in zip(chunked, whole):
        assert (a.i, a.j, a.n_putative, a.n_candidates, a.method) == (b.i, b.j, b.n_putative, b.n_candidates, "guided")
        np.testing.assert_array_equal(a.idx_i, b.idx_i)
        np.testing.assert_array_equal(a.idx_j, b.idx_j)


def test_match_pairs_runs_both_methods(pair):
    """Both methods, through :func:`match_pairs`, return the listed pairs with matches that the true geometry
    confirms.

    Threshold for a correct match, from SIFT's localisation noise (sigma = 0.5 px per coordinate, as
    MatchOptions assumes): the keypoint of j and the true transfer of the keypoint of i differ by two
    independent localisation errors, sigma_d = sigma sqrt(2) = 0.71 px per coordinate (the transfer between
    these near-parallel views has unit gain), so the norm is Rayleigh(sigma_d) and lies beyond
    sigma_d sqrt(2 ln 1000) = 2.63 px for one correct match in a thousand. ``true_match_error_px`` reads the
    depth at the keypoint's nearest pixel, up to sqrt(2)/2 px away: on the dome's steepest wall (64.6 deg at
    the rim of the R = 17.5 mm, 10 mm deep cavity) that changes the depth by (sqrt(2)/2)(z/f) tan 64.6 deg
    and the transfer by f b dz / z^2 = b (sqrt(2)/2) tan 64.6 deg / z = 0.49 px (b = 5 mm, z = 15 mm).
    Total 3.1 px. Each pair must keep at least ``min_matches`` correct matches (fewer and the matcher drops
    the pair); most of what a method returns must be correct, as RANSAC's verification presumes (wrong matches
    that the epipolar geometry cannot reject remain: on the dome ~5-10 %, along the predicted segment for the
    guided matcher, on a degenerate plate model for the exhaustive one; tracks and the off-surface filter drop
    them later, see test_map); and prediction must find at least as many correct matches as exhaustive
    search (the reference's Fig. 3.4 / 4.5).
    """
    seq, feats = pair
    sigma_d = SIFT_SIGMA_PX * np.sqrt(2.0)
    rim_slope = np.arcsin(np.sqrt(17.5**2 - 7.5**2) / 17.5)
    threshold = sigma_d * np.sqrt(2.0 * np.log(1000.0)) + 5.0 * np.sqrt(0.5) * np.tan(rim_slope) / 15.0
    pairs = [(0, 1, 1.0), (1, 2, 1.0)]
    g = match_pairs(seq.camera, feats, seq.measured_poses, pairs, DepthPrior(12.0, 28.0))
    e = match_pairs(seq.camera, feats, seq.measured_poses, pairs, None, method="exhaustive")
    assert [(m.i, m.j) for m in g] == [(m.i, m.j) for m in e] == [(0, 1), (1, 2)]
    assert {m.method for m in g} == {"guided"} and {m.method for m in e} == {"exhaustive"}
    # per method and pair: (matches, correct, fraction correct, worst error px), all shown on failure
    found = {}
    for m in g + e:
        err = true_match_error_px(seq.camera, seq.true_poses[m.i], seq.true_poses[m.j], seq.depths[m.i],
                                  feats[m.i].keypoints[m.idx_i], feats[m.j].keypoints[m.idx_j])
        found[m.method, m.i, m.j] = (len(m), int(np.sum(err < threshold)), round(float(np.mean(err < threshold)), 3),
                                     round(float(np.nanmax(err)), 1))
    assert all(n_correct >= MatchOptions().min_matches for _, n_correct, _, _ in found.values()), found
    assert all(fraction > 0.5 for _, _, fraction, _ in found.values()), found
    for i, j, _ in pairs:
        assert found["guided", i, j][1] >= found["exhaustive", i, j][1], found


def test_ratio_test_among_grouped_candidates():
    a = np.array([0, 0, 1, 2, 2, 2])
    b = np.array([5, 6, 7, 8, 9, 10])
    d2 = np.array([1.0, 4.0, 3.0, 9.0, 1.0, 1.1], np.float32)
    ma, mb, _ = _ratio_select_grouped(a, b, d2, 0.8)
    # 0: 1 < 0.64 * 4 passes; 1: alone passes; 2: 1 vs 1.1 fails
    assert ma.tolist() == [0, 1] and mb.tolist() == [5, 7]


def test_two_nearest_equals_opencv_brute_force(pair, monkeypatch):
    import cv2

    from scope3d.feature import matching

    # blocks of ~500 rows, so that both cases cross block boundaries
    monkeypatch.setattr(matching, "_NEAREST_BLOCK_ENTRIES", 500 * 1300)
    # real SIFT descriptors (integers, norm ~512: the matrix-product distances are exact), and random
    # non-integer ones in blocks of rows across the block size, with duplicated rows for exact ties
    _, feats = pair
    rng = np.random.default_rng(0)
    noisy = rng.random((1500, 128), dtype=np.float32) * 40.0
    noisy[1100:1110] = noisy[:10]
    cases = [(feats[0].descriptors, feats[1].descriptors), (noisy[:1300], noisy[200:])]
    for desc_a, desc_b in cases:
        knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(desc_a, desc_b, k=2)
        nearest, best, second = two_nearest(desc_a, desc_b)
        assert nearest.tolist() == [m[0].trainIdx for m in knn]
        if desc_a is feats[0].descriptors:  # integer arithmetic below 2^24: exact
            assert np.array_equal(best, [m[0].distance for m in knn])
            assert np.array_equal(second, [m[1].distance for m in knn])
        else:  # float32 rounding of |a|^2 + |b|^2 - 2 a.b: ~100 ulps of |a|^2 + |b|^2 (~1e5 here) in the square
            scale = 1e-5 * (np.einsum("ij,ij->i", desc_a, desc_a) + np.max(np.einsum("ij,ij->i", desc_b, desc_b)))
            assert np.all(np.abs(best**2 - np.array([m[0].distance for m in knn])**2) <= scale)
            assert np.all(np.abs(second**2 - np.array([m[1].distance for m in knn])**2) <= scale)


def test_bad_inputs(pair):
    seq, feats = pair
    with pytest.raises(ValueError):
        DepthPrior(0.0, 10.0)
    with pytest.raises(ValueError):
        DepthPrior(20.0, 10.0)
    with pytest.raises(ValueError):
        MatchOptions(ratio=1.5)
    with pytest.raises(ValueError):
        MatchOptions(geometric_model="affine")
    with pytest.raises(ValueError):
        PairOptions(min_overlap=2.0)
    with pytest.raises(ValueError, match="method"):
        match_pairs(seq.camera, feats, seq.measured_poses, [(0, 1, 1.0)], None, method="magic")
    with pytest.raises(ValueError, match="depth prior"):
        match_pairs(seq.camera, feats, seq.measured_poses, [(0, 1, 1.0)], None)


def test_depth_prior_is_data_that_pickles_and_keeps_its_ray_ranges():
    """Cluster workers receive depth priors by pickling: the box and the surface band must survive it
    and give the same per-ray ranges (the box's slab test is exact: a ray through the box centre
    enters and leaves it at the box's near and far faces)."""
    import pickle

    from scope3d.scene.surface import SurfaceOptions, fit_surface
    from scope3d.sfm.depth_priors import box_depth_prior

    pose = Pose.from_centre(np.eye(3), [0.0, 0.0, -20.0])  # looking along +z from 20 mm before the origin
    box = box_depth_prior([-5.0, -5.0, -2.0], [5.0, 5.0, 2.0], [pose])
    rays = np.array([[0.0, 0.0, 1.0], [0.1, -0.05, 1.0], [5.0, 0.0, 1.0]])  # centre, inside, missing the box
    near, far = box.ray_ranges(pose, rays)
    np.testing.assert_allclose([near[0], far[0]], [18.0, 22.0])
    assert np.isnan(near[2]) and np.isnan(far[2])
    rng = np.random.default_rng(0)
    xy = rng.uniform(-6, 6, (600, 2))
    surface = fit_surface(np.column_stack([xy, 0.02 * (xy ** 2).sum(axis=1)]), options=SurfaceOptions(grid_step_mm=0.5),
                          towards=np.array([0.0, 0.0, -1.0]))
    band = DepthPrior(10.0, 30.0).with_band(surface, 0.5)
    for prior in (box, band):
        back = pickle.loads(pickle.dumps(prior))
        for a, b in zip(prior.ray_ranges(pose, rays), back.ray_ranges(pose, rays)):
            np.testing.assert_array_equal(a, b)
    lo, hi = band.ray_ranges(pose, rays[:2])
    np.testing.assert_allclose(hi - lo, 1.0, rtol=0.05)  # +-0.5 mm along a normal within a few degrees of the ray


def test_best_two_per_query_is_the_sorted_pairs_first_and_second():
    rng = np.random.default_rng(3)
    desc = rng.integers(0, 4, size=(60, 4)).astype(np.float32)  # few distinct values: many tied distances
    query, cand = rng.integers(0, 40, 3000), rng.integers(0, 60, 3000)
    d2 = pair_squared_distances(desc, desc, cand, query)
    np.testing.assert_array_equal(d2, ((desc[cand] - desc[query]) ** 2).sum(1))
    best, best_d2, second_d2 = best_two_per_query(query, cand, d2, 45)
    # the reference: the pairs sorted by (query, d2, candidate), the first and second of each query
    order = np.lexsort((cand, d2, query))
    for q in range(45):
        mine = order[query[order] == q]
        if len(mine) == 0:
            assert best[q] == -1 and best_d2[q] == np.inf and second_d2[q] == np.inf
            continue
        assert (best[q], best_d2[q]) == (cand[mine[0]], d2[mine[0]])
        assert second_d2[q] == (d2[mine[1]] if len(mine) > 1 else np.inf)
