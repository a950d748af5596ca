"""``scope3d check`` and ``scope3d import``: validate datasets and convert other formats into them.

Thin layer: each handler parses its arguments and calls the function a user would import
(:func:`scope3d.io.dataset.load_dataset`, :func:`scope3d.io.import_middlebury`,
:func:`scope3d.io.import_colmap`). Problems are raised as InputError; ``main`` prints them on one
line and exits with status 2.
"""
from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

from scope3d.cli import commands_import_frames
from scope3d.cli.job_output import (
    add_job_arguments,
    check_dataset_output,
    dataset_report_writer,
    finish_import,
    show_progress,
)
from scope3d.cli.lazy import LazyChoices
from scope3d.errors import InputError


def register(subparsers) -> None:
    check = subparsers.add_parser(
        "check",
        help="validate a dataset folder and say what it holds",
        description="Validate a dataset (parse every file, decode every image) and check it against what a job "
                    "refuses before any work (the job's own check, so the message is the job's), then print what "
                    "it holds, or the first problem found in one line (exit status 2).",
    )
    check.add_argument("dataset", metavar="DATASET", type=Path, help="dataset folder")
    check.add_argument("--for", dest="job", choices=sorted(CHECKED_JOBS), default="map", metavar="JOB",
                       help="the job to check the dataset for: %(choices)s (default map; with its default options)")
    add_job_arguments(check)  # --quiet accepted for uniformity: the check shows no progress bar
    check.set_defaults(func=run_check)

    imp = subparsers.add_parser(
        "import",
        help="convert a Middlebury or COLMAP set, a ROS bag or a video into a scope3d dataset",
        description="Convert another tool's multi-view set into a scope3d dataset folder (mm).",
    )
    formats = imp.add_subparsers(dest="format", metavar="FORMAT", required=True)

    mid = formats.add_parser(
        "middlebury",
        help="Middlebury multi-view stereo set (*_par.txt with images beside it)",
        description="Import a Middlebury multi-view set: images beside PAR_FILE, P = K[R|t], world in "
                    "metres (converted to mm). Poses are exact unless --tolerance is given.",
    )
    mid.add_argument("par_file", metavar="PAR_FILE", type=Path, help="the set's *_par.txt")
    _add_output_arguments(mid)
    mid.set_defaults(func=run_import_middlebury)

    col = formats.add_parser(
        "colmap",
        help="COLMAP sparse text model and its images",
        description="Import a COLMAP text model (cameras.txt, images.txt; points3D.txt optional) and its "
                    "image folder. Poses are exact unless --tolerance is given.",
    )
    col.add_argument("model_dir", metavar="MODEL_DIR", type=Path, help="folder with cameras.txt and images.txt")
    col.add_argument("images", metavar="IMAGES", type=Path, help="folder the image names are relative to")
    col.add_argument("--model-unit", choices=LazyChoices("scope3d.io.dataset", "LENGTH_UNITS_TO_MM", sort=True),
                     default="mm", metavar="UNIT",
                     help="length unit of the model's translations: %(choices)s (default mm)")
    _add_output_arguments(col)
    col.set_defaults(func=run_import_colmap)

    bag = formats.add_parser(
        "rosbag",
        help="ROS 1 or ROS 2 bag: camera images and camera poses, synchronised",
        description="Import a ROS 1 (.bag) or ROS 2 (folder) bag: images (sensor_msgs/Image or CompressedImage) "
                    "paired with the camera's pose (PoseStamped, PoseWithCovarianceStamped, TransformStamped, "
                    "Odometry or /tf) stamped nearest, within the slop, each used once. Poses are of the "
                    "camera's optical frame (z forward, x right, y down) in metres (converted to mm). Without "
                    "--tolerance the poses' box comes from their covariance (3 sigma) when they carry one, "
                    "else they are exact. See docs/rosbag.md.",
    )
    bag.add_argument("bag", metavar="BAG", type=Path, help="the .bag file (ROS 1) or bag folder (ROS 2)")
    bag.add_argument("--image-topic", required=True, metavar="T", help="camera image topic")
    bag.add_argument("--pose-topic", required=True, metavar="T", help="camera pose topic (e.g. /tf)")
    bag.add_argument("--camera-frame", metavar="FRAME",
                     help="child frame id of the camera in a tf / TransformStamped / Odometry stream")
    intrinsics = bag.add_mutually_exclusive_group(required=True)
    intrinsics.add_argument("--camera-info-topic", metavar="T", help="sensor_msgs/CameraInfo topic")
    intrinsics.add_argument("--camera", metavar="CAMERA_JSON", type=Path, help="camera.json (see docs/datasets.md)")
    bag.add_argument("--hand-eye", metavar="HAND_EYE_JSON", type=Path,
                     help="hand_eye.json (scope3d calibrate-hand-eye): the pose stream (or --camera-frame's tf "
                          "frame) is the robot's flange, turned into the camera's pose through it")
    bag.add_argument("--slop-ms", type=float, default=20.0,
                     help="largest gap between an image's stamp and its pose's, ms (default 20)")
    _add_output_arguments(bag)
    bag.set_defaults(func=run_import_rosbag)

    vid = formats.add_parser(
        "video",
        help="video file (MP4, AVI, ...): every Nth frame or the key frames",
        description="Import a video file (any container and codec OpenCV's FFmpeg decodes): every frame, every "
                    "Nth frame, or the key frames (a frame is kept when the view has moved by --min-shift of the "
                    "image since the last key frame, or no longer matches it by a shift). Poses are unknown "
                    "(tolerance inf) unless --plan assigns the scan plan's poses by time, within --tolerance. "
                    "Frames FFmpeg could decode only with errors (and conceal) are imported, and named in the "
                    "output and in dataset.json (source.decode_damage); damage that leaves a valid stream is "
                    "not seen. See docs/datasets.md.",
    )
    vid.add_argument("video", metavar="VIDEO", type=Path, help="the video file")
    vid.add_argument("--out", metavar="DIR", type=Path, required=True,
                     help="dataset folder to write (replaced only if it is a scope3d dataset)")
    pick = vid.add_mutually_exclusive_group()
    pick.add_argument("--every", type=int, default=1, metavar="N", help="keep frames 0, N, 2N... (default 1: all)")
    pick.add_argument("--keyframes", action="store_true", help="keep the key frames (looks at every frame)")
    vid.add_argument("--min-shift", type=float, metavar="F",
                     help="with --keyframes: the image fraction the view must move by (default 0.2)")
    vid.add_argument("--min-response", type=float, metavar="R",
                     help="with --keyframes: also keep a frame whose phase-correlation peak with the last key "
                          "frame is below R (rolled, zoomed or cut away; default 0.1)")
    lens = vid.add_mutually_exclusive_group(required=True)
    lens.add_argument("--camera", metavar="CAMERA_JSON", type=Path, help="camera.json (see docs/datasets.md)")
    lens.add_argument("--fov", type=float, metavar="DEG",
                      help="no calibration: a pinhole with this field of view across the width, centred, no "
                           "distortion (written as such in dataset.json)")
    plan = vid.add_argument_group("planned poses")
    plan.add_argument("--plan", metavar="PLAN_JSON", type=Path,
                      help="scan plan (scope3d plan-scan): each frame gets the planned pose at its time")
    plan.add_argument("--tolerance", metavar="MM", type=_non_negative,
                      help="with --plan (required): half-width of the camera-centre box around a planned pose, mm")
    plan.add_argument("--tolerance-deg", metavar="DEG", type=_non_negative,
                      help="with --plan (required): half-width of the orientation box, degrees")
    plan.add_argument("--seconds-per-view", type=float, default=600.0 / 529.0, metavar="S",
                      help="with --plan: time from one planned view to the next (default 1.13 s, the reference's "
                           "10 min for 529 views)")
    plan.add_argument("--plan-start", type=float, default=0.0, metavar="S",
                      help="with --plan: time into the video at which the scope is at the first view (default 0)")
    add_job_arguments(vid)
    vid.set_defaults(func=run_import_video)
    commands_import_frames.register(formats)


