"""Image-only 3-D panorama (sfm.cavity_mapping, metrology.star_scale, ``scope3d panorama``) on the bladder
phantom: star scale, the map from planned poses, clear errors for unusable input."""
from __future__ import annotations

import csv
import json
import pickle
import shutil
from dataclasses import replace

import numpy as np
import pytest

from scope3d.cli.main import main
from scope3d.errors import InputError
from scope3d.estimators.triangulation import TrackOptions, ray_angles_deg, triangulate_tracks
from scope3d.feature.detection import detect
from scope3d.feature.matching import match_exhaustive
from scope3d.feature.tracks import build_tracks
from scope3d.io.dataset import load_dataset
from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import look_at
from scope3d.metrology.evaluation import true_track_points
from scope3d.metrology.star_scale import combine_views, pentagram_area_mm2, star_scale
from scope3d.scene.tracks import Tracks
from scope3d.sensor.camera import Camera
from scope3d.phantoms import generate, write
from scope3d.pipelines.panorama import Panorama3dOptions, evaluate, run
from scope3d.sfm.cavity_mapping import (CavityOptions, _cap_priority, _wall_distance, adjust_cavity, map_cavity,
                                        overlapping_pairs, pair_poses, verified_matches)

# frames 10-23 of the 36-frame spiral: one turn, with three stars seen whole (frames 13, 14, 17, 22)
FIRST, LAST = 10, 23


def _subset(src, dst, keep):
    """A copy of dataset ``src`` holding only the frames whose index is in ``keep``."""
    shutil.copytree(src, dst)
    for table in (dst / "poses.csv", dst / "ground_truth" / "poses.csv"):
        rows = list(csv.reader(table.open()))
        kept = [rows[0]] + [r for k, r in enumerate(rows[1:]) if k in keep]
        with table.open("w", newline="") as f:
            csv.writer(f).writerows(kept)
    names = sorted(p.name for p in (src / "frames").iterdir())
    for k, name in enumerate(names):
        if k not in keep:
            for folder in ("frames", "fluorescence"):
                (dst / folder / name).unlink()
            for p in (dst / "ground_truth" / "depth").glob(name.rsplit(".", 1)[0] + ".*"):
                p.unlink()
    return dst


@pytest.fixture(scope="module")
def bladder(tmp_path_factory):
    seq = generate("bladder", size=(200, 200))
    root = tmp_path_factory.mktemp("panorama") / "bladder"
    write(seq, root)
    return _subset(root, root.parent / "turn", set(range(FIRST, LAST + 1)))


@pytest.fixture(scope="module")
def turn_features(bladder):
    """The turn's dataset and its frames' SIFT features (shared: detection is most of these tests' time)."""
    ds = load_dataset(bladder)
    return ds, [detect(ds.frame(k), ds.camera) for k in range(len(ds))]


def test_pentagram_area():
    # the phantom's 6 mm star: outer radius 3 mm, flat area 10.103 mm^2 (scene.json flat_area_mm2)
    assert pentagram_area_mm2(6.0) == pytest.approx(10.1031, abs=1e-4)


def test_views_combine_by_their_uncertainties():
    # equal sigmas: the plain mean; views agreeing within their sigmas: the mean's sigma, 1/sqrt(n)
    scale, sigma = combine_views(np.array([1.0, 1.002]), np.array([0.01, 0.01]))
    assert scale == pytest.approx(1.001, rel=1e-4) and sigma == pytest.approx(0.01 / np.sqrt(2), rel=0.01)
    # a view four times as certain pulls the mean (weights 16:1); views far apart inflate the sigma
    assert combine_views(np.array([1.0, 1.01]), np.array([0.0025, 0.01]))[0] == pytest.approx(1.0 + 0.01 / 17, abs=2e-5)
    assert combine_views(np.array([0.9, 1.1]), np.array([0.001, 0.001]))[1] > 0.05


