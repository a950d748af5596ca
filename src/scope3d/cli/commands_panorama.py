"""``scope3d plan-scan``, ``scope3d mosaic`` and ``scope3d panorama``: organ panorama commands (reference ch. 2)."""
from __future__ import annotations

from pathlib import Path

from scope3d.cli.job_output import add_job_arguments, finish_job, job_folder, show_progress


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "plan-scan",
        help="plan a spiral scan of a cavity: perpendicular views at a stand-off, with coverage",
        description="Plan a spiral of views inside a closed cavity (a phantom name such as 'bladder', or a PLY "
                    "mesh), each looking along the wall normal from the stand-off distance, neighbours along and "
                    "across the spiral overlapping by the given fraction (reference sec. 2.3.2). Writes "
                    "DIR/plan.json (n_views, coverage_fraction by ray casting the views onto the mesh, poses), "
                    "DIR/plan.png, DIR/report.json (the plan's figures) and DIR/report.html.",
    )
    p.add_argument("surface", help="phantom name (bladder) or PLY mesh of the cavity wall, mm")
    p.add_argument("--standoff", type=float, default=15.0, metavar="MM", help="distance to the wall, mm (default 15)")
    p.add_argument("--overlap", type=float, default=0.5, metavar="F",
                   help="fraction of the footprint shared by neighbouring views (default 0.5)")
    p.add_argument("--fov", type=float, default=70.0, metavar="DEG",
                   help="field of view across the circular image, degrees (default 70, the phantom endoscope's)")
    p.add_argument("--bend-limit", type=float, metavar="DEG",
                   help="largest angle between the tip's optical axis and the insertion direction (-z); views "
                        "needing more are dropped and the coverage lost is reported (the reference: ~125)")
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="output folder (written atomically, replaced)")
    add_job_arguments(p)  # --quiet accepted for uniformity: the planner shows no progress bar
    p.set_defaults(func=_run_plan)
    register_mosaic(subparsers)
    register_panorama(subparsers)


def _run_plan(args) -> int:
    from scope3d.errors import InputError
    from scope3d.pipelines.scan_plan import run
    from scope3d.sfm.scan_planning import ScanPlanOptions

    try:
        options = ScanPlanOptions(standoff_mm=args.standoff, overlap=args.overlap, fov_deg=args.fov,
                                  bend_limit_deg=args.bend_limit)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    with job_folder(args.out) as staged:
        result = run(options, args.surface, staged)
    return finish_job(args, args.out, result.report,
                      [result.summary(), f"wrote {args.out}/plan.json, plan.png, report.json"])


def register_mosaic(subparsers) -> None:
    p = subparsers.add_parser(
        "mosaic",
        help="2-D mosaic of scope frames with the scope's path and a coverage map",
        description="SIFT + RANSAC homographies between every pair of frames (iterations for 0.99 success), "
                    "global least-squares alignment of all frames, feathered blending. Several datasets (e.g. "
                    "15 mm and 30 mm scans) are combined into one map. Writes DIR/mosaic.png, mosaic_path.png "
                    "(frame centres joined per scan section), coverage.png and report.json (n_frames, "
                    "coverage_fraction, and alignment_error_px against the truth for planar phantoms).",
    )
    p.add_argument("datasets", type=Path, nargs="+", metavar="DATASET", help="dataset folder(s)")
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="output folder (written atomically, replaced)")
    add_job_arguments(p)
    p.set_defaults(func=_run_mosaic)


def _run_mosaic(args) -> int:
    from scope3d.cli.progress import progress_bar
    from scope3d.io.dataset import load_dataset
    from scope3d.pipelines.mosaic import run
    from scope3d.registration.mosaic import MosaicOptions

    datasets = [load_dataset(d) for d in args.datasets]
    with job_folder(args.out) as staged, progress_bar(show_progress(args), "pair") as progress:
        result = run(MosaicOptions(), datasets, staged, progress=progress)
    return finish_job(args, args.out, result.report, [
        result.summary(), f"wrote {args.out}/ (mosaic.png, mosaic_path.png, coverage.png, report.json)"])


