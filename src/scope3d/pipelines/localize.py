"""Localization of a frame sequence against a surgical-field map (reference ch. 5), as ``scope3d localize`` runs it.

Method, one stage per function, run top to bottom by :func:`run`:

1. :func:`load_inputs` — the map's points with descriptors (``MAP_DIR/map_points.npz``, written by
   ``scope3d map``), the dataset, and the mask of the tool (``--mask``, or the dataset's
   ``tool_mask.png`` when it has one).
2. :func:`localize_frames` — the frames streamed through one
   :class:`~scope3d.sfm.localization.Localizer` in order (tracking, guided or global matching, PnP +
   RANSAC, pose refinement inside the reported pose's tolerance box).
3. :func:`evaluate_frames` — per-frame errors against the ground-truth poses, where the dataset has them.
4. :func:`write_outputs` — ``poses.csv`` (the dataset's columns; frames not localized are left out; the
   tolerance of each pose is ``tolerance_sigmas`` standard deviations of its estimate), ``report.json``
   and ``localization_errors.png`` (error per frame along the trajectory).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from scope3d.errors import InputError
from scope3d.io.dataset import Dataset
from scope3d.io.images import read_image
from scope3d.io.map_points import MapPoints, read_map_points
from scope3d.io.poses_csv import format_poses_csv
from scope3d.phantoms.lab import TOOL_MASK_FILE
from scope3d.sensor.pose_tolerance import MeasuredPose, PoseTolerance
from scope3d.sfm.localization import LocalizationResult, Localizer, LocalizerOptions
from scope3d.utils.atomic import atomic_directory
from scope3d.utils.figures import new_figure, save_figure
from scope3d.utils.jsonio import write_json
from scope3d.utils.progress import Progress, advance, stage


@dataclass(frozen=True)
class LocalizeOptions:
    """localizer : :class:`~scope3d.sfm.localization.LocalizerOptions`.
    use_reported_poses : bool, give the localizer each frame's reported pose and tolerance (default True;
        False: the image alone, as with an infinite tolerance).
    tolerance_sigmas : float, the tolerance written for a localized pose, in standard deviations of its
        estimate (default 3).
    figures : bool, write the error figure (default True).
    """

    localizer: LocalizerOptions = field(default_factory=LocalizerOptions)
    use_reported_poses: bool = True
    tolerance_sigmas: float = 3.0
    figures: bool = True

    def __post_init__(self) -> None:
        if not self.tolerance_sigmas > 0:
            raise ValueError(f"tolerance_sigmas must be positive, got {self.tolerance_sigmas}")


@dataclass
class LocalizeResult:
    """What :func:`run` returns: the report (also in ``out_dir/report.json``) and per-frame results."""

    report: dict
    out_dir: Path
    frames: list[LocalizationResult]

    @property
    def cam_from_world(self) -> np.ndarray:
        """(m, 4, 4) each frame's localized pose as a matrix, NaN where it was not localized."""
        return np.array([f.pose.matrix if f.pose is not None else np.full((4, 4), np.nan)
                         for f in self.frames]).reshape(-1, 4, 4)

    def summary(self) -> str:
        r = self.report
        line = (f"{r['n_localized']} of {r['n_frames']} frames localized, {r['frames_per_s']:.1f} frames/s "
                f"({r['cpu_ms_per_frame']:.1f} ms CPU per frame)")
        if r.get("median_position_error_mm") is not None:
            line += (f"; median error {r['median_position_error_mm']:.3f} mm, "
                     f"{r['median_orientation_error_deg']:.3f} deg")
        return line


def load_blocked_mask(path: str | Path, width: int, height: int) -> np.ndarray:
    """(H, W) bool from a mask image: True (white, > 127) where the tool hides the scene."""
    path = Path(path)
    image = read_image(path)
    grey = image if image.ndim == 2 else image[..., 0]
    if grey.shape != (height, width):
        raise InputError(f"{path}: mask is {grey.shape[1]}x{grey.shape[0]}, the frames {width}x{height}")
    return grey > 127


