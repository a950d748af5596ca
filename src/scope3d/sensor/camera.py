"""Pinhole camera with two-term radial distortion, the model of the reference's bundle adjustment (sec. 6.2).

A point ``X_cam = (X, Y, Z)`` (mm, camera frame, +z forward) projects to normalised coordinates
``x = X/Z, y = Y/Z``, is distorted radially, ``x_d = x (1 + k1 r^2 + k2 r^4)`` with ``r^2 = x^2 + y^2``,
and lands at pixel ``u = fx x_d + cx, v = fy y_d + cy``. Pixel coordinates have their origin at the
centre of the top-left pixel, u to the right and v down; an image of width W spans u in [-0.5, W-0.5].

Intrinsic parameters are ordered ``(fx, fy, cx, cy, k1, k2)`` everywhere in scope3d (pixels, pixels,
pixels, pixels, unitless, unitless). Pose parameters in Jacobians are ``(w, t)``: the rotation vector of
``R = exp([w]x)`` (rad) and the translation (mm) of ``cam_from_world``.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import hat, rotvec_to_matrix, so3_left_jacobian

INTRINSIC_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2")
_UNDISTORT_ITERATIONS = 20


@dataclass(frozen=True)
class Camera:
    """Intrinsics of one camera.

    width, height : int, pixels.
    fx, fy : float, focal lengths in pixels; cx, cy : float, principal point in pixels.
    k1, k2 : float, radial distortion on normalised coordinates.
    mask_radius_px : float or None. The scanning-fibre endoscope's image is a disc inside a square
        frame; pixels farther than this from the image centre are not part of the image.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    k1: float = 0.0
    k2: float = 0.0
    mask_radius_px: float | None = None

    def __post_init__(self) -> None:
        values = [self.fx, self.fy, self.cx, self.cy, self.k1, self.k2]
        if not np.all(np.isfinite(values)):
            raise ValueError(f"camera intrinsics must be finite, got {values}")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"camera image size must be positive, got {self.width}x{self.height}")
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"camera focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        if self.mask_radius_px is not None and self.mask_radius_px <= 0:
            raise ValueError("camera mask radius must be positive")

    # --- construction ------------------------------------------------------------------------
    @classmethod
    def from_fov(
        cls,
        width: int,
        height: int,
        fov_deg: float,
        *,
        k1: float = 0.0,
        k2: float = 0.0,
        mask_radius_px: float | None = None,
    ) -> "Camera":
        """Square pixels, principal point at the image centre, ``fov_deg`` across the image width."""
        fx = focal_from_fov(width, fov_deg)
        return cls(width, height, fx, fx, (width - 1) / 2.0, (height - 1) / 2.0, k1, k2, mask_radius_px)

    @classmethod
    def from_intrinsics(cls, width: int, height: int, intrinsics: np.ndarray, **kw) -> "Camera":
        """intrinsics : (6,) (fx, fy, cx, cy, k1, k2)."""
        fx, fy, cx, cy, k1, k2 = (float(v) for v in np.asarray(intrinsics, dtype=float).reshape(6))
        return cls(width, height, fx, fy, cx, cy, k1, k2, **kw)

    @property
    def intrinsics(self) -> np.ndarray:
        """(6,) (fx, fy, cx, cy, k1, k2)."""
        return np.array([self.fx, self.fy, self.cx, self.cy, self.k1, self.k2])

    def with_intrinsics(self, intrinsics: np.ndarray) -> "Camera":
        fx, fy, cx, cy, k1, k2 = (float(v) for v in np.asarray(intrinsics, dtype=float).reshape(6))
        return replace(self, fx=fx, fy=fy, cx=cx, cy=cy, k1=k1, k2=k2)

    @property
    def K(self) -> np.ndarray:
        """(3, 3) calibration matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def fov_deg(self) -> float:
        """Full field of view across the image width (undistorted pinhole), degrees."""
        return fov_from_focal(self.width, self.fx)

    @property
    def distortion_coeffs(self) -> np.ndarray:
        """OpenCV's (k1, k2, p1, p2) for the same model."""
        return np.array([self.k1, self.k2, 0.0, 0.0])

    # --- distortion ---------------------------------------------------------------------------
    def distort(self, normalised: np.ndarray) -> np.ndarray:
        """(N, 2) undistorted normalised coordinates -> (N, 2) distorted normalised coordinates."""
        xy = np.asarray(normalised, dtype=float)
        r2 = np.sum(xy * xy, axis=-1, keepdims=True)
        return xy * (1.0 + self.k1 * r2 + self.k2 * r2 * r2)

    def undistort(self, distorted: np.ndarray) -> np.ndarray:
        """Inverse of :meth:`distort`, by Newton's method on the radius (exact to ~1e-12 in the image)."""
        xy_d = np.asarray(distorted, dtype=float)
        if self.k1 == 0.0 and self.k2 == 0.0:
            return xy_d.copy()
        rd = np.linalg.norm(xy_d, axis=-1)
        r = rd.copy()
        for _ in range(_UNDISTORT_ITERATIONS):
            r2 = r * r
            f = r * (1.0 + self.k1 * r2 + self.k2 * r2 * r2) - rd
            df = 1.0 + 3.0 * self.k1 * r2 + 5.0 * self.k2 * r2 * r2
            r = r - f / np.where(np.abs(df) < 1e-12, 1e-12, df)
        scale = np.where(rd > 0, r / np.where(rd > 0, rd, 1.0), 1.0)
        return xy_d * scale[..., None]

    # --- projection ---------------------------------------------------------------------------
    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """points_cam : (N, 3) mm in the camera frame -> (N, 2) pixels. Points behind give NaN."""
        p = np.asarray(points_cam, dtype=float)
        z = p[..., 2:3]
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = np.where(z > 0, p[..., :2] / z, np.nan)
        xy_d = self.distort(xy)
        return np.stack([self.fx * xy_d[..., 0] + self.cx, self.fy * xy_d[..., 1] + self.cy], axis=-1)

    def project_world(self, pose: Pose, points_world: np.ndarray) -> np.ndarray:
        """points_world : (N, 3) mm -> (N, 2) pixels in the camera at ``pose``."""
        return self.project(pose.transform(points_world))

    def pixel_to_normalised(self, pixels: np.ndarray) -> np.ndarray:
        """(N, 2) pixels -> (N, 2) undistorted normalised coordinates."""
        uv = np.asarray(pixels, dtype=float)
        xy_d = np.stack([(uv[..., 0] - self.cx) / self.fx, (uv[..., 1] - self.cy) / self.fy], axis=-1)
        return self.undistort(xy_d)

    def unproject(self, pixels: np.ndarray, depth_mm: np.ndarray | float | None = None) -> np.ndarray:
        """Back-project pixels.

        pixels : (N, 2). Without ``depth_mm``, returns unit rays (N, 3) in the camera frame;
        with ``depth_mm`` (N,) or scalar, the z-depth, returns points (N, 3) mm in the camera frame.
        """
        xy = self.pixel_to_normalised(pixels)
        rays = np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], axis=-1)
        if depth_mm is None:
            return rays / np.linalg.norm(rays, axis=-1, keepdims=True)
        return rays * np.asarray(depth_mm, dtype=float)[..., None]

    def pixel_rays_world(self, pose: Pose, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rays through pixels in the world: origins (N, 3) mm (the camera centre), unit directions (N, 3)."""
        dirs = self.unproject(pixels) @ pose.rotation
        origins = np.broadcast_to(pose.centre, dirs.shape).copy()
        return origins, dirs

    # --- image domain -------------------------------------------------------------------------
    def pixel_grid(self) -> np.ndarray:
        """(H, W, 2) pixel coordinates of every pixel centre."""
        u, v = np.meshgrid(np.arange(self.width, dtype=float), np.arange(self.height, dtype=float))
        return np.stack([u, v], axis=-1)

    def mask(self) -> np.ndarray:
        """(H, W) bool, True where the image is valid (inside the circular field when it has one)."""
        if self.mask_radius_px is None:
            return np.ones((self.height, self.width), dtype=bool)
        grid = self.pixel_grid()
        centre = np.array([(self.width - 1) / 2.0, (self.height - 1) / 2.0])
        return np.linalg.norm(grid - centre, axis=-1) <= self.mask_radius_px

    def in_image(self, pixels: np.ndarray, margin_px: float = 0.0) -> np.ndarray:
        """(N,) bool: pixel inside the frame (and the circular mask), at least ``margin_px`` from its edge."""
        uv = np.asarray(pixels, dtype=float)
        ok = np.all(np.isfinite(uv), axis=-1)
        ok &= (uv[..., 0] >= margin_px - 0.5) & (uv[..., 0] <= self.width - 0.5 - margin_px)
        ok &= (uv[..., 1] >= margin_px - 0.5) & (uv[..., 1] <= self.height - 0.5 - margin_px)
        if self.mask_radius_px is not None:
            centre = np.array([(self.width - 1) / 2.0, (self.height - 1) / 2.0])
            ok &= np.linalg.norm(uv - centre, axis=-1) <= self.mask_radius_px - margin_px
        return ok


def focal_from_fov(size_px: float, fov_deg: float) -> float:
    """Focal length (px) of a pinhole whose full field of view across ``size_px`` pixels is ``fov_deg``."""
    if not 0.0 < fov_deg < 180.0:
        raise ValueError(f"field of view must be in (0, 180) degrees, got {fov_deg}")
    return size_px / 2.0 / np.tan(np.deg2rad(fov_deg) / 2.0)


def fov_from_focal(size_px: float, focal_px: float) -> float:
    """Full field of view (deg) across ``size_px`` pixels for focal length ``focal_px``."""
    return float(np.rad2deg(2.0 * np.arctan(size_px / 2.0 / focal_px)))


def project_with_camera_jacobian(points_cam: np.ndarray, intrinsics: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project points given in the camera frame and return d pixel / d point_cam.

    points_cam : (N, 3) mm, +z forward. intrinsics : (N, 6) or (6,) ``(fx, fy, cx, cy, k1, k2)``.
    Returns pixels (N, 2) and the Jacobian (N, 2, 3).
    """
    p_cam = np.asarray(points_cam, dtype=float)
    n = p_cam.shape[0]
    intr = np.broadcast_to(np.asarray(intrinsics, dtype=float), (n, 6))
    fx, fy, k1, k2 = intr[:, 0], intr[:, 1], intr[:, 4], intr[:, 5]
    inv_z = 1.0 / p_cam[:, 2]
    x = p_cam[:, 0] * inv_z
    y = p_cam[:, 1] * inv_z
    r2 = x * x + y * y
    d = 1.0 + k1 * r2 + k2 * r2 * r2
    pixels = np.stack([fx * d * x + intr[:, 2], fy * d * y + intr[:, 3]], axis=-1)

    dd_dr2 = k1 + 2.0 * k2 * r2
    # d(u, v) / d(x, y)
    j_xy = np.empty((n, 2, 2))
    j_xy[:, 0, 0] = fx * (d + 2.0 * x * x * dd_dr2)
    j_xy[:, 0, 1] = fx * (2.0 * x * y * dd_dr2)
    j_xy[:, 1, 0] = fy * (2.0 * x * y * dd_dr2)
    j_xy[:, 1, 1] = fy * (d + 2.0 * y * y * dd_dr2)
    # d(x, y) / d p_cam
    j_norm = np.zeros((n, 2, 3))
    j_norm[:, 0, 0] = inv_z
    j_norm[:, 0, 2] = -x * inv_z
    j_norm[:, 1, 1] = inv_z
    j_norm[:, 1, 2] = -y * inv_z
    return pixels, j_xy @ j_norm


def project_with_jacobians(
    points_world: np.ndarray,
    rotvecs: np.ndarray,
    translations: np.ndarray,
    intrinsics: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Project N observations and return analytic Jacobians, vectorised over observations.

    Each row is one observation: a world point seen by a camera with its own pose and intrinsics
    (broadcast rows from per-camera arrays with fancy indexing before calling).

    Parameters
    ----------
    points_world : (N, 3) mm.
    rotvecs : (N, 3) rad, rotation vector of ``R = exp([w]x)`` (cam_from_world).
    translations : (N, 3) mm.
    intrinsics : (N, 6) or (6,) ``(fx, fy, cx, cy, k1, k2)``.

    Returns
    -------
    pixels : (N, 2)
    d_point : (N, 2, 3) d pixel / d point_world
    d_pose : (N, 2, 6) d pixel / d (w, t)
    d_intrinsics : (N, 2, 6) d pixel / d (fx, fy, cx, cy, k1, k2)
    """
    points_world = np.asarray(points_world, dtype=float)
    n = points_world.shape[0]
    intr = np.broadcast_to(np.asarray(intrinsics, dtype=float), (n, 6))
    rotations = rotvec_to_matrix(rotvecs)
    rotated = np.einsum("nij,nj->ni", rotations, points_world)
    p_cam = rotated + translations
    pixels, d_pcam = project_with_camera_jacobian(p_cam, intr)
    fx, fy, k1, k2 = intr[:, 0], intr[:, 1], intr[:, 4], intr[:, 5]
    x, y = p_cam[:, 0] / p_cam[:, 2], p_cam[:, 1] / p_cam[:, 2]
    r2 = x * x + y * y
    d = 1.0 + k1 * r2 + k2 * r2 * r2

    d_point = d_pcam @ rotations
    d_rot = -hat(rotated) @ so3_left_jacobian(rotvecs)
    d_pose = np.concatenate([d_pcam @ d_rot, d_pcam], axis=-1)

    d_intr = np.zeros((n, 2, 6))
    d_intr[:, 0, 0] = d * x
    d_intr[:, 1, 1] = d * y
    d_intr[:, 0, 2] = 1.0
    d_intr[:, 1, 3] = 1.0
    d_intr[:, 0, 4] = fx * x * r2
    d_intr[:, 1, 4] = fy * y * r2
    d_intr[:, 0, 5] = fx * x * r2 * r2
    d_intr[:, 1, 5] = fy * y * r2 * r2
    return pixels, d_point, d_pose, d_intr
