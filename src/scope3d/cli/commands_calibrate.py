"""``scope3d calibrate`` (intrinsics with uncertainty from board images) and ``scope3d calibrate-hand-eye``
(camera-from-flange from board images and robot poses); reference sec. 6.3, 8.1."""
from __future__ import annotations

from pathlib import Path

from scope3d.cli.commands_import_frames import add_log_format_arguments, log_format, max_gap
from scope3d.cli.job_output import add_job_arguments, finish_job, job_folder, show_progress


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "calibrate",
        help="calibrate a scope from checkerboard or ChArUco images: intrinsics, their sigmas, BCBA bounds",
        description="Detect the board in every image, fit the lens model (--model: radial, the pinhole + k1, "
        "k2 model scope3d's jobs use; opencv; full-opencv; fisheye), drop outlier views, and write "
        "DIR/camera.json of that model, DIR/intrinsic_bounds.json (value +- k sigma of each of its parameters, "
        "for `scope3d map --intrinsic-bounds`, which refines every parameter of any model inside them, and "
        "`scope3d bundle-adjust --intrinsic-bounds`, which takes the radial model's f, k1, k2), DIR/report.json (rms_px, n_views_used, intrinsics with value and std, "
        "per-view errors, rejected views and why), DIR/coverage.png and DIR/residuals.png.",
    )
    p.add_argument("images", type=Path, nargs="+", help="board images of one camera (same size)")
    p.add_argument("--board", required=True, metavar="COLSxROWS",
                   help="inner corners, OpenCV's convention (a 10x7-square board is 9x6)")
    p.add_argument("--square", type=float, required=True, metavar="MM", help="side of one square, mm")
    p.add_argument("--out", type=Path, required=True, help="output folder (written atomically, replaced)")
    p.add_argument("--model", choices=("radial", "opencv", "full-opencv", "fisheye", "pinhole"), default="radial",
                   help="radial: fx, fy, cx, cy, k1, k2 (default; camera.json model pinhole_radial_k1k2, the "
                   "jobs' camera; 'pinhole' is its old name); opencv: + p1, p2 (COLMAP OPENCV); full-opencv: + "
                   "k3..k6, the rational model (COLMAP FULL_OPENCV); fisheye: Kannala-Brandt k1..k4 "
                   "(COLMAP OPENCV_FISHEYE, cv2.fisheye; capsule and wide-angle scopes)")
    p.add_argument("--charuco", action="store_true", help="the board is a ChArUco board (cv2.aruco)")
    p.add_argument("--charuco-dictionary", default="DICT_4X4_50", help="ArUco dictionary (default DICT_4X4_50)")
    p.add_argument("--marker", type=float, metavar="MM", help="ChArUco marker side, mm (default 0.7 square)")
    p.add_argument("--mask-circle", action="store_true",
                   help="the image is a lit disc (scanning-fibre scope): ignore what lies outside it")
    refine = p.add_mutually_exclusive_group()
    refine.add_argument("--no-refine", action="store_false", dest="refine",
                        help="keep OpenCV's sector detector's own corners (no cornerSubPix): a smaller residual on "
                        "small, strongly distorted images such as a capsule's (docs/calibration.md), but sigmas "
                        "too small on sharp boards")
    refine.add_argument("--refine", action="store_true",
                        help="refine checkerboard corners with cornerSubPix after OpenCV's sector detector (the "
                        "default: the more accurate corners against rendered truth, and honest sigmas)")
    p.add_argument("--k-sigma", type=float, default=3.0,
                   help="half-width of the bounds in standard deviations (default 3)")
    p.add_argument("--min-views", type=int, default=3, help="fewest usable views (default 3)")
    add_job_arguments(p)
    p.set_defaults(func=_run, refine=True)
    register_hand_eye(subparsers)


def _run(args) -> int:
    from scope3d.cli.progress import progress_bar
    from scope3d.errors import InputError
    from scope3d.pipelines.calibrate import CalibrateOptions, run
    from scope3d.sensor.calibration import BoardSpec, CalibrationOptions, DetectionOptions

    if not args.k_sigma > 0:
        raise InputError("--k-sigma must be positive")
    if args.min_views < 3:
        raise InputError("--min-views must be at least 3")
    kind = "charuco" if args.charuco else "checkerboard"
    board = BoardSpec.parse(args.board, args.square, kind=kind, marker_mm=args.marker,
                            dictionary=args.charuco_dictionary)
    options = CalibrateOptions(board, model=args.model, k_sigma=args.k_sigma, mask_circle=args.mask_circle,
                               detection=DetectionOptions(refine_corners=args.refine),
                               calibration=CalibrationOptions(min_views=args.min_views))
    show = show_progress(args) and len(args.images) > 20
    with job_folder(args.out) as staged, progress_bar(show, "image") as progress:
        result = run(options, args.images, staged, progress=progress)
    return finish_job(args, args.out, result.report, [
        result.summary(),
        f"wrote {args.out}/ (camera.json, intrinsic_bounds.json, report.json, coverage.png, residuals.png)"])


