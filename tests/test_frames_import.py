"""``scope3d import frames``: a robot log at its own rate, unit, layout and clock, through a hand-eye
transform, onto frames at 30 Hz; checked against the analytic motion the log was sampled from."""
from __future__ import annotations

import csv
import json
import pickle

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from scope3d.cli.main import main
from scope3d.errors import InputError
from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import rotation_angle_between
from scope3d.geometry.trajectory import Trajectory
from scope3d.io.camera_json import camera_to_dict
from scope3d.io.dataset import load_dataset
from scope3d.io.robot_log import PoseLogFormat, read_pose_log
from scope3d.pipelines.frames_import import FramesImportOptions, FrameTiming, run
from scope3d.sensor.camera import Camera
from scope3d.sensor.pose_tolerance import PoseTolerance

OMEGA = 0.8  # rad/s about the base's z, and a nod of NOD rad at 1 rad/s about the flange's x
NOD = 0.3
RADIUS_MM = 25.0
CLIMB_MM_S = 4.0
LOG_HZ = 250.0
CLOCK_OFFSET_S = 1.7  # the log's clock reads this much more than the camera's
FLANGE_FROM_CAM = Pose.from_centre(Rotation.from_rotvec([0.2, -0.4, 1.1]).as_matrix().T, np.array([3.0, -5.0, 40.0]))


