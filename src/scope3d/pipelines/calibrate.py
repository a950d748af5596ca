"""Scope calibration from board images, with uncertainty and bounds for BCBA (reference sec. 6.3, 8.1).

Read top to bottom like the method section::

    images      <- read grey
    field       <- circular_field_radius          (scanning-fibre scope: the lit disc; optional)
    detections  <- detect_board per image          (corners, sub-pixel; which images lack the board)
    calibration <- calibrate(model)                (radial, opencv, full-opencv or fisheye: the camera
                                                    model's parameters + covariance)
    files       <- camera.json (that model), intrinsic_bounds.json (its parameters, value +- k sigma),
                   report.json, coverage.png, residuals.png

``run(options, image_paths, out_dir) -> CalibrateResult`` is what the CLI (``scope3d calibrate``) calls.
camera.json records the calibrated model by name (:mod:`scope3d.io.camera_json`); scope3d's datasets and
jobs take the radial model (``pinhole_radial_k1k2``) until they take every model (issue 32).
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from scope3d.errors import InputError
from scope3d.io.camera_json import camera_to_dict
from scope3d.io.images import read_image
from scope3d.io.intrinsic_bounds import write_intrinsic_bounds
from scope3d.sensor.calibration import (
    CAMERA_MODEL_OF,
    BoardSpec,
    Calibration,
    CalibrationOptions,
    DetectionOptions,
    calibrate,
    circular_field_radius,
    detect_board,
)
from scope3d.utils.figures import new_figure, save_figure
from scope3d.utils.jsonio import write_json
from scope3d.utils.progress import Progress, advance, stage


@dataclass(frozen=True)
class CalibrateOptions:
    """board : the board. model : "radial", "opencv", "full-opencv" or "fisheye" ("pinhole": "radial"),
    the model fitted and written (:data:`scope3d.sensor.calibration.CAMERA_MODEL_OF`).
    k_sigma : half-width of the bounds in standard deviations (3: a 99.7 % interval for a Gaussian error).
    mask_circle : find the circular field of a scanning-fibre scope and ignore what lies outside.
    detection, calibration : the stages' options (calibration.model is set from ``model``)."""

    board: BoardSpec
    model: str = "radial"
    k_sigma: float = 3.0
    mask_circle: bool = False
    detection: DetectionOptions = field(default_factory=DetectionOptions)
    calibration: CalibrationOptions = field(default_factory=CalibrationOptions)

    def __post_init__(self) -> None:
        if self.model not in CAMERA_MODEL_OF:
            raise ValueError(f"model must be one of {', '.join(CAMERA_MODEL_OF)}, got {self.model!r}")
        if not self.k_sigma > 0:
            raise ValueError("k_sigma must be positive")


@dataclass
class CalibrateResult:
    """calibration : the fitted model. report : what report.json holds."""

    calibration: Calibration
    report: dict

    def summary(self) -> str:
        lines = [self.calibration.summary()]
        for name, why in self.calibration.rejected.items():
            lines.append(f"  rejected {name}: {why}")
        return "\n".join(lines)


def run(options: CalibrateOptions, image_paths: list[str | Path], out_dir: str | Path, *,
        progress: Progress | None = None) -> CalibrateResult:
    image_paths = [Path(p) for p in image_paths]
    if not image_paths:
        raise InputError("no images given")
    images = [read_image(p, grey=True) for p in image_paths]
    sizes = {im.shape for im in images}
    if len(sizes) > 1:
        raise InputError(f"images differ in size ({', '.join(f'{w}x{h}' for h, w in sorted(sizes))}); "
                         "calibrate one camera at a time")
    height, width = images[0].shape
    mask_radius = circular_field_radius(images) if options.mask_circle else None
    detection = replace(options.detection, mask_radius_px=mask_radius)
    stage(progress, "detect", len(images))
    detections = []
    for path, image in zip(image_paths, images):
        detections.append(detect_board(image, options.board, name=path.name, options=detection))
        advance(progress)
    cal = calibrate(detections, options.board, (width, height), mask_radius_px=mask_radius,
                    options=replace(options.calibration, model=options.model))
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    report = _report(options, cal, [p.name for p in image_paths])
    write_json(out / "camera.json", camera_to_dict(cal.camera()))
    write_intrinsic_bounds(out / "intrinsic_bounds.json", cal.values, cal.std, options.k_sigma,
                           source=f"scope3d calibrate, {len(cal.views)} views, RMS {cal.rms_px:.3f} px",
                           model=cal.model, names=cal.names)
    plot_coverage(cal, out / "coverage.png")
    plot_residuals(cal, out / "residuals.png")
    write_json(out / "report.json", report)
    return CalibrateResult(cal, report)