def register_hand_eye(subparsers) -> None:
    p = subparsers.add_parser(
        "calibrate-hand-eye",
        help="camera-from-flange transform of a robot-held scope from board images and the robot's poses",
        description="Detect the board in every image, find its pose through the calibrated camera, solve "
        "AX = XB in closed form (Park-Martin) and refine it jointly; write DIR/hand_eye.json "
        "(flange_from_cam, cam_from_flange, residuals, pose tolerance = k x (residual RMS and the intrinsics' "
        "share in quadrature)) and DIR/poses.csv "
        "(every robot row turned into a camera pose with that tolerance: a dataset's poses.csv).",
    )
    p.add_argument("images", type=Path, nargs="+", help="board images, named as in the robot poses file")
    robot = p.add_argument_group("the robot's pose at each image: --robot-poses, or --robot-log with --frame-times")
    which = robot.add_mutually_exclusive_group(required=True)
    which.add_argument("--robot-poses", type=Path, metavar="CSV",
                       help="poses.csv format (docs/datasets.md); each row is the flange pose in the robot base "
                       "(x_mm, y_mm, z_mm: flange origin; qw..qz: base_from_flange)")
    which.add_argument("--robot-log", type=Path, metavar="LOG_CSV",
                       help="the robot's log of the session, read as `scope3d import frames --poses` reads it; "
                            "each image's pose interpolated at its time (--frame-times)")
    robot.add_argument("--frame-times", type=Path, metavar="CSV",
                       help="with --robot-log: a table image,t giving each image's time on the log's clock")
    add_log_format_arguments(robot)
    p.add_argument("--camera", type=Path, required=True, help="camera.json of the calibrated scope")
    p.add_argument("--board", required=True, metavar="COLSxROWS", help="inner corners (use one odd, one even "
                   "side: an even x even board's orientation is ambiguous)")
    p.add_argument("--square", type=float, required=True, metavar="MM", help="side of one square, mm")
    p.add_argument("--out", type=Path, required=True, help="output folder (written atomically, replaced)")
    p.add_argument("--no-refine", action="store_true", help="closed form only, no joint refinement")
    p.add_argument("--tolerance-sigmas", type=float, default=3.0,
                   help="pose tolerance = this many residual RMS per axis, the intrinsics' share added in "
                        "quadrature (default 3)")
    p.add_argument("--intrinsic-bounds", type=Path, metavar="JSON",
                   help="intrinsic_bounds.json of `scope3d calibrate`: its sigmas give the intrinsics' share of "
                        "the tolerance (a focal length's error moves every board alike, which the residuals "
                        "cannot show). Default: the intrinsic_bounds.json beside --camera when there is one")
    add_job_arguments(p)  # --quiet accepted for uniformity: the job shows no progress bar
    p.set_defaults(func=_run_hand_eye)


def _run_hand_eye(args) -> int:
    from scope3d.errors import InputError
    from scope3d.io.camera_json import read_camera_json
    from scope3d.io.intrinsic_bounds import read_intrinsic_sigmas
    from scope3d.io.robot_log import read_frame_times
    from scope3d.pipelines.hand_eye import HandEyeRunOptions, robot_poses_from_log, run
    from scope3d.sensor.calibration import BoardSpec
    from scope3d.sensor.hand_eye import HandEyeOptions

    if not args.tolerance_sigmas > 0:
        raise InputError("--tolerance-sigmas must be positive")
    board = BoardSpec.parse(args.board, args.square)
    options = HandEyeRunOptions(board, hand_eye=HandEyeOptions(refine=not args.no_refine,
                                                               tolerance_sigmas=args.tolerance_sigmas))
    camera = read_camera_json(args.camera)
    bounds = args.intrinsic_bounds
    if bounds is None and (args.camera.parent / "intrinsic_bounds.json").is_file():
        bounds = args.camera.parent / "intrinsic_bounds.json"
    sigmas = None if bounds is None else read_intrinsic_sigmas(bounds, camera.model, camera.param_names)
    robot = args.robot_poses
    if args.robot_log is not None:
        if args.frame_times is None:
            raise InputError("--robot-log needs --frame-times: when each image was taken, on the log's clock")
        robot = robot_poses_from_log(args.robot_log, log_format(args), read_frame_times(args.frame_times, args.time_unit),
                                     max_gap_s=max_gap(args))
    elif args.frame_times is not None:
        raise InputError("--frame-times goes with --robot-log")
    with job_folder(args.out) as staged:
        result = run(options, args.images, robot, camera, staged, intrinsic_sigmas=sigmas,
                     intrinsic_sigmas_source=None if bounds is None else str(bounds))
    return finish_job(args, args.out, result.report, [result.summary(), f"wrote {args.out}/ (hand_eye.json, poses.csv)"])