def flange_motion(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """base_from_flange rotations (N, 3, 3) and flange positions (N, 3) mm at log-clock times t."""
    t = np.asarray(t, dtype=float)
    positions = np.stack([RADIUS_MM * np.cos(OMEGA * t), RADIUS_MM * np.sin(OMEGA * t), CLIMB_MM_S * t], axis=1)
    rotations = (Rotation.from_rotvec(np.outer(OMEGA * t, [0, 0, 1]))
                 * Rotation.from_rotvec(np.outer(NOD * np.sin(t), [1, 0, 0]))).as_matrix()
    return rotations, positions


def true_cam_from_world(t_log: np.ndarray) -> list[Pose]:
    rotations, positions = flange_motion(t_log)
    base_from_flange = [Pose(r, p) for r, p in zip(rotations, positions)]
    return [(b @ FLANGE_FROM_CAM).inverse() for b in base_from_flange]


def interpolation_bound_mm_rad(dt: float) -> tuple[float, float]:
    """Worst error of linear + slerp interpolation over samples dt apart: |x''| dt^2 / 8 for the centre and
    |w'| dt^2 / 8 for the angle (constant velocity is exact); the camera's centre also swings with the
    angular error on its 40 mm lever. Bounds of |x''| and |w'| of the motion above, taken generously."""
    lever = np.linalg.norm(FLANGE_FROM_CAM.translation)
    accel = RADIUS_MM * OMEGA**2  # the circle's centripetal acceleration (the climb is uniform)
    angular_accel = NOD + OMEGA * NOD  # the nod's own, and the turning of its axis about z
    angle = angular_accel * dt**2 / 8
    # the log prints metres with 9 decimals (1e-6 mm) and quaternions with 12 digits
    return accel * dt**2 / 8 + lever * angle + 2e-6, angle + 1e-11


def write_log(path, times_log, *, fmt="xyz-qxyzw", unit_mm=1000.0, columns=None):
    rotations, positions = flange_motion(times_log)
    names = {"xyz-qxyzw": ["t", "x", "y", "z", "qx", "qy", "qz", "qw"],
             "xyz-qwxyz": ["t", "x", "y", "z", "qw", "qx", "qy", "qz"],
             "xyz-euler-ZYX": ["t", "x", "y", "z", "r1", "r2", "r3"],
             "matrix44": ["t"] + [f"m{i}{j}" for i in range(4) for j in range(4)]}[fmt]
    header = [(columns or {}).get(n, n) for n in names]
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        for t, r, p in zip(times_log, rotations, positions):
            pos = [f"{v / unit_mm:.9f}" for v in p]
            q = Rotation.from_matrix(r).as_quat()
            if fmt == "xyz-qxyzw":
                rest = [f"{v:.12f}" for v in q]
            elif fmt == "xyz-qwxyz":
                rest = [f"{v:.12f}" for v in (q[3], q[0], q[1], q[2])]
            elif fmt == "xyz-euler-ZYX":
                rest = [f"{v:.12f}" for v in Rotation.from_matrix(r).as_euler("ZYX", degrees=True)]
            else:
                m = np.eye(4)
                m[:3, :3], m[:3, 3] = r, p / unit_mm
                w.writerow([f"{t:.6f}"] + [f"{v:.12g}" for v in m.ravel()])
                continue
            w.writerow([f"{t:.6f}"] + pos + rest)


@pytest.fixture()
def recording(tmp_path):
    """A folder of 30 Hz frames (camera clock), a frame-time table, a 250 Hz log in metres (log clock),
    a camera.json and a hand_eye.json as `calibrate-hand-eye` writes it."""
    camera = Camera(64, 48, 60.0, 60.0, 31.5, 23.5)
    frames = tmp_path / "frames"
    frames.mkdir()
    frame_times = np.arange(30) / 30.0 + 0.25
    rng = np.random.default_rng(0)
    with open(tmp_path / "frame_times.csv", "w") as fh:
        fh.write("image,t\n")
        for i, t in enumerate(frame_times):
            cv2.imwrite(str(frames / f"img_{i}.png"), rng.integers(0, 255, (48, 64), dtype=np.uint8))
            fh.write(f"img_{i}.png,{t + CLOCK_OFFSET_S:.6f}\n")
    times_log = CLOCK_OFFSET_S + np.arange(0.0, 1.5, 1.0 / LOG_HZ)
    write_log(tmp_path / "log.csv", times_log)
    (tmp_path / "camera.json").write_text(json.dumps(camera_to_dict(camera)))
    (tmp_path / "hand_eye.json").write_text(json.dumps({"flange_from_cam": {
        "rotation": FLANGE_FROM_CAM.rotation.tolist(), "translation_mm": FLANGE_FROM_CAM.translation.tolist()}}))
    return tmp_path, camera, frame_times + CLOCK_OFFSET_S


def _pose_errors(dataset, times_log):
    truth = true_cam_from_world(times_log)
    centre = np.array([np.linalg.norm(m.pose.centre - t.centre) for m, t in zip(dataset.poses, truth)])
    angle = np.array([rotation_angle_between(m.pose.rotation, t.rotation) for m, t in zip(dataset.poses, truth)])
    return centre, angle


def test_the_issues_command_imports_frames_onto_the_true_camera_poses(recording, capsys):
    root, camera, times_log = recording
    status = main(["import", "frames", str(root / "frames"), "--camera", str(root / "camera.json"),
                   "--poses", str(root / "log.csv"), "--pose-format", "xyz-qxyzw", "--unit", "m",
                   "--frame-times", str(root / "frame_times.csv"), "--hand-eye", str(root / "hand_eye.json"),
                   "--tolerance", "0.5", "--tolerance-deg", "0.25", "--out", str(root / "dataset"), "--quiet"])
    assert status == 0
    dataset = load_dataset(root / "dataset", check_images=True)
    assert dataset.names == [f"img_{i}.png" for i in range(30)]  # natural order, not img_1, img_10, ...
    centre, angle = _pose_errors(dataset, times_log)
    bound_mm, bound_rad = interpolation_bound_mm_rad(1.0 / LOG_HZ)
    assert centre.max() <= bound_mm and angle.max() <= bound_rad
    np.testing.assert_allclose(dataset.poses[0].tolerance.position_mm, 0.5)
    np.testing.assert_allclose(dataset.poses[0].tolerance.orientation_deg, 0.25)
    report = json.loads((root / "dataset" / "report.json").read_text())
    assert report["log"]["rows_used"] == 375 and report["interpolation"]["gap_s_max"] <= 1.0 / LOG_HZ + 1e-9


def test_without_the_hand_eye_or_the_clock_offset_the_poses_are_measurably_wrong(recording):
    """The checks above can fail: the flange is 41 mm from the camera, and 1.7 s of clock is 34 mm of path."""
    root, camera, times_log = recording
    table = {f"img_{i}.png": t for i, t in enumerate(times_log)}
    base = FramesImportOptions(log=PoseLogFormat("xyz-qxyzw", length_unit="m"), tolerance=PoseTolerance.exact())
    run(base, root / "frames", root / "log.csv", camera, root / "no_hand_eye", frame_times=table)
    assert _pose_errors(load_dataset(root / "no_hand_eye"), times_log)[0].min() > 30.0
    shifted = {k: t - CLOCK_OFFSET_S for k, t in table.items()}
    with pytest.raises(InputError, match="outside the log"):
        run(base, root / "frames", root / "log.csv", camera, root / "unshifted", frame_times=shifted,
            hand_eye=FLANGE_FROM_CAM)
    timing = FrameTiming(clock_offset_s=CLOCK_OFFSET_S)
    result = run(FramesImportOptions(log=base.log, timing=timing), root / "frames", root / "log.csv", camera,
                 root / "offset", frame_times=shifted, hand_eye=FLANGE_FROM_CAM)
    centre, angle = _pose_errors(load_dataset(root / "offset"), times_log)
    assert centre.max() <= interpolation_bound_mm_rad(1.0 / LOG_HZ)[0]
    assert "30 frames" in result.summary()
    assert pickle.loads(pickle.dumps(result)).summary() == result.summary()  # results travel to cluster workers


@pytest.mark.parametrize("fmt", ["xyz-qwxyz", "xyz-euler-ZYX", "matrix44"])
def test_every_log_layout_gives_the_same_poses(recording, fmt):
    root, camera, times_log = recording
    columns = {"t": "time", "x": "X"} if fmt != "matrix44" else {"t": "stamp"}
    write_log(root / "other.csv", times_log[0] + np.arange(0.0, 1.5, 1.0 / LOG_HZ) - 0.0, fmt=fmt, unit_mm=1.0,
              columns=columns)
    options = FramesImportOptions(log=PoseLogFormat(fmt, columns=columns, length_unit="mm"),
                                  timing=FrameTiming(rate_hz=30.0, first_frame_s=times_log[0]))
    run(options, root / "frames", root / "other.csv", camera, root / fmt, hand_eye=FLANGE_FROM_CAM)
    centre, angle = _pose_errors(load_dataset(root / fmt), times_log)
    bound_mm, bound_rad = interpolation_bound_mm_rad(1.0 / LOG_HZ)
    # the Euler and matrix logs print 12 significant digits: the same rounding as the quaternions
    assert centre.max() <= bound_mm and angle.max() <= bound_rad


def _log_lines(root):
    return (root / "log.csv").read_text().splitlines()


@pytest.mark.parametrize("edit, message", [
    (lambda cells: cells[:1] + ["nan"] + cells[2:], "row 12: not a finite number"),
    (lambda cells: cells[:4] + ["0.5", "0.5", "0.5", "0.9"], "row 12: quaternion norm 1.249"),
    (lambda cells: ["0.1"] + cells[1:], "row 12: time 0.1 is not after the previous row's"),
    (lambda cells: cells[:3], "row 12: not a finite number"),
])
def test_a_bad_row_is_refused_naming_it_or_dropped_and_counted(recording, edit, message):
    root, camera, times_log = recording
    lines = _log_lines(root)
    lines[11] = ",".join(edit(lines[11].split(",")))
    (root / "log.csv").write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError) as info:
        read_pose_log(root / "log.csv", PoseLogFormat(length_unit="m"))
    assert str(info.value).startswith(f"{root / 'log.csv'} {message}") and "\n" not in str(info.value)
    log = read_pose_log(root / "log.csv", PoseLogFormat(length_unit="m", drop_bad_rows=True))
    assert len(log) == 374 and sum(log.dropped.values()) == 1 and list(log.first_dropped_row.values()) == [12]


