"""The dome's survey as a video with frame times, and a resection during it (issue 36)."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from scope3d.errors import InputError
from scope3d.io.dataset import load_dataset
from scope3d.io.poses_csv import format_poses_csv, read_pose_times, read_poses_csv
from scope3d.phantoms import build_scene, build_trajectory, generate, write
from scope3d.phantoms.resection import Resection, resect, wall_moved_mm
from scope3d.phantoms.trajectories import SURVEY_VIDEO_SPEED_MM_S, survey_video
from scope3d.sensor.pose_tolerance import MICRO_STAGE, MeasuredPose

SMALL = (64, 48)


def test_survey_video_flies_the_grid_at_its_speed():
    stops = build_trajectory("grid5x6")
    video = survey_video(stops, 30.0)
    # 29 moves of 5 mm at 10 mm/s: 14.5 s, a frame every 1/30 s from 0 to 14.5 s inclusive
    assert len(video) == 436 >= 300
    np.testing.assert_allclose(video.times_s, np.arange(436) / 30.0, atol=1e-12)
    centres = np.array([p.centre for p in video.poses])
    steps = np.linalg.norm(np.diff(centres, axis=0), axis=1)
    # straight moves at constant speed: every step is speed / fps, except the chords across the 5 turns
    assert np.sum(np.abs(steps - SURVEY_VIDEO_SPEED_MM_S / 30.0) > 1e-9) <= 5
    # every stop is passed through at its time (arc length / speed: whole frames at 30 fps here)
    for k, stop in enumerate(stops.poses):
        frame = int(round(video.params["stop_times_s"][k] * 30.0))
        np.testing.assert_allclose(video.poses[frame].centre, stop.centre, atol=1e-9)
        np.testing.assert_allclose(video.poses[frame].rotation, stop.rotation, atol=1e-9)


def test_dome_video_writes_times_in_poses_csv(tmp_path):
    seq = generate("dome", size=SMALL, video_fps=25.0, n_frames=12, scan_speed_mm_s=20.0)
    assert seq.trajectory.name == "grid5x6_video" and len(seq) == 12
    out = write(seq, tmp_path / "video")
    data = load_dataset(out)
    np.testing.assert_allclose(data.times_s, np.arange(12) / 25.0, atol=1e-9)
    np.testing.assert_allclose(read_pose_times(out / "ground_truth" / "poses.csv"), data.times_s)
    # 20 mm/s at 25 fps: 0.8 mm between frames along the first row
    centres = np.array([m.pose.centre for m in data.poses])
    np.testing.assert_allclose(np.linalg.norm(np.diff(centres, axis=0), axis=1), 0.8, atol=1e-9)
    assert data.ground_truth.scene["trajectory"]["speed_mm_s"] == 20.0
    assert data.ground_truth.scene["trajectory"]["frames_used"] == 12
    # a still survey has no times
    still = write(generate("dome", size=SMALL, n_frames=2), tmp_path / "still")
    assert load_dataset(still).times_s is None


def test_time_column_refuses_a_frame_out_of_order(tmp_path):
    poses = [MeasuredPose(p, MICRO_STAGE) for p in build_trajectory("grid5x6").poses[:3]]
    path = tmp_path / "poses.csv"
    path.write_text(format_poses_csv(["a.png", "b.png", "c.png"], poses, times_s=[0.0, 0.5, 0.5]))
    with pytest.raises(InputError, match=r"poses.csv row 4: time_s = 0.5 is not after"):
        read_pose_times(path)
    text = format_poses_csv(["a.png", "b.png", "c.png"], poses, times_s=[0.0, 0.5, 1.0])
    path.write_text(text.replace(",1\n", ",nan\n"))
    with pytest.raises(InputError, match=r"row 4: time_s is nan"):
        read_poses_csv(path) and read_pose_times(path)


def test_resection_cuts_the_stated_pit():
    dome = build_scene("dome")
    cut, truth = resect(dome, Resection(1.0, radius_mm=2.5, depth_mm=1.2, centre_xy_mm=(3.0, -4.0)), seed=0)
    before, after = dome.mesh.vertices, cut.mesh.vertices
    moved = np.linalg.norm(after - before, axis=1)
    # every vertex moved by the profile, outwards along the sphere's radius (the plate stays)
    np.testing.assert_allclose(moved, wall_moved_mm(before, truth) * (np.abs(np.linalg.norm(
        before - truth["sphere_centre_mm"], axis=1) - 17.5) < 1e-6), atol=1e-9)
    assert moved.max() == pytest.approx(1.2, abs=0.01)  # a vertex within 0.15 mm of the centre
    centre = np.asarray(truth["centre_mm"])
    assert np.hypot(*centre[:2] - [3.0, -4.0]) < 1e-12
    assert np.all(moved[np.linalg.norm(before - centre, axis=1) >= 2.5] == 0)
    # drawn from the seed: the same place for the same seed, inside half the opening radius
    a = resect(dome, Resection(1.0), seed=5)[1]["centre_mm"]
    assert a == resect(dome, Resection(1.0), seed=5)[1]["centre_mm"]
    assert a != resect(dome, Resection(1.0), seed=6)[1]["centre_mm"]
    assert np.hypot(*a[:2]) <= 0.5 * dome.info["dome"]["opening_radius_mm"]
    with pytest.raises(InputError, match="past its rim"):
        resect(dome, Resection(1.0, radius_mm=3.0, centre_xy_mm=(14.0, 0.0)), seed=0)
    with pytest.raises(InputError, match="dome only"):
        resect(build_scene("sheet"), Resection(1.0), seed=0)


def test_resected_video_sees_the_pit_from_its_time_on(tmp_path):
    # the first row passes over a pit under (0, 9) mm; cut at 0.2 s, frame 5 at 25 fps
    seq = generate("dome", size=(96, 72), video_fps=25.0, n_frames=8,
                   resection=Resection(0.2, radius_mm=3.0, depth_mm=1.5, centre_xy_mm=(0.0, 9.0)))
    truth = seq.scene_info["resection"]
    assert truth["first_frame"] == 5
    plain = generate("dome", size=(96, 72), video_fps=25.0, n_frames=8)
    for i in range(8):
        deeper = seq.depths[i] - plain.depths[i]
        if i < 5:
            assert np.array_equal(seq.frames[i], plain.frames[i])
        else:
            # the wall moved away by up to 1.5 mm along a direction 31° from the view: never more in depth
            # than 1.5 / cos(31° + the ray's 27° at most) = 2.8 mm; and some pixels see the pit's floor
            assert np.nanmax(deeper) > 1.0 and np.nanmin(deeper) >= -1e-6 and np.nanmax(deeper) < 2.8
    out = write(seq, tmp_path / "cut")
    data = load_dataset(out)
    assert data.ground_truth.scene["resection"]["first_frame"] == 5
    assert (out / "ground_truth" / "surface_resected.ply").is_file()
    assert (out / "ground_truth" / "surface.ply").is_file()


def _phantom(*args):
    return subprocess.run([sys.executable, "-m", "scope3d.cli.main", "phantom", *args], capture_output=True, text=True)


@pytest.mark.parametrize("args, message", [
    (["dome", "--resect", "1"], "--resect needs --video"),
    (["sheet", "--video", "30", "--resect", "1"], "dome only"),
    (["dome", "--video", "30", "--resect", "1:2"], "--resect must be"),
    (["dome", "--video", "30", "--frames", "3", "--resect", "5"], "after the video's last frame"),
    (["dome", "--video", "30", "--trajectory", "approach", "--target", "1"], "grid survey or a plan"),
])
def test_bad_video_or_resection_is_one_line(tmp_path, args, message):
    run = _phantom(*args, "--size", "32x32", "--quiet", "--out", str(tmp_path / "x"))
    assert run.returncode == 2 and message in run.stderr and "Traceback" not in run.stderr
    assert len(run.stderr.strip().splitlines()) == 1 and not (tmp_path / "x").exists()