def register_panorama(subparsers) -> None:
    p = subparsers.add_parser(
        "panorama",
        help="image-only 3-D panorama of a cavity's wall (poses and points from the images, star scale)",
        description="Camera poses and points of a cavity seen from inside, from the images alone: pairs by "
                    "capture order and retrieval, relative poses chosen by the wall's shape, rotation averaging, "
                    "centres from baselines scaled by the wall's distance, bundle adjustment; points outside an "
                    "anatomical shell (20-70 mm radius) dropped. Planned poses (finite tolerance in poses.csv) "
                    "also choose the pairs they say overlap, and start and bound the poses. The physical scale comes from the 6 mm star targets in the fluorescence frames. "
                    "Writes DIR/report.json (n_frames, n_registered, n_points, time_s; with ground truth "
                    "scale_error_fraction and surface_error_mm.after_similarity), sparse/ (COLMAP text), "
                    "points.ply, mesh.ply (closed wall), wall.obj/.mtl/.png (the wall textured from the frames), "
                    "panorama_3d.png, and the 2-D map of the whole cavity: organ_map.png (the frames on the fitted "
                    "ellipsoid, unwrapped, with the scope's path and the uncovered regions), organ_coverage.png "
                    "(the coverage mask) and report.json organ_map (coverage_fraction, uncovered_regions; with ground truth alignment and "
                    "true_coverage_fraction).",
    )
    p.add_argument("datasets", type=Path, nargs="+", metavar="DATASET",
                   help="dataset folder; further folders: other videos of the same cavity (e.g. a 15 mm and a 30 mm "
                        "scan), each mapped on its own and drawn on one organ map with the first (planned poses "
                        "only: their plans share one frame); the 3-D files are the first's")
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="output folder (replaced atomically)")
    p.add_argument("--no-scale", action="store_true",
                   help="no star targets: an unscaled model (scale_source none) or the plan's scale")
    p.add_argument("--star-mm", type=float, default=6.0, metavar="MM",
                   help="outer (tip circle) diameter of the star targets, mm (default 6)")
    p.add_argument("--ignore-poses", action="store_true",
                   help="do not use planned poses even when poses.csv gives finite tolerances (image-only)")
    p.add_argument("--texel-mm", type=float, default=None, metavar="MM",
                   help="texel size of the textured wall on the wall, mm (default: the frames' own pixel footprint, "
                        "as fine as --atlas-px allows; report.json's texture_texel_mm says what was used)")
    p.add_argument("--atlas-px", type=int, default=2048, metavar="N",
                   help="the texture atlas's longest side at most (default 2048, 2.8 M texels: on a 15 mm spiral "
                        "0.1 mm texels; 4096 halves the texel and takes ~3x the texturing time)")
    p.add_argument("--keep-implausible", action="store_true",
                   help="write the map even when its self-check fails (cameras far off the wall's centre, or a "
                        "wall radius outside the anatomical 20-70 mm); by default such a map is refused (exit 2). "
                        "Images only, a map whose two candidate maps disagree (p95 over half the wall's radius) is "
                        "written with a warning, not refused")
    add_job_arguments(p)
    p.set_defaults(func=_run_panorama)


def _run_panorama(args) -> int:
    from scope3d.cli.progress import progress_bar
    from scope3d.errors import InputError
    from scope3d.io.dataset import load_dataset
    from scope3d.metrology.star_scale import StarScaleOptions
    from scope3d.mvs.texturing import TextureOptions
    from scope3d.pipelines.panorama import Panorama3dOptions, run

    try:
        stars = None if args.no_scale else StarScaleOptions(outer_diameter_mm=args.star_mm)
        texture = TextureOptions(texel_mm=args.texel_mm, max_atlas_px=args.atlas_px)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    options = Panorama3dOptions(stars=stars, use_planned_poses=not args.ignore_poses, texture=texture,
                                refuse_implausible=not args.keep_implausible)
    dataset, *more = [load_dataset(d) for d in args.datasets]
    with job_folder(args.out) as staged, progress_bar(show_progress(args), "frame") as progress:
        result = run(options, dataset, staged, progress=progress, more=more)
    lines = [result.summary()]
    lines.append(f"wrote {args.out}/ (report.json, sparse/, points.ply, mesh.ply, wall.obj, organ_map.png, "
                 "panorama_3d.png)")
    return finish_job(args, args.out, result.report, lines)
