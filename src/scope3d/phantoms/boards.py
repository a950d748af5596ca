"""The phantom lab renders calibration boards: checkerboard and ChArUco views with exact truth.

A board lies in its own z = 0 plane (mm); inner corner ``i`` is at :meth:`BoardSpec.object_points`
``[i]``. Each view is rendered by casting ``supersample x supersample`` rays per pixel through the
camera's distortion (:meth:`Camera.unproject`, so k1, k2 and the circular field are those of the camera)
onto the plane and averaging the board's reflectance there, as a sensor integrates light over its pixel;
then optical blur, Gaussian read noise and 8-bit quantisation. The truth is the camera, every pose
``cam_from_board`` and the corners' exact projections.

Typical use::

    views = render_board_views(camera, board, n_views=12, seed=0)
    views.images[0], views.corners_px[0], views.poses[0]
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import rotvec_to_matrix
from scope3d.sensor.calibration import BoardSpec
from scope3d.sensor.camera import Camera

_BLACK, _WHITE, _BACKGROUND = 0.08, 0.85, 0.45
_CHARUCO_TEXELS_PER_SQUARE = 40
# the lab's checkerboard: odd x even, an unambiguous orientation; 20 x 14 mm fills an endoscope's view at ~25 mm
LAB_BOARD = BoardSpec(9, 6, 2.0)


@dataclass(frozen=True)
class BoardRenderOptions:
    """How board views are posed and imaged.

    max_tilt_deg : largest angle between the board's normal and the optical axis (45: beyond ~60 deg
        corner detectors fail, and Zhang's method needs tilted views to separate focal length from depth).
    fill_range : (lo, hi) fraction of the image width the board's width spans (sets the distance).
    supersample : rays per pixel side (anti-aliasing of the square edges; 4 makes the edge position
        exact to ~1/30 px for the corner detector).
    blur_sigma_px : Gaussian optical blur (px). noise_grey : std of Gaussian read noise, grey levels (0-255).
    margin_px : every corner stays this far inside the frame (and the circular field).
    """

    max_tilt_deg: float = 45.0
    fill_range: tuple[float, float] = (0.45, 0.8)
    supersample: int = 4
    blur_sigma_px: float = 0.6
    noise_grey: float = 2.0
    margin_px: float = 6.0

    def __post_init__(self) -> None:
        if not 0 <= self.max_tilt_deg < 80:
            raise ValueError("max_tilt_deg must be in [0, 80)")
        lo, hi = self.fill_range
        if not 0 < lo <= hi <= 1.5:
            raise ValueError("fill_range must satisfy 0 < lo <= hi <= 1.5")
        if not 1 <= self.supersample <= 8:
            raise ValueError("supersample must be 1..8")
        if self.blur_sigma_px < 0 or self.noise_grey < 0 or self.margin_px < 0:
            raise ValueError("blur, noise and margin must be non-negative")


# how the lab poses its board (the raw recording's calibration and hand-eye views, a dataset's --boards): up
# to 50 deg of tilt, which the detectors still find and which separates focal length from depth
LAB_BOARD_OPTIONS = BoardRenderOptions(max_tilt_deg=50)


@dataclass
class BoardViews:
    """Rendered board views and their truth.

    camera : the true camera. board : the board. images : list of (H, W) uint8 grey.
    poses : list of true cam_from_board. corners_px : list of (cols * rows, 2) exact corner projections.
    """

    camera: Camera
    board: BoardSpec
    images: list[np.ndarray]
    poses: list[Pose]
    corners_px: list[np.ndarray]


def random_board_poses(camera: Camera, board: BoardSpec, n_views: int, *, seed: int,
                       options: BoardRenderOptions = BoardRenderOptions()) -> list[Pose]:
    """``n_views`` cam_from_board poses with every corner inside the image, drawn from ``seed``."""
    rng = np.random.default_rng(seed)
    obj = board.object_points()
    centre_board = obj.mean(axis=0)
    board_width = (board.cols + 1) * board.square_mm
    poses: list[Pose] = []
    for _ in range(1000 * n_views):
        if len(poses) == n_views:
            break
        # Tilt about a random axis in the image plane, then a random in-plane turn (<= 30 deg keeps the
        # detectors' row order unambiguous for an odd x even board).
        axis_angle = rng.uniform(0, 2 * np.pi)
        tilt = np.deg2rad(options.max_tilt_deg) * np.sqrt(rng.uniform())
        spin = np.deg2rad(rng.uniform(-30, 30))
        rotation = rotvec_to_matrix(tilt * np.array([np.cos(axis_angle), np.sin(axis_angle), 0.0])) \
            @ rotvec_to_matrix(np.array([0.0, 0.0, spin]))
        distance = camera.fx * board_width / (rng.uniform(*options.fill_range) * camera.width)
        # Shift the board across the field so the corners cover the sensor (distortion lives at the edges).
        offset = rng.uniform(-0.35, 0.35, 2) * np.array([camera.width / camera.fx, camera.height / camera.fy])
        centre_cam = np.array([offset[0] * distance, offset[1] * distance, distance])
        pose = Pose(rotation, centre_cam - rotation @ centre_board)
        if np.all(camera.in_image(camera.project(pose.transform(obj)), margin_px=options.margin_px)):
            poses.append(pose)
    if len(poses) < n_views:
        raise ValueError(f"could not place {n_views} board views inside the image; lower fill_range")
    return poses


def render_board_view(camera: Camera, board: BoardSpec, pose: Pose, *, rng: np.random.Generator,
                      options: BoardRenderOptions = BoardRenderOptions(), _rays: np.ndarray | None = None,
                      ) -> np.ndarray:
    """(H, W) uint8 grey image of ``board`` at ``pose`` (cam_from_board) through ``camera``."""
    rays = _sub_rays(camera, options.supersample) if _rays is None else _rays
    origin = -pose.rotation.T @ pose.translation  # camera centre in the board frame
    dirs = rays @ pose.rotation  # R^T d, row-wise
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = -origin[2] / dirs[..., 2]
    hit = np.isfinite(lam) & (lam > 0)
    xy = origin[:2] + np.where(hit, lam, 0.0)[..., None] * dirs[..., :2]
    value = np.where(hit, _reflectance(board, xy), _BACKGROUND)
    s = options.supersample
    h, w = camera.height, camera.width
    img = value.reshape(h, s, w, s).mean(axis=(1, 3)).astype(np.float32)
    if options.blur_sigma_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), options.blur_sigma_px)
    img = img * 255.0 + options.noise_grey * rng.standard_normal(img.shape).astype(np.float32)
    img[~camera.valid_mask()] = 0.0
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def render_board_views(camera: Camera, board: BoardSpec, *, n_views: int, seed: int,
                       options: BoardRenderOptions = BoardRenderOptions(), noise_seed: int | None = None,
                       ) -> BoardViews:
    """``n_views`` rendered views at poses drawn from ``seed``; image noise from ``noise_seed``
    (default ``seed``), so the same poses can be re-imaged with fresh noise."""
    poses = random_board_poses(camera, board, n_views, seed=seed, options=options)
    rng = np.random.default_rng([seed if noise_seed is None else noise_seed, 1])
    rays = _sub_rays(camera, options.supersample)
    obj = board.object_points()
    images = [render_board_view(camera, board, p, rng=rng, options=options, _rays=rays) for p in poses]
    corners = [camera.project(p.transform(obj)) for p in poses]
    return BoardViews(camera, board, images, poses, corners)


def _sub_rays(camera: Camera, s: int) -> np.ndarray:
    """(H, s, W, s, 3) camera-frame rays through a ``s x s`` grid of points in each pixel square."""
    offsets = (np.arange(s) + 0.5) / s - 0.5
    v = (np.arange(camera.height)[:, None] + offsets[None, :]).ravel()
    u = (np.arange(camera.width)[:, None] + offsets[None, :]).ravel()
    uu, vv = np.meshgrid(u, v)
    rays = camera.unproject(np.stack([uu, vv], axis=-1).reshape(-1, 2))
    return rays.reshape(camera.height, s, camera.width, s, 3)


def _reflectance(board: BoardSpec, xy: np.ndarray) -> np.ndarray:
    """Reflectance at board-plane points ``xy`` (..., 2) mm."""
    sq = board.square_mm
    if board.kind == "charuco":
        return _charuco_reflectance(board, xy)
    i = np.floor(xy[..., 0] / sq).astype(np.int64)
    j = np.floor(xy[..., 1] / sq).astype(np.int64)
    on_squares = (i >= -1) & (i <= board.cols - 1) & (j >= -1) & (j <= board.rows - 1)
    on_paper = (i >= -2) & (i <= board.cols) & (j >= -2) & (j <= board.rows)
    # Square (-1, -1), at the first inner corner's top-left, is white: OpenCV's detectors then number the
    # corners of a board with one odd and one even side as object_points does (an even x even board is
    # symmetric under a half turn, and its order is ambiguous to any detector).
    black = on_squares & ((i + j) % 2 == 1)
    return np.where(black, _BLACK, np.where(on_paper, _WHITE, _BACKGROUND))


def _charuco_reflectance(board: BoardSpec, xy: np.ndarray) -> np.ndarray:
    """The OpenCV ChArUco board image, bilinearly sampled; its first inner corner is our origin."""
    texels = _CHARUCO_TEXELS_PER_SQUARE
    size = ((board.cols + 1) * texels, (board.rows + 1) * texels)
    texture = board.charuco_board().generateImage(size, marginSize=0, borderBits=1).astype(np.float32) / 255.0
    texture = _BLACK + (_WHITE - _BLACK) * texture
    # Texel k covers [k, k + 1) texel units; the board's outer corner is at -1 square from our origin.
    tx = (xy[..., 0] / board.square_mm + 1.0) * texels - 0.5
    ty = (xy[..., 1] / board.square_mm + 1.0) * texels - 0.5
    inside = (tx >= -0.5) & (tx <= size[0] - 0.5) & (ty >= -0.5) & (ty <= size[1] - 0.5)
    rows = int(np.prod(tx.shape[:2]))  # remap takes a 2-D map of at most 32767 rows and columns
    sampled = cv2.remap(texture, tx.astype(np.float32).reshape(rows, -1), ty.astype(np.float32).reshape(rows, -1),
                        cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).reshape(tx.shape)
    margin = (tx >= -texels) & (tx <= size[0] + texels) & (ty >= -texels) & (ty <= size[1] + texels)
    return np.where(inside, sampled, np.where(margin, _WHITE, _BACKGROUND))