def load_inputs(map_dir: str | Path, dataset: Dataset, mask: str | Path | None) -> tuple[MapPoints, np.ndarray | None]:
    """The map's points and the tool's mask (``mask``, else the dataset's ``tool_mask.png``, else None)."""
    points = read_map_points(map_dir)
    if mask is None and (dataset.root / TOOL_MASK_FILE).is_file():
        mask = dataset.root / TOOL_MASK_FILE
    blocked = None if mask is None else load_blocked_mask(mask, dataset.camera.width, dataset.camera.height)
    return points, blocked


def localize_frames(options: LocalizeOptions, localizer: Localizer, dataset: Dataset, blocked: np.ndarray | None, *,
                    progress: Progress | None = None) -> tuple[list[LocalizationResult], float]:
    """Every frame through ``localizer`` in order. Returns the results and the wall time spent in
    :meth:`~scope3d.sfm.localization.Localizer.localize` (frame reading excluded: a live stream delivers
    decoded frames)."""
    results, busy = [], 0.0
    stage(progress, "localize", len(dataset))
    for k in range(len(dataset)):
        image = dataset.frame(k)
        reported = dataset.poses[k] if options.use_reported_poses else None
        result = localizer.localize(image, reported, blocked=blocked)
        busy += result.time_s
        results.append(result)
        advance(progress)
    return results, busy


def evaluate_frames(dataset: Dataset, results: list[LocalizationResult]) -> list[dict]:
    """Per frame: name, status, mode, matches, inliers, time, and the errors against the ground truth."""
    truth = dataset.ground_truth.poses if dataset.ground_truth is not None else None
    rows = []
    for k, (name, r) in enumerate(zip(dataset.names, results)):
        row = {"frame": name, "status": r.status, "mode": r.mode, "matches": r.n_matches, "inliers": r.n_inliers,
               "time_ms": round(1000 * r.time_s, 3), "cpu_ms": round(1000 * r.cpu_s, 3)}
        if r.ok:
            row["position_sigma_mm"] = np.sqrt(np.diag(r.covariance)[3:]).round(5).tolist()
        if r.ok and truth is not None:
            d_mm, d_rad = r.pose.distance_to(truth[k])
            row["position_error_mm"], row["orientation_error_deg"] = d_mm, float(np.rad2deg(d_rad))
        rows.append(row)
    return rows


def measured(result: LocalizationResult, sigmas: float) -> MeasuredPose:
    """A localized pose as a measurement: the tolerance is ``sigmas`` standard deviations per axis."""
    sd = np.sqrt(np.maximum(np.diag(result.covariance), 0.0))
    return MeasuredPose(result.pose, PoseTolerance(sigmas * sd[3:], sigmas * sd[:3]))


def write_outputs(options: LocalizeOptions, dataset: Dataset, out_dir: Path, results: list[LocalizationResult],
                  rows: list[dict], busy_s: float, map_dir: Path, n_map_points: int, blocked: np.ndarray | None) -> dict:
    """poses.csv, report.json and the error figure into ``out_dir`` (already a temporary folder)."""
    ok = [k for k, r in enumerate(results) if r.ok]
    (out_dir / "poses.csv").write_text(format_poses_csv([dataset.names[k] for k in ok],
                                                        [measured(results[k], options.tolerance_sigmas) for k in ok]))
    pos = [row["position_error_mm"] for row in rows if "position_error_mm" in row]
    ori = [row["orientation_error_deg"] for row in rows if "orientation_error_deg" in row]
    statuses, modes = {}, {}
    for r in results:
        statuses[r.status] = statuses.get(r.status, 0) + 1
        modes[r.mode] = modes.get(r.mode, 0) + 1
    report = {
        "map": str(map_dir), "dataset": str(dataset.root), "n_map_points": n_map_points, "n_frames": len(results),
        "n_localized": len(ok), "statuses": statuses, "modes": modes,
        "tool_mask_fraction": None if blocked is None else float(blocked.mean()),
        "used_reported_poses": options.use_reported_poses,
        "median_position_error_mm": float(np.median(pos)) if pos else None,
        "median_orientation_error_deg": float(np.median(ori)) if ori else None,
        "max_position_error_mm": float(np.max(pos)) if pos else None,
        "max_orientation_error_deg": float(np.max(ori)) if ori else None,
        "frames_per_s": len(results) / busy_s if busy_s > 0 else None,
        "cpu_ms_per_frame": 1000 * float(np.mean([r.cpu_s for r in results])) if results else None,
        "frames": rows,
    }
    write_json(out_dir / "report.json", report)
    if options.figures:
        save_error_figure(out_dir / "localization_errors.png", dataset, results, rows)
    return report


