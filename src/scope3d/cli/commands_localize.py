"""``scope3d localize``: where was the scope in each frame? Frames matched against a surgical-field map (ch. 5)."""
from __future__ import annotations

from pathlib import Path

from scope3d.cli.job_output import add_job_arguments, finish_job, job_folder, show_progress


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "localize",
        help="pose of every frame of a dataset from the images, against a map made by `scope3d map`",
        description="Localize each frame of DATASET against the map in MAP_DIR (its map_points.npz): optical-flow "
        "tracking of the map points, SIFT matching near their predicted positions or against the whole map "
        "when tracking is lost, PnP + RANSAC, then the pose refined inside the frame's reported tolerance box "
        "(an infinite tolerance: the image alone). Frames that cannot be localized are reported, never given a "
        "pose. Writes poses.csv (localized frames only, tolerance 3 sigma), report.json (per frame: status, "
        "inliers, time_ms and, with ground truth, position_error_mm and orientation_error_deg) and "
        "localization_errors.png.",
    )
    p.add_argument("map_dir", type=Path, metavar="MAP_DIR", help="output folder of `scope3d map`")
    p.add_argument("dataset", type=Path, metavar="DATASET", help="dataset folder of the frames (see docs/datasets.md)")
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="output folder (replaced if it exists)")
    p.add_argument("--mask", type=Path, metavar="PNG",
                   help="white where a tool hides the scene in every frame (default: DATASET/tool_mask.png if present)")
    p.add_argument("--ignore-reported-poses", action="store_true",
                   help="localize from the images alone, whatever the reported poses' tolerance")
    p.add_argument("--no-tracking", action="store_true",
                   help="match every frame by SIFT (no optical-flow tracking between frames)")
    p.add_argument("--preset", choices=("default", "threaded"), default="default",
                   help="threaded: the SIFT refresh of the tracked points runs on a second thread at half size "
                   "and is merged 2 frames later, so the stream only tracks (same outputs on every run; see "
                   "docs/localization.md)")
    add_job_arguments(p)
    p.set_defaults(func=_run)


def _run(args) -> int:
    from dataclasses import replace

    from scope3d.cli.progress import progress_bar
    from scope3d.io.dataset import load_dataset
    from scope3d.pipelines.localize import LocalizeOptions, run
    from scope3d.sfm.localization import LOCALIZER_PRESETS

    dataset = load_dataset(args.dataset)
    options = replace(LocalizeOptions(), use_reported_poses=not args.ignore_reported_poses,
                      localizer=replace(LOCALIZER_PRESETS[args.preset], tracking=not args.no_tracking))
    with job_folder(args.out) as staged, progress_bar(show_progress(args), "frame") as progress:
        result = run(options, args.map_dir, dataset, staged, mask=args.mask, progress=progress)
    return finish_job(args, args.out, result.report,
                      [result.summary(), f"wrote {args.out}/ (poses.csv, report.json, localization_errors.png)"])
