"""Every job is called one way, ``run(options, inputs..., out_dir, *, progress=None) -> <Job>Result`` with a
``summary()``, and every job's result pickles (cluster workers send results back; a result holding a
closure cannot travel). Small real runs where they are cheap; a result built from real parts where the job
itself takes minutes (its real run is pickled in its own test file: tests/test_map.py, test_axial_pipeline.py,
test_panorama_3d.py, test_frames_import.py)."""
from __future__ import annotations

import dataclasses
import importlib
import inspect
import pickle
import pkgutil
import typing

import numpy as np
import pytest

import scope3d.pipelines
from scope3d.geometry.pose import Pose

JOBS = sorted(m.name for m in pkgutil.iter_modules(scope3d.pipelines.__path__))


def _round_trip(result):
    """``result`` pickled and back; its summary (a reading of every field it shows) must survive."""
    back = pickle.loads(pickle.dumps(result))
    assert type(back) is type(result) and back.summary() == result.summary()
    return back


@pytest.mark.parametrize("name", JOBS)
def test_every_job_is_called_one_way(name):
    module = importlib.import_module(f"scope3d.pipelines.{name}")
    params = list(inspect.signature(module.run).parameters.values())
    positional = [p for p in params if p.kind is p.POSITIONAL_OR_KEYWORD]
    assert positional[0].name == "options" and positional[-1].name == "out_dir", [p.name for p in positional]
    progress = inspect.signature(module.run).parameters["progress"]
    assert progress.kind is progress.KEYWORD_ONLY and progress.default is None
    result_type = typing.get_type_hints(module.run, vars(module))["return"]
    assert result_type.__name__.endswith("Result") and dataclasses.is_dataclass(result_type)
    assert callable(getattr(result_type, "summary", None))


def _registration():
    """A real joint solve of four quadrants at 90° steps (each pair's correspondences exact under a small
    mount offset), with both models' parameter -> pose maps."""
    from scope3d.geometry.rotation import rotvec_to_matrix
    from scope3d.registration.panorama import PairRegistration, PanoramaOptions, joint_solve

    rng = np.random.default_rng(0)
    angles = [0.0, 90.0, 180.0, 270.0]
    truth = [Pose(rotvec_to_matrix([0.0, 0.0, np.deg2rad(a)]), [0.01, -0.02, 0.0]) for a in angles]
    pairs = []
    for i, j in [(0, 1), (1, 2), (2, 3), (3, 0)]:
        world = rng.normal(0.0, 3.0, (40, 3))
        points_i, points_j = truth[i].inverse().transform(world), truth[j].inverse().transform(world)
        pairs.append(PairRegistration(i, j, truth[i].inverse() @ truth[j], points_i, points_j, 40, 0.0, 0.0))
    out = {}
    for model in ("stage", "free"):
        poses, rms, x, cov, pose_model = joint_solve(pairs, angles, options=PanoramaOptions(model=model))
        out[model] = (poses, rms, x, cov, pose_model, pairs)
    return out


@pytest.mark.parametrize("model", ["stage", "free"])
def test_thread_scan_result_pickles_with_its_registration_model(model):
    from scope3d.pipelines.thread_scan import ThreadScanResult
    from scope3d.registration.panorama import PanoramaResult

    poses, rms, x, cov, pose_model, pairs = _registration()[model]
    cov = np.eye(len(x)) * 1e-6 if cov is None else cov + np.eye(len(x)) * 1e-6
    panorama = PanoramaResult(poses, pairs, 0.0, 0.0, rms, 90.0, True, [], x, cov, pose_model)
    result = ThreadScanResult([], panorama, [], np.zeros((0, 3)), None, None, gauge_message="no thread")
    back = _round_trip(result)
    # the parameter -> pose map survives: the same draws give the same poses
    for a, b in zip(result.panorama.sample_world_from_stacked(3, seed=1),
                    back.panorama.sample_world_from_stacked(3, seed=1)):
        for pa, pb in zip(a, b):
            assert np.array_equal(pa.matrix, pb.matrix)


def test_panorama_result_pickles():
    from scope3d.pipelines.panorama import Panorama3dResult
    from scope3d.scene.tracks import Tracks
    from scope3d.geometry.sphere import fit_sphere
    from scope3d.sfm.cavity_mapping import CavityMap

    rng = np.random.default_rng(0)
    directions = rng.normal(size=(200, 3))
    points = 30.0 * directions / np.linalg.norm(directions, axis=1, keepdims=True)
    n = len(points)
    tracks = Tracks(np.arange(n), np.zeros(n, int), np.arange(n), np.zeros((n, 2)), np.zeros((n, 3), np.uint8),
                    points)
    centre, radius = fit_sphere(points)
    cavity = CavityMap(tracks, [Pose.identity()], centre, radius, np.ones(1, bool), [], [], 0, [], False)
    report = {"n_registered": 1, "n_frames": 1, "n_points": n, "scale_source": "none", "time_s": 1.0,
              "self_check": {"map_choice": None, "warnings": [], "passed": True, "problems": []}}
    back = _round_trip(Panorama3dResult(report, cavity))
    assert np.array_equal(back.cavity.tracks.points, points)
    assert np.array_equal(back.points, points) and back.colors.shape == (n, 3)
    assert np.array_equal(back.cam_from_world, np.eye(4)[None])


