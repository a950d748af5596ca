"""Local image features (SIFT) for endoscope frames: the first step of the map (reference sec. 3.3, 4.4.4).

The reference used VLFeat's SIFT on the reflectance channel; we use OpenCV's, which computes the same
difference-of-Gaussians keypoints and 128-d gradient-histogram descriptors (Lowe 2004).

Two things make scanning-fibre endoscope frames different from photographs:

* the image is a disc inside a square frame. Without a mask, SIFT fires on the disc's rim (a strong,
  perfectly repeatable edge that does *not* move with the scene), and those features poison matching.
  We detect only inside the camera's circular mask, shrunk by a margin so that no descriptor window
  straddles the rim.
* frames are dim and low-contrast when the scope is far from tissue (reference sec. 4.4.2). SIFT's
  contrast threshold is absolute, so dim frames yield few features. Contrast-limited adaptive histogram
  equalisation (CLAHE) lifts local contrast before detection; the ``DIM_ENDOSCOPE`` preset turns it on
  and lowers the contrast threshold.

Keypoints are in pixels, origin at the centre of the top-left pixel (the convention of
:mod:`scope3d.sensor.camera`), which is also OpenCV's keypoint convention.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from scope3d.sensor.camera import Camera


@dataclass(frozen=True)
class FeatureOptions:
    """How SIFT features are detected.

    max_features : int, strongest features kept per frame (0 = all). 4000 keeps the per-pair
        matching cheap while leaving hundreds of matches per overlapping pair.
    contrast_threshold : float, OpenCV SIFT's DoG contrast threshold (its default 0.04, for images
        scaled to [0, 1] and divided by the number of octave layers).
    edge_threshold : float, SIFT's principal-curvature ratio for rejecting edge responses (default 10).
    sigma : float, Gaussian blur of the first octave (default 1.6, Lowe's value).
    n_octave_layers : int, DoG layers per octave (default 3).
    clahe_clip_limit : float, CLAHE clip limit; 0 disables CLAHE (default off: it amplifies noise
        on bright frames and barely changes the match count there).
    clahe_tile_grid : int, CLAHE tiles per image side (default 8).
    mask_margin_px : float, keypoints closer than this to the edge of the circular field of view are
        dropped (default 8 px, about half a descriptor window at the finest scale).
    precise_upscale : bool, OpenCV's exact 2x upsampling of the first octave (default False: meant to
        remove a sub-pixel shift of the finest-scale keypoints, it did not lower the reprojection error on
        the Middlebury temple, 0.351 vs 0.335 px).
    wide_field_deg, wide_field_clahe_clip_limit : a lens whose field across the image is wider than
        ``wide_field_deg`` (:attr:`Camera.fov_deg`; default 120 deg, a fisheye) gets CLAHE at this clip
        limit (default 2.0) when ``clahe_clip_limit`` is 0. Such a lens passes less light off its axis (a
        relative illumination ``cos(theta)^n`` is 0.5 or less beyond 60 deg for any n >= 1) and squeezes the
        periphery's texture into fewer pixels, so SIFT's absolute contrast threshold finds little there:
        on the dome through the 140 deg fisheye (seed 5) 375 features per frame and 68 in a corner frame,
        which then could not be mapped, and holes in the surface over half the targets; with CLAHE 1,750 per
        frame, every frame mapped and every target found (benchmarks/results/map_lenses*.json). The
        scene's 53 deg pinhole and the 70 deg barrel lens stay as they were.
    """

    max_features: int = 4000
    contrast_threshold: float = 0.04
    edge_threshold: float = 10.0
    sigma: float = 1.6
    n_octave_layers: int = 3
    clahe_clip_limit: float = 0.0
    clahe_tile_grid: int = 8
    mask_margin_px: float = 8.0
    precise_upscale: bool = False
    wide_field_deg: float = 120.0
    wide_field_clahe_clip_limit: float = 2.0

    def __post_init__(self) -> None:
        if self.max_features < 0:
            raise ValueError(f"max_features must be >= 0, got {self.max_features}")
        if self.contrast_threshold <= 0 or self.edge_threshold <= 0 or self.sigma <= 0:
            raise ValueError("contrast_threshold, edge_threshold and sigma must be positive")
        if self.n_octave_layers < 1:
            raise ValueError(f"n_octave_layers must be >= 1, got {self.n_octave_layers}")
        if self.clahe_clip_limit < 0 or self.clahe_tile_grid < 1 or self.wide_field_clahe_clip_limit < 0:
            raise ValueError("clahe_clip_limit, wide_field_clahe_clip_limit must be >= 0 and clahe_tile_grid >= 1")
        if not 0 < self.wide_field_deg <= 360:
            raise ValueError(f"wide_field_deg must be in (0, 360], got {self.wide_field_deg}")
        if self.mask_margin_px < 0:
            raise ValueError(f"mask_margin_px must be >= 0, got {self.mask_margin_px}")


#: Named presets. ``dim_endoscope``: CLAHE on and a lower contrast threshold for frames taken far from
#: tissue or with weak illumination (fluorescence mode uses only the blue laser for reflectance).
#: ``photograph``: sharp calibrated photographs, no circular field; contrast threshold 0.02, half OpenCV's,
#: because the features were what bound a known-pose map's points: at 0.04 OpenCV found 840-890 per
#: 320 px frame of the dome ring where COLMAP's SIFT finds 1,950-2,080, and 79 % of them were already
#: matched and 95 % of those triangulated (benchmarks/diag_map_views_stages.py, docs/surgical_map.md);
#: at 0.02 it finds 1,680-1,830 and the rings' points double (2.2x on the ring of 8 to 2.1x on 48).
FEATURE_PRESETS: dict[str, FeatureOptions] = {
    "default": FeatureOptions(),
    "dim_endoscope": FeatureOptions(contrast_threshold=0.02, clahe_clip_limit=2.0),
    "photograph": FeatureOptions(max_features=8000, contrast_threshold=0.02, mask_margin_px=0.0),
}


@dataclass(frozen=True)
class Features:
    """Features of one frame.

    keypoints : (N, 2) float64, pixels (u right, v down, origin at the top-left pixel's centre).
    descriptors : (N, 128) float32, SIFT descriptors (L2 norm ~512 as OpenCV scales them).
    scales : (N,) float32, keypoint diameter in pixels (OpenCV ``size``).
    colors : (N, 3) uint8, RGB of the frame at each keypoint (for coloured point clouds).
    """

    keypoints: np.ndarray
    descriptors: np.ndarray
    scales: np.ndarray
    colors: np.ndarray

    def __len__(self) -> int:
        return len(self.keypoints)

    @classmethod
    def empty(cls) -> "Features":
        return cls(np.zeros((0, 2)), np.zeros((0, 128), np.float32), np.zeros(0, np.float32), np.zeros((0, 3), np.uint8))


def clahe_clip_limit(camera: Camera | None, options: FeatureOptions) -> float:
    """The CLAHE clip limit detection uses on this camera's frames (0: none): ``options.clahe_clip_limit``,
    or for a lens wider than ``options.wide_field_deg`` its ``wide_field_clahe_clip_limit``."""
    if options.clahe_clip_limit > 0 or camera is None:
        return options.clahe_clip_limit
    return options.wide_field_clahe_clip_limit if camera.fov_deg > options.wide_field_deg else 0.0


def detection_mask(camera: Camera, margin_px: float) -> np.ndarray:
    """(H, W) uint8 mask (255 = detect) of the valid image shrunk by ``margin_px``."""
    h, w = camera.height, camera.width
    if camera.mask_radius_px is None:
        mask = np.zeros((h, w), np.uint8)
        m = int(np.ceil(margin_px))
        mask[m : h - m, m : w - m] = 255
        return mask
    grid_v, grid_u = np.mgrid[0:h, 0:w]
    r = np.hypot(grid_u - (w - 1) / 2.0, grid_v - (h - 1) / 2.0)
    return np.where(r <= camera.mask_radius_px - margin_px, 255, 0).astype(np.uint8)


def to_grey(image: np.ndarray) -> np.ndarray:
    """(H, W, 3) RGB or (H, W) uint8 -> (H, W) uint8 grey (luma)."""
    img = np.asarray(image)
    if img.ndim == 2:
        return img.astype(np.uint8, copy=False)
    if img.ndim == 3 and img.shape[2] == 3:
        return cv2.cvtColor(img.astype(np.uint8, copy=False), cv2.COLOR_RGB2GRAY)
    raise ValueError(f"image must be (H, W) or (H, W, 3), got shape {img.shape}")


def detect(image: np.ndarray, camera: Camera | None = None, *, options: FeatureOptions = FeatureOptions()) -> Features:
    """Detect and describe SIFT features in one frame.

    Parameters
    ----------
    image : (H, W, 3) uint8 RGB or (H, W) uint8 grey.
    camera : the frame's camera; its circular mask (if any) limits detection. None = whole frame.
    options : detection options (see :class:`FeatureOptions` and :data:`FEATURE_PRESETS`).

    Returns
    -------
    Features, strongest first, at most ``options.max_features``.
    """
    img = np.asarray(image)
    if img.size == 0:
        raise ValueError("image is empty")
    grey = to_grey(img)
    if camera is not None and grey.shape != (camera.height, camera.width):
        raise ValueError(f"image is {grey.shape[1]}x{grey.shape[0]} but camera is {camera.width}x{camera.height}")
    clip = clahe_clip_limit(camera, options)
    if clip > 0:
        clahe = cv2.createCLAHE(clipLimit=clip, tileGridSize=(options.clahe_tile_grid,) * 2)
        grey = clahe.apply(grey)
    mask = detection_mask(camera, options.mask_margin_px) if camera is not None else None
    sift = cv2.SIFT_create(
        nfeatures=options.max_features,
        nOctaveLayers=options.n_octave_layers,
        contrastThreshold=options.contrast_threshold,
        edgeThreshold=options.edge_threshold,
        sigma=options.sigma,
        enable_precise_upscale=options.precise_upscale,
    )
    kps, desc = sift.detectAndCompute(grey, mask)
    if not kps:
        return Features.empty()
    keypoints = np.array([k.pt for k in kps], dtype=np.float64)
    scales = np.array([k.size for k in kps], dtype=np.float32)
    response = np.array([k.response for k in kps])
    order = np.argsort(-response, kind="stable")
    if options.max_features:
        order = order[: options.max_features]
    keypoints, desc, scales = keypoints[order], desc[order].astype(np.float32), scales[order]
    rgb = img if img.ndim == 3 else np.repeat(img[..., None], 3, axis=2)
    iu = np.clip(np.rint(keypoints[:, 0]).astype(int), 0, rgb.shape[1] - 1)
    iv = np.clip(np.rint(keypoints[:, 1]).astype(int), 0, rgb.shape[0] - 1)
    return Features(keypoints, desc, scales, rgb[iv, iu].astype(np.uint8))
