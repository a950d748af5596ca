"""``scope3d import frames``: a folder of frames or a video, and a robot's pose log, as a dataset.

Thin layer over :func:`scope3d.pipelines.frames_import.run`: it parses the flags into
:class:`~scope3d.pipelines.frames_import.FramesImportOptions` and reads the camera, the hand-eye and the
frame-time table.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

from scope3d.cli.job_output import (
    add_job_arguments,
    check_dataset_output,
    dataset_report_writer,
    finish_import,
    show_progress,
)
from scope3d.errors import InputError

ROBOT_CLASS_NAMES = ("micro-stage", "optical-tracker", "industrial-arm", "cable-driven-arm")


def register(formats) -> None:
    """Add ``frames`` to the ``scope3d import`` formats."""
    frm = formats.add_parser(
        "frames",
        help="a folder of frames or a video, with a robot's pose log (CSV) and its hand-eye",
        description="Import a scope's frames (a folder of images, or a video) with the poses a robot controller "
                    "or tracker logged: one pose per row of a CSV with a header, a time column, any unit and "
                    "column layout, at its own rate and clock. Each frame's pose is interpolated in time "
                    "(linear, slerp), taken through the hand-eye transform onto the camera, and given the "
                    "robot's tolerance. Example: scope3d import frames FRAMES --camera camera.json --poses "
                    "log.csv --pose-format xyz-qxyzw --unit m --frame-times frame_times.csv --hand-eye "
                    "hand_eye.json --tolerance 0.5 --tolerance-deg 0.25 --out DIR. See docs/own_data.md.",
    )
    frm.add_argument("source", metavar="SOURCE", type=Path, help="folder of images, or a video file")
    frm.add_argument("--out", metavar="DIR", type=Path, required=True,
                     help="dataset folder to write (replaced only if it is a scope3d dataset)")
    frm.add_argument("--camera", metavar="CAMERA_JSON", type=Path, required=True,
                     help="camera.json (scope3d calibrate)")
    log = frm.add_argument_group("robot log")
    log.add_argument("--poses", metavar="LOG_CSV", type=Path, required=True,
                     help="the robot's log: a CSV with a header, a time column and the pose columns")
    add_log_format_arguments(log)
    times = frm.add_argument_group("frame times (on the camera's clock; a video has its own)")
    which = times.add_mutually_exclusive_group()
    which.add_argument("--frame-times", metavar="CSV", type=Path,
                       help="a table with a header image,t: each frame's time (a video's frame: its index)")
    which.add_argument("--times-in-names", metavar="UNIT", choices=("s", "ms", "us", "ns"),
                       help="each frame's time is the last number in its file name, in UNIT")
    which.add_argument("--fps", type=float, metavar="HZ",
                       help="frames at a constant rate: frame i (in name order) at --first-frame + i / HZ")
    times.add_argument("--first-frame", type=float, default=0.0, metavar="S",
                       help="with --fps: the first frame's time (default 0)")
    times.add_argument("--clock-offset", type=float, default=0.0, metavar="S",
                       help="added to every frame time to put it on the log's clock (default 0)")
    times.add_argument("--skip-unposed-frames", action="store_true",
                       help="leave out frames outside the log or in a longer gap (listed in dataset.json) "
                            "instead of refusing")
    frm.add_argument("--every", type=int, default=1, metavar="N", help="a video: keep frames 0, N, 2N... (default 1)")
    frm.add_argument("--hand-eye", metavar="HAND_EYE_JSON", type=Path,
                     help="hand_eye.json (scope3d calibrate-hand-eye): the log holds flange poses; without it "
                          "the log holds the camera's own poses")
    tol = frm.add_argument_group("tolerance (how far the camera may be from its logged pose)")
    tol.add_argument("--tolerance", metavar="MM", type=float, help="half-width per world axis, mm")
    tol.add_argument("--tolerance-deg", metavar="DEG", type=float, help="half-width per camera axis, degrees")
    tol.add_argument("--robot", choices=ROBOT_CLASS_NAMES,
                     help="a named class of device instead of numbers (each states its source; your data sheet's "
                          "figures are better)")
    add_job_arguments(frm)
    frm.set_defaults(func=run_import_frames)


def add_log_format_arguments(group) -> None:
    """The flags that say how to read a robot log (shared with ``calibrate-hand-eye --robot-log``)."""
    group.add_argument("--pose-format", default="xyz-qxyzw", metavar="FORMAT",
                       help="xyz-qxyzw (x,y,z,qx,qy,qz,qw; default), xyz-qwxyz, xyz-euler-AXES (x,y,z,r1,r2,r3; "
                            "AXES as SciPy: xyz extrinsic, ZYX intrinsic), xyz-rotvec (x,y,z,rx,ry,rz), matrix44 "
                            "(m00..m33, row-major)")
    group.add_argument("--columns", metavar="NAME=COLUMN,...", default="",
                       help="the file's own column names where they differ, e.g. t=time,x=X,qw=W")
    group.add_argument("--unit", default="mm", choices=("mm", "cm", "m", "um"), help="the log's length unit")
    group.add_argument("--time-unit", default="s", choices=("s", "ms", "us", "ns"),
                       help="the log's (and the frame-time table's) time unit (default s)")
    group.add_argument("--angle-unit", default="deg", choices=("deg", "rad"),
                       help="Euler angles' and rotation vectors' unit (default deg)")
    group.add_argument("--drop-bad-rows", action="store_true",
                       help="leave out (and count) rows with NaN, a non-unit quaternion or a time out of order, "
                            "instead of refusing the log")
    group.add_argument("--max-gap", type=float, default=None, metavar="S",
                       help="longest stretch of log a pose may be interpolated across (default 0.1 s)")


def log_format(args):
    """The :class:`~scope3d.io.robot_log.PoseLogFormat` the flags of :func:`add_log_format_arguments` name."""
    from scope3d.io.robot_log import PoseLogFormat

    try:
        return PoseLogFormat(args.pose_format, _column_map(args.columns), args.unit, args.time_unit, args.angle_unit,
                             args.drop_bad_rows)
    except ValueError as exc:
        raise InputError(str(exc)) from None


def max_gap(args) -> float:
    from scope3d.pipelines.frames_import import DEFAULT_MAX_GAP_S

    if args.max_gap is not None and not args.max_gap > 0:
        raise InputError(f"--max-gap must be positive, got {args.max_gap}")
    return DEFAULT_MAX_GAP_S if args.max_gap is None else args.max_gap


def _column_map(text: str) -> dict[str, str]:
    out = {}
    for item in filter(None, (part.strip() for part in text.split(","))):
        name, sep, column = item.partition("=")
        if not sep or not name.strip() or not column.strip():
            raise InputError(f"--columns: {item!r} is not NAME=COLUMN")
        out[name.strip()] = column.strip()
    return out


def _tolerance(args):
    from scope3d.sensor.pose_tolerance import ROBOT_CLASSES, PoseTolerance

    numbers = args.tolerance is not None or args.tolerance_deg is not None
    if args.robot and numbers:
        raise InputError("give either --robot or --tolerance/--tolerance-deg, not both")
    if args.robot:
        robot = ROBOT_CLASSES[args.robot]
        return robot.tolerance, robot.source
    if args.tolerance is None or args.tolerance_deg is None:
        raise InputError("the logged poses need a tolerance: --tolerance MM and --tolerance-deg DEG (or --robot "
                         "CLASS); use inf for unknown")
    for flag, value in (("--tolerance", args.tolerance), ("--tolerance-deg", args.tolerance_deg)):
        if not value >= 0:
            raise InputError(f"{flag} must be zero or positive (inf = unknown), got {value}")
    return PoseTolerance.from_degrees(args.tolerance, args.tolerance_deg), "given"


def run_import_frames(args) -> int:
    from scope3d.cli.progress import progress_bar
    from scope3d.io.camera_json import read_camera_json
    from scope3d.io.hand_eye_json import read_hand_eye_json
    from scope3d.io.json_object import read_json_object
    from scope3d.io.robot_log import read_frame_times
    from scope3d.pipelines.frames_import import FramesImportOptions, FrameTiming, run

    tolerance, source = _tolerance(args)
    try:
        options = FramesImportOptions(
            log=log_format(args), timing=FrameTiming(args.times_in_names, args.fps, args.first_frame, args.clock_offset),
            tolerance=tolerance, tolerance_source=source, max_gap_s=max_gap(args),
            skip_unposed_frames=args.skip_unposed_frames, every=args.every)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    check_dataset_output(args.out)
    camera = read_camera_json(args.camera)
    hand_eye = read_hand_eye_json(args.hand_eye) if args.hand_eye else None
    frame_times = read_frame_times(args.frame_times, args.time_unit) if args.frame_times else None
    report = {"job": "import frames", "source": str(args.source), "log": str(args.poses)}
    write_report = dataset_report_writer(report, args.out.name, time.perf_counter())

    def finish(folder: Path) -> None:  # the log's rows, dropped rows and interpolation gaps into report.json too
        source = read_json_object(folder / "dataset.json")["source"]
        report.update({key: source[key] for key in ("log", "interpolation", "tolerance", "frames_without_pose")})
        write_report(folder)

    with progress_bar(show_progress(args), "frame") as progress:
        result = run(options, args.source, args.poses, camera, args.out, frame_times=frame_times, hand_eye=hand_eye,
                     progress=progress, finish=finish)
    return finish_import(args, result.out_dir, report, tuple(result.summary().splitlines()[1:]))
