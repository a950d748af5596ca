"""``scope3d live``: the live map — a recording replayed frame by frame through the live mapper (issue 36)."""
from __future__ import annotations

from pathlib import Path

from scope3d.cli.job_output import add_job_arguments, finish_job, job_folder, show_progress


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "live",
        help="replay a recording through the live mapper: every frame tracked and fused with the robot's pose, "
        "the map grown by keyframes",
        description="Replay DATASET's frames with their reported poses through the live mapper "
        "(scope3d.sfm.live_mapping): each frame tracked against the local map and fused with the robot's pose "
        "by a Kalman filter, keyframes when the view moved, local bounded bundle adjustment in a worker process, "
        "global bounded bundle adjustment at the end. Writes poses.csv (every frame's fused pose, tolerance 3 "
        "sigma), frames.csv (status, latency, errors), keyframes.csv, map.ply, keyframe_maps/, report.json "
        "(latency_ms median and p99; with ground truth tracking_error, pose_error and surface_error_mm) and "
        "live.png. See docs/live.md.",
    )
    p.add_argument("dataset", type=Path, metavar="DATASET", help="dataset folder of the frames (see docs/datasets.md)")
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="output folder (replaced if it exists)")
    p.add_argument("--no-wait", action="store_true",
                   help="replay as fast as possible instead of at the recording's frame rate")
    p.add_argument("--fps", type=float, metavar="FPS",
                   help="the recording's frame rate (default: the phantom video's, from its ground truth)")
    p.add_argument("--preset", choices=("default", "dim_endoscope"), default="default",
                   help="dim_endoscope: CLAHE and a lower SIFT threshold, for dark or small frames (as `scope3d map "
                   "--preset dim_endoscope`)")
    p.add_argument("--changing-tissue", action="store_true",
                   help="test each keyframe for tissue that changed (resected, moved) and map it again from the new "
                   "keyframes (mvs.surface_change; 0.5-1.5 s of the worker per keyframe: the stream may wait for "
                   "it; docs/live.md)")
    add_job_arguments(p)
    p.set_defaults(func=_run)


def _run(args) -> int:
    from scope3d.cli.progress import progress_bar
    from scope3d.errors import InputError
    from scope3d.io.dataset import load_dataset
    from scope3d.mvs.surface_change import SurfaceChangeOptions
    from scope3d.pipelines.live import LiveOptions, run
    from scope3d.sfm.live_mapping import LIVE_PRESETS

    dataset = load_dataset(args.dataset)
    try:
        options = LiveOptions(LIVE_PRESETS[args.preset], wait=not args.no_wait, fps=args.fps,
                              change=SurfaceChangeOptions() if args.changing_tissue else None)
    except ValueError as exc:
        raise InputError(f"--fps: {exc}") from None
    with job_folder(args.out) as staged, progress_bar(show_progress(args), "frame") as progress:
        result = run(options, dataset, staged, progress=progress)
    return finish_job(args, args.out, result.report,
                      [result.summary(), f"wrote {args.out}/ (poses.csv, frames.csv, keyframes.csv, map.ply, "
                                         "keyframe_maps/, report.json, live.png)"])
