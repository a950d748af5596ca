"""A map's self-checks for data without ground truth (issue 16 part 5): frames left out are named, pose
corrections and tolerance-edge hits are reported, a missing camera.json is refused with what to do."""
from __future__ import annotations

import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from scope3d.cli.main import main
from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import rotvec_to_matrix
from scope3d.scene.tracks import Tracks
from scope3d.sensor.pose_tolerance import MeasuredPose, PoseTolerance
from scope3d.sfm.model_checks import check_model, model_checks_summary

TEMPLE = Path(__file__).resolve().parents[2] / "shared" / "data" / "middlebury_templeSparseRing"


def _tracks_in_frames(frames: list[int]) -> Tracks:
    frame = np.array(frames)
    k = len(frame)
    return Tracks(np.zeros(k, np.int64), frame, np.arange(k), np.zeros((k, 2)), np.zeros((1, 3), np.uint8))


def test_check_model_names_unused_frames_and_finds_corrections_on_the_tolerance_edge():
    tol = PoseTolerance.from_degrees(1.0, 0.5)
    reported = [Pose.from_centre(np.eye(3), np.array([float(k), 0.0, 0.0])) for k in range(4)]
    measured = [MeasuredPose(p, tol) for p in reported]
    adjusted = [
        Pose.from_centre(np.eye(3), reported[0].centre + [0.3, 0.0, 0.0]),  # inside the box
        Pose.from_centre(np.eye(3), reported[1].centre + [0.0, 1.0, 0.0]),  # on its position edge
        Pose.from_centre(rotvec_to_matrix(np.deg2rad([0.0, 0.0, 0.5])), reported[2].centre),  # orientation edge
        reported[3],
    ]
    checks = check_model(["a", "b", "c", "d"], measured, adjusted, _tracks_in_frames([0, 0, 1, 2]))
    assert checks.unused_frames == ["d"]
    np.testing.assert_allclose(checks.position_correction_mm, [0.3, 1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(np.rad2deg(checks.orientation_correction_rad), [0.0, 0.0, 0.5], atol=1e-9)
    assert checks.on_position_edge.tolist() == [False, True, False]
    assert checks.on_orientation_edge.tolist() == [False, False, True]
    d = checks.as_dict()
    assert d["frames_used"] == 3 and d["frames_used_fraction"] == 0.75
    assert d["pose_correction"]["on_position_tolerance_edge_fraction"] == pytest.approx(1 / 3)
    line = model_checks_summary(d)
    assert "3 of 4 frames" in line and "not used: d" in line


def test_an_unknown_tolerance_has_no_edge():
    measured = [MeasuredPose(Pose.from_centre(np.eye(3), np.zeros(3)), PoseTolerance.unknown())]
    adjusted = [Pose.from_centre(np.eye(3), np.array([50.0, 0.0, 0.0]))]
    checks = check_model(["a"], measured, adjusted, _tracks_in_frames([0]))
    assert not checks.on_position_edge.any() and checks.position_correction_mm[0] == pytest.approx(50.0)


def test_a_reported_pose_off_by_more_than_its_tolerance_ends_on_the_edge_of_its_box(tmp_path):
    """One frame's reported centre 3 mm off with a 0.5 mm tolerance (a tracker glitch): the other frames'
    images fix where it was to far better than 2.5 mm, so the adjustment must take it to the edge of its
    box, and the report must say so for that frame (a shift of every pose alike would be invisible:
    images do not see where the world's origin is)."""
    from scope3d import phantoms
    from scope3d.io.dataset import load_dataset
    from scope3d.pipelines.surgical_map import MapOptions, run

    seq = phantoms.generate("dome", "grid5x6", size=(320, 240), seed=0, n_frames=12, pose_noise_mm=0.5)
    dataset = load_dataset(phantoms.write(seq, tmp_path / "dome"))
    glitch = 6
    poses = list(dataset.poses)
    m = poses[glitch]
    poses[glitch] = MeasuredPose(Pose.from_centre(m.pose.rotation, m.pose.centre + [3.0, 0.0, 0.0]), m.tolerance)
    result = run(replace(MapOptions(), figures=False), replace(dataset, poses=poses), tmp_path / "map")
    checks = check_model(dataset.names, poses, result.sparse.poses, result.sparse.tracks)
    assert dataset.names[glitch] not in checks.unused_frames
    used = [k for k in range(len(dataset)) if dataset.names[k] not in checks.unused_frames]
    assert checks.on_position_edge[used.index(glitch)]
    reported = dict(result.report["model_checks"])
    reported.pop("reported_pose_test", None)  # the per-frame test of the reports (tests/test_pose_checks.py)
    assert reported == checks.as_dict()


def test_a_dataset_without_intrinsics_is_refused_with_what_to_do(tmp_path, capsys):
    """Real images and calibrated poses, but no camera.json (a new user's usual state): one line naming
    the file and the way to provide it, exit 2, no output folder."""
    from scope3d.io.middlebury import import_middlebury

    if not (TEMPLE / "templeSR_par.txt").is_file():
        pytest.fail(f"real data missing: {TEMPLE} (see ../shared/data/README.md)")
    root = import_middlebury(TEMPLE / "templeSR_par.txt", tmp_path / "temple")
    (root / "camera.json").unlink()
    out = tmp_path / "map"
    assert main(["map", str(root), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(root / "camera.json") in err[0] and "scope3d calibrate" in err[0]
    assert not out.exists()
    shutil.rmtree(root)
