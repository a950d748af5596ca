"""The live map (issue 36) on a short rendered video: the dome's survey path at 30 fps, 320 px frames, the robot
reporting every frame within +-3 mm / +-1.5 deg (uniform, independent per frame).

Bounds from the set-up:

* the true centre lies within 3 mm of every report per axis; the tracking's image pose is in the map's
  world, whose keyframes each stay inside their report's box, so that world is off the truth by at most one
  box (3 mm per axis) and the image pose (refined inside twice the report's box) within 3 mm of the truth
  plus the tracking's own error; the fused pose mixes these measurements, so after the filter has settled
  (the first second) its error per axis stays within 6 mm;
* fusion must help: the image pose is good to the map's ~0.1-1 mm, the report to 3 mm per axis (median
  norm ~2.6 mm for a uniform box), so the fused median must be below the robot's median;
* the final map is the map's own bounded-adjustment stage over the same keyframes with the robot's boxes:
  its surface error after ICP (which removes the common offset of all poses the images cannot see) is
  within a factor 1.5 of ``scope3d map``'s on the same keyframes (the issue's benchmark target is 10 %; the
  factor here guards against a broken map: an unadjusted or wrongly gauged one is 10-30 times worse).
"""
from __future__ import annotations

import json
import pickle
from dataclasses import replace

import numpy as np
import pytest

from scope3d import phantoms
from scope3d.cli.main import main
from scope3d.feature.detection import FEATURE_PRESETS
from scope3d.io.dataset import load_dataset, write_dataset
from scope3d.io.scan_plan import PlanFile
from scope3d.phantoms.trajectories import build_trajectory
from scope3d.pipelines.live import LiveOptions
from scope3d.pipelines.live import run as run_live
from scope3d.pipelines.surgical_map import MapOptions
from scope3d.pipelines.surgical_map import run as run_map
from scope3d.sfm.live_mapping import LIVE_PRESETS, LIVE_STATUSES, LiveMapper, LiveMapperOptions

SIZE = 320
N_FRAMES = 100
ROBOT_MM = 3.0


@pytest.fixture(scope="module")
def video(tmp_path_factory):
    grid = build_trajectory("grid5x6")
    camera = phantoms.generate("dome", size=(SIZE, SIZE), n_frames=1).camera
    plan = PlanFile(list(grid.poses), np.zeros(len(grid.poses), int), camera.fov_deg, {})
    seq = phantoms.generate("dome", seed=0, pose_noise_mm=ROBOT_MM, size=(SIZE, SIZE), plan=plan, video_fps=30.0,
                            n_frames=N_FRAMES)
    return load_dataset(phantoms.write(seq, tmp_path_factory.mktemp("live") / "dome_video"))


@pytest.fixture(scope="module")
def streamed(video):
    options = replace(LIVE_PRESETS["dim_endoscope"], worker="inline")
    with LiveMapper(video.camera, options) as mapper:
        frames = [mapper.add_frame(video.frame(k), video.poses[k], k / 30.0) for k in range(len(video))]
        during = mapper.current_map()
        final = mapper.finish()
    return frames, during, final


def test_every_frame_gets_a_fused_pose_within_the_physics(video, streamed):
    frames, _, _ = streamed
    truth = video.ground_truth.poses
    assert [f.index for f in frames] == list(range(len(video)))
    assert {f.status for f in frames} <= set(LIVE_STATUSES)
    assert sum(f.image_pose is not None for f in frames) >= len(frames) // 4  # the map is used, not only the robot
    settled = [f for f in frames if f.time_s >= 1.0]
    fused = np.array([np.abs(f.pose.centre - truth[f.index].centre) for f in settled])
    assert fused.max() <= 2 * ROBOT_MM
    fused_norm = np.linalg.norm(fused, axis=1)
    robot_norm = np.array([np.linalg.norm(video.poses[f.index].pose.centre - truth[f.index].centre) for f in settled])
    assert np.median(fused_norm) < np.median(robot_norm)
    for f in frames:
        assert f.covariance.shape == (6, 6) and np.all(np.linalg.eigvalsh(f.covariance) > 0)
        assert f.latency_ms > 0


def test_keyframes_are_all_in_the_final_map(streamed):
    frames, during, final = streamed
    kept = [f.index for f in frames if f.keyframe is not None]
    assert [f.keyframe for f in frames if f.keyframe is not None] == list(range(len(kept)))
    assert len(kept) >= 3 and final.final
    assert final.keyframe_frames.tolist() == kept
    assert len(final.keyframe_poses) == len(kept)
    seen = np.bincount(final.tracks.frame, minlength=len(kept))
    assert np.all(seen >= 15)  # every keyframe holds points (15: the absolute pose's minimum of inliers)
    assert len(during.keyframe_frames) == len(kept) and len(during.points) > 0 and not during.final


