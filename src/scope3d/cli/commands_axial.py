"""``scope3d axial``: dense axial-stereo metrology of an internal surface (reference ch. 7, sec. 9.2)."""
from __future__ import annotations

from pathlib import Path

from scope3d.cli.job_output import add_job_arguments, finish_job, job_folder, show_progress


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "axial",
        help="dense 3D of a bore from frames taken along the viewing direction (axial stereo)",
        description="Axial-stereo reconstruction: two frames (sgm, sad) or many fused frames (multiview). "
        "Writes cloud.ply, mesh.ply, depth.png, report.json and, with ground truth, error_histogram.png.",
    )
    p.add_argument("dataset", type=Path, help="dataset folder (see docs/datasets.md)")
    p.add_argument("--out", type=Path, required=True, help="output folder (written atomically, replaced)")
    p.add_argument("--frames", type=int, nargs=2, metavar=("I", "J"), help="the two frames (default: middle pair)")
    p.add_argument("--method", choices=("sgm", "sad", "multiview"), default="sgm",
                   help="sgm: semi-global matching (default); sad: the reference's 7x7 block matcher; "
                   "multiview: multi-baseline fusion along the whole sequence")
    p.add_argument("--true-poses", action="store_true", help="use ground-truth poses (phantom datasets)")
    p.add_argument("--min-depth-mm", type=float, default=3.0,
                   help="nearest surface along the motion; sets the disparity search range (default 3)")
    add_job_arguments(p)
    p.set_defaults(func=_run)


def _run(args) -> int:
    from dataclasses import replace

    from scope3d.cli.progress import progress_bar
    from scope3d.errors import InputError
    from scope3d.io.dataset import load_dataset
    from scope3d.pipelines.axial import AxialOptions, run

    if args.frames is not None and args.method == "multiview":
        raise InputError("--frames selects a two-view pair; multiview uses every frame")
    if not args.min_depth_mm > 0:
        raise InputError("--min-depth-mm must be positive")
    dataset = load_dataset(args.dataset)
    base = AxialOptions()
    options = replace(base, method=args.method, frames=tuple(args.frames) if args.frames else None,
                      use_true_poses=args.true_poses,
                      two_view=replace(base.two_view, min_depth_mm=args.min_depth_mm))
    show = args.method == "multiview" and show_progress(args)
    with job_folder(args.out) as staged, progress_bar(show, "frame") as progress:
        result = run(options, dataset, staged, progress=progress)
    return finish_job(args, args.out, result.report,
                      [result.summary(), f"wrote {args.out}/ (cloud.ply, mesh.ply, depth.png, report.json)"])
