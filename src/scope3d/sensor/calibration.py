"""Scope calibration from board views, with the covariance of the intrinsics (reference sec. 6.3, 8.1).

The reference calibrated its scopes with a checkerboard toolbox and fed the field of view to BCBA as a
*range* (sec. 6.3: 50-56 deg); here the range comes from the calibration's own covariance. Steps::

    detections  <- detect_board per image          (checkerboard: OpenCV's sector-based detector with
                                                    sub-pixel accuracy, falling back to the classic one
                                                    + cornerSubPix; ChArUco through cv2.aruco)
    calibration <- calibrate(detections, ...)       (OpenCV's Levenberg-Marquardt for one of the models of
                                                    :mod:`scope3d.sensor.camera_models`; outlier views
                                                    dropped one at a time and the fit repeated)
    covariance  <- J, residuals                     (sigma^2 (J^T J)^-1 over intrinsics and every view's
                                                    pose, sigma^2 = sum r^2 / (2 N - p); the intrinsic
                                                    block is the marginal covariance)
    bounds      <- value +- k sigma                 (:meth:`Calibration.bounds`, for BCBA, eq. 6.2)

Pixel coordinates have their origin at the centre of the top-left pixel (OpenCV's and scope3d's
convention). A board pose is ``cam_from_board`` (board frame: z = 0 plane, x along the columns, mm).

Models (``CalibrationOptions.model``, ``scope3d calibrate --model``) and the camera model each fits, in
COLMAP's parameter order (:mod:`scope3d.sensor.camera_models`):

* ``"radial"`` (also ``"pinhole"``, its old name): ``pinhole_radial_k1k2``, ``(fx, fy, cx, cy, k1, k2)``,
  the model scope3d's jobs use; OpenCV's calibrateCamera with no tangential terms and no k3.
* ``"opencv"``: ``OPENCV``, ``(fx, fy, cx, cy, k1, k2, p1, p2)``; calibrateCamera without k3.
* ``"full-opencv"``: ``FULL_OPENCV``, ``(fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6)``, the rational
  model; calibrateCamera with CALIB_RATIONAL_MODEL.
* ``"fisheye"``: ``OPENCV_FISHEYE``, ``(fx, fy, cx, cy, k1, k2, k3, k4)``, Kannala-Brandt:
  ``theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)``, ``theta`` the angle
  from the optical axis; a capsule's or wide-angle endoscope's lens; cv2.fisheye.calibrate.

The covariance comes from scope3d's analytic Jacobians of the same model (the pose's by the chain rule).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.optimize import least_squares

from scope3d.errors import InputError
from scope3d.geometry.pose import Pose
from scope3d.sensor.camera import Camera
from scope3d.sensor.camera_models import lens_model, project_world_with_jacobians

# calibrate's model names -> the camera model each fits ("pinhole" is the radial model's old name)
CAMERA_MODEL_OF = {"radial": "pinhole_radial_k1k2", "pinhole": "pinhole_radial_k1k2", "opencv": "OPENCV",
                   "full-opencv": "FULL_OPENCV", "fisheye": "OPENCV_FISHEYE"}
MODELS = tuple(CAMERA_MODEL_OF)
BOARD_KINDS = ("checkerboard", "charuco")


# --- the board -----------------------------------------------------------------------------------
@dataclass(frozen=True)
class BoardSpec:
    """A planar calibration board.

    cols, rows : int, inner corners along x and y (OpenCV's convention: a 9x6 board has 10x7 squares).
    square_mm : float, side of one square.
    kind : "checkerboard" or "charuco" (a ChArUco board of ``cols + 1`` x ``rows + 1`` squares).
    marker_mm : float, side of a ChArUco marker (default 0.7 of the square).
    dictionary : str, name of the cv2.aruco dictionary of a ChArUco board.
    """

    cols: int
    rows: int
    square_mm: float
    kind: str = "checkerboard"
    marker_mm: float | None = None
    dictionary: str = "DICT_4X4_50"

    def __post_init__(self) -> None:
        if self.cols < 2 or self.rows < 2:
            raise ValueError(f"a board needs at least 2x2 inner corners, got {self.cols}x{self.rows}")
        if not self.square_mm > 0:
            raise ValueError(f"the square size must be positive, got {self.square_mm} mm")
        if self.kind not in BOARD_KINDS:
            raise ValueError(f"board kind must be one of {BOARD_KINDS}, got {self.kind!r}")
        if self.marker_mm is not None and not 0 < self.marker_mm < self.square_mm:
            raise ValueError("a ChArUco marker must be smaller than the square")
        if self.kind == "charuco" and not hasattr(cv2.aruco, self.dictionary):
            raise ValueError(f"unknown ArUco dictionary {self.dictionary!r}")

    @classmethod
    def parse(cls, text: str, square_mm: float, **kw) -> "BoardSpec":
        """``"9x6"`` (inner corners, COLSxROWS) -> BoardSpec; a malformed text is an InputError."""
        parts = text.lower().split("x")
        if len(parts) != 2 or not all(p.strip().isdigit() for p in parts):
            raise InputError(f"--board {text!r}: expected COLSxROWS inner corners, e.g. 9x6")
        try:
            return cls(int(parts[0]), int(parts[1]), float(square_mm), **kw)
        except ValueError as exc:
            raise InputError(f"--board {text}: {exc}") from None

    @property
    def num_corners(self) -> int:
        return self.cols * self.rows

    def object_points(self) -> np.ndarray:
        """(cols * rows, 3) mm, corner ``i`` at ``(i % cols, i // cols, 0) * square`` (row-major, OpenCV's order)."""
        grid = np.mgrid[0:self.rows, 0:self.cols]
        xy = np.stack([grid[1].ravel(), grid[0].ravel()], axis=-1) * self.square_mm
        return np.concatenate([xy, np.zeros((xy.shape[0], 1))], axis=-1)

    def charuco_board(self):
        """The cv2.aruco.CharucoBoard of this spec (its chessboard corners are our object points)."""
        marker = self.marker_mm if self.marker_mm is not None else 0.7 * self.square_mm
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard((self.cols + 1, self.rows + 1), self.square_mm, marker, dictionary)


# --- detection -----------------------------------------------------------------------------------
@dataclass(frozen=True)
class DetectionOptions:
    """How corners are found.

    subpixel_window_px : int, largest half-size of cornerSubPix's window (5 px: a corner's neighbourhood on
        200-1000 px scope images); smaller boards in the image get a smaller window (0.4 square).
    mask_radius_px : float or None, the radius of the circular field of a scanning-fibre scope, centred
        on the image; the black outside is filled with the image's median inside so the detector sees no
        false edge at the rim, and corners closer to the rim than ``subpixel_window_px`` are dropped.
    min_charuco_corners : int, a ChArUco view with fewer corners is not used (6: more than the 4 a
        homography needs, so one wrong marker cannot define the pose).
    refine_corners : bool, refine a checkerboard's corners from OpenCV's sector detector (which has its own
        sub-pixel accuracy, CALIB_CB_ACCURACY) with cornerSubPix. Off by default: on the real EndoSLAM capsule
        images (squares of 10-15 px through a fisheye lens) the sector detector's corners fit every model
        better (fisheye 0.256 vs 0.373 px RMS, radial 0.556 vs 0.603; benchmarks/bench_calibration_models.py),
        while on sharp rendered boards with exact truth cornerSubPix cuts the corner error from 0.09 to
        0.03 px RMS (benchmarks/bench_calibration.py). A ChArUco board's corners are always refined (its
        detector's own are off by ~0.15 px).
    """

    subpixel_window_px: int = 5
    mask_radius_px: float | None = None
    min_charuco_corners: int = 6
    refine_corners: bool = False

    def __post_init__(self) -> None:
        if self.subpixel_window_px < 1:
            raise ValueError("subpixel_window_px must be >= 1")
        if self.mask_radius_px is not None and not self.mask_radius_px > 0:
            raise ValueError("mask_radius_px must be positive")
        if self.min_charuco_corners < 4:
            raise ValueError("min_charuco_corners must be >= 4")


@dataclass(frozen=True)
class BoardDetection:
    """The corners found in one image.

    name : str, the image's name (file name).
    pixels : (N, 2) float64 pixels, or None when the board was not found.
    corner_ids : (N,) int64, index of each corner in :meth:`BoardSpec.object_points`.
    reason : str, why the board was not found ("" when it was).
    """

    name: str
    pixels: np.ndarray | None
    corner_ids: np.ndarray | None
    reason: str = ""

    @property
    def found(self) -> bool:
        return self.pixels is not None


def circular_field_radius(images: list[np.ndarray], *, threshold_fraction: float = 0.25) -> float:
    """Radius (px) of the lit disc of a scanning-fibre scope, centred on the image.

    images : grey (H, W) uint8. A pixel is lit when the per-pixel maximum over the images exceeds
    ``threshold_fraction`` of its 99th percentile; the radius is the 99.5th percentile of the lit pixels'
    distances to the image centre (robust to a few stray bright pixels outside the disc).
    """
    stack = np.max(np.stack([np.asarray(im, dtype=float) for im in images]), axis=0)
    h, w = stack.shape
    lit = stack > threshold_fraction * np.percentile(stack, 99)
    v, u = np.nonzero(lit)
    if u.size == 0:
        raise InputError("no lit pixels: cannot find the circular field")
    dist = np.hypot(u - (w - 1) / 2.0, v - (h - 1) / 2.0)
    return float(np.percentile(dist, 99.5))


def detect_board(image: np.ndarray, board: BoardSpec, *, name: str = "",
                 options: DetectionOptions = DetectionOptions()) -> BoardDetection:
    """Find the board's corners in one grey (H, W) uint8 image (RGB is converted)."""
    grey = np.asarray(image)
    if grey.ndim == 3:
        grey = cv2.cvtColor(grey, cv2.COLOR_RGB2GRAY)
    if grey.dtype != np.uint8:
        raise ValueError("detect_board expects a uint8 image")
    inside = None
    if options.mask_radius_px is not None:
        h, w = grey.shape
        v, u = np.mgrid[0:h, 0:w]
        inside = np.hypot(u - (w - 1) / 2.0, v - (h - 1) / 2.0) <= options.mask_radius_px
        grey = grey.copy()
        grey[~inside] = np.uint8(np.median(grey[inside]))
    if board.kind == "charuco":
        pixels, ids = _detect_charuco(grey, board, options)
    else:
        pixels, ids = _detect_checkerboard(grey, board, options)
    if pixels is None:
        return BoardDetection(name, None, None, ids)
    if inside is not None:
        h, w = grey.shape
        keep = np.hypot(pixels[:, 0] - (w - 1) / 2.0, pixels[:, 1] - (h - 1) / 2.0) \
            <= options.mask_radius_px - options.subpixel_window_px
        if board.kind == "checkerboard" and not keep.all():
            return BoardDetection(name, None, None, "board crosses the rim of the circular field")
        pixels, ids = pixels[keep], ids[keep]
    return BoardDetection(name, pixels, ids)


def _detect_checkerboard(grey, board, options):
    size = (board.cols, board.rows)
    # The sector-based detector finds boards the classic one misses (blur, vignetting, strong distortion);
    # the classic one is the fallback (its corners are pixel-level: always refined by cornerSubPix). The
    # sector detector's are refined only when asked (DetectionOptions.refine_corners).
    ok, corners = cv2.findChessboardCornersSB(grey, size, flags=cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY)
    if not ok:
        ok, corners = cv2.findChessboardCorners(
            grey, size, flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
        if not ok:
            return None, f"no {board.cols}x{board.rows} checkerboard found"
        return _refine_corners(grey, corners, options.subpixel_window_px), np.arange(board.num_corners)
    if not options.refine_corners:
        return corners.reshape(-1, 2).astype(np.float64), np.arange(board.num_corners)
    return _refine_corners(grey, corners, options.subpixel_window_px), np.arange(board.num_corners)


def _subpixel_window(corners: np.ndarray, max_half_px: int, fraction: float) -> int:
    """Half-size of cornerSubPix's window: at most ``max_half_px`` and under ``fraction`` of the shortest
    distance between two corners, so the window never reaches the next corner or a ChArUco marker (which
    would pull the estimate)."""
    diff = corners[:, None, :] - corners[None, :, :]
    dist = np.linalg.norm(diff, axis=-1)
    np.fill_diagonal(dist, np.inf)
    return int(min(np.floor(fraction * dist.min()), max_half_px))


def _refine_corners(grey: np.ndarray, corners: np.ndarray, max_half_px: int, fraction: float = 0.4) -> np.ndarray:
    corners = corners.reshape(-1, 1, 2).astype(np.float32)
    win = _subpixel_window(corners.reshape(-1, 2), max_half_px, fraction)
    if win < 2:
        # A 3x3 window holds too few gradients to beat the detector's own estimate: keep it.
        return corners.reshape(-1, 2).astype(np.float64)
    refined = cv2.cornerSubPix(grey, corners, (win, win), (-1, -1),
                               (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3))
    return refined.reshape(-1, 2).astype(np.float64)


def _detect_charuco(grey, board, options):
    detector = cv2.aruco.CharucoDetector(board.charuco_board())
    corners, ids, _, _ = detector.detectBoard(grey)
    if ids is None or len(ids) < options.min_charuco_corners:
        n = 0 if ids is None else len(ids)
        return None, f"only {n} ChArUco corners found (need {options.min_charuco_corners})"
    # On small scope images (squares of ~10 px) the detector's own corners are off by ~0.15 px RMS;
    # cornerSubPix brings them to ~0.03 px (rendered boards with exact truth, 320x240).
    # The window stays within the white margin around a marker: (1 - marker / square) / 2 of a square.
    marker = board.marker_mm if board.marker_mm is not None else 0.7 * board.square_mm
    fraction = 0.9 * (1.0 - marker / board.square_mm) / 2.0
    return _refine_corners(grey, corners, options.subpixel_window_px, fraction), ids.ravel().astype(np.int64)


# --- calibration ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class CalibrationOptions:
    """How intrinsics are fitted.

    model : "radial" (fx, fy, cx, cy, k1, k2: the jobs' camera), "opencv", "full-opencv" or "fisheye" (see
        the module docstring; "pinhole" is "radial").
    min_views : int, fewer usable views is an InputError (3: with fewer, a planar board leaves the
        focal length and the principal point inseparable, Zhang 2000).
    outlier_ratio : float, a view whose RMS reprojection error exceeds ``outlier_ratio`` times the median
        view's is dropped (the worst first, then the fit is repeated). 3: with Gaussian corner noise every
        view's RMS over ~50 corners is within ~20 % of the median, so 3x means a wrong detection or a
        view the model cannot fit.
    outlier_floor_px : float, views under this RMS are never outliers however small the median is
        (0.3 px: a well-detected corner's error on a real scope image).
    """

    model: str = "radial"
    min_views: int = 3
    outlier_ratio: float = 3.0
    outlier_floor_px: float = 0.3

    def __post_init__(self) -> None:
        if self.model not in MODELS:
            raise ValueError(f"model must be one of {MODELS}, got {self.model!r}")
        if self.min_views < 3:
            raise ValueError("min_views must be >= 3")
        if not self.outlier_ratio > 1.0:
            raise ValueError("outlier_ratio must be > 1")
        if not self.outlier_floor_px >= 0.0:
            raise ValueError("outlier_floor_px must be >= 0")


@dataclass
class Calibration:
    """The fitted camera, its uncertainty and the views behind it.

    model : the camera model's name (:mod:`scope3d.sensor.camera_models`); names : its parameters' names.
    width, height : int, image size (px).
    values : (p,) fitted intrinsics. covariance : (p, p), marginal over the views' poses, from
        ``sigma^2 (J^T J)^-1`` with ``sigma^2`` the residual variance. std : (p,) its square roots.
    opencv_std : (p,) or None, OpenCV's ``stdDeviationsIntrinsics`` (pinhole family), an independent check.
    rms_px : float, RMS reprojection error over every used corner (per coordinate pair, OpenCV's).
    views : names of the used views; view_rms_px : (n_views,) their RMS.
    poses : cam_from_board of each used view. pixels, residuals_px : per used view (N_i, 2) corner
        pixels and (observed - predicted) residuals.
    rejected : {image name: why it was not used}.
    """

    model: str
    names: tuple[str, ...]
    width: int
    height: int
    values: np.ndarray
    covariance: np.ndarray
    opencv_std: np.ndarray | None
    rms_px: float
    views: list[str]
    view_rms_px: np.ndarray
    poses: list[Pose]
    pixels: list[np.ndarray]
    residuals_px: list[np.ndarray]
    rejected: dict[str, str] = field(default_factory=dict)
    mask_radius_px: float | None = None

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))

    def camera(self) -> Camera:
        """The fitted Camera, of the calibrated model."""
        return Camera.from_params(self.width, self.height, self.model, self.values, mask_radius_px=self.mask_radius_px)

    def bounds(self, k_sigma: float = 3.0) -> tuple[np.ndarray, np.ndarray]:
        """(lower, upper) (p,): ``value -+ k_sigma * std`` per parameter."""
        if not k_sigma > 0:
            raise ValueError("k_sigma must be positive")
        return self.values - k_sigma * self.std, self.values + k_sigma * self.std

    def summary(self) -> str:
        parts = ", ".join(f"{n}={v:.5g}±{s:.2g}" for n, v, s in zip(self.names, self.values, self.std))
        return (f"{self.model}: RMS {self.rms_px:.3f} px over {len(self.views)} views "
                f"({len(self.rejected)} rejected); {parts}")


def calibrate(detections: list[BoardDetection], board: BoardSpec, image_size: tuple[int, int], *,
              options: CalibrationOptions = CalibrationOptions(), mask_radius_px: float | None = None,
              ) -> Calibration:
    """Fit intrinsics to the detected corners; drop outlier views; compute the intrinsics' covariance.

    image_size : (width, height) px. Raises InputError naming the images without a board and the count
    left when fewer than ``options.min_views`` views remain.
    """
    width, height = int(image_size[0]), int(image_size[1])
    rejected = {d.name: d.reason for d in detections if not d.found}
    usable = [d for d in detections if d.found]
    _check_enough(usable, rejected, options)
    obj_all = board.object_points()
    model = CAMERA_MODEL_OF[options.model]
    while True:
        fit = _fit(usable, obj_all, (width, height), model)
        view_rms = np.array([np.sqrt(np.mean(np.sum(r * r, axis=1))) for r in fit["residuals"]])
        limit = max(options.outlier_ratio * float(np.median(view_rms)), options.outlier_floor_px)
        worst = int(np.argmax(view_rms))
        if view_rms[worst] <= limit or len(usable) <= options.min_views:
            break
        rejected[usable[worst].name] = (f"outlier view: RMS {view_rms[worst]:.2f} px > {limit:.2f} px "
                                        f"({options.outlier_ratio:g} x the median view's)")
        del usable[worst]
    jac = _jacobian(fit, usable, obj_all, model)
    residuals = np.concatenate([r.ravel() for r in fit["residuals"]])
    covariance = _intrinsic_covariance(jac, residuals, len(fit["values"]))
    return Calibration(
        model=model, names=lens_model(model).param_names,
        width=width, height=height, values=fit["values"], covariance=covariance,
        opencv_std=fit.get("opencv_std"), rms_px=float(np.sqrt(np.mean(residuals ** 2) * 2.0)),
        views=[d.name for d in usable], view_rms_px=view_rms, poses=fit["poses"],
        pixels=[d.pixels for d in usable], residuals_px=fit["residuals"], rejected=rejected,
        mask_radius_px=mask_radius_px,
    )


def _check_enough(usable, rejected, options):
    if len(usable) >= options.min_views:
        return
    missing = ", ".join(sorted(rejected)) or "none"
    raise InputError(f"only {len(usable)} usable board view(s), need {options.min_views}; "
                     f"board not found in {len(rejected)} image(s): {missing}")


# OpenCV's calibrateCamera flags per pinhole-family model; its distortion vector is (k1, k2, p1, p2, k3[, k4,
# k5, k6]) and stdDeviationsIntrinsics (fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6, ...): the models'
# parameters are their first 6, 8 and 12 entries (FULL_OPENCV's order is OpenCV's).
_OPENCV_FLAGS = {
    "pinhole_radial_k1k2": cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K3,
    "OPENCV": cv2.CALIB_FIX_K3,
    "FULL_OPENCV": cv2.CALIB_RATIONAL_MODEL,
}


def _fit(usable, obj_all, size, model):
    obj = [obj_all[d.corner_ids].astype(np.float64).reshape(-1, 1, 3) for d in usable]
    img = [d.pixels.astype(np.float64).reshape(-1, 1, 2) for d in usable]
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    p = lens_model(model).num_params
    try:
        if model in _OPENCV_FLAGS:
            out = cv2.calibrateCameraExtended(
                [o.astype(np.float32) for o in obj], [i.astype(np.float32) for i in img], size, None, None,
                flags=_OPENCV_FLAGS[model], criteria=criteria)
            _, k, dist, rvecs, tvecs, std_intr = out[:6]
            values = np.array([k[0, 0], k[1, 1], k[0, 2], k[1, 2], *dist.ravel()[:p - 4]])
            opencv_std = np.asarray(std_intr, dtype=float).ravel()[:p]
        else:
            opencv_std = None
            try:
                flags = cv2.CALIB_RECOMPUTE_EXTRINSIC | cv2.CALIB_FIX_SKEW
                # OpenCV 5's fisheye functions want (1, N, C) point arrays.
                _, k, dist, rvecs, tvecs = cv2.fisheye.calibrate(
                    [o.reshape(1, -1, 3) for o in obj], [i.reshape(1, -1, 2) for i in img], size, None, None,
                    flags=flags, criteria=criteria)
                values = np.array([k[0, 0], k[1, 1], k[0, 2], k[1, 2], *np.asarray(dist).ravel()[:4]])
            except cv2.error:
                # cv2.fisheye's per-view initialisation can fail outright on a very wide lens (an assertion
                # in InitExtrinsics: 1 of 20 rendered 165 deg sets). Start instead from the radial pinhole
                # fit's focal length and principal point, no distortion, and let _polish find every pose from
                # the rays and fit the fisheye.
                radial = _fit(usable, obj_all, size, "pinhole_radial_k1k2")["values"]
                values = np.concatenate([radial[:4], np.zeros(4)])
                rvecs, tvecs = [np.zeros(3)] * len(usable), [np.array([0.0, 0.0, 1.0])] * len(usable)
    except cv2.error as exc:
        first = str(exc).strip().splitlines()[-1] if str(exc).strip() else "failed"
        raise InputError(f"calibration of {len(usable)} views failed in OpenCV ({first})") from None
    poses = [Pose.from_rotvec(np.ravel(r), np.ravel(t)) for r, t in zip(rvecs, tvecs)]
    fit = {"values": values, "poses": poses, "opencv_std": opencv_std}
    fit["residuals"] = [d.pixels - project(model, values, p, obj_all[d.corner_ids]) for d, p in zip(usable, poses)]
    return _polish(fit, usable, obj_all, model)


def _sum_sq(residuals: list[np.ndarray]) -> float:
    return float(sum(np.sum(r * r) for r in residuals))


def _polish(fit: dict, usable, obj_all, model: str) -> dict:
    """OpenCV's fit, then each view's pose solved again from its corners' rays through the fitted lens
    (where that fits the view better) and everything refined jointly by Levenberg-Marquardt with the model's
    analytic Jacobians. cv2.fisheye.calibrate initialises from a pinhole homography, which on a 150-170 deg
    lens can leave a view's pose in a wrong minimum (56 px RMS on one rendered view while the others had
    0.3 px); a pose from the rays starts it in the right one. The result is kept only when its sum of
    squares is lower than OpenCV's, so scope3d never fits worse than OpenCV on the same corners."""
    lens = lens_model(model)
    values = fit["values"]
    poses = list(fit["poses"])
    for i, d in enumerate(usable):
        rays = lens.unproject(values, d.pixels)
        front = rays[:, 2] > 0.1  # PnP on normalised coordinates needs rays well in front of the camera
        if front.sum() < 6:
            continue
        ok, rvec, tvec = cv2.solvePnP(obj_all[d.corner_ids][front], rays[front, :2] / rays[front, 2:],
                                      np.eye(3), None, flags=cv2.SOLVEPNP_ITERATIVE)
        if not ok:
            continue
        candidate = Pose.from_rotvec(np.ravel(rvec), np.ravel(tvec))
        now = _sum_sq([d.pixels - project(model, values, poses[i], obj_all[d.corner_ids])])
        new = _sum_sq([d.pixels - project(model, values, candidate, obj_all[d.corner_ids])])
        if np.isfinite(new) and not new >= now:  # also where the current pose puts corners out of view (NaN)
            poses[i] = candidate
    p, n_views = len(values), len(usable)
    x0 = np.concatenate([values] + [np.concatenate([q.rotvec, q.translation]) for q in poses])

    def unpack(x):
        return x[:p], [Pose.from_rotvec(x[p + 6 * v:p + 6 * v + 3], x[p + 6 * v + 3:p + 6 * v + 6])
                       for v in range(n_views)]

    def residuals(x):
        vals, ps = unpack(x)
        r = np.concatenate([(d.pixels - project(model, vals, q, obj_all[d.corner_ids])).ravel()
                            for d, q in zip(usable, ps)])
        return np.where(np.isfinite(r), r, 1e6)  # a corner pushed out of the lens's field: far off

    def jacobian(x):
        vals, ps = unpack(x)
        return _jacobian({"values": vals, "poses": ps}, usable, obj_all, model)

    try:
        sol = least_squares(residuals, x0, jac=jacobian, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15,
                            max_nfev=200 * len(x0))
    except ValueError:  # fewer residuals than parameters: OpenCV's fit stands
        return fit
    vals, ps = unpack(sol.x)
    res = [d.pixels - project(model, vals, q, obj_all[d.corner_ids]) for d, q in zip(usable, ps)]
    if not np.isfinite(_sum_sq(res)) or _sum_sq(res) >= _sum_sq(fit["residuals"]):  # NaN before: not >=
        return fit
    try:
        Camera.from_params(1, 1, model, vals)  # positive focal lengths, finite parameters
    except ValueError:
        return fit
    return {"values": vals, "poses": ps, "opencv_std": fit["opencv_std"], "residuals": res}


def project(model: str, values: np.ndarray, pose: Pose, points: np.ndarray) -> np.ndarray:
    """(N, 3) mm board points -> (N, 2) pixels through camera model ``model`` with parameters ``values``
    at ``pose``."""
    return lens_model(model).project(values, pose.transform(points))


def _jacobian(fit, usable, obj_all, model):
    """(2 N, p + 6 V) d residual / d (intrinsics, each view's (w, t)); rows ordered like the residuals."""
    p = len(fit["values"])
    n_views = len(usable)
    blocks = []
    for v, (d, pose) in enumerate(zip(usable, fit["poses"])):
        pts = obj_all[d.corner_ids]
        n = pts.shape[0]
        jac = np.zeros((2 * n, p + 6 * n_views))
        _, _, d_pose, d_intr = project_world_with_jacobians(
            model, fit["values"], pts, np.broadcast_to(pose.rotvec, pts.shape),
            np.broadcast_to(pose.translation, pts.shape))
        jac[:, :p] = d_intr.reshape(2 * n, p)
        jac[:, p + 6 * v:p + 6 * v + 6] = d_pose.reshape(2 * n, 6)
        blocks.append(-jac)  # residual = observed - predicted
    return np.concatenate(blocks, axis=0)


def _intrinsic_covariance(jac: np.ndarray, residuals: np.ndarray, p: int) -> np.ndarray:
    """Marginal covariance of the first ``p`` parameters: sigma^2 (J^T J)^-1 (Gauss-Newton at the optimum),
    sigma^2 = |r|^2 / (rows - columns), the unbiased residual variance per coordinate."""
    dof = jac.shape[0] - jac.shape[1]
    if dof <= 0:
        raise InputError(f"{jac.shape[0] // 2} corners cannot determine {jac.shape[1]} parameters")
    sigma2 = float(residuals @ residuals) / dof
    # Scale columns (pixels vs unitless distortion terms), then invert through the SVD of the Jacobian itself,
    # not of J^T J: the rational model's numerator and denominator terms nearly cancel (condition ~1e7 of J,
    # 1e14 of J^T J), and truncating J^T J's small eigenvalues would drop exactly the large variances of
    # those directions (sigma of k1 0.01 where the error was 2.7). Only directions the data leave undetermined
    # to rounding (singular values under eps * size of the largest) are dropped.
    scale = np.linalg.norm(jac, axis=0)
    scale[scale == 0] = 1.0
    js = jac / scale
    _, sv, vt = np.linalg.svd(js, full_matrices=False)
    keep = sv > sv[0] * np.finfo(float).eps * max(js.shape)
    cov_s = (vt[keep].T / sv[keep] ** 2) @ vt[keep]
    cov = cov_s / np.outer(scale, scale)
    return sigma2 * cov[:p, :p]