def test_final_map_matches_the_map_on_the_same_keyframes(video, streamed, tmp_path):
    _, _, final = streamed
    kf = final.keyframe_frames.tolist()
    gt = video.ground_truth
    root = write_dataset(tmp_path / "keyframes", video.camera, [video.frame_paths[k] for k in kf],
                         [video.poses[k] for k in kf], names=[video.names[k] for k in kf],
                         true_poses=[gt.poses[k] for k in kf], true_surface=gt.surface(),
                         true_depths=[gt.depth(k) for k in kf], scene=gt.scene)
    mapped = run_map(MapOptions(features=FEATURE_PRESETS["dim_endoscope"], figures=False, fluorescence=None),
                     load_dataset(root), tmp_path / "map")
    from scope3d.metrology.evaluation import surface_errors
    from scope3d.scene.mesh import SampledSurface

    live, _, _ = surface_errors(final.points, SampledSurface(gt.surface(), 0.05))
    reference = mapped.report["surface_error_mm"]
    assert live["after_icp"]["mean"] <= 1.5 * reference["after_icp"]["mean"]


def test_workers_give_the_same_answer(video):
    """The keyframe work applied at a fixed frame: a worker process, a thread and inline agree exactly."""
    n = 60
    poses = {}
    for worker in ("inline", "process"):
        with LiveMapper(video.camera, replace(LIVE_PRESETS["dim_endoscope"], worker=worker)) as mapper:
            poses[worker] = [mapper.add_frame(video.frame(k), video.poses[k], k / 30.0).pose.matrix for k in range(n)]
    np.testing.assert_array_equal(np.array(poses["inline"]), np.array(poses["process"]))


def test_options_refuse_nonsense():
    with pytest.raises(ValueError):
        LiveMapperOptions(worker="gpu")
    with pytest.raises(ValueError):
        LiveMapperOptions(local_window=1)
    with pytest.raises(ValueError):
        LiveMapperOptions(min_inlier_fraction=0.0)


def test_live_job_writes_its_outputs_and_its_result_pickles(video, tmp_path):
    """The job as `scope3d live` runs it (worker process, as fast as possible), through the Python API so
    that its result can be pickled (cluster workers send results back)."""
    out = tmp_path / "live"
    result = run_live(LiveOptions(LIVE_PRESETS["dim_endoscope"], wait=False), video, out)
    report = json.loads((out / "report.json").read_text())
    assert report["n_frames"] == len(video)
    assert set(report["latency_ms"]) >= {"median", "p99"}
    assert {"surface_error_mm", "pose_error", "tracking_error"} <= set(report)
    for name in ("poses.csv", "frames.csv", "keyframes.csv", "map.ply", "live.png"):
        assert (out / name).is_file()
    assert len((out / "poses.csv").read_text().splitlines()) == len(video) + 1
    assert len(list((out / "keyframe_maps").glob("*.ply"))) == report["n_keyframes"]
    back = pickle.loads(pickle.dumps(result))
    assert back.summary() == result.summary()


