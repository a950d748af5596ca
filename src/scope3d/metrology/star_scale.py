"""Physical scale of an image-only map from star targets of known size (reference sec. 2.4: a 6 mm star).

An image-only map is known up to a scale. Each fluorescent star seen whole in a frame is measured on the
map: its pixels, weighted by how much of each pixel the star covers (the fluorescence above the local
background over the star's own level, so the partial pixels of the edge count by their fraction), are cast
onto the wall around it as the map points there describe it, and the area they cover (map units squared) is
compared with the star's true area. Each view gives ``scale = sqrt(true area / map area)`` (true mm per map
unit).

The wall around a star: the inverse depth ``1/z`` of the map points near it, in the view's camera frame, as
a quadratic function of the normalised image coordinates about the star's centre (a plane is the linear
part of it: ``1/z = (n . (u, v, 1)) / c``). The quadratic terms are the wall's curvature: a cavity seen
from inside curves towards the scope, so a plane through the points around a star passes in front of it.
Measured on the unseen cavity's 15 mm spiral against the truth (a 6 mm star 14-15 mm away, points within
7 mm of it on a wall of ~35 mm radius): with the tracks' *true* points and true poses the plane put three
of five views +1.6 to +2.9 % off (the map's own points: the same), while the star's pixels alone, cast with
the true per-pixel depth, are within 0.2 %.

The scale's uncertainty per view is that of the fitted inverse depth at the star's centre (the fit's
residuals, its covariance) and half that of the area from the pixels' noise (the ring's scatter), as a
fraction; not the segmentation's bias (measured: -0.1 to +0.1 % for a star of 8,600 px, -1.0 to +0.4 %
for one of 180-320 px); the map's scale is the inverse-variance weighted mean over the
views, its uncertainty the weighted mean's, inflated by the views' scatter when they disagree by more than
their uncertainties (Birge ratio).

Units: mm; pixels with their origin at the top-left pixel's centre. Poses are ``cam_from_world``.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from scope3d.errors import InputError
from scope3d.geometry.pose import Pose
from scope3d.metrology.fluorescence import FluorescenceOptions, auto_threshold, segment
from scope3d.scene.tracks import Tracks
from scope3d.sensor.camera import Camera


def pentagram_area_mm2(outer_diameter_mm: float) -> float:
    """Area (mm^2) of a regular five-pointed star (pentagram outline) of the given tip circle diameter:
    ten triangles between the outer radius R and the inner radius r = R sin 18 deg / sin 126 deg."""
    R = 0.5 * outer_diameter_mm
    r = R * np.sin(np.deg2rad(18.0)) / np.sin(np.deg2rad(126.0))
    return float(5.0 * R * r * np.sin(np.deg2rad(36.0)))


@dataclass(frozen=True)
class StarScaleOptions:
    """outer_diameter_mm : the stars' tip circle diameter (default 6 mm, the reference's targets).
    min_area_px : a star must cover at least this many pixels (default 40: a 6 mm star at 30 mm seen by a
        70 deg, 256 px scope covers ~100; below 40 the edge pixels are most of it).
    border_px : the star must lie this far inside the circular field (default 3 px), or it may be cut.
    min_plane_points : map points needed around the star to fit the wall (default 6, a plane with
        residuals; the curved wall needs ``2 x 6`` points, else the plane is fitted).
    neighbourhood : map points within this many star radii (of the disc of the star's area) of its centre
        describe the wall (default 4: the star itself has few features; 7 mm for a 6 mm star).
    curved_wall : fit the wall's curvature about the star (a quadratic inverse depth; default True). False:
        a plane, as before: on a 30-45 mm cavity its points 7 mm from the star lie 0.5-1 mm in front of
        the tangent plane, 1-3 % of the scale at 15 mm (module docstring).
    fluorescence : thresholds and cleaning of the fluorescence frames.
    """

    outer_diameter_mm: float = 6.0
    min_area_px: float = 40.0
    border_px: float = 3.0
    min_plane_points: int = 6
    neighbourhood: float = 4.0
    curved_wall: bool = True
    fluorescence: FluorescenceOptions = field(default_factory=FluorescenceOptions)

    def __post_init__(self) -> None:
        if self.outer_diameter_mm <= 0 or self.min_area_px <= 0 or self.border_px < 0:
            raise ValueError("need outer_diameter_mm > 0, min_area_px > 0, border_px >= 0")
        if self.min_plane_points < 4 or self.neighbourhood <= 0:
            raise ValueError("need min_plane_points >= 4 (a plane and its residuals), neighbourhood > 0")


@dataclass
class StarScale:
    """scale : true mm per map unit (inverse-variance weighted mean over views); views : per measured view
    (frame, star centre pixel, scale, its ``sigma`` as a fraction, the wall's points and model);
    spread : median absolute deviation of the views' scales over the scale; uncertainty : the scale's
    standard uncertainty as a fraction (the weighted mean's, inflated by the views' scatter)."""

    scale: float
    views: list[dict]
    spread: float
    uncertainty: float

    def to_dict(self) -> dict:
        return {"scale": self.scale, "uncertainty_fraction": self.uncertainty, "n_views": len(self.views),
                "spread": self.spread, "views": self.views}


@dataclass(frozen=True)
class LocalWall:
    """The wall about a star in a view's camera frame: inverse depth ``1/z = c . q(u - u0, v - v0)`` with
    ``q = (1, du, dv, du^2, du dv, dv^2)`` (or its first three terms: a plane) over normalised coordinates
    (u, v). centre_uv : (u0, v0); coefficients : (3,) or (6,) 1/map units; sigma_fraction : standard
    uncertainty of the inverse depth at the centre over its value (the fit's covariance); n_points."""

    centre_uv: np.ndarray
    coefficients: np.ndarray
    sigma_fraction: float
    n_points: int

    def depth(self, uv: np.ndarray) -> np.ndarray:
        """(K,) z of the wall (map units) along the rays of normalised coordinates (K, 2)."""
        return 1.0 / (_terms(uv - self.centre_uv, len(self.coefficients)) @ self.coefficients)


def _terms(duv: np.ndarray, n_terms: int) -> np.ndarray:
    du, dv = duv[:, 0], duv[:, 1]
    return np.stack([np.ones_like(du), du, dv, du * du, du * dv, dv * dv][:n_terms], axis=1)


def fit_local_wall(camera: Camera, pose: Pose, points_world: np.ndarray, centre_px: np.ndarray,
                   curved: bool = True) -> LocalWall | None:
    """The wall about the pixel ``centre_px`` from the map points (N, 3) around it (``LocalWall``): a
    quadratic inverse depth with ``curved`` and at least 12 points, else a plane; None when the points do
    not fix it (fewer than 4, behind the camera, or a degenerate spread)."""
    x = points_world @ pose.rotation.T + pose.translation
    if len(x) < 4 or np.any(x[:, 2] <= 0):
        return None
    centre_uv = camera.pixel_to_normalised(np.asarray(centre_px, float)[None])[0]
    n_terms = 6 if curved and len(x) >= 12 else 3
    design = _terms(x[:, :2] / x[:, 2:] - centre_uv, n_terms)
    w = 1.0 / x[:, 2]
    coef, _, rank, _ = np.linalg.lstsq(design, w, rcond=None)
    if rank < n_terms or coef[0] <= 0:
        return None
    dof = len(x) - n_terms
    residual_var = float(np.sum((design @ coef - w) ** 2)) / dof if dof > 0 else np.inf
    cov00 = np.linalg.inv(design.T @ design)[0, 0]
    return LocalWall(centre_uv, coef, float(np.sqrt(residual_var * cov00)) / float(coef[0]), len(x))


def _covered_area(camera: Camera, wall: LocalWall, pixels: np.ndarray, weights: np.ndarray) -> float:
    """Area (map units^2) on the wall (camera frame) of the pixels (K, 2), each counted by its weight: each
    pixel's footprint from its corners lifted onto the wall."""
    def cast(p):
        uv = camera.pixel_to_normalised(p)
        return np.c_[uv, np.ones(len(p))] * wall.depth(uv)[:, None]
    a, b, c = cast(pixels - 0.5), cast(pixels + [0.5, -0.5]), cast(pixels + [-0.5, 0.5])
    return float(np.sum(weights * np.linalg.norm(np.cross(b - a, c - a), axis=1)))


def combine_views(scales: np.ndarray, sigmas: np.ndarray) -> tuple[float, float]:
    """(scale, uncertainty as a fraction): the inverse-variance weighted mean of the views' scales
    (sigmas: fractions), its standard uncertainty inflated by the Birge ratio ``sqrt(chi^2 / (n - 1))``
    when the views scatter more than their sigmas say. A view without a finite sigma (a fit without
    residual degrees of freedom) gets the largest finite one; none finite: the median and the scatter."""
    scales, sigmas = np.asarray(scales, float), np.asarray(sigmas, float)
    finite = np.isfinite(sigmas) & (sigmas > 0)
    if not finite.any():
        scale = float(np.median(scales))
        spread = float(np.std(scales, ddof=1)) / scale / np.sqrt(len(scales)) if len(scales) > 1 else np.inf
        return scale, spread
    sigmas = np.where(finite, sigmas, sigmas[finite].max())
    weights = 1.0 / (sigmas * scales) ** 2
    scale = float(np.sum(weights * scales) / np.sum(weights))
    uncertainty = float(np.sqrt(1.0 / np.sum(weights))) / scale
    if len(scales) > 1:
        birge = np.sqrt(np.sum(weights * (scales - scale) ** 2) / (len(scales) - 1))
        uncertainty *= max(1.0, float(birge))
    return scale, uncertainty


def star_scale(camera: Camera, poses: list[Pose], tracks: Tracks, fluorescence: list[np.ndarray],
               options: StarScaleOptions = StarScaleOptions(), *, where: str = "dataset") -> StarScale:
    """The map's scale from the stars (module docstring). poses, tracks : the map (points in map units);
    fluorescence : (H, W) uint8 per frame. Raises InputError when no star is seen whole with enough map
    points around it (no scale is invented)."""
    threshold = auto_threshold(fluorescence, options.fluorescence)
    yy, xx = np.mgrid[0:camera.height, 0:camera.width]
    radius = np.hypot(xx - camera.cx, yy - camera.cy)
    inside = radius <= (camera.mask_radius_px or np.inf) - options.border_px
    true_area = pentagram_area_mm2(options.outer_diameter_mm)
    views = []
    for k, image in enumerate(fluorescence):
        on = segment(image, threshold, options.fluorescence)
        n_labels, labels, stats, centroids = cv2.connectedComponentsWithStats(on.astype(np.uint8), connectivity=8)
        sel = tracks.frame == k
        if n_labels <= 1 or sel.sum() < options.min_plane_points:
            continue
        seen_px, seen_points = tracks.pixels[sel], tracks.points[tracks.track[sel]]
        for label in range(1, n_labels):
            blob = labels == label
            if stats[label, cv2.CC_STAT_AREA] < options.min_area_px or not inside[blob].all():
                continue
            grown = cv2.dilate(blob.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
            ring = cv2.dilate(grown.astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool) & ~grown
            if not inside[grown].all():
                continue
            level = image.astype(float)
            background = float(np.median(level[ring & inside]))
            # the star's own level: its interior, away from the partial pixels of the edge; weights are not
            # clipped above 1, so the shading across the star averages out (clipped at the 75th percentile
            # they measured 1 % too little area on the bladder phantom's true depth)
            core = cv2.erode(blob.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
            full = float(np.mean(level[core])) if core.any() else 0.0
            if full <= background:
                continue
            # not clipped at 0 either: the ring's noise about its median then sums to ~0 over the grown
            # region's edge, where clipped it added ~0.4 sigma per pixel (-0.4 % of the scale for a star of
            # 250 px, measured against the true depth: -0.71 -> -0.33 % mean over 4 views)
            weight = (level[grown] - background) / (full - background)
            # the pixels' noise in the area (a fraction of it), half of it in the scale
            noise = float(np.std(level[ring & inside])) / (full - background) * np.sqrt(grown.sum()) / weight.sum()
            star_radius_px = np.sqrt(stats[label, cv2.CC_STAT_AREA] / np.pi)
            near = np.linalg.norm(seen_px - centroids[label], axis=1) <= options.neighbourhood * star_radius_px
            if near.sum() < options.min_plane_points:
                continue
            wall = fit_local_wall(camera, poses[k], seen_points[near], centroids[label], options.curved_wall)
            if wall is None:
                continue
            pixels = np.c_[xx[grown], yy[grown]].astype(float)
            area = _covered_area(camera, wall, pixels, weight)
            if area > 0:
                views.append({"frame": k, "pixel": [float(v) for v in centroids[label]],
                              "area_px": float(weight.sum()), "scale": float(np.sqrt(true_area / area)),
                              # scale = sqrt(true / area) and area ~ z^2: the inverse depth's fraction
                              "sigma": float(np.hypot(wall.sigma_fraction, 0.5 * noise)), "n_points": wall.n_points,
                              "wall": "curved" if len(wall.coefficients) == 6 else "plane"})
    if not views:
        raise InputError(f"{where}: no star target seen whole with map points around it: cannot set the physical "
                         "scale (use --no-scale for an unscaled model)")
    scales = np.array([v["scale"] for v in views])
    scale, uncertainty = combine_views(scales, np.array([v["sigma"] for v in views]))
    return StarScale(scale, views, float(np.median(np.abs(scales - scale)) / scale), uncertainty)