def test_frames_in_a_hole_of_the_log_are_refused_or_skipped(recording):
    root, camera, times_log = recording
    lines = _log_lines(root)
    # rows 2..376 hold t = 1.7 + k / 250; take out 0.5-0.7 s of camera time (frames 8-13 of 30 Hz from 0.25 s)
    t = np.array([float(line.split(",")[0]) for line in lines[1:]])
    hole = (t > CLOCK_OFFSET_S + 0.5) & (t < CLOCK_OFFSET_S + 0.7)
    (root / "log.csv").write_text("\n".join([lines[0]] + [ln for ln, h in zip(lines[1:], hole) if not h]) + "\n")
    table = {f"img_{i}.png": t for i, t in enumerate(times_log)}
    options = FramesImportOptions(log=PoseLogFormat(length_unit="m"))
    with pytest.raises(InputError, match=r"img_8.png: the frame at 2.2166\d* s falls in a 20\d ms gap of the log"):
        run(options, root / "frames", root / "log.csv", camera, root / "refused", frame_times=table)
    assert not (root / "refused").exists()
    skipping = FramesImportOptions(log=options.log, skip_unposed_frames=True)
    result = run(skipping, root / "frames", root / "log.csv", camera, root / "kept", frame_times=table,
                 hand_eye=FLANGE_FROM_CAM)
    in_hole = [i for i, tt in enumerate(times_log) if CLOCK_OFFSET_S + 0.5 < tt < CLOCK_OFFSET_S + 0.7]
    assert sorted(result.skipped) == sorted(f"img_{i}.png" for i in in_hole)
    assert len(load_dataset(root / "kept")) == 30 - len(in_hole)