def save_error_figure(path: Path, dataset: Dataset, results: list[LocalizationResult], rows: list[dict]) -> None:
    """Error per frame along the trajectory: the path seen from above and from the side with each
    localized frame coloured by its position error, and the errors and inliers per frame."""
    truth = dataset.ground_truth.poses if dataset.ground_truth is not None else None
    fig = new_figure((13.0, 4.2), dpi=100)
    axes = fig.subplots(1, 3)
    ok = [k for k, r in enumerate(results) if r.ok]
    est = np.array([results[k].pose.centre for k in ok]).reshape(-1, 3)
    err = np.array([rows[k].get("position_error_mm", np.nan) for k in ok])
    for ax, (a, b, label) in zip(axes[:2], ((0, 1, "from above: x, y (mm)"), (0, 2, "from the side: x, z (mm)"))):
        if truth is not None:
            c = np.array([p.centre for p in truth])
            ax.plot(c[:, a], c[:, b], "-", color="0.6", label="true path")
        colour = {"c": err, "cmap": "viridis"} if np.any(np.isfinite(err)) else {}
        sc = ax.scatter(est[:, a], est[:, b], s=18, label="localized", **colour)
        ax.set_title(label, fontsize=9)
        ax.set_aspect("equal", adjustable="datalim")
        ax.legend(fontsize=7)
    if np.any(np.isfinite(err)):
        fig.colorbar(sc, ax=axes[1], label="position error (mm)")
    ax = axes[2]
    frames = np.arange(len(results))
    pe = np.array([row.get("position_error_mm", np.nan) for row in rows])
    oe = np.array([row.get("orientation_error_deg", np.nan) for row in rows])
    ax.plot(frames, pe, "o-", ms=3, label="position error (mm)")
    ax.plot(frames, oe, "s-", ms=3, label="orientation error (deg)")
    failed = [k for k, r in enumerate(results) if not r.ok]
    if failed:
        ax.plot(failed, np.zeros(len(failed)), "rx", label="not localized")
    ax.set_xlabel("frame")
    ax.set_title("error per frame", fontsize=9)
    twin = ax.twinx()
    twin.plot(frames, [r.n_inliers for r in results], color="0.7", lw=1)
    twin.set_ylabel("inliers", color="0.5")
    ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    save_figure(fig, path)


def run(options: LocalizeOptions, map_dir: str | Path, dataset: Dataset, out_dir: str | Path, *,
        mask: str | Path | None = None, progress: Progress | None = None) -> LocalizeResult:
    """Localize every frame of ``dataset`` against the map in ``map_dir``; write ``out_dir`` atomically."""
    t0 = time.perf_counter()
    points, blocked = load_inputs(map_dir, dataset, mask)
    try:
        localizer = Localizer(points, dataset.camera, options.localizer)
    except ValueError as exc:
        raise InputError(f"{map_dir}: {exc}") from None
    with localizer:  # stops the refresh thread, if the options started one
        results, busy = localize_frames(options, localizer, dataset, blocked, progress=progress)
    rows = evaluate_frames(dataset, results)
    with atomic_directory(Path(out_dir)) as tmp:
        report = write_outputs(options, dataset, tmp, results, rows, busy, Path(map_dir), len(points), blocked)
        report["time_s"] = time.perf_counter() - t0
        write_json(tmp / "report.json", report)
    return LocalizeResult(report, Path(out_dir), results)
