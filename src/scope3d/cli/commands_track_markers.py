"""``scope3d track-markers``: the pose of a marker plate from an optical tracker's export, Kalman-filtered."""
from __future__ import annotations

from pathlib import Path

from scope3d.cli.job_output import add_job_arguments, finish_job, job_folder


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "track-markers",
        help="plate poses from an NDI tracker export (CSV or .xlsx): rigid fit per frame, Kalman filter",
        description="Read an NDI Track export (port, tool, frame, face, state, q0..qz, tx..tz, rms, number of "
        "markers, then state,x,y,z per marker; CSV, or .xlsx first sheet; header row optional). Rows and "
        "markers whose state is not OK never reach the fit. Per frame the plate's rigid pose from three or more "
        "markers, smoothed by a constant-velocity Kalman filter; frames with too few markers are predicted and "
        "flagged. Writes poses.csv (one row per frame, tolerance 3 sigma of the filter) and report.json "
        "(n_frames, n_fitted, n_predicted, agreement with the tracker's own tool pose).",
    )
    p.add_argument("tracker_file", type=Path, metavar="TRACKER_FILE", help="NDI Track export (.csv or .xlsx)")
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="output folder (replaced if it exists)")
    p.add_argument("--rate", type=float, default=60.0, metavar="HZ", help="tracker frame rate (default 60)")
    p.add_argument("--marker-sigma", type=float, default=0.25, metavar="MM",
                   help="noise of one marker position per axis (default 0.25 mm)")
    p.add_argument("--no-filter", action="store_true", help="write the raw per-frame fits (no Kalman filter)")
    add_job_arguments(p)  # --quiet accepted for uniformity: the job shows no progress bar
    p.set_defaults(func=_run)


def _run(args) -> int:
    from scope3d.errors import InputError
    from scope3d.pipelines.track_markers import TrackMarkersOptions, run

    try:
        options = TrackMarkersOptions(rate_hz=args.rate, marker_sigma_mm=args.marker_sigma, filter=not args.no_filter)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    with job_folder(args.out) as staged:
        result = run(options, args.tracker_file, staged)
    return finish_job(args, args.out, result.report, [result.summary(), f"wrote {args.out}/ (poses.csv, report.json)"])