def test_star_scale_on_a_map_with_the_true_poses_is_within_one_percent(turn_features):
    ds, features = turn_features
    # consecutive frames matched (fundamental-matrix RANSAC): the points only need true poses here
    matches = [match_exhaustive(ds.camera, features[k], features[k + 1], i=k, j=k + 1) for k in range(len(ds) - 1)]
    tracks = triangulate_tracks(ds.camera, ds.ground_truth.poses, build_tracks(features, matches))
    fluorescence = [ds.fluorescence_frame(k) for k in range(len(ds))]
    scale = star_scale(ds.camera, ds.ground_truth.poses, tracks, fluorescence)
    # the map is in true mm here, so the stars must say 1. The area is counted by each pixel's fluorescence
    # over the star's level, so edge pixels count by their coverage; what is left is the local plane's
    # depth error (two-view points, ~0.5 mm at 25 mm = 2 % of area, averaged over 10+ points: < 1 %)
    assert len(scale.views) >= 2
    assert scale.scale == pytest.approx(1.0, abs=0.01)
    # and a blank fluorescence channel is no scale: refused, not invented
    with pytest.raises(InputError, match="no star"):
        star_scale(ds.camera, ds.ground_truth.poses, tracks, [np.zeros_like(f) for f in fluorescence])


def test_panorama_from_planned_exact_poses_registers_every_frame_near_the_true_wall(bladder, tmp_path):
    out = tmp_path / "pano"
    assert main(["panorama", str(bladder), "--out", str(out), "--quiet"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["n_registered"] == report["n_frames"] == LAST - FIRST + 1
    assert report["scale_source"] == "stars"
    err = report["surface_error_mm"]["after_similarity"]
    # the phantom's poses are exact (0.01 mm tolerance); points are mostly two-view with ~7 deg of
    # parallax at 20-30 mm, 0.5 px keypoint noise at f = 143 px: depth error 25 mm x 0.5 / 143 / 0.12 rad
    # ~ 0.7 mm per point, half of it on average, so a mean of 1 mm bounds a correct map
    assert err["mean"] < 1.0
    # scale from the stars on this map: the 1 %. Measured against the truth on these 200 px frames
    # the stars are 180-320 px, and their pixels alone (cast with the true per-pixel depth) are -1.0 to
    # +0.4 % off per view; the map's points add 0.5-1.7 % per view (the fit's sigma, 16-50 points at
    # 0.4 mm); weighted over four views: -0.3 % (truth) and +0.7 % (this map)
    assert abs(report["scale_error_fraction"]) < 0.01
    # the scale's own uncertainty is reported, and an error of ~1 % lies within a few of it
    assert 0 < report["scale_uncertainty_fraction"] < 0.01
    for name in ("points.ply", "mesh.ply", "panorama_3d.png", "sparse/images.txt", "report.html", "organ_map.png",
                 "organ_coverage.png"):
        assert (out / name).stat().st_size > 0
    # the organ map of one turn of the spiral: every frame on it, against the truth within the issue's
    # targets (1 px p95, coverage within 1 %), and its section in the page
    organ = report["organ_map"]
    assert organ["n_frames_on_map"] == report["n_frames"]
    assert organ["alignment"]["p95_px"] <= 1.0
    assert abs(organ["coverage_error_fraction"]) <= 0.01
    assert 'id="organ-map"' in (out / "report.html").read_text()


def test_two_videos_of_one_cavity_share_one_organ_map(bladder, tmp_path, capsys):
    # the turn split in two "videos" (frames 0-7 and 6-13, planned poses): on one map each covers part of the
    # wall, together what the turn covers, both against the truth within the targets
    first = _subset(bladder, tmp_path / "a", set(range(0, 8)))
    second = _subset(bladder, tmp_path / "b", set(range(6, 14)))
    out = tmp_path / "both"
    assert main(["panorama", str(first), str(second), "--no-scale", "--out", str(out), "--quiet"]) == 0
    organ = json.loads((out / "report.json").read_text())["organ_map"]
    alone = [v["coverage_fraction"] for v in organ["videos"]]
    assert [v["n_registered"] for v in organ["videos"]] == [8, 8]
    assert max(alone) < organ["coverage_fraction"] <= alone[0] + alone[1]
    assert abs(organ["coverage_error_fraction"]) <= 0.01  # the truth: both videos' true poses
    assert organ["alignment"]["p95_px"] <= 1.0 and organ["n_frames_on_map"] == 16
    # images only, two videos' maps have no common frame: refused before any work, in one line
    assert main(["panorama", str(first), str(second), "--no-scale", "--ignore-poses", "--out",
                 str(tmp_path / "refused"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "planned poses" in err and "Traceback" not in err and not (tmp_path / "refused").exists()


def test_frames_without_overlap_are_refused(bladder, tmp_path, capsys):
    # three frames a third of a turn apart see different parts of the wall
    far = _subset(bladder, tmp_path / "far", {0, 6, 12})
    ds = load_dataset(far)
    features = [detect(ds.frame(k), ds.camera) for k in range(len(ds))]
    with pytest.raises(InputError, match="overlap"):
        map_cavity(ds.camera, features)
    assert main(["panorama", str(far), "--out", str(tmp_path / "p"), "--quiet"]) == 2
    assert "overlap" in capsys.readouterr().err
    assert not (tmp_path / "p").exists()


def test_scale_requested_without_star_frames_is_refused(bladder, tmp_path, capsys):
    bare = tmp_path / "bare"
    shutil.copytree(bladder, bare)
    shutil.rmtree(bare / "fluorescence")
    assert main(["panorama", str(bare), "--out", str(tmp_path / "p"), "--quiet"]) == 2
    assert "--no-scale" in capsys.readouterr().err
    assert not (tmp_path / "p").exists()


def test_planned_poses_place_every_frame_of_an_unseen_cavity(tmp_path):
    # another shape than the default (issue 11: --shape-seed 5 --cavity-mm 40,35,30): the image-only pair
    # test (the wall's depth spread) refused the consecutive pairs that joined frames 7-16 to the rest,
    # and the panorama exited 2 although the plan places every frame
    data = tmp_path / "unseen"
    assert main(["phantom", "bladder", "--shape-seed", "5", "--cavity-mm", "40,35,30", "--size", "160x160",
                 "--pose-noise", "1", "--seed", "7", "--out", str(data), "--quiet"]) == 0
    ds = load_dataset(data)
    result = run(Panorama3dOptions(stars=None, figures=False), ds, tmp_path / "pano")
    report, cavity = result.report, result.cavity
    assert pickle.loads(pickle.dumps(result)).summary() == result.summary()  # results travel to cluster workers
    assert report["n_registered"] == report["n_frames"] == 36
    assert report["scale_source"] == "plan"
    # the plan's ±1 mm and ±0.5 deg on 2-4 mm baselines move a two-view point by a large part of its
    # depth; the bounded adjustment must place the same tracks closer to the wall than the plan as given
    planned = [m.pose for m in ds.poses]
    as_planned = triangulate_tracks(ds.camera, planned, cavity.tracks, TrackOptions())
    plan_error = evaluate(ds, replace(cavity, tracks=as_planned, poses=planned), 0.25)["surface_error_mm"]
    assert report["surface_error_mm"]["after_similarity"]["mean"] < plan_error["after_similarity"]["mean"]


def test_pairs_the_start_says_overlap_are_matched_and_verified_against_the_truth(turn_features):
    ds, features = turn_features
    cam, poses = ds.camera, ds.ground_truth.poses
    chain = [match_exhaustive(cam, features[k], features[k + 1], i=k, j=k + 1) for k in range(len(ds) - 1)]
    tried = {(m.i, m.j) for m in chain}
    more = overlapping_pairs(cam, features, poses, build_tracks(features, chain), tried, CavityOptions())
    # the poses place the wall: frames two apart or across the turn overlap, and only untried pairs come back
    assert any(m.j - m.i >= 2 for m in more) and not tried & {(m.i, m.j) for m in more}
    verified, relative = verified_matches(cam, features, more, poses)
    assert verified and len(relative) == len(verified)

    def wrong(pairs):  # each match against the truth: frame i's keypoint lifted by its true depth into frame j
        out = []
        for m in pairs:
            depth = ds.ground_truth.depth(m.i)
            px = features[m.i].keypoints[m.idx_i]
            z = depth[np.rint(px[:, 1]).astype(int), np.rint(px[:, 0]).astype(int)]
            world = poses[m.i].inverse().transform(np.c_[cam.pixel_to_normalised(px), np.ones(len(px))] * z[:, None])
            err = np.linalg.norm(cam.project_world(poses[m.j], world) - features[m.j].keypoints[m.idx_j], axis=1)
            out.append(err[np.isfinite(err)] > 3.0)  # 3 px: 6 sigma of SIFT's 0.5 px plus the depth lookup
        return np.concatenate(out)

    # the essential matrix's inliers keep fewer wrong matches than the fundamental matrix's (608 px spiral:
    # 1.0 % against 5-10 %); a few dozen cross-turn matches here, so at most 5 % (2 of 40)
    assert wrong(verified).sum() <= wrong(more).sum()
    assert wrong(verified).mean() <= 0.05


def test_the_adjustment_keeps_the_best_determined_tracks_under_its_cap(turn_features):
    ds, features = turn_features
    cam, gt = ds.camera, ds.ground_truth
    pairs = [match_exhaustive(cam, features[k], features[k + d], i=k, j=k + d) for d in (1, 2)
             for k in range(len(ds) - d)]
    tracks = build_tracks(features, pairs)
    every = triangulate_tracks(cam, gt.poses, tracks, CavityOptions().tracks)
    # a cap of half the tracks, the phantom's poses (exact: 0.01 mm, bounded) holding the rays in place
    options = CavityOptions(max_points=every.n_tracks // 2)
    kept, poses, _ = adjust_cavity(cam, tracks, [m.pose for m in ds.poses], options, ds.poses)

    def observations(t):  # each track as its set of (frame, feature)
        return [frozenset(zip(t.frame[t.track == k].tolist(), t.feature[t.track == k].tolist())) for k in range(t.n_tracks)]

    kept_keys = set(observations(kept))
    is_kept = np.array([key in kept_keys for key in observations(every)])
    length, angle = every.lengths(), ray_angles_deg(cam, gt.poses, every)
    # the tracks are two-view here (consecutive and two-apart pairs); after each frame's few widest
    # (:func:`_cap_priority`) the widest rays are kept (measured with the true poses; the bounded poses and
    # the adjusted points move the angles by hundredths of a degree), and every frame keeps some
    two = length == 2
    assert two.mean() > 0.9 and 0 < is_kept.sum() <= options.max_points
    assert np.median(angle[two & is_kept]) > np.percentile(angle[two & ~is_kept], 90)
    assert set(kept.frame.tolist()) == set(every.frame.tolist())
    # physics: a point's depth error is its distance times the keypoint noise over its rays' angle, so the
    # kept two-view points lie nearer their true positions than the dropped ones (with the true poses), by
    # about the ratio of their mean inverse angles (0.86 here; measured 0.82): each mean of ~500 points whose
    # errors spread by about their mean is good to ~5 %, the ratio to ~7 %, so within 3 of those
    truth = true_track_points(cam, gt.poses, gt.depth, every.frame, every.track, every.pixels, every.n_tracks)
    error = np.linalg.norm(every.points - truth, axis=1)
    ratio = np.nanmean(error[two & is_kept]) / np.nanmean(error[two & ~is_kept])
    expected = np.mean(1 / angle[two & is_kept]) / np.mean(1 / angle[two & ~is_kept])
    assert ratio < 1.0 and abs(ratio - expected) < 0.2


def test_the_cap_keeps_each_frames_widest_tracks_even_when_all_its_rays_are_narrow():
    cam = Camera.from_fov(200, 200, 70.0)
    # frames 0 and 1 5 mm apart, frame 2 0.5 mm from frame 1, a wall 30 mm away: tracks 0-1 meet at ~10 deg,
    # tracks 1-2 at ~1 deg
    centres = [np.array([-2.5, 0, 0]), np.array([2.5, 0, 0]), np.array([3.0, 0, 0])]
    poses = [Pose.from_centre(look_at(c, np.array([0.0, 0.0, 30.0])), c) for c in centres]
    rng = np.random.default_rng(0)
    X = np.c_[rng.uniform(-5, 5, (30, 2)), np.full(30, 30.0)]
    pairs = [(0, 1)] * 20 + [(1, 2)] * 10
    track = np.repeat(np.arange(30), 2)
    frame = np.array(pairs).ravel()
    pixels = np.array([cam.project_world(poses[f], X[t][None])[0] for t, f in zip(track, frame)])
    tracks = Tracks(track, frame, np.arange(60), pixels, np.zeros((30, 3), np.uint8), X)
    kept = tracks.strongest(12, _cap_priority(cam, poses, tracks, 4))
    # by the angle alone the 12 would all be 0-1 tracks and frame 2 would lose every observation; each
    # frame's 4 widest first, then the widest: frame 2 keeps its 4, the other 8 are 0-1 tracks
    assert kept.n_tracks == 12 and np.sum(kept.frame == 2) == 4


def test_planned_pairs_found_at_the_measured_wall_distance(turn_features):
    ds, features = turn_features
    default = pair_poses(ds.camera, features, CavityOptions(), measured=ds.poses)
    at_wall = pair_poses(ds.camera, features, CavityOptions(plan_overlap_at_wall=True), measured=ds.poses)
    # the first pairs measure the wall's distance: against the true depth maps of the frames (z-depths;
    # the distance along a ray is up to 1/cos(35 deg) = 1.22 x longer at the field's edge, ~1.1 x on average)
    posed = [(m, r) for m, r in zip(at_wall[0], at_wall[1])]
    distance = _wall_distance(ds.camera, features, [p.pose for p in ds.poses], posed)
    true_depth = np.nanmedian(np.concatenate([ds.ground_truth.depth(k)[ds.camera.mask()].ravel() for k in range(len(ds))]))
    assert 0.95 * true_depth < distance < 1.3 * true_depth
    # this turn sees the wall at 25-35 mm, near the shell's 37 mm: the same pairs are posed
    assert {(m.i, m.j) for m in at_wall[0]} == {(m.i, m.j) for m in default[0]}


def test_pairs_disagreeing_with_the_averaged_rotations_are_inconsistent():
    from scope3d.estimators.averaging import RelativePose
    from scope3d.geometry.rotation import rotvec_to_matrix
    from scope3d.estimators.cavity_start import consistent_pairs
    rng = np.random.default_rng(3)
    rotations = np.stack([rotvec_to_matrix(rng.normal(0.0, 0.5, 3)) for _ in range(6)])
    sigma = np.deg2rad(0.5)  # a consecutive pair's rotation sigma on the 608 px spiral: 0.1-0.8 deg
    pairs = []
    for i, j in [(0, 1), (1, 2), (2, 3), (3, 4), (4, 5), (0, 2), (1, 3), (2, 4)]:
        noise = rotvec_to_matrix(rng.normal(0.0, sigma / np.sqrt(3.0), 3))  # errors of the pair's own sigma
        pairs.append(RelativePose(i, j, noise @ rotations[j] @ rotations[i].T, np.array([1.0, 0, 0]),
                                  np.ones(20, bool), sigma, sigma))
    # a pair fallen into another solution: 10 deg off (the unseen cavity's were 10-110 deg off at 0.2-1.5 deg sigma)
    pairs.append(RelativePose(1, 4, rotvec_to_matrix(np.deg2rad([10.0, 0, 0])) @ rotations[4] @ rotations[1].T,
                              np.array([1.0, 0, 0]), np.ones(20, bool), sigma, sigma))
    keep = consistent_pairs(rotations, pairs)
    assert keep[:-1].all() and not keep[-1]


def test_wall_spread_is_small_for_a_wall_at_one_distance_and_grows_when_scattered():
    from scope3d.geometry.sphere import wall_spread
    rng = np.random.default_rng(4)
    d = rng.normal(size=(2000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    ellipsoid = d * np.array([45.0, 38.0, 32.0]) + 7.0  # the bladder phantom's semi-axes (~90 x 76 x 64 mm)
    scattered = d * rng.uniform(20.0, 70.0, (2000, 1))  # points anywhere in the anatomical shell
    # the ellipsoid's distances from its centre: semi-axes within +-17 % of their mean, median absolute
    # deviation ~0.06; uniform radii between 20 and 70 mm: 12.5 / 45 ~ 0.28
    assert wall_spread(ellipsoid) < 0.15 < 0.2 < wall_spread(scattered)
    assert wall_spread(ellipsoid[:3]) == float("inf")


def test_the_anatomical_shell_keeps_the_near_wall_of_an_elongated_cavity_despite_far_points():
    from scope3d.geometry.sphere import fit_sphere
    from scope3d.sfm.cavity_mapping import anatomical_shell, inside_shell
    rng = np.random.default_rng(3)
    semi_axes = np.array([45.0, 38.0, 32.0])  # the bladder phantom's (~90 x 76 x 64 mm)

    def on_wall(directions):
        d = directions / np.linalg.norm(directions, axis=1, keepdims=True)
        return d / np.sqrt(((d / semi_axes) ** 2).sum(axis=1, keepdims=True))

    d = rng.normal(size=(6000, 3))
    # seen unevenly: 2000 points all round, 2000 more at the -x end of the long axis (the 30 mm default
    # spiral's frame 27 looks there), 0.2 mm of noise (the maps' wall error)
    near_end = d[2000:][d[2000:, 0] < -0.6][:2000]
    wall = on_wall(np.r_[d[:2000], near_end]) + rng.normal(scale=0.2, size=(2000 + len(near_end), 3))
    # 2 % triangulated far off along the long axis, 100-250 mm away (rays meeting at small angles: the
    # start of that spiral had 1 % of its points 100-240 mm from the centre)
    toward = d[-60:] * [1.0, 0.5, 0.5]
    toward[:, 0] = -np.abs(toward[:, 0]) - 1.0
    far = toward / np.linalg.norm(toward, axis=1, keepdims=True) * rng.uniform(100.0, 250.0, (60, 1))
    points = np.r_[wall, far]
    options = CavityOptions()
    centre, r_min, r_max = shell = anatomical_shell(points, [], options)
    # the wall is 32-45 mm from the true centre: a centre within a few mm keeps all of it inside 20-70 mm
    assert np.linalg.norm(centre) < 3.0 and 36.0 < fit_sphere(points, robust=True)[1] < 41.0
    keep = inside_shell(points, shell)
    assert keep[:len(wall)].all() and not keep[len(wall):].any()
    # the algebraic fit (squared radii) is pulled tens of mm towards the far points, and the same shell
    # about it cut the near end's wall (as it did frame 27's)
    algebraic_centre, algebraic_radius = fit_sphere(points)
    s = algebraic_radius / options.nominal_radius_mm
    cut = inside_shell(points, (algebraic_centre, s * options.min_radius_mm, s * options.max_radius_mm))
    assert np.linalg.norm(algebraic_centre) > 20.0 and not cut[:len(wall)].all()


CAMERA_608 = Camera.from_fov(608, 608, 70.0)  # the phantom's frames


def _cavity_map(points, centres, radius_scale=1.0):
    """A CavityMap of ``points`` (N, 3) seen by cameras at ``centres`` (n, 3), each observation of a point by
    frame 0 (only the points and poses matter to the self-check)."""
    from scope3d.scene.tracks import Tracks
    from scope3d.geometry.sphere import fit_sphere
    from scope3d.sfm.cavity_mapping import CavityMap
    n_points = len(points)
    tracks = Tracks(np.arange(n_points), np.zeros(n_points, int), np.arange(n_points), np.zeros((n_points, 2)),
                    np.zeros((n_points, 3), np.uint8), np.asarray(points, float))
    poses = [Pose.from_centre(np.eye(3), c) for c in centres]
    centre, radius = fit_sphere(points)
    return CavityMap(tracks, poses, centre, radius_scale * radius, np.ones(len(centres), bool), [], [], 0, [], False)


def _wall_and_cap():
    """The bladder phantom's wall (semi-axes 45, 38, 32 mm) with cameras on a spiral 8 mm about its centre
    (the 36-frame spiral's camera spread), and the measured failure's shape: a cap of a sphere 3.4 times
    larger (131 mm radius, 30 deg wide) with the same cameras pressed against it (its points 5 mm away)."""
    rng = np.random.default_rng(5)
    d = rng.normal(size=(3000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    wall = d * np.array([45.0, 38.0, 32.0])
    t = np.linspace(0.0, 4.0 * np.pi, 36)
    cameras = np.c_[8.0 * np.cos(t), 8.0 * np.sin(t), np.linspace(-6.0, 6.0, 36)]
    cone = d[d[:, 2] > np.cos(np.deg2rad(30.0))]
    cap = 131.0 * cone - np.array([0.0, 0.0, 131.0 - 5.0])  # the cap's apex 5 mm above the cameras' centroid
    return wall, cap, cameras


def test_cameras_off_centre_separates_a_cavity_seen_from_inside_from_a_cap_seen_from_its_wall():
    from scope3d.geometry.sphere import wall_spread
    from scope3d.sfm.cavity_map_choice import MAX_OFF_CENTRE, cameras_off_centre
    wall, cap, cameras = _wall_and_cap()
    poses = [Pose.from_centre(np.eye(3), c) for c in cameras]
    # the cameras' centroid is the wall's centre: 0 up to the fit of an ellipsoid by a sphere; the cap's
    # centre is 126 mm from them on a 131 mm radius: 0.96 (the unseen wet cavity's broken map: 0.97)
    assert cameras_off_centre(wall, poses) < 0.1 < MAX_OFF_CENTRE < 0.9 < cameras_off_centre(cap, poses)
    assert wall_spread(cap) < wall_spread(wall)  # why the wall's spread alone chose the cap (0.025 vs 0.039)
    assert cameras_off_centre(wall[:3], poses) == float("inf")


def test_self_check_flags_cameras_off_centre_and_a_radius_outside_the_anatomical_shell():
    from scope3d.pipelines.panorama import self_check
    wall, cap, cameras = _wall_and_cap()
    options = CavityOptions()
    good = self_check(_cavity_map(wall, cameras), options, scaled=True, camera=CAMERA_608)
    assert good["passed"] and not good["problems"] and 32.0 < good["wall_radius_mm"] < 45.0
    bad = self_check(_cavity_map(cap, cameras), options, scaled=True, camera=CAMERA_608)
    assert not bad["passed"] and len(bad["problems"]) == 2  # off centre, and 131 mm > 70 mm
    # without a physical scale only the cameras' place is checked
    unscaled = self_check(_cavity_map(cap, cameras), options, scaled=False, camera=CAMERA_608)
    assert unscaled["wall_radius_mm"] is None and len(unscaled["problems"]) == 1
    # a right shape at a wrong scale (stars 3x off) is flagged by the anatomical radius alone
    big = self_check(_cavity_map(wall, cameras, radius_scale=3.0), options, scaled=True, camera=CAMERA_608)
    assert not big["passed"] and "anatomical" in big["problems"][0]


def test_a_map_failing_the_self_check_is_refused_unless_kept(bladder, tmp_path, monkeypatch):
    import scope3d.pipelines.panorama as panorama
    ds = load_dataset(bladder)
    _, cap, cameras = _wall_and_cap()
    broken = _cavity_map(cap, cameras[:len(ds)])
    monkeypatch.setattr(panorama, "map_cavity", lambda *args, **kwargs: broken)
    monkeypatch.setattr(panorama, "evaluate", lambda *args: {})  # the fake map has no true positions
    options = Panorama3dOptions(stars=None, use_planned_poses=False, figures=False, texture=None)
    with pytest.raises(InputError, match="no cavity seen from inside"):
        run(options, ds, tmp_path / "refused")
    assert not (tmp_path / "refused").exists()  # nothing half-written
    report = run(replace(options, refuse_implausible=False), ds, tmp_path / "kept").report
    saved = json.loads((tmp_path / "kept" / "report.json").read_text())
    assert not report["self_check"]["passed"] and saved["self_check"]["cameras_off_centre"] > 0.9


@pytest.fixture(scope="module")
def fisheye_turn(tmp_path_factory):
    """The same turn of the spiral through the phantom lab's 140° capsule fisheye (OPENCV_FISHEYE)."""
    seq = generate("bladder", size=(200, 200), lens="fisheye-140")
    root = tmp_path_factory.mktemp("panorama_fisheye") / "bladder"
    write(seq, root)
    return _subset(root, root.parent / "turn", set(range(FIRST, LAST + 1)))


def test_panorama_through_a_fisheye_lens_registers_every_frame_near_the_true_wall(fisheye_turn, tmp_path):
    out = tmp_path / "pano"
    assert main(["panorama", str(fisheye_turn), "--out", str(out), "--quiet"]) == 0
    report = json.loads((out / "report.json").read_text())
    camera = load_dataset(fisheye_turn).camera
    assert camera.model == "OPENCV_FISHEYE"
    assert report["n_registered"] == report["n_frames"] == LAST - FIRST + 1
    # the pinhole test's bound (1 mm: a point's depth error ~ range x noise / focal / parallax, half of it
    # on average) scaled by the focal lengths: the fisheye spreads 140 deg over the field the pinhole
    # spends 70 deg on, so each pixel spans 143 / fx = 1.9 times the angle at the centre (more at the rim)
    pinhole_fx = Camera.from_fov(200, 200, 70.0).fx
    err = report["surface_error_mm"]["after_similarity"]
    assert err["mean"] < 1.0 * pinhole_fx / camera.fx
    # the stars through the fisheye: 1.9 times smaller in each direction, so their edge pixels weigh
    # 1.9 times more in the area; the scale's own uncertainty must cover its error (3 sigma)
    assert abs(report["scale_error_fraction"]) <= 3 * report["scale_uncertainty_fraction"]
    # the organ map projects every frame through the lens model: the targets as for the pinhole
    organ = report["organ_map"]
    assert organ["n_frames_on_map"] == report["n_frames"]
    assert organ["alignment"]["p95_px"] <= 1.0
    assert abs(organ["coverage_error_fraction"]) <= 0.01
    for name in ("points.ply", "mesh.ply", "wall.obj", "organ_map.png", "sparse/cameras.txt"):
        assert (out / name).stat().st_size > 0
    assert "OPENCV_FISHEYE" in (out / "sparse" / "cameras.txt").read_text()