def _add_output_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", metavar="DIR", type=Path, required=True,
                        help="dataset folder to write (replaced only if it is a scope3d dataset)")
    parser.add_argument("--tolerance", metavar="MM", type=_non_negative, default=None,
                        help="half-width of the camera-centre tolerance per axis, mm (default 0: exact)")
    parser.add_argument("--tolerance-deg", metavar="DEG", type=_non_negative, default=0.0,
                        help="half-width of the orientation tolerance per axis, degrees (default 0)")
    add_job_arguments(parser)  # --quiet accepted for uniformity: these imports show no progress bar


def _non_negative(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if math.isnan(value) or value < 0:
        raise argparse.ArgumentTypeError(f"{text} must be zero or positive (inf = unknown)")
    return value


def _tolerance(args):
    from scope3d.sensor.pose_tolerance import PoseTolerance

    return PoseTolerance.from_degrees(args.tolerance or 0.0, args.tolerance_deg)


# --- handlers ----------------------------------------------------------------------------------


#: The jobs ``check --for`` knows: name -> (pipeline module, options class); each module's
#: ``check_dataset(options, dataset)`` is what its ``run`` calls before any work.
CHECKED_JOBS = {"map": ("scope3d.pipelines.surgical_map", "MapOptions"),
                "axial": ("scope3d.pipelines.axial", "AxialOptions"),
                "panorama": ("scope3d.pipelines.panorama", "Panorama3dOptions"),
                "thread-scan": ("scope3d.pipelines.thread_scan", "ThreadScanOptions")}


def run_check(args) -> int:
    import importlib

    from scope3d.cli.job_output import finish_job
    from scope3d.io.dataset import load_dataset

    dataset = load_dataset(args.dataset, check_images=True)
    module_name, options_name = CHECKED_JOBS[args.job]
    module = importlib.import_module(module_name)
    module.check_dataset(getattr(module, options_name)(), dataset)
    report = {"job": "check", "dataset": str(args.dataset), "for": args.job, "n_frames": len(dataset), "ok": True}
    return finish_job(args, None, report, [dataset.summary(),
                                           f"ok: every file parsed, every image decoded, {args.job} accepts it"])


def _import_report(args, source: str) -> tuple[dict, object]:
    """The import's report (completed when the dataset is written) and the hook that writes it there."""
    report = {"job": f"import {args.format}", "source": source}
    return report, dataset_report_writer(report, args.out.name, time.perf_counter())


def run_import_middlebury(args) -> int:
    from scope3d.io.middlebury import import_middlebury

    check_dataset_output(args.out)
    report, finish = _import_report(args, str(args.par_file))
    out = import_middlebury(args.par_file, args.out, tolerance=_tolerance(args), finish=finish)
    return finish_import(args, out, report)


def run_import_colmap(args) -> int:
    from scope3d.io.colmap import import_colmap
    from scope3d.io.dataset import LENGTH_UNITS_TO_MM

    check_dataset_output(args.out)
    report, finish = _import_report(args, str(args.model_dir))
    out = import_colmap(args.model_dir, args.images, args.out, tolerance=_tolerance(args),
                        length_scale_to_mm=LENGTH_UNITS_TO_MM[args.model_unit], finish=finish)
    return finish_import(args, out, report)


def run_import_rosbag(args) -> int:
    from scope3d.io.camera_json import read_camera_json
    from scope3d.io.hand_eye_json import read_hand_eye_json
    from scope3d.io.rosbag import RosbagOptions, import_rosbag

    if not args.slop_ms > 0:
        raise InputError("--slop-ms must be positive")
    check_dataset_output(args.out)
    given = args.tolerance is not None or args.tolerance_deg > 0
    flange_from_cam = read_hand_eye_json(args.hand_eye) if args.hand_eye else None
    options = RosbagOptions(flange_from_cam=flange_from_cam, image_topic=args.image_topic, pose_topic=args.pose_topic,
                            camera_frame=args.camera_frame,
                            camera_info_topic=args.camera_info_topic, slop_s=args.slop_ms / 1000.0,
                            tolerance=_tolerance(args) if given else None)
    camera = read_camera_json(args.camera) if args.camera else None
    report, finish = _import_report(args, str(args.bag))
    out = import_rosbag(args.bag, args.out, options=options, camera=camera, finish=finish)
    return finish_import(args, out, report)


def run_import_video(args) -> int:
    from scope3d.cli.progress import progress_bar
    from scope3d.feature.keyframes import KeyframeOptions
    from scope3d.io.camera_json import read_camera_json
    from scope3d.io.scan_plan import read_scan_plan
    from scope3d.io.video import probe_video
    from scope3d.io.json_object import read_json_object
    from scope3d.pipelines.video_import import VideoImportOptions, decode_damage_summary, run
    from scope3d.sensor.camera import Camera
    from scope3d.sensor.pose_tolerance import PoseTolerance

    if args.every < 1:
        raise InputError(f"--every must be 1 or more, got {args.every}")
    tuning = {name: value for name, value in (("min_shift_fraction", args.min_shift),
                                               ("min_response", args.min_response)) if value is not None}
    if tuning and not args.keyframes:
        raise InputError("--min-shift and --min-response apply to --keyframes")
    given = [flag for flag, value in (("--tolerance", args.tolerance), ("--tolerance-deg", args.tolerance_deg))
             if value is not None]
    if args.plan is None and given:
        raise InputError(f"{given[0]} applies to planned poses: give --plan too")
    if args.plan is not None and len(given) < 2:
        raise InputError("--plan needs --tolerance MM and --tolerance-deg DEG: how far the scope may be from its plan")
    if args.fov is not None and not 0 < args.fov < 180:
        raise InputError(f"--fov must be between 0 and 180 degrees, got {args.fov}")
    check_dataset_output(args.out)
    try:
        keyframes = KeyframeOptions(**tuning) if args.keyframes else None
        options = VideoImportOptions(
            every=args.every, keyframes=keyframes, seconds_per_view=args.seconds_per_view,
            plan_start_s=args.plan_start,
            plan_tolerance=PoseTolerance.from_degrees(args.tolerance, args.tolerance_deg) if args.plan else
            PoseTolerance.unknown())
    except ValueError as exc:
        raise InputError(str(exc)) from None
    plan = read_scan_plan(args.plan) if args.plan else None
    if args.camera:
        camera, intrinsics = read_camera_json(args.camera), f"from {args.camera}"
    else:
        info = probe_video(args.video)
        camera = Camera.from_fov(info.width, info.height, args.fov)
        intrinsics = f"nominal, not calibrated: pinhole, {args.fov:g} deg across the width, centred, no distortion"
    report, finish = _import_report(args, str(args.video))

    def finish_with_damage(folder: Path) -> None:  # the damaged frames into report.json too
        report["decode_damage"] = read_json_object(folder / "dataset.json")["source"]["decode_damage"]
        finish(folder)

    with progress_bar(show_progress(args), "frame") as progress:
        result = run(options, args.video, camera, args.out, plan=plan, intrinsics=intrinsics, progress=progress,
                     finish=finish_with_damage)
    return finish_import(args, result.dataset_dir, report, tuple(decode_damage_summary(report["decode_damage"])))