def _intrinsics_dict(cal: Calibration) -> dict:
    return {n: {"value": float(v), "std": float(s)} for n, v, s in zip(cal.names, cal.values, cal.std)}


def _report(options, cal, names) -> dict:
    report = {
        "model": cal.model,
        "board": {"cols": options.board.cols, "rows": options.board.rows, "square_mm": options.board.square_mm,
                  "kind": options.board.kind},
        "image_size": [cal.width, cal.height],
        "rms_px": cal.rms_px,
        "n_images": len(names),
        "n_views_used": len(cal.views),
        "intrinsics": _intrinsics_dict(cal),
        "per_view_rms_px": dict(zip(cal.views, map(float, cal.view_rms_px))),
        "rejected": cal.rejected,
        "k_sigma": options.k_sigma,
        "mask_radius_px": cal.mask_radius_px,
    }
    if cal.opencv_std is not None:
        report["opencv_std"] = dict(zip(cal.names, map(float, cal.opencv_std)))
    return report


def plot_coverage(cal: Calibration, path: str | Path) -> None:
    """Where on the sensor corners were seen (one colour per view), with the circular field if any."""
    fig = new_figure((5.5, 5.5 * cal.height / cal.width + 0.6), dpi=110)
    ax = fig.add_subplot()
    for name, px in zip(cal.views, cal.pixels):
        ax.plot(px[:, 0], px[:, 1], ".", ms=3, label=name)
    if cal.mask_radius_px is not None:
        t = np.linspace(0, 2 * np.pi, 200)
        ax.plot((cal.width - 1) / 2 + cal.mask_radius_px * np.cos(t),
                (cal.height - 1) / 2 + cal.mask_radius_px * np.sin(t), "k--", lw=0.8)
    _image_axes(ax, cal)
    ax.set_title(f"corner coverage: {len(cal.views)} views, {sum(len(p) for p in cal.pixels)} corners")
    if len(cal.views) <= 12:
        ax.legend(fontsize=6, loc="upper right")
    save_figure(fig, path)


def _image_axes(ax, cal: Calibration) -> None:
    """Axes in image pixels, v down, as the sensor sees them."""
    ax.set_xlim(-0.5, cal.width - 0.5)
    ax.set_ylim(cal.height - 0.5, -0.5)
    ax.set_aspect("equal")
    ax.set_xlabel("u (px)")
    ax.set_ylabel("v (px)")


def plot_residuals(cal: Calibration, path: str | Path) -> None:
    """Residual vectors (observed - fitted) at every used corner, magnified so the largest spans ~5 % of
    the image width; a structured pattern means the model (or the detector) misses something."""
    px = np.concatenate(cal.pixels)
    res = np.concatenate(cal.residuals_px)
    longest = float(np.max(np.linalg.norm(res, axis=1))) or 1.0
    gain = 0.05 * cal.width / longest
    fig = new_figure((5.5, 5.5 * cal.height / cal.width + 0.6), dpi=110)
    ax = fig.add_subplot()
    ax.quiver(px[:, 0], px[:, 1], res[:, 0] * gain, res[:, 1] * gain, angles="xy", scale_units="xy", scale=1,
              width=0.003, color="tab:red")
    _image_axes(ax, cal)
    ax.set_title(f"{cal.model} residuals x{gain:.0f} (RMS {cal.rms_px:.3f} px, longest {longest:.2f} px)")
    save_figure(fig, path)
