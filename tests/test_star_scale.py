"""The stars' scale (metrology.star_scale) on synthetic stars and walls whose truth is exact: the star's area
from its blurred, noisy pixels, and the wall about it."""
from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.stats import norm

from scope3d.geometry.pose import Pose
from scope3d.metrology.star_scale import StarScaleOptions, fit_local_wall, star_blobs, surrounds
from scope3d.sensor.camera import Camera

# a pentagram's perimeter over the square root of its area (outer radius R, inner R sin 18 / sin 126)
PERIMETER_PER_SQRT_AREA = 6.857


def _star_image(outer_radius_px: float, blur_px: float, seed: int, size: int = 200, background: float = 30.0,
                amplitude: float = 150.0, noise: float = 2.0) -> tuple[np.ndarray, float]:
    """A pentagram drawn 16x finer and averaged down (each pixel's coverage), blurred, with Gaussian noise
    of ``noise`` grey levels; and its true area in pixels (the coverage's sum)."""
    inner = outer_radius_px * np.sin(np.deg2rad(18.0)) / np.sin(np.deg2rad(126.0))
    a = np.deg2rad(90.0 + 36.0 * np.arange(10))
    r = np.where(np.arange(10) % 2 == 0, outer_radius_px, inner)
    centre = (size - 1) / 2 + 0.37  # off the pixel grid
    corners = np.c_[centre + r * np.cos(a), centre + r * np.sin(a)]
    fine = np.zeros((16 * size, 16 * size), np.uint8)
    cv2.fillPoly(fine, [np.round(((corners + 0.5) * 16 - 0.5) * 16).astype(np.int32)], 255, shift=4)
    coverage = cv2.resize(fine.astype(float) / 255.0, (size, size), interpolation=cv2.INTER_AREA)
    image = background + amplitude * coverage
    if blur_px > 0:
        image = cv2.GaussianBlur(image, (0, 0), blur_px)
    image += np.random.default_rng(seed).normal(0.0, noise, image.shape)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8), float(coverage.sum())


@pytest.mark.parametrize("outer_radius_px", [20.0, 40.0])  # 450 and 1,800 px: a 6 mm star at ~60 and ~30 mm, 608 px
@pytest.mark.parametrize("blur_px", [0.0, 1.0])
def test_star_area_from_blurred_noisy_pixels(outer_radius_px, blur_px):
    image, true_px = _star_image(outer_radius_px, blur_px, seed=int(outer_radius_px + 10 * blur_px))
    inside = np.ones(image.shape, bool)
    (blob,) = star_blobs(image, 100, inside)
    # What may remain, from the physics: the blur's light beyond the 2 px the star is grown by (per unit of
    # edge sigma (phi(t) - t (1 - Phi(t))), t = 2 px / sigma), the level 3 px inside the edge dimmed by the
    # blur by 1 - Phi(3 px / sigma) (which the level's deficit adds to the area), and three of the pixels'
    # noise's own sigmas (blob.noise).
    edge_px = PERIMETER_PER_SQRT_AREA * np.sqrt(true_px)
    tail = 0.0
    dimmed = 0.0
    if blur_px > 0:
        t = 2.0 / blur_px
        tail = blur_px * (norm.pdf(t) - t * norm.sf(t)) * edge_px / true_px
        dimmed = norm.sf(3.0 / blur_px)
    tolerance = tail + dimmed + 3.0 * blob.noise
    assert blob.weights.sum() / true_px - 1.0 == pytest.approx(0.0, abs=tolerance)
    if blur_px > 0:
        # the level measured 2 px inside the edge (the old 3 x 3 erosion's) is dimmed by the blur: the area
        # comes out too large by more than that tolerance
        (shallow,) = star_blobs(image, 100, inside, options=StarScaleOptions(core_px=2.0))
        assert shallow.weights.sum() / true_px - 1.0 > tolerance


def test_points_surround_a_star_only_when_no_half_plane_is_empty():
    angles = np.deg2rad(np.arange(0, 360, 30))
    ring = np.c_[np.cos(angles), np.sin(angles)] * 10.0 + [100.0, 50.0]
    assert surrounds(ring, np.array([100.0, 50.0]))
    # the same points seen from a centre beyond them, or a half ring: the wall would be extrapolated there
    assert not surrounds(ring, np.array([125.0, 50.0]))
    assert not surrounds(ring[np.cos(angles) > 0.1], np.array([100.0, 50.0]))


WALLS = {
    # a sphere of 35 mm radius seen from 15 mm inside its wall (the 15 mm spiral): the wall 7 mm from the
    # star lies up to 0.7 mm in front of its tangent plane, so a plane through the points passes ~0.35 mm in
    # front of the star (2.3 % of the depth); the quadratic leaves the sphere's fourth-order terms (< 0.01 mm
    # at 7 mm) and the noise averaged over 80 points (0.02 / sqrt(80) x ~2 ~ 0.005 mm)
    "sphere": (15.0, lambda x, y: 35.0 - np.sqrt(35.0 ** 2 - x ** 2 - y ** 2), 0.02, 80, 0.03),
    # a wall curved by 25 mm one way and 45 mm the other (an ellipsoidal cavity's end) seen from 27 mm (the
    # 36-frame spiral): its sag 7 mm out is 1.0 and 0.5 mm, and its anisotropic part (+-0.22 mm) cancels
    # over points spread around the star, which the isotropic quadratic relies on; left: that part's
    # imbalance over 60 random points (0.22 / sqrt(60) ~ 0.03 mm, three of them) and the noise averaged by
    # the fit (0.1 / sqrt(60) x ~2 ~ 0.03 mm)
    "ellipsoid": (27.0, lambda x, y: x ** 2 / (2 * 25.0) + y ** 2 / (2 * 45.0), 0.1, 60, 0.1),
}


@pytest.mark.parametrize("wall", sorted(WALLS))
def test_curved_wall_about_a_star_seen_from_inside(wall):
    depth, sag, noise_mm, n, tolerance_mm = WALLS[wall]
    camera = Camera(608, 608, 434.0, 434.0, 303.5, 303.5)
    rng = np.random.default_rng(1)
    r = 7.0 * np.sqrt(rng.uniform(0, 1, n))  # within 7 mm: a 6 mm star's 4 radii
    a = rng.uniform(0, 2 * np.pi, n)
    x, y = r * np.cos(a), r * np.sin(a)
    points = np.c_[x, y, depth - sag(x, y)] + rng.normal(0, noise_mm, (n, 3))
    centre_px = np.array([303.5, 303.5])
    curved = fit_local_wall(camera, Pose.identity(), points, centre_px)
    plane = fit_local_wall(camera, Pose.identity(), points, centre_px, curved=False)
    assert curved.depth(np.zeros((1, 2)))[0] == pytest.approx(depth, abs=tolerance_mm)
    # the plane passes in front of the star by about the mean sag over the points
    assert plane.depth(np.zeros((1, 2)))[0] < depth - 0.2
    # the fit's stated sigma at the centre: the noise over sqrt(n), twice that for the intercept of a
    # quadratic over points spread evenly on a disc (its r^2 term correlates with the constant)
    assert curved.sigma_fraction * depth / (noise_mm / np.sqrt(n)) == pytest.approx(2.0, rel=0.5)
