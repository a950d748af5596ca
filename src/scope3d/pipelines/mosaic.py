"""2-D mosaic of scope frames (reference sec. 2.3.3), ``scope3d mosaic``. :func:`run` reads as the method::

    frames    <- every frame of every dataset (a 15 mm and a 30 mm scan fill each other's gaps, sec. 2.4.2)
    links     <- SIFT + RANSAC homographies between every pair of frames (registration.mosaic)
    alignment <- global least-squares alignment of all frames in the first frame's plane
    image     <- feathered blending; the scope's path per scan section; the coverage map
    truth     <- where every dataset has true poses on one flat surface: the alignment error in pixels
    files     <- mosaic.png, mosaic_path.png, coverage.png, report.json
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from scope3d.errors import InputError
from scope3d.io.dataset import Dataset
from scope3d.io.images import write_image
from scope3d.registration import mosaic as mos
from scope3d.registration.mosaic import Mosaic, MosaicOptions
from scope3d.utils.jsonio import write_json
from scope3d.utils.progress import Progress, stage


@dataclass
class MosaicResult:
    """report : report.json as written; mosaic : the aligned and blended mosaic (image, coverage, per-frame
    homographies)."""

    report: dict
    mosaic: Mosaic

    @property
    def image(self) -> np.ndarray | None:
        """(H, W, 3) uint8, the blended mosaic (mosaic.png)."""
        return self.mosaic.image

    def summary(self) -> str:
        r = self.report
        err = r["alignment_error_px"]
        return (f"{r['n_registered']}/{r['n_frames']} frames in the mosaic, coverage {r['coverage_fraction']:.1%}"
                + (f", alignment error {err['mean']:.2f} px mean, {err['p95']:.2f} px p95" if err else ""))


def _sections(dataset) -> np.ndarray:
    """Scan section (spiral turn) per frame from the phantom's trajectory, else one section."""
    gt = dataset.ground_truth
    traj = (gt.scene.get("trajectory") or {}) if gt is not None else {}
    sections = traj.get("sections")
    if isinstance(sections, list) and len(sections) == len(dataset):
        return np.asarray(sections, dtype=int)
    return np.zeros(len(dataset), dtype=int)


def _planar_truth(datasets) -> tuple[np.ndarray, np.ndarray] | None:
    """(origin, normal) of the true surface when every dataset has true poses and the same flat surface."""
    planes = []
    for ds in datasets:
        gt = ds.ground_truth
        if gt is None or gt.poses is None or gt.surface_path is None:
            return None
        v = gt.surface().vertices
        centre = v.mean(axis=0)
        _, s, vt = np.linalg.svd(v - centre, full_matrices=False)
        if s[2] > 1e-9 * max(s[0], 1.0):
            return None
        planes.append((centre, vt[2]))
    o, n = planes[0]
    if any(abs(np.dot(n2, o2 - o)) > 1e-6 or abs(abs(np.dot(n2, n)) - 1) > 1e-9 for o2, n2 in planes[1:]):
        return None
    return o, n


def run(options: MosaicOptions, datasets: list[Dataset], out_dir: str | Path, *,
        progress: Progress | None = None) -> MosaicResult:
    """2-D mosaic of one or more datasets (reference sec. 2.3.3) into ``out_dir``: ``mosaic.png``,
    ``mosaic_path.png`` (with the scope's path per scan section), ``coverage.png``, ``report.json``.

    Frames of all datasets are matched together (a 15 mm and a 30 mm scan fill each other's gaps, sec.
    2.4.2); frame 0 of the first dataset is the mosaic's frame. ``alignment_error_px`` is measured where the
    truth is a plane.
    """
    t0, c0 = time.perf_counter(), time.process_time()
    frames, cameras, sections, owner, true_poses = [], [], [], [], []
    for k, ds in enumerate(datasets):
        frames += [ds.frame(i) for i in range(len(ds))]
        cameras += [ds.camera] * len(ds)
        sections += list(_sections(ds) + 1000 * k)
        owner += [k] * len(ds)
        if ds.ground_truth is not None and ds.ground_truth.poses is not None:
            true_poses += list(ds.ground_truth.poses)
    if len(frames) < 2:
        raise InputError("a mosaic needs at least two frames")
    stage(progress, "mosaic: matching pairs", len(frames) * (len(frames) - 1) // 2)
    links = mos.link_frames(frames, cameras, options=options, progress=progress)
    try:
        result = mos.align_globally(len(frames), links, [(c.width, c.height) for c in cameras], options=options)
    except ValueError as exc:
        raise InputError(f"{datasets[0].root}: {exc} (frames without overlap)") from None
    mos.blend(result, frames, cameras, options=options)
    centres = mos.frame_centres(result, cameras)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_image(out / "mosaic.png", result.image)
    write_image(out / "mosaic_path.png", mos.draw_path(result.image, centres, np.asarray(sections)))
    write_image(out / "coverage.png", (result.coverage * 255).astype(np.uint8))
    report = {
        "n_frames": len(frames),
        "n_registered": int(result.registered.sum()),
        "n_linked_pairs": len(result.links),
        "datasets": [str(ds.root) for ds in datasets],
        "frames_per_dataset": [len(ds) for ds in datasets],
        "registered_per_dataset": [int(result.registered[np.asarray(owner) == k].sum()) for k in range(len(datasets))],
        "coverage_fraction": mos.coverage_fraction(result.coverage),
        "coverage_definition": "mosaic pixels seen by some frame over the convex hull of them (holes = missed areas)",
        "residual_px": {"mean": float(result.residual_px.mean()), "p95": float(np.percentile(result.residual_px, 95))},
        "canvas_px": list(result.image.shape[1::-1]),
        "time_s": time.perf_counter() - t0,
        "cpu_s": time.process_time() - c0,
    }
    plane = _planar_truth(datasets) if len(true_poses) == len(frames) else None
    if plane is not None:
        truth = mos.true_plane_homographies(cameras, true_poses, *plane)
        err = mos.alignment_errors_px(result, truth, cameras)
        report["alignment_error_px"] = {"mean": float(err.mean()), "p95": float(np.percentile(err, 95)),
                                        "unit": "rectified pixels of the first frame (the mosaic's frame)"}
        own = mos.alignment_errors_frame_px(result, truth, cameras)
        report["alignment_error_frame_px"] = {"mean": float(own.mean()), "p95": float(np.percentile(own, 95)),
                                              "unit": "each frame's own pixels, through its lens (any lens alike)"}
    else:
        report["alignment_error_px"] = report["alignment_error_frame_px"] = None
        report["alignment_error_note"] = "no planar ground truth (a curved wall has no exact 2-D mosaic)"
    write_json(out / "report.json", report)
    return MosaicResult(report, result)