def test_live_command_refuses_bad_input(tmp_path, capsys):
    assert main(["live", str(tmp_path / "missing"), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "missing" in err[0]
    assert not (tmp_path / "out").exists()


def test_kalman_change_world_moves_the_estimate_exactly():
    """A map moved by its adjustment: the filter's pose becomes ``pose @ new_from_old^-1`` to rounding."""
    from scope3d.estimators.kalman import PoseKalmanFilter
    from scope3d.geometry.pose import Pose
    from scope3d.geometry.rotation import rotvec_to_matrix

    kf = PoseKalmanFilter()
    for w, x in ((0.3, 1.0), (0.31, 1.1)):  # two poses 0.1 mm apart: a velocity to carry over
        pose = Pose.from_centre(rotvec_to_matrix(np.array([0.1, 0.2, w])), np.array([x, 2.0, 3.0]))
        kf.update(pose, np.eye(6) * 1e-4)
    kf.predict(0.1)
    new_from_old = Pose.from_centre(rotvec_to_matrix(np.array([0.05, -0.02, 0.01])), np.array([0.5, -0.3, 0.2]))
    before, speed = kf.pose, np.linalg.norm(kf.state[9:12])
    kf.change_world(new_from_old)
    np.testing.assert_allclose(kf.pose.matrix, (before @ new_from_old.inverse()).matrix, atol=1e-12)
    assert np.isclose(np.linalg.norm(kf.state[9:12]), speed)  # a rigid move keeps the speed


def test_a_mirrored_or_collapsed_window_is_not_a_map():
    """Two keyframes a few mm apart can adjust to points behind the cameras, or all onto them: such a window
    gives no depth prior (None), so the local map is refused instead of the depth prior raising."""
    from scope3d.geometry.pose import Pose
    from scope3d.scene.tracks import Tracks
    from scope3d.sfm.live_mapping import _KeyframeWork

    camera = phantoms.generate("dome", size=(64, 64), n_frames=1).camera
    work = _KeyframeWork(camera, LiveMapperOptions())
    poses = [Pose.identity(), Pose.identity()]
    n = 50

    def tracks(z):
        xyz = np.column_stack([np.zeros(n), np.zeros(n), z])
        return Tracks(np.repeat(np.arange(n), 2), np.tile([0, 1], n), np.zeros(2 * n, np.int64),
                      np.zeros((2 * n, 2)), np.zeros((n, 3), np.uint8), xyz)

    near, far = LiveMapperOptions().working_range_mm
    good = work._depth_prior(poses, tracks(np.linspace(10.0, 20.0, n)))
    assert good is not None and good.near_mm <= 10.0 and good.far_mm >= 20.0
    assert work._depth_prior(poses, tracks(np.linspace(-20.0, 20.0, n))) is None  # half behind: mirrored
    assert work._depth_prior(poses, tracks(np.full(n, near / 10))) is None  # collapsed onto the cameras


def test_retired_features_leave_every_match():
    """A keyframe's features that saw tissue since changed (the change test retires them) are in no match the
    local or the global BCBA builds tracks from; the other matches are kept as they were."""
    from scope3d.feature.matching import PairMatches
    from scope3d.sfm.live_mapping import _KeyframeWork

    camera = phantoms.generate("dome", size=(64, 64), n_frames=1).camera
    work = _KeyframeWork(camera, LiveMapperOptions())
    work.retired = [np.zeros(10, bool), np.zeros(10, bool)]
    work.retired[0][[2, 5]] = True
    work.retired[1][[0, 7]] = True
    m = PairMatches(0, 1, np.arange(10), np.arange(10)[::-1])  # feature i of 0 with 9 - i of 1
    kept = work._usable(m)
    assert kept.idx_i.tolist() == [0, 1, 3, 4, 6, 7, 8]  # 2, 5 retired in 0; 9 (with 0) and 2 (with 7) in 1
    np.testing.assert_array_equal(kept.idx_j, 9 - kept.idx_i)
    work.retired = [np.zeros(10, bool), np.zeros(10, bool)]
    assert work._usable(m) is m


def test_the_change_tests_reduced_camera_sees_the_reduced_image():
    """The change test sweeps keyframes reduced twice: a point's pixel in the reduced camera is the mean of
    the 2 x 2 full pixels it averages, u' = (u + 0.5) / 2 - 0.5, to rounding."""
    from scope3d.sfm.live_mapping import _reduced, _reduced_camera

    camera = phantoms.generate("dome", size=(SIZE, SIZE), n_frames=1).camera
    small = _reduced_camera(camera, 2)
    assert (small.width, small.height) == (SIZE // 2, SIZE // 2)
    assert _reduced(np.zeros((SIZE, SIZE, 3), np.uint8), 2).shape == (SIZE // 2, SIZE // 2, 3)
    points = np.random.default_rng(0).uniform([-5, -5, 10], [5, 5, 30], (50, 3))
    np.testing.assert_allclose(small.project(points), (camera.project(points) + 0.5) / 2 - 0.5, atol=1e-9)


def test_the_gauge_step_between_local_maps_is_recovered():
    """Two local maps whose worlds differ by a known rigid step (rotation, shift) with keyframes on one line:
    the step fitted to their common keyframes (centres and a point down each optical axis) is it, to
    rounding."""
    from scope3d.estimators.gauge import moved_by
    from scope3d.geometry.pose import Pose
    from scope3d.geometry.rotation import rotvec_to_matrix
    from scope3d.geometry.similarity import Similarity
    from scope3d.scene.tracks import Tracks
    from scope3d.sfm.live_mapping import _LocalMap, _world_step

    down = np.diag([1.0, -1.0, -1.0])
    poses = [Pose.from_centre(down, np.array([x, 12.5, 15.0])) for x in (0.0, 3.0, 6.0, 9.0)]
    step = Similarity(1.0, rotvec_to_matrix(np.array([0.01, -0.02, 0.03])), np.zeros(3), np.array([0.4, -0.3, 0.2]))
    empty = Tracks(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2)),
                   np.zeros((0, 3), np.uint8))
    old = _LocalMap([0, 1, 2, 3], poses, empty, None)
    new = _LocalMap([1, 2, 3, 4], moved_by(poses[1:], step) + [poses[0]], empty, None)
    fitted = _world_step(old, new, 20.0)
    probe = np.random.default_rng(1).uniform(-10, 10, (20, 3))
    np.testing.assert_allclose(fitted.apply(probe), step.apply(probe), atol=1e-9)


def test_the_change_test_retires_the_resected_walls_old_features():
    """The worker's change test on the phantom's resection: the dome's first survey row at 30 fps, a pit of 3 mm
    radius and 1.5 mm depth cut at 1 s under (0, 9) mm, in view all along. The local map: points of the wall
    as it was (frame 24's true depths, every 6th pixel), each seen by keyframe 0 (frame 24, before the cut) and
    keyframe 1; keyframes 1-3 (frames 40, 45, 50, after it, 1.7 mm apart: at the survey's keyframe spacing,
    3.3 mm, the half-size sweep kept a depth on none of the pit's deep points, docs/live.md) are the test's
    sweeps, with their true poses (as a local BCBA gives them: relative errors of hundredths of a
    millimetre). Keyframe 0's features over the pit's deep part (the wall moved 1 mm or more) are retired,
    none far from the pit, and no feature of the keyframes that saw the new wall."""
    from functools import partial
    from types import SimpleNamespace

    from scope3d.feature.depth_prior import DepthPrior
    from scope3d.mvs.surface_change import detect_surface_change
    from scope3d.phantoms.resection import Resection, wall_moved_mm
    from scope3d.scene.tracks import Tracks
    from scope3d.sfm.live_mapping import _KeyframeWork, _LocalMap, _reduced

    seq = phantoms.generate("dome", seed=0, size=(320, 240), video_fps=30.0, n_frames=60,
                            resection=Resection(1.0, radius_mm=3.0, depth_mm=1.5, centre_xy_mm=(0.0, 9.0)))
    truth = seq.scene_info["resection"]
    frames = [24, 40, 45, 50]
    camera, poses = seq.camera, [seq.true_poses[f] for f in frames]
    depth = seq.depths[frames[0]]
    v, u = np.mgrid[0:camera.height:6, 0:camera.width:6].reshape(2, -1)
    ok = np.isfinite(depth[v, u]) & camera.in_image(np.stack([u, v], 1).astype(float))
    px = np.stack([u[ok], v[ok]], 1).astype(float)
    points = poses[0].inverse().transform(camera.unproject(px, depth[v[ok], u[ok]]))
    n = len(points)
    seen_in_1 = camera.project_world(poses[1], points)
    tracks = Tracks(np.repeat(np.arange(n), 2), np.tile([0, 1], n), np.repeat(np.arange(n), 2),
                    np.stack([px, seen_in_1], 1).reshape(-1, 2), np.zeros((n, 3), np.uint8), points)
    options = replace(LiveMapperOptions(), change_test=partial(detect_surface_change))
    work = _KeyframeWork(camera, options)
    work.features = [SimpleNamespace(keypoints=px)] + [SimpleNamespace(keypoints=seen_in_1)] * 3
    work.retired = [np.zeros(n, bool) for _ in frames]
    work.images = {k: _reduced(seq.frames[f], options.change_scale) for k, f in enumerate(frames)}
    work.posed = dict(enumerate(poses))
    work.depth_prior = DepthPrior(10.0, 35.0)
    dropped = work._drop_changed(_LocalMap([0, 1, 2, 3], poses, tracks, None))

    moved = wall_moved_mm(points, truth)
    deep = moved >= 1.0
    retired = work.retired[0]
    assert deep.sum() > 20 and len(dropped) > 0
    assert retired[deep].mean() >= 0.9
    # what is retired is over the pit or within the footprint's reach of its rim: the grid's 6 px are 0.41 mm
    # at 22 mm (fx 321 px), and 16 neighbours on a square grid reach sqrt(16 / pi) = 2.3 spacings, 0.93 mm
    off = np.linalg.norm(points - np.asarray(truth["centre_mm"]), axis=1) - truth["radius_mm"]
    assert np.all(off[retired] <= 1.0)
    assert not any(work.retired[k].any() for k in (1, 2, 3))


def test_thinning_tracking_keeps_one_keyframe_with_baseline_not_a_burst():
    """The keyframe rule on a slow stretch (bench_live's dome survey kept every frame from 268 to 275, 8
    keyframes 0.15 mm apart: tracking had fallen below half the inliers of the local map's first frame, and
    nothing changed that until the next local map, 30 frames later). Here the scope creeps 0.03 mm a frame at
    15 mm from the wall and tracking holds 40 inliers after the first keyframe's 100, below half every frame.
    A keyframe needs triangulation's 1 deg of parallax at the map's depth, 15 tan(1 deg) = 0.262 mm: frame 9
    (0.27 mm) is the first with it (frame 8: 0.24 mm); after it the inliers are measured against its own 40,
    so no later frame is kept. Robot and image report the true pose (the image to 1e-3 mm), so the fused
    pose is the truth to far below the 0.01-0.02 mm margins."""
    from scope3d.geometry.pose import Pose
    from scope3d.sensor.pose_tolerance import MeasuredPose, PoseTolerance
    from scope3d.sfm.localization import LocalizationResult

    camera = phantoms.generate("dome", size=(64, 64), n_frames=1).camera
    image = np.random.default_rng(0).integers(0, 255, (64, 64, 3), dtype=np.uint8)
    poses = [Pose.from_centre(np.diag([1.0, -1.0, -1.0]), np.array([0.03 * k, 0.0, 15.0])) for k in range(30)]
    box = PoseTolerance(np.full(3, 3.0), np.full(3, np.deg2rad(1.5)))

    class Localizer:  # tracking's answer: the true pose, 100 inliers on the first frame, then 40
        def localize(self, image, measured):
            k = len(frames)
            return LocalizationResult("ok", "tracking", poses[k], 100, 100 if k == 0 else 40,
                                      np.diag(np.r_[np.full(3, 1e-8), np.full(3, 1e-6)]), 0.3, 0.0, 0.0)

    class Worker:  # no local map: the keyframe rule alone
        def submit(self, *args):
            pass

        def was_late(self):
            return False

        def close(self):
            pass

    frames = []
    with LiveMapper(camera, replace(LiveMapperOptions(), worker="inline")) as mapper:
        mapper._localizer, mapper._worker, mapper._map_depth_mm = Localizer(), Worker(), 15.0
        for k, pose in enumerate(poses):
            frames.append(mapper.add_frame(image, MeasuredPose(pose, box), k / 30.0))
    assert [f.index for f in frames if f.keyframe is not None] == [0, 9]
    assert all(f.status == "tracked" for f in frames if f.index not in (0, 9))


def test_points_without_parallax_at_the_maps_depth_leave_the_map():
    """A track of two views 0.02 mm apart whose point the adjustment pulled 1 mm in front of them spans
    2 atan(0.01 / 1) = 1.15 deg there, so triangulation's 1 deg gate keeps it; at the map's near depth
    (10 mm) the same views span 0.11 deg, and it is dropped. A wall point 15 mm from views 3 mm apart
    (11 deg) is kept, and one 15 mm from the near-identical views (0.08 deg) is dropped."""
    from scope3d.estimators.triangulation import ray_angles_deg
    from scope3d.geometry.pose import Pose
    from scope3d.scene.tracks import Tracks
    from scope3d.sfm.live_mapping import _with_parallax

    camera = phantoms.generate("dome", size=(64, 64), n_frames=1).camera
    down = np.diag([1.0, -1.0, -1.0])
    poses = [Pose.from_centre(down, np.array([x, 0.0, 15.0])) for x in (0.0, 0.02, 3.0)]
    points = np.array([[0.01, 0.0, 14.0], [1.5, 0.0, 0.0], [0.01, 0.0, 0.0]])  # collapsed, wall, wall
    frame = np.array([0, 1, 0, 2, 0, 1])
    pixels = np.concatenate([camera.project_world(poses[f], points[[t]]) for t, f in zip([0, 0, 1, 1, 2, 2], frame)])
    tracks = Tracks(np.array([0, 0, 1, 1, 2, 2]), frame, np.arange(6), pixels, np.zeros((3, 3), np.uint8), points)
    assert ray_angles_deg(camera, poses, tracks)[0] >= 1.0  # the collapsed point passes triangulation's gate
    kept = _with_parallax(camera, poses, tracks, 10.0, 1.0)
    np.testing.assert_array_equal(kept.points, points[[1]])
