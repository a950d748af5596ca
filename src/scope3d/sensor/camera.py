"""The camera of a dataset: image size, a lens model and its parameters, and the optional circular field.

The default model, ``pinhole_radial_k1k2``, is the model of the reference's bundle adjustment (sec. 6.2):
a point ``X_cam = (X, Y, Z)`` (mm, camera frame, +z forward) projects to normalised coordinates
``x = X/Z, y = Y/Z``, is distorted radially, ``x_d = x (1 + k1 r^2 + k2 r^4)`` with ``r^2 = x^2 + y^2``,
and lands at pixel ``u = fx x_d + cx, v = fy y_d + cy``. Pixel coordinates have their origin at the
centre of the top-left pixel, u to the right and v down; an image of width W spans u in [-0.5, W-0.5].
A Camera carries any model of :mod:`scope3d.sensor.camera_models` (``model`` names it; the parameters
after ``(fx, fy, cx, cy, k1, k2)`` are in ``extra``, see :attr:`Camera.params`).

Intrinsic parameters of the default model are ordered ``(fx, fy, cx, cy, k1, k2)`` everywhere in scope3d
(pixels, pixels, pixels, pixels, unitless, unitless). Pose parameters in Jacobians are ``(w, t)``: the
rotation vector of ``R = exp([w]x)`` (rad) and the translation (mm) of ``cam_from_world``.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np

from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import hat, rotvec_to_matrix, so3_left_jacobian
from scope3d.sensor.camera_models import DEFAULT_MODEL, LensModel, lens_model, opencv_distortion

INTRINSIC_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2")
# A pixel is inside the lens's image when its ray projects back onto it within this (px): the round trip
# is exact to ~1e-9 px inside the field and misses by far where the map folds back.
_ROUND_TRIP_PX = 1e-6


@dataclass(frozen=True)
class Camera:
    """Intrinsics of one camera.

    width, height : int, pixels.
    fx, fy : float, focal lengths in pixels; cx, cy : float, principal point in pixels.
    k1, k2 : float, the model's first two distortion coefficients (radial k1, k2 of the pinhole family;
        the fisheye's k1, k2 on theta); 0 for ``PINHOLE``.
    mask_radius_px : float or None. The scanning-fibre endoscope's image is a disc inside a square
        frame; pixels farther than this from the image centre are not part of the image.
    model : str, a name of :data:`scope3d.sensor.camera_models.MODELS` (default ``pinhole_radial_k1k2``).
    extra : tuple of float, the model's parameters after k2 in its order (OPENCV: p1, p2; FULL_OPENCV:
        p1, p2, k3, k4, k5, k6; OPENCV_FISHEYE: k3, k4).
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
    model: str = DEFAULT_MODEL
    extra: tuple[float, ...] = field(default=())

    def __post_init__(self) -> None:
        lens = lens_model(self.model)
        values = [self.fx, self.fy, self.cx, self.cy, self.k1, self.k2, *self.extra]
        if not np.all(np.isfinite(values)):
            raise ValueError(f"camera intrinsics must be finite, got {values}")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"camera image size must be positive, got {self.width}x{self.height}")
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"camera focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        if self.mask_radius_px is not None and self.mask_radius_px <= 0:
            raise ValueError("camera mask radius must be positive")
        if lens.num_params < 6 and (self.k1 != 0.0 or self.k2 != 0.0 or self.extra):
            raise ValueError(f"a {self.model} camera has no distortion, got k1={self.k1}, k2={self.k2}, "
                             f"extra={self.extra}")
        if lens.num_params >= 6 and len(self.extra) != lens.num_params - 6:
            raise ValueError(f"{self.model} takes {lens.num_params} parameters ({', '.join(lens.param_names)}), "
                             f"got {6 + len(self.extra)}")
        object.__setattr__(self, "extra", tuple(float(v) for v in self.extra))

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

    @classmethod
    def from_params(cls, width: int, height: int, model: str, params, *,
                    mask_radius_px: float | None = None) -> "Camera":
        """A camera of any model from its parameter vector in the model's order (ValueError when the count
        does not fit the model or the name is unknown)."""
        lens = lens_model(model)
        p = [float(v) for v in lens.check(np.asarray(params, dtype=float).ravel())]
        head = (p + [0.0, 0.0])[:6]
        return cls(width, height, *head, mask_radius_px=mask_radius_px, model=model, extra=tuple(p[6:]))

    @property
    def lens(self) -> LensModel:
        return lens_model(self.model)

    @property
    def params(self) -> np.ndarray:
        """(P,) the model's parameters in its order (:attr:`LensModel.param_names`)."""
        head = [self.fx, self.fy, self.cx, self.cy, self.k1, self.k2]
        return np.array((head + list(self.extra))[:self.lens.num_params], dtype=float)

    @property
    def param_names(self) -> tuple[str, ...]:
        return self.lens.param_names

    def with_params(self, params: np.ndarray) -> "Camera":
        """The same camera and model with other parameters."""
        return Camera.from_params(self.width, self.height, self.model, params, mask_radius_px=self.mask_radius_px)

    @property
    def intrinsics(self) -> np.ndarray:
        """(6,) (fx, fy, cx, cy, k1, k2) of the default model (the jobs' bundle adjustment's vector)."""
        self._require_default("intrinsics")
        return np.array([self.fx, self.fy, self.cx, self.cy, self.k1, self.k2])

    def with_intrinsics(self, intrinsics: np.ndarray) -> "Camera":
        self._require_default("with_intrinsics")
        fx, fy, cx, cy, k1, k2 = (float(v) for v in np.asarray(intrinsics, dtype=float).reshape(6))
        return replace(self, fx=fx, fy=fy, cx=cx, cy=cy, k1=k1, k2=k2)

    def _require_default(self, what: str) -> None:
        # The 6-vector means (fx, fy, cx, cy, k1, k2) of the radial model to every caller: another model's
        # parameters read through it would be silently wrong (a fisheye's k1 is no radial k1).
        if self.model != DEFAULT_MODEL:
            raise ValueError(f"Camera.{what} is the {DEFAULT_MODEL} vector; a {self.model} camera has "
                             f"params {self.param_names}")

    @property
    def K(self) -> np.ndarray:
        """(3, 3) calibration matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def fov_deg(self) -> float:
        """Full field of view across the image width: of the undistorted pinhole for the default model (as
        scope3d always reported it); through the lens, at the principal point's row, for the others."""
        if self.model == DEFAULT_MODEL:
            return fov_from_focal(self.width, self.fx)
        rays = self.lens.unproject(self.params, np.array([[self.cx + self.width / 2.0, self.cy]]))
        return float(np.rad2deg(2.0 * np.arctan2(np.hypot(rays[0, 0], rays[0, 1]), rays[0, 2])))

    @property
    def distortion_coeffs(self) -> np.ndarray:
        """OpenCV's distortion vector for the same model: (k1, k2, p1, p2[, k3, k4, k5, k6]) for
        cv2.projectPoints, (k1, k2, k3, k4) of a fisheye for cv2.fisheye."""
        return opencv_distortion(self.model, self.params)

    @cached_property
    def max_half_angle_rad(self) -> float:
        """Half-angle from the optical axis up to which the lens's image does not fold back (past pi/2 for
        a fisheye that sees that far)."""
        return self.lens.max_half_angle(self.params)

    # --- distortion ---------------------------------------------------------------------------
    def distort(self, normalised: np.ndarray) -> np.ndarray:
        """(N, 2) undistorted normalised coordinates -> (N, 2) distorted normalised coordinates."""
        return self.lens.distort(self.params, normalised)

    def undistort(self, distorted: np.ndarray) -> np.ndarray:
        """Inverse of :meth:`distort` (Newton's method, exact to ~1e-12 in the image)."""
        return self.lens.undistort(self.params, distorted)

    # --- projection ---------------------------------------------------------------------------
    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """points_cam : (N, 3) mm in the camera frame -> (N, 2) pixels. Points the lens cannot see give NaN:
        at or behind the camera plane for the pinhole family, beyond :attr:`max_half_angle_rad` for a fisheye."""
        pixels = self.lens.project(self.params, points_cam)
        if self.lens.is_fisheye:
            outside = ~self.lens.in_field(self.params, points_cam)
            pixels = np.where(outside[..., None], np.nan, pixels)
        return pixels

    def project_world(self, pose: Pose, points_world: np.ndarray) -> np.ndarray:
        """points_world : (N, 3) mm -> (N, 2) pixels in the camera at ``pose``."""
        return self.project(pose.transform(points_world))

    def project_with_jacobians(self, points_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """pixels (N, 2), d pixel / d point_cam (N, 2, 3) and d pixel / d :attr:`params` (N, 2, P), any model
        (the pose's Jacobian: :func:`scope3d.sensor.camera_models.project_world_with_jacobians`)."""
        return self.lens.project_with_jacobians(self.params, points_cam)

    def pixel_to_normalised(self, pixels: np.ndarray) -> np.ndarray:
        """(N, 2) pixels -> (N, 2) undistorted normalised coordinates (rays in front of the camera)."""
        return self.undistort(self.lens.to_distorted(self.params, pixels))

    def unproject(self, pixels: np.ndarray, depth_mm: np.ndarray | float | None = None) -> np.ndarray:
        """Back-project pixels.

        pixels : (N, 2). Without ``depth_mm``, returns unit rays (N, 3) in the camera frame (a fisheye's
        may point backwards, past 90 deg); with ``depth_mm`` (N,) or scalar, the z-depth, returns points
        (N, 3) mm in the camera frame.
        """
        if self.lens.is_fisheye:
            rays = self.lens.unproject(self.params, pixels)
            if depth_mm is None:
                return rays
            with np.errstate(divide="ignore", invalid="ignore"):
                return rays / rays[..., 2:3] * np.asarray(depth_mm, dtype=float)[..., None]
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

    def valid_mask(self) -> np.ndarray:
        """(H, W) bool: :meth:`mask` and the lens sees through the pixel, i.e. its ray lies inside
        :attr:`max_half_angle_rad` and projects back onto it (where the image folds back it does not)."""
        grid = self.pixel_grid().reshape(-1, 2)
        return self.mask() & self.sees_pixels(grid).reshape(self.height, self.width)

    def sees_pixels(self, pixels: np.ndarray) -> np.ndarray:
        """(N,) bool: each pixel is the image of one ray inside the lens's field (frame and mask aside)."""
        uv = np.asarray(pixels, dtype=float)
        rays = self.unproject(uv)
        inside = self.lens.in_field(self.params, rays)
        with np.errstate(invalid="ignore"):
            back = self.lens.project(self.params, np.where(inside[..., None], rays, np.nan))
            return inside & (np.linalg.norm(back - uv, axis=-1) <= _ROUND_TRIP_PX)

    def nearest_pixels(self, pose: Pose, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Where world points (N, 3) mm fall in the frame taken from ``pose`` (``cam_from_world``): the indices
        (M,) of those in front of the camera and inside the image (and mask), their nearest pixels (M, 2) int
        (column, row) and their z-depths (M,) mm."""
        p = pose.transform(np.asarray(points_world, float).reshape(-1, 3))
        front = p[:, 2] > 1e-6
        uv = np.full((len(p), 2), -1.0)
        uv[front] = self.project(p[front])
        idx = np.flatnonzero(front & self.in_image(uv))
        ij = np.rint(uv[idx]).astype(int)
        ij[:, 0] = np.clip(ij[:, 0], 0, self.width - 1)
        ij[:, 1] = np.clip(ij[:, 1], 0, self.height - 1)
        return idx, ij, p[idx, 2]

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


#: Two calibrations that put every pixel of an image within this distance (px) of each other are one camera,
#: and a skew or perspective term of K that moves no pixel by more than this is zero: 1/30 of SIFT's ~0.3 px
#: keypoint precision, and added in quadrature to a 0.4 px reprojection error it changes it by 1e-4 px. It
#: holds what real files carry: a K decomposed from a projection matrix printed to 8 digits keeps a skew of
#: ~1e-7 fx (2.5e-4 px on a 1600 x 1200 camera, moving no pixel by 1e-4 px), and one camera's per-view K
#: decomposed so differ by ~0.004 px.
SAME_CALIBRATION_PX = 0.01


def without_skew(k: np.ndarray) -> np.ndarray:
    """(3, 3) K without its skew and with the third row [0 0 1]: what a :class:`Camera` holds of it."""
    k = np.asarray(k, float)
    return np.array([[k[0, 0], 0.0, k[0, 2]], [0.0, k[1, 1], k[1, 2]], [0.0, 0.0, 1.0]])


def calibration_shift_px(k_a: np.ndarray, k_b: np.ndarray, width: float, height: float) -> float:
    """Largest distance (px) between where two (3, 3) calibration matrices put the same ray, over the rays
    of a ``width`` x ``height`` image seen through ``k_b``. ``k_a k_b^-1`` maps one's pixels to the other's;
    it is affine when both third rows are [0 0 1], so the largest displacement over the image is at one of
    its corners, which are what is measured (a third row off [0 0 1] by rounding bends the map by as
    little; one off by more is refused at the corners already)."""
    corners = np.array([[-0.5, -0.5, 1.0], [width - 0.5, -0.5, 1.0], [-0.5, height - 0.5, 1.0],
                        [width - 0.5, height - 0.5, 1.0]]).T
    rays = np.linalg.solve(np.asarray(k_b, float), corners)
    a, b = np.asarray(k_a, float) @ rays, np.asarray(k_b, float) @ rays
    with np.errstate(divide="ignore", invalid="ignore"):
        shift = np.linalg.norm(a[:2] / a[2] - b[:2] / b[2], axis=0)
    return float(np.max(shift)) if np.all(np.isfinite(shift)) else float("inf")


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
