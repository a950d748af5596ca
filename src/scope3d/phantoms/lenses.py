"""The phantom lab's lenses: the pinhole it always rendered through, and real scopes' wide, distorted lenses.

A lens is a camera model of :mod:`scope3d.sensor.camera_models` with fixed distortion, a field of view and
a vignetting law; the renderer casts each pixel's ray through the model's ``unproject``
(:mod:`scope3d.phantoms.render`, :mod:`scope3d.phantoms.boards`), so the images, the ground truth and the
written ``camera.json`` all hold the same lens:

``pinhole``
    the scene's camera as before (scope3d's ``pinhole_radial_k1k2`` with k1 = k2 = 0, the scene's FOV).
``fisheye-140``
    a capsule-like scope: ``OPENCV_FISHEYE``, 140 deg across its circular field (70 deg half-angle at the
    circle's edge, radius ``ENDOSCOPE_MASK_FRACTION * min(width, height)`` px), a mildly stereographic
    profile (``theta_d = theta + theta^3 / 25 + ...``: the edge less compressed than an equidistant lens's,
    as capsule lenses are), and relative illumination ``cos(theta)`` (0.34 at the edge of the field).
``barrel-70``
    a rigid scope with strong barrel distortion: ``OPENCV`` with k1 = -0.28, k2 = 0.07 (the image's
    edge is 12 % closer to the centre than a pinhole's) and a small decentring (p1, p2), 70 deg across
    the width; relative illumination ``cos(theta)^2`` (0.67 at the width's edge). Its circular field is
    the scene's (the endoscope's, none on the borescope).

Vignetting multiplies the radiance reaching each pixel by ``cos(theta)^n`` with ``theta`` the angle of the
pixel's ray from the optical axis (the ``cos^4`` law of a thin lens is ``n = 4``; wide-angle designs
flatten it, which a smaller ``n`` stands for).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scope3d.sensor.camera import Camera, focal_from_fov

# the scanning-fibre endoscope's circular field: ~300 px radius in a 608 px frame (reference sec. 3.1)
ENDOSCOPE_MASK_FRACTION = 300.0 / 608.0


@dataclass(frozen=True)
class Lens:
    """One lens of the lab.

    name : the ``--lens`` name. model : the camera model (COLMAP's name or ``pinhole_radial_k1k2``).
    fov_deg : full field of view (None: the scene's). fov_across : ``"width"`` (across the image width at
    the principal point's row) or ``"circle"`` (across the circular field's diameter).
    distortion : the model's coefficients after (fx, fy, cx, cy), in its order.
    vignetting : exponent n of the relative illumination ``cos(theta)^n`` (0: none).
    circular_field : the lens always images a circle (fisheye), whatever the scene's camera.
    """

    name: str
    description: str
    model: str
    fov_deg: float | None
    fov_across: str
    distortion: tuple[float, ...]
    vignetting: float
    circular_field: bool = False

    def camera(self, width: int, height: int, *, fov_deg: float, mask_radius_px: float | None) -> Camera:
        """The camera of this lens on a ``width x height`` sensor, principal point at the image centre, square
        pixels. ``fov_deg``, ``mask_radius_px``: the scene's camera's (used where the lens has none of its own)."""
        fov = self.fov_deg if self.fov_deg is not None else fov_deg
        if self.circular_field:
            mask_radius_px = ENDOSCOPE_MASK_FRACTION * min(width, height)
        if self.model == PINHOLE.model and not any(self.distortion):
            return Camera.from_fov(width, height, fov, mask_radius_px=mask_radius_px)
        edge_px = mask_radius_px if self.fov_across == "circle" else width / 2.0
        # the focal length that puts the ray at half the field on the edge: distort that ray with f = 1
        half = np.deg2rad(fov / 2.0)
        unit = Camera.from_params(width, height, self.model, [1.0, 1.0, 0.0, 0.0, *self.distortion])
        edge_normalised = unit.project(np.array([[np.sin(half), 0.0, np.cos(half)]]))[0, 0]
        focal = edge_px / edge_normalised
        return Camera.from_params(width, height, self.model,
                                  [focal, focal, (width - 1) / 2.0, (height - 1) / 2.0, *self.distortion],
                                  mask_radius_px=mask_radius_px)


PINHOLE = Lens("pinhole", "the scene's pinhole camera (as before)", "pinhole_radial_k1k2", None, "width",
               (0.0, 0.0), 0.0)
LENSES: dict[str, Lens] = {lens.name: lens for lens in (
    PINHOLE,
    Lens("fisheye-140", "capsule-like fisheye (OPENCV_FISHEYE), 140 deg across its circular field, "
                        "vignetting cos(theta)", "OPENCV_FISHEYE", 140.0, "circle", (0.04, 0.004, -0.0003, 0.0),
         1.0, circular_field=True),
    Lens("barrel-70", "rigid scope with strong barrel distortion (OPENCV, k1 = -0.28), 70 deg across the "
                      "width, vignetting cos(theta)^2", "OPENCV", 70.0, "width", (-0.28, 0.07, 3e-4, -2e-4), 2.0),
)}


def lens_named(name: str) -> Lens:
    """The lens of that name (ValueError naming the known ones otherwise)."""
    try:
        return LENSES[name]
    except KeyError:
        raise ValueError(f"unknown lens {name!r} (use one of {', '.join(LENSES)})") from None


def vignetting(rays_cam: np.ndarray, exponent: float) -> np.ndarray:
    """(N,) relative illumination ``cos(theta)^exponent`` of unit camera-frame rays (N, 3); 1 on the axis.
    Rays past 90 deg (a lens that sees behind itself) get 0."""
    return np.maximum(rays_cam[..., 2], 0.0) ** exponent
