"""Physical scale of an image-only map from star targets of known size (reference sec. 2.4: a 6 mm star).

An image-only map is known up to a scale. Each fluorescent star seen whole in a frame is measured on the
map: its pixels, weighted by how much of each pixel the star covers (the fluorescence above the local
background over the star's own level, so the partial pixels of the edge count by their fraction), are cast
onto the wall around it as the map points there describe it, and the area they cover (map units squared) is
compared with the star's true area. Each view gives ``scale = sqrt(true area / map area)`` (true mm per map
unit).

The wall around a star: the inverse depth ``1/z`` of the map points near it, in the view's camera frame, as
an isotropic quadratic function of the normalised image coordinates about the star's centre (a plane is
the linear part of it: ``1/z = (n . (u, v, 1)) / c``; the quadratic term ``du^2 + dv^2`` is the wall's mean
curvature). A cavity seen from inside curves towards the scope, so a plane through the points around a
star passes in front of it. Measured on the unseen cavity's 15 mm spiral against the truth (a 6 mm star
14-15 mm away, points within 7 mm of it on a wall of ~35 mm radius): with the tracks' *true* points and
true poses the plane put three of five views +1.6 to +2.9 % off (the map's own points: the same), while the
star's pixels alone, cast with the true per-pixel depth, are within 0.2 %. The points must surround the
star (:func:`surrounds`): fitted to points on one side of it, the wall at the star is extrapolated (on the
36-frame spirals of the sweep, ``benchmarks/bench_star_scale_sweep.py``, such views were 1.2 and 2.9 %
off, and the wall fitted to the same tracks' true points within 0.1 %).

The scale's uncertainty per view (``sigma_parts``, fractions of the scale) is that of the fitted inverse
depth at the star's centre (the fit's residuals, its covariance), and half that of the area from the
pixels' noise (the ring's scatter) and from the edge's aliasing (each edge pixel counted 0 or 1 by the ray
through its centre when the optics do not blur it); the map's scale is the inverse-variance weighted mean
over the views, its uncertainty the weighted mean's, inflated by the views' scatter when they disagree by
more than their uncertainties (Birge ratio). Over the sweep's 17 good maps of unseen cavities the errors
over these uncertainties had an rms of 1.04 and all were within 2 of them (docs/panorama.md). Not in it:
the phantom's stars are drawn on the curved wall by projection, so their true area is 0.05-0.14 % more
than the flat pentagram's (-0.03 to -0.07 % of the scale).

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
from scope3d.utils.robust import relative_spread


#: a regular pentagram's perimeter over the square root of its area
PERIMETER_PER_SQRT_AREA = 6.857


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
    min_points : map points needed around the star to fit the wall (default 8: the curved wall's four
        terms and as many residual degrees of freedom).
    neighbourhood : map points within this many star radii (of the disc of the star's area) of its centre
        describe the wall (default 4: the star itself has few features; 7 mm for a 6 mm star). They must
        surround the star (no angular gap of 180 deg or more about its centre), or the wall at the star
        would be extrapolated and the view is not used.
    curved_wall : fit the wall's curvature about the star (an isotropic quadratic inverse depth; default
        True). False: a plane, as before: on a 30-45 mm cavity its points 7 mm from the star lie 0.5-1 mm
        in front of the tangent plane, 1-3 % of the scale at 15 mm (module docstring).
    core_px : the star's own level is the mean of its pixels at least this far inside its segmented edge
        (default 3 px; the deepest ones when the star has none so deep): closer in, an optical blur of
        sigma ~1 px dims them, the level comes out low and the area high (a synthetic 450 px star blurred
        by 1 px: +3.5 % of area measured 2 px inside, +0.15 % at 3 px).
    fluorescence : thresholds and cleaning of the fluorescence frames.
    """

    outer_diameter_mm: float = 6.0
    min_area_px: float = 40.0
    border_px: float = 3.0
    min_points: int = 8
    neighbourhood: float = 4.0
    curved_wall: bool = True
    core_px: float = 3.0
    fluorescence: FluorescenceOptions = field(default_factory=FluorescenceOptions)

    def __post_init__(self) -> None:
        if self.outer_diameter_mm <= 0 or self.min_area_px <= 0 or self.border_px < 0:
            raise ValueError("need outer_diameter_mm > 0, min_area_px > 0, border_px >= 0")
        if self.min_points < 5 or self.neighbourhood <= 0 or self.core_px < 1:
            raise ValueError("need min_points >= 5 (the curved wall and its residuals), neighbourhood > 0, "
                             "core_px >= 1")


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
    ``q = (1, du, dv, du^2 + dv^2)`` (or its first three terms: a plane) over normalised coordinates
    (u, v). centre_uv : (u0, v0); coefficients : (3,) or (4,) 1/map units; sigma_fraction : standard
    uncertainty of the inverse depth at the centre over its value (the fit's covariance); n_points."""

    centre_uv: np.ndarray
    coefficients: np.ndarray
    sigma_fraction: float
    n_points: int

    def depth(self, uv: np.ndarray) -> np.ndarray:
        """(K,) z of the wall (map units) along the rays of normalised coordinates (K, 2)."""
        return 1.0 / (_terms(uv - self.centre_uv, len(self.coefficients)) @ self.coefficients)


def _terms(duv: np.ndarray, n_terms: int) -> np.ndarray:
    """The wall's terms (plane, then the isotropic curvature). The curvature's anisotropic part (du^2 - dv^2,
    du dv) is left out: a star's five-fold symmetry cancels it in the area, and fitted from the few, often
    lopsided points about a star it was unstable (a view of 11 points: -8.7 % with it, -1.2 % without)."""
    du, dv = duv[:, 0], duv[:, 1]
    return np.stack([np.ones_like(du), du, dv, du * du + dv * dv][:n_terms], axis=1)


def fit_local_wall(camera: Camera, pose: Pose, points_world: np.ndarray, centre_px: np.ndarray,
                   curved: bool = True) -> LocalWall | None:
    """The wall about the pixel ``centre_px`` from the map points (N, 3) around it (``LocalWall``): a
    quadratic inverse depth with ``curved``, else a plane; None when the points do not fix it (no residual
    degree of freedom, behind the camera, or a degenerate spread)."""
    x = points_world @ pose.rotation.T + pose.translation
    n_terms = 4 if curved else 3
    if len(x) <= n_terms or np.any(x[:, 2] <= 0):
        return None
    centre_uv = camera.pixel_to_normalised(np.asarray(centre_px, float)[None])[0]
    design = _terms(x[:, :2] / x[:, 2:] - centre_uv, n_terms)
    w = 1.0 / x[:, 2]
    coef, _, rank, _ = np.linalg.lstsq(design, w, rcond=None)
    if rank < n_terms or coef[0] <= 0:
        return None
    dof = len(x) - n_terms
    residual_var = float(np.sum((design @ coef - w) ** 2)) / dof
    cov00 = np.linalg.inv(design.T @ design)[0, 0]
    return LocalWall(centre_uv, coef, float(np.sqrt(residual_var * cov00)) / float(coef[0]), len(x))


def covered_area(camera: Camera, wall: LocalWall, pixels: np.ndarray, weights: np.ndarray) -> float:
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


@dataclass(frozen=True)
class StarBlob:
    """One star seen whole in a fluorescence frame. centre_px : (2,) its centroid; pixels : (K, 2) the
    pixels of the star grown by 2 px (the edge's partial pixels); weights : (K,) each pixel's share of the
    star (its fluorescence over the background, over the star's own level); noise : the area's standard
    uncertainty from the pixels' noise, a fraction; edge : from the edge pixels' partial coverage (aliasing),
    a fraction; radius_px : of the disc of the segmented area."""

    centre_px: np.ndarray
    pixels: np.ndarray
    weights: np.ndarray
    noise: float
    edge: float
    radius_px: float


def star_blobs(image: np.ndarray, threshold: int, inside: np.ndarray,
               *,
               options: StarScaleOptions = StarScaleOptions()) -> list[StarBlob]:
    """The stars seen whole in one fluorescence frame (H, W) uint8: segmented at ``threshold``, at least
    ``min_area_px``, grown region within ``inside`` (the field less its border)."""
    on = segment(image, threshold, options=options.fluorescence)
    n_labels, labels, stats, centroids = cv2.connectedComponentsWithStats(on.astype(np.uint8), connectivity=8)
    level = image.astype(float)
    blobs = []
    for label in range(1, n_labels):
        blob = labels == label
        if stats[label, cv2.CC_STAT_AREA] < options.min_area_px or not inside[blob].all():
            continue
        grown = cv2.dilate(blob.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
        ring = cv2.dilate(grown.astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool) & ~grown
        if not inside[grown].all():
            continue
        background = float(np.median(level[ring & inside]))
        # the star's own level: its interior, away from the partial pixels of the edge; weights are not
        # clipped above 1, so the shading across the star averages out (clipped at the 75th percentile
        # they measured 1 % too little area on the bladder phantom's true depth)
        inner = cv2.distanceTransform(blob.astype(np.uint8), cv2.DIST_L2, 5)
        core = inner >= min(options.core_px, float(inner.max()))
        full = float(np.mean(level[core]))
        if full <= background:
            continue
        # not clipped at 0 either: the ring's noise about its median then sums to ~0 over the grown
        # region's edge, where clipped it added ~0.4 sigma per pixel (-0.4 % of the scale for a star of
        # 250 px, measured against the true depth: -0.71 -> -0.33 % mean over 4 views)
        weight = (level[grown] - background) / (full - background)
        noise = float(np.std(level[ring & inside])) / (full - background) * np.sqrt(grown.sum()) / weight.sum()
        # the edge's pixels each count a fraction of a pixel that blur, shading and (without blur) aliasing
        # make uncertain; aliased, a pixel's coverage p is counted 0 or 1 by the ray through its centre:
        # variance p (1 - p), 1/6 on average along an edge of P px (P = 6.86 sqrt(area) for a pentagram)
        edge = float(np.sqrt(PERIMETER_PER_SQRT_AREA * np.sqrt(weight.sum()) / 6.0)) / weight.sum()
        yy, xx = np.nonzero(grown)
        blobs.append(StarBlob(np.asarray(centroids[label], float), np.c_[xx, yy].astype(float), weight, noise,
                              edge, float(np.sqrt(stats[label, cv2.CC_STAT_AREA] / np.pi))))
    return blobs


def surrounds(pixels: np.ndarray, centre_px: np.ndarray) -> bool:
    """Whether the pixels (N, 2) surround ``centre_px``: no angular gap of 180 deg or more about it (else
    the centre lies outside their hull and a wall fitted to them is extrapolated there). Measured: the two
    views of the sweep whose points left a 254-257 deg gap were 1.2 and 2.9 % off where the wall fitted to
    the same tracks' true points was within 0.1 % (docs/panorama.md)."""
    angles = np.sort(np.arctan2(pixels[:, 1] - centre_px[1], pixels[:, 0] - centre_px[0]))
    return len(angles) >= 3 and float(np.max(np.diff(np.r_[angles, angles[0] + 2 * np.pi]))) < np.pi


def field_inside(camera: Camera, border_px: float) -> np.ndarray:
    """(H, W) bool: the pixels at least ``border_px`` inside the circular field (all pixels without one)."""
    yy, xx = np.mgrid[0:camera.height, 0:camera.width]
    return np.hypot(xx - camera.cx, yy - camera.cy) <= (camera.mask_radius_px or np.inf) - border_px


def star_scale(camera: Camera, poses: list[Pose], tracks: Tracks, fluorescence: list[np.ndarray],
               *,
               options: StarScaleOptions = StarScaleOptions(), where: str = "dataset") -> StarScale:
    """The map's scale from the stars (module docstring). poses, tracks : the map (points in map units);
    fluorescence : (H, W) uint8 per frame. Raises InputError when no star is seen whole with enough map
    points around it (no scale is invented)."""
    threshold = auto_threshold(fluorescence, options=options.fluorescence)
    inside = field_inside(camera, options.border_px)
    true_area = pentagram_area_mm2(options.outer_diameter_mm)
    views = []
    for k, image in enumerate(fluorescence):
        sel = tracks.frame == k
        if sel.sum() < options.min_points:
            continue
        seen_px, seen_points = tracks.pixels[sel], tracks.points[tracks.track[sel]]
        for blob in star_blobs(image, threshold, inside, options=options):
            near = np.linalg.norm(seen_px - blob.centre_px, axis=1) <= options.neighbourhood * blob.radius_px
            if near.sum() < options.min_points or not surrounds(seen_px[near], blob.centre_px):
                continue
            wall = fit_local_wall(camera, poses[k], seen_points[near], blob.centre_px, options.curved_wall)
            if wall is None:
                continue
            area = covered_area(camera, wall, blob.pixels, blob.weights)
            if area > 0:
                # scale = sqrt(true / area) and area ~ z^2: the inverse depth's fraction, and half the
                # area's (the pixels' noise, the edge's aliasing)
                parts = {"wall": float(wall.sigma_fraction), "pixels": 0.5 * float(blob.noise),
                         "edge": 0.5 * float(blob.edge)}
                views.append({"frame": k, "pixel": [float(v) for v in blob.centre_px],
                              "area_px": float(blob.weights.sum()), "scale": float(np.sqrt(true_area / area)),
                              "sigma": float(np.sqrt(sum(v * v for v in parts.values()))), "sigma_parts": parts,
                              "n_points": wall.n_points, "wall": "curved" if len(wall.coefficients) == 4 else "plane"})
    if not views:
        raise InputError(f"{where}: no star target seen whole with map points around it: cannot set the physical "
                         "scale (use --no-scale for an unscaled model)")
    scales = np.array([v["scale"] for v in views])
    scale, uncertainty = combine_views(scales, np.array([v["sigma"] for v in views]))
    return StarScale(scale, views, relative_spread(scales, about=scale), uncertainty)
