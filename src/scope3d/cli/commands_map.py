"""``scope3d map``: the metric, textured, multimodal map of a surgical field (see
:mod:`scope3d.pipelines.surgical_map`). A thin layer: parse, load, call ``run``, print the summary."""
from __future__ import annotations

from scope3d.cli.job_output import add_job_arguments, finish_job, job_folder, show_progress
from scope3d.cli.lazy import LazyChoices
from scope3d.errors import InputError

_PIPELINE = "scope3d.pipelines.surgical_map"


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "map",
        help="map a surgical field: points, textured mesh, fluorescent targets, accuracy report",
        description="Reconstruct a dataset folder into a metric 3D map: SIFT features, pose-guided matching "
                    "(poses whose tolerance is too wide to guide it are first re-estimated from the images: "
                    "similar frames, essential matrices, rotation and position averaging, BCBA), "
                    "triangulation, bundle adjustment (poses fixed, free, or bounded by their tolerance), "
                    "thin-plate-spline surface with texture and fluorescence, targets table, figures, "
                    "COLMAP text model, the adjusted poses as poses_refined.csv (the dataset's poses.csv form, with "
                    "their remaining sigma), and report.json (with errors against ground truth when present).",
    )
    p.add_argument("dataset", metavar="DATASET", help="dataset folder (see scope3d.io.dataset)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (written atomically, replaced)")
    p.add_argument("--pose-mode", choices=LazyChoices(_PIPELINE, "POSE_MODES"), default="bounded", metavar="MODE",
                   help="%(choices)s: bundle adjustment with poses fixed, free (gauge fixed), or bounded by the "
                        "pose tolerance (default bounded)")
    p.add_argument("--matcher", choices=LazyChoices(_PIPELINE, "MATCHERS"), default="guided", metavar="MATCHER",
                   help="%(choices)s: guided = feature position prediction from the poses (default); "
                        "exhaustive = baseline")
    p.add_argument("--preset", choices=LazyChoices(_PIPELINE, "MAP_PRESETS", sort=True), default="default",
                   metavar="PRESET",
                   help="option preset: default, dim_endoscope (CLAHE, lower SIFT threshold), photograph "
                        "(calibrated photos around an object: no surface, no targets)")
    p.add_argument("--intrinsic-bounds", metavar="FILE",
                   help="intrinsic_bounds.json from `scope3d calibrate`: the bundle adjustment refines fx, fy, "
                        "cx, cy, k1, k2 within these bounds and holds one the file leaves out (the dataset's "
                        "camera.json is the start); the model's later parameters are held unless "
                        "--refine-later-intrinsics")
    p.add_argument("--refine-later-intrinsics", action="store_true",
                   help="with --intrinsic-bounds: also refine the camera model's parameters after k2 (OPENCV's p1, "
                        "p2; FULL_OPENCV's p1, p2, k3-k6; the fisheye's k3, k4) within the file's bounds. Off by "
                        "default: on the phantom lab's lenses with calibrated bounds it was no better (barrel-70 "
                        "direct surface error 6 %% lower, fisheye-140 2 %% higher, 3 seeds; docs/calibration.md)")
    p.add_argument("--pose-false-alarm-rate", type=float, default=0.0, metavar="RATE",
                   help="bounded mode: test every reported pose against the images and the other reports, and "
                        "map again with the reports found wrong beyond their tolerance released; RATE is the "
                        "chance of flagging any frame of a map whose reports are all right, e.g. 0.01 "
                        "(default 0: trust every report; measured on the dome: no clean map of 12 or 30 frames "
                        "flagged, glitches of 2 mm and more mostly found, 0.1-0.2 s CPU per 12-frame map and "
                        "0.5-1.2 s per 30-frame map; see docs/reliability.md)")
    p.add_argument("--surface", choices=("spline", "dense"), default="spline",
                   help="spline: the thin-plate-spline height field through the points (default); dense: also a "
                        "depth map per frame, fused where the views agree (dense.ply), and a mesh of it that "
                        "follows overhangs (mesh.ply; the spline's is then mesh_spline.ply)")
    p.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    add_job_arguments(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from dataclasses import replace

    from scope3d.cli.progress import progress_bar
    from scope3d.io.dataset import load_dataset
    from scope3d.pipelines.surgical_map import MAP_PRESETS
    from scope3d.pipelines.surgical_map import run as run_map

    if not 0.0 <= args.pose_false_alarm_rate < 1.0:
        raise InputError(f"--pose-false-alarm-rate must be in [0, 1), got {args.pose_false_alarm_rate}")
    dataset = load_dataset(args.dataset)
    options = replace(MAP_PRESETS[args.preset], pose_mode=args.pose_mode, matcher=args.matcher,
                      figures=not args.no_figures)
    if args.surface == "dense":
        from scope3d.mvs.dense_map import DenseOptions

        options = replace(options, dense=DenseOptions())
    if args.pose_false_alarm_rate == 0.0:
        options = replace(options, pose_check=None)
    else:
        from scope3d.sfm.pose_checks import PoseCheckOptions

        options = replace(options, pose_check=PoseCheckOptions(false_alarm_rate=args.pose_false_alarm_rate))
    if args.refine_later_intrinsics and not args.intrinsic_bounds:
        raise InputError("--refine-later-intrinsics needs --intrinsic-bounds (the box they move in)")
    if args.intrinsic_bounds:
        from scope3d.estimators.bundle.problem import extra_layout
        from scope3d.io.intrinsic_bounds import read_intrinsic_bounds
        from scope3d.sensor.camera import INTRINSIC_NAMES

        later = extra_layout(dataset.camera.model) if args.refine_later_intrinsics else ()
        lower, upper = read_intrinsic_bounds(args.intrinsic_bounds, dataset.camera.model,
                                             names=INTRINSIC_NAMES + later)
        options = replace(options, bundle=replace(options.bundle, refine_intrinsics=True,
                                                  intrinsic_bounds=(tuple(lower), tuple(upper))))
    try:
        with job_folder(args.out) as staged, progress_bar(show_progress(args), "step") as progress:
            result = run_map(options, dataset, staged, progress=progress)
    except ValueError as exc:
        from numpy.linalg import LinAlgError

        if isinstance(exc, (InputError, LinAlgError)):  # a singular solve is our bug, not the user's data
            raise
        # a degenerate scene (no overlap, too few points for a surface) is the user's data, not a bug
        raise InputError(f"{args.dataset}: {exc}") from None
    return finish_job(args, args.out, result.report, [result.summary(), f"wrote {args.out}"])
