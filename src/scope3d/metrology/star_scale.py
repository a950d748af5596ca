"""Physical scale of an image-only map from star targets of known size (reference sec. 2.4: a 6 mm star).

An image-only map is known up to a scale. Each fluorescent star seen whole in a frame is measured on the
map: its pixels, weighted by how much of each pixel the star covers (the fluorescence above the local
background over the star's own level, so the partial pixels of the edge count by their fraction), are cast
onto the plane of the map points around it, and the area they cover there (map units squared) is compared
with the star's true area. Each view gives ``scale = sqrt(true area / map area)`` (true mm per map unit);
the median over views is the map's scale.

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
    min_plane_points : map points needed around the star to fit its plane (default 6).
    neighbourhood : map points within this many star radii of its centre define the plane (default 4: the
        star itself has few features; the wall around it is flat to ~0.1 mm over 4 radii of a 6 mm star
        on a 30-45 mm cavity).
    fluorescence : thresholds and cleaning of the fluorescence frames.
    """

    outer_diameter_mm: float = 6.0
    min_area_px: float = 40.0
    border_px: float = 3.0
    min_plane_points: int = 6
    neighbourhood: float = 4.0
    fluorescence: FluorescenceOptions = field(default_factory=FluorescenceOptions)

    def __post_init__(self) -> None:
        if self.outer_diameter_mm <= 0 or self.min_area_px <= 0 or self.border_px < 0:
            raise ValueError("need outer_diameter_mm > 0, min_area_px > 0, border_px >= 0")
        if self.min_plane_points < 3 or self.neighbourhood <= 0:
            raise ValueError("need min_plane_points >= 3, neighbourhood > 0")


@dataclass
class StarScale:
    """scale : true mm per map unit (median over views); views : per measured view (frame, star centre
    pixel, scale); spread : median absolute deviation of the views' scales over the scale."""

    scale: float
    views: list[dict]
    spread: float

    def to_dict(self) -> dict:
        return {"scale": self.scale, "n_views": len(self.views), "spread": self.spread, "views": self.views}


def _plane_in_camera(pose: Pose, points_world: np.ndarray) -> tuple[np.ndarray, float]:
    """Plane ``n . x = c`` (camera frame, n towards the camera's side... unit) through points (N, 3)."""
    x = points_world @ pose.rotation.T + pose.translation
    centre = x.mean(axis=0)
    n = np.linalg.svd(x - centre)[2][2]
    return n, float(n @ centre)


def _covered_area(camera: Camera, normal: np.ndarray, offset: float, pixels: np.ndarray, weights: np.ndarray) -> float:
    """Area (map units^2) on the plane ``n . x = offset`` (camera frame) of the pixels (K, 2), each
    counted by its weight: each pixel's footprint from its corners cast onto the plane."""
    def cast(p):
        d = np.c_[camera.pixel_to_normalised(p), np.ones(len(p))]
        return d * (offset / (d @ normal))[:, None]
    a, b, c = cast(pixels - 0.5), cast(pixels + [0.5, -0.5]), cast(pixels + [-0.5, 0.5])
    return float(np.sum(weights * np.linalg.norm(np.cross(b - a, c - a), axis=1)))


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
            weight = np.maximum((level[grown] - background) / (full - background), 0.0)
            star_radius_px = np.sqrt(stats[label, cv2.CC_STAT_AREA] / np.pi)
            near = np.linalg.norm(seen_px - centroids[label], axis=1) <= options.neighbourhood * star_radius_px
            if near.sum() < options.min_plane_points:
                continue
            normal, offset = _plane_in_camera(poses[k], seen_points[near])
            pixels = np.c_[xx[grown], yy[grown]].astype(float)
            area = _covered_area(camera, normal, offset, pixels, weight)
            if area > 0:
                views.append({"frame": k, "pixel": [float(v) for v in centroids[label]],
                              "area_px": float(weight.sum()), "scale": float(np.sqrt(true_area / area))})
    if not views:
        raise InputError(f"{where}: no star target seen whole with map points around it: cannot set the physical "
                         "scale (use --no-scale for an unscaled model)")
    scales = np.array([v["scale"] for v in views])
    scale = float(np.median(scales))
    return StarScale(scale, views, float(np.median(np.abs(scales - scale)) / scale))