def test_thread_batch_and_localize_results_pickle(tmp_path):
    from scope3d.pipelines.localize import LocalizeResult
    from scope3d.pipelines.thread_batch import ThreadBatchResult

    rows = [{"hole": "a", "status": "done", "verdict": "pass", "minor_diameter_mm": 6.8, "major_diameter_mm": 8.1,
             "pitch_diameter_mm": 7.3, "pitch_mm": 1.25, "defects": 0},
            {"hole": "b", "status": "error", "verdict": "", "message": "no quadrants.json"}]
    _round_trip(ThreadBatchResult(rows, ["a"], 2.0, 2))
    report = {"n_frames": 0, "n_localized": 0, "frames_per_s": 0.0, "cpu_ms_per_frame": 0.0}
    assert _round_trip(LocalizeResult(report, tmp_path, [])).cam_from_world.shape == (0, 4, 4)


def test_track_markers_result_pickles(tmp_path):
    from test_tracking import _markers, _truth, _write_ndi

    from scope3d.pipelines.track_markers import TrackMarkersOptions, run

    truth = _truth(30)
    _write_ndi(tmp_path / "ndi.csv", truth, _markers(truth, seed=1), header=False)
    result = run(TrackMarkersOptions(), tmp_path / "ndi.csv", tmp_path / "out")
    back = _round_trip(result)
    assert np.array_equal(back.fitted, result.fitted)


def test_calibrate_and_hand_eye_results_pickle(tmp_path):
    from test_calibration import BOARD, CAMERA

    from scope3d.io.images import write_image
    from scope3d.io.poses_csv import format_poses_csv
    from scope3d.phantoms.boards import render_board_views
    from scope3d.pipelines import calibrate, hand_eye
    from scope3d.sensor.pose_tolerance import MeasuredPose, PoseTolerance

    views = render_board_views(CAMERA, BOARD, n_views=6, seed=3)
    paths = [tmp_path / f"view{i}.png" for i in range(len(views.images))]
    for path, image in zip(paths, views.images):
        write_image(path, image)
    _round_trip(calibrate.run(calibrate.CalibrateOptions(BOARD), paths, tmp_path / "cal"))
    # the robot's flange where the board's poses put it (flange = camera), exactly
    base_from_board = Pose.from_rotvec([3.0, 0.2, 0.1], [200.0, 50.0, 10.0])
    flange_from_base = [c @ base_from_board.inverse() for c in views.poses]
    (tmp_path / "robot.csv").write_text(format_poses_csv(
        [p.name for p in paths], [MeasuredPose(p, PoseTolerance.unknown()) for p in flange_from_base]))
    result = hand_eye.run(hand_eye.HandEyeRunOptions(BOARD), paths, tmp_path / "robot.csv", CAMERA, tmp_path / "he")
    _round_trip(result)


def test_scan_plan_mosaic_and_video_import_results_pickle(tmp_path):
    from scope3d.io.video import write_video
    from scope3d.pipelines import mosaic, scan_plan, video_import
    from scope3d.phantoms import generate, write
    from scope3d.registration.mosaic import MosaicOptions
    from scope3d.sfm.scan_planning import ScanPlanOptions

    plan = _round_trip(scan_plan.run(ScanPlanOptions(standoff_mm=30.0, fov_deg=70.0), "bladder", tmp_path / "plan"))
    assert plan.report["n_views"] == len(plan.plan.poses)
    seq = generate("sheet", "grid5x6", size=(160, 160), n_frames=4)
    dataset = write(seq, tmp_path / "sheet")
    from scope3d.io.dataset import load_dataset

    result = _round_trip(mosaic.run(MosaicOptions(), [load_dataset(dataset)], tmp_path / "mosaic"))
    assert result.image is result.mosaic.image and result.image.ndim == 3
    write_video(tmp_path / "v.mp4", seq.frames, 10.0)
    imported = video_import.run(video_import.VideoImportOptions(every=2), tmp_path / "v.mp4", seq.camera,
                                tmp_path / "imported")
    assert _round_trip(imported).source["frames_kept"] == 2


@pytest.mark.parametrize("name", sorted(__import__("scope3d").JOBS))
def test_the_package_exports_every_job(name):
    """``scope3d.<job>`` is its pipeline's ``run`` with the options after the inputs."""
    import scope3d

    module, options_class = scope3d.JOBS[name]
    pipeline = importlib.import_module(f"scope3d.pipelines.{module}")
    assert getattr(scope3d, name).__wrapped__ is pipeline.run
    assert getattr(scope3d, options_class) is getattr(pipeline, options_class)


def test_scope3d_map_maps_a_dataset_folder(tmp_path):
    import scope3d
    from scope3d.phantoms import generate, write

    folder = write(generate("dome", "grid5x6", size=(128, 128), seed=0, n_frames=6), tmp_path / "dome")
    result = scope3d.map(folder, tmp_path / "map", scope3d.MapOptions(figures=False))
    assert isinstance(result, scope3d.MapResult) and (tmp_path / "map" / "report.json").is_file()
    assert result.report["n_frames"] == 6 and result.points.shape == (result.report["n_points"], 3)