def test_bad_command_lines_and_files_exit_2_with_one_line(recording, capsys):
    root, camera, times_log = recording
    args = ["import", "frames", str(root / "frames"), "--camera", str(root / "camera.json"), "--poses",
            str(root / "log.csv"), "--unit", "m", "--frame-times", str(root / "frame_times.csv"), "--out",
            str(root / "out"), "--quiet"]
    cases = [
        (["--tolerance", "0.5"], "--tolerance MM and --tolerance-deg DEG"),
        (["--robot", "industrial-arm", "--tolerance", "1", "--tolerance-deg", "1"], "either --robot or"),
        (["--robot", "industrial-arm", "--pose-format", "xyz-euler-XXY"], "two successive Euler axes must differ"),
        (["--robot", "industrial-arm", "--columns", "t=time,qq=W"], "column map names qq"),
        (["--robot", "industrial-arm", "--columns", "t=time"], "no column 'time'"),
        (["--robot", "industrial-arm", "--hand-eye", str(root / "camera.json")], "no 'flange_from_cam'"),
    ]
    for extra, message in cases:
        assert main(args + extra) == 2
        err = capsys.readouterr().err.strip()
        assert message in err and "\n" not in err and "Traceback" not in err
    assert not (root / "out").exists()
    assert main(args + ["--robot", "industrial-arm", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["tolerance"]["source"].startswith("uncalibrated six-axis industrial arm")


def test_trajectory_interpolation_is_exact_for_constant_velocity():
    times = np.array([0.0, 0.5, 1.0])
    axis = np.array([0.3, -0.2, 0.9]) / np.linalg.norm([0.3, -0.2, 0.9])
    rotations = Rotation.from_rotvec(np.outer(times * 1.2, axis)).as_matrix()
    positions = np.outer(times, [10.0, -4.0, 2.0])
    q = np.array([0.0, 0.1, 0.5, 0.77, 1.0, 1.2, -0.1])
    r, p, gap = Trajectory(times, rotations, positions).at(q)
    inside = slice(0, 5)
    np.testing.assert_allclose(p[inside], np.outer(q[inside], [10.0, -4.0, 2.0]), atol=1e-12)
    truth = Rotation.from_rotvec(np.outer(q[inside] * 1.2, axis)).as_matrix()
    assert rotation_angle_between(r[inside], truth).max() < 1e-14
    np.testing.assert_array_equal(gap, [0.0, 0.5, 0.0, 0.5, 0.0, np.inf, np.inf])
