"""Your robot, your scope: from a lab's raw recording to a map with the Python API, no glue code.

    python examples/own_data.py [--recording DIR] [--out runs/example_own_data] [--size 304]

The same path as docs/own_data.md's commands: calibrate the camera on checkerboard views, calibrate the
hand-eye transform from board stills and the robot's log, import the scan video with the robot's 250 Hz
log (metres, x-y-z-w quaternions, its own clock) through the hand-eye, check, map. Without --recording
the phantom lab renders one first (``scope3d phantom dome --raw-recording``), and the map is compared
with the truth the lab keeps.
"""
from __future__ import annotations

import argparse
from pathlib import Path

from scope3d.io.camera_json import read_camera_json
from scope3d.io.dataset import load_dataset
from scope3d.io.hand_eye_json import read_hand_eye_json
from scope3d.io.intrinsic_bounds import read_intrinsic_sigmas
from scope3d.io.robot_log import PoseLogFormat, read_frame_times
from scope3d.phantoms.boards import LAB_BOARD
from scope3d.phantoms.recording import RecordingOptions, write_recording
from scope3d.pipelines import calibrate, frames_import, hand_eye, surgical_map
from scope3d.sensor.pose_tolerance import PoseTolerance


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--recording", type=Path, help="a raw recording (default: render one)")
    parser.add_argument("--out", type=Path, default=Path("runs/example_own_data"))
    parser.add_argument("--size", type=int, default=304, help="square frame size of a rendered recording")
    args = parser.parse_args(argv)

    recording = args.recording
    if recording is None:
        recording = write_recording(RecordingOptions(size=(args.size, args.size), speed_mm_s=50.0),
                                    args.out / "recording")

    # 1. the camera, from the checkerboard views (the endoscope's lit disc: ignore what lies outside it)
    calibrate.run(calibrate.CalibrateOptions(LAB_BOARD, mask_circle=True),
                  sorted((recording / "calibration").glob("*.png")), args.out / "calibration")
    camera = read_camera_json(args.out / "calibration" / "camera.json")

    # 2. the hand-eye transform, from board stills and the robot's log of that session; the camera's sigmas
    #    give the intrinsics' share of its tolerance
    log_format = PoseLogFormat("xyz-qxyzw", length_unit="m")
    bounds = args.out / "calibration" / "intrinsic_bounds.json"
    hand_eye.run(hand_eye.HandEyeRunOptions(LAB_BOARD), sorted((recording / "hand_eye").glob("*.png")),
                 hand_eye.robot_poses_from_log(recording / "hand_eye" / "robot_log.csv", log_format,
                                               read_frame_times(recording / "hand_eye" / "frame_times.csv")),
                 camera, args.out / "hand_eye",
                 intrinsic_sigmas=read_intrinsic_sigmas(bounds, camera.model, camera.param_names),
                 intrinsic_sigmas_source=str(bounds))
    flange_from_cam = read_hand_eye_json(args.out / "hand_eye" / "hand_eye.json")

    # 3. the scan: every third video frame with its pose from the robot's log, through the hand-eye
    options = frames_import.FramesImportOptions(log=log_format, tolerance=PoseTolerance.from_degrees(0.5, 0.25),
                                                every=3)
    frames_import.run(options, recording / "scan" / "video.mkv", recording / "scan" / "robot_log.csv", camera,
                      args.out / "dataset", frame_times=read_frame_times(recording / "scan" / "frame_times.csv"),
                      hand_eye=flange_from_cam)

    # 4. check and map (the same checks `scope3d check` makes)
    dataset = load_dataset(args.out / "dataset", check_images=True)
    result = surgical_map.run(surgical_map.MapOptions(), dataset, args.out / "map")
    print(result.summary())
    return result.report


if __name__ == "__main__":
    main()
