"""Hand-eye calibration: the camera on a robot's flange, from robot poses and board views (reference
sec. 8.1, where the scope rode on a robot whose reported poses fed BCBA).

Frames: ``base`` (the robot's or tracker's world), ``flange`` (the tool the robot reports), ``cam`` and
``board``. Inputs per view ``i``: ``base_from_flange[i]`` (the robot log) and ``cam_from_board[i]`` (the
board's pose from its corners and the calibrated camera). Unknowns: ``flange_from_cam`` (X, the hand-eye
transform) and ``base_from_board`` (Y, where the board stands). Every view closes the loop
``base_from_flange[i] @ X @ cam_from_board[i] = Y`` (AX = XB).

1. Park and Martin's closed form (1994) gives X from the relative motions of every pair of views:
   rotation by the least-squares fit of the motions' rotation vectors, then translation by linear least
   squares. (OpenCV's ``cv2.calibrateHandEye`` implements it among others, but the OpenCV 5.0 Python build
   scope3d uses does not expose that function; the method is twenty lines.)
2. A joint refinement of (X, Y) minimises, over every view, the disagreement between the camera pose the
   robot predicts (``cam_from_base = X^-1 @ base_from_flange[i]^-1``) and the one the board shows
   (``cam_from_board[i] @ Y^-1``): camera centre (mm) and orientation (rad), each divided by its RMS after
   the closed form, so millimetres and radians weigh as the noise makes them (SciPy's Levenberg-Marquardt).
   Minimising the corners' reprojection error instead (robot poses taken as exact) fits the robot's
   rotation noise: on rendered views with +-0.1 deg robot noise it moved X by 0.9 deg and 0.4 mm away
   from the truth while the closed form was 0.05 deg and 0.08 mm off.
3. The residual of each view, the camera pose the robot predicts against the one the board shows, turns
   into a :class:`~scope3d.sensor.pose_tolerance.PoseTolerance` for datasets built from robot poses:
   ``cam_from_base[i] = X^-1 @ base_from_flange[i]^-1``.
4. The residuals cannot show the intrinsics' own error: a focal length off by a fraction e puts every
   board e times its distance too far, alike in every view, and X absorbs it (on the walkthrough's
   recording, fx 0.15 % long moved X 0.058 mm along the optical axis with boards ~40 mm away, while
   the residuals' RMS was 0.012 mm). Given the calibration's sigmas, X is solved again with each intrinsic
   moved by its sigma; the camera poses the robot then predicts move by that intrinsic's share, and the
   shares (taken as independent, summed in quadrature) join the residuals' RMS in the tolerance.

``Pose`` objects here are rigid transforms named ``b_from_a`` (``x_b = R x_a + t``), mm and rad.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.optimize import least_squares

from scope3d.errors import InputError
from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import matrix_to_rotvec, rotvec_to_matrix
from scope3d.sensor.camera import Camera
from scope3d.sensor.pose_tolerance import PoseTolerance

@dataclass(frozen=True)
class HandEyeOptions:
    """refine : jointly refine (X, Y) on the corners' reprojection error after the closed form (default True).
    tolerance_sigmas : the pose tolerance is this many RMS residuals per axis (3: a box that holds the
        truth for ~99 % of views if the residuals are Gaussian).
    include_intrinsics : add the intrinsics' share (module docstring, step 4) when their sigmas are given."""

    refine: bool = True
    tolerance_sigmas: float = 3.0
    include_intrinsics: bool = True

    def __post_init__(self) -> None:
        if not self.tolerance_sigmas > 0:
            raise ValueError("tolerance_sigmas must be positive")


@dataclass
class HandEyeResult:
    """flange_from_cam : X. base_from_board : Y. closed_form : X from OpenCV's method alone.
    rms_px : corner RMS reprojection error through the robot poses (after refinement).
    position_residual_mm : (n, 3) camera centre predicted by the robot minus seen by the board, base frame.
    orientation_residual_rad : (n,) angle between the predicted and the seen camera orientation.
    tolerance : the pose tolerance for datasets made from robot poses (see module docstring).
    intrinsics_share_mm, intrinsics_share_rad : (3,) per base axis, the RMS move of the predicted camera
        poses for one sigma of the intrinsics (module docstring, step 4); zeros when no sigmas were given."""

    flange_from_cam: Pose
    base_from_board: Pose
    closed_form: Pose
    rms_px: float
    position_residual_mm: np.ndarray
    orientation_residual_rad: np.ndarray
    tolerance: PoseTolerance
    intrinsics_share_mm: np.ndarray = field(default_factory=lambda: np.zeros(3))
    intrinsics_share_rad: np.ndarray = field(default_factory=lambda: np.zeros(3))

    @property
    def cam_from_flange(self) -> Pose:
        return self.flange_from_cam.inverse()

    def camera_poses(self, base_from_flange: list[Pose]) -> list[Pose]:
        """cam_from_base of each robot pose: what a dataset's poses.csv holds."""
        x_inv = self.flange_from_cam.inverse()
        return [x_inv @ b.inverse() for b in base_from_flange]

    def summary(self) -> str:
        return (f"hand-eye: RMS {self.rms_px:.3f} px; residual RMS "
                f"{np.sqrt(np.mean(self.position_residual_mm ** 2)):.3f} mm, "
                f"{np.rad2deg(np.sqrt(np.mean(self.orientation_residual_rad ** 2))):.3f} deg; intrinsics' share "
                f"{np.linalg.norm(self.intrinsics_share_mm):.3f} mm, "
                f"{np.rad2deg(np.linalg.norm(self.intrinsics_share_rad)):.3f} deg; tolerance "
                f"{np.round(self.tolerance.position_mm, 3).tolist()} mm, "
                f"{np.round(np.rad2deg(self.tolerance.orientation_rad), 3).tolist()} deg")


def board_pose(camera: Camera, object_points: np.ndarray, pixels: np.ndarray) -> Pose:
    """cam_from_board from corners (N, 2) px of board points (N, 3) mm through a calibrated camera."""
    ok, rvec, tvec = cv2.solvePnP(object_points.astype(np.float64), pixels.astype(np.float64), camera.K,
                                  camera.distortion_coeffs, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        raise InputError("board pose could not be estimated (solvePnP failed)")
    return Pose.from_rotvec(np.ravel(rvec), np.ravel(tvec))


def calibrate_hand_eye(
    base_from_flange: list[Pose],
    cam_from_board: list[Pose],
    *,
    camera: Camera,
    object_points: list[np.ndarray],
    pixels: list[np.ndarray],
    options: HandEyeOptions = HandEyeOptions(),
    intrinsic_sigmas: np.ndarray | None = None,
) -> HandEyeResult:
    """X = flange_from_cam from n >= 3 views (robot pose, board pose, the board's corners in that view).

    object_points, pixels : per view (N_i, 3) mm and (N_i, 2) px, the corners behind ``cam_from_board``.
    intrinsic_sigmas : (P,) the calibration's standard deviation of each of ``camera.params`` (NaN or 0:
        none), for the intrinsics' share of the tolerance (module docstring, step 4).
    Raises InputError for fewer than 3 views or lists of different lengths.
    """
    n = len(base_from_flange)
    if n != len(cam_from_board) or n != len(object_points) or n != len(pixels):
        raise InputError(f"{n} robot poses for {len(cam_from_board)} board views: one robot pose per view")
    if n < 3:
        raise InputError(f"hand-eye calibration needs at least 3 views with distinct rotations, got {n}")
    closed = park_martin(base_from_flange, cam_from_board)
    x, y = _solve(closed, base_from_flange, cam_from_board, options.refine)
    residuals = _reprojection(x, y, base_from_flange, camera, object_points, pixels)
    rms = float(np.sqrt(np.mean(residuals ** 2) * 2.0))
    # What the robot predicts for the camera against what the board shows, in the base frame.
    rot_axes, pos = _loop_residuals(x, y, base_from_flange, cam_from_board)
    ang = np.linalg.norm(rot_axes, axis=1)
    share_mm, share_rad = np.zeros(3), np.zeros(3)
    if intrinsic_sigmas is not None and options.include_intrinsics:
        share_mm, share_rad = _intrinsics_share(x, base_from_flange, camera, object_points, pixels,
                                                np.asarray(intrinsic_sigmas, dtype=float), options.refine)
    k = options.tolerance_sigmas
    tolerance = PoseTolerance(k * np.hypot(np.sqrt(np.mean(pos ** 2, axis=0)), share_mm),
                              k * np.hypot(np.sqrt(np.mean(rot_axes ** 2, axis=0)), share_rad))
    return HandEyeResult(x, y, closed, rms, pos, ang, tolerance, share_mm, share_rad)


def _solve(start: Pose, base_from_flange: list[Pose], cam_from_board: list[Pose], refine: bool) -> tuple[Pose, Pose]:
    """(X, Y) from the closed form's X (``start``), jointly refined when ``refine``."""
    y = _mean_pose([b @ start @ c for b, c in zip(base_from_flange, cam_from_board)])
    return _refine(start, y, base_from_flange, cam_from_board) if refine else (start, y)


def _intrinsics_share(x: Pose, base_from_flange: list[Pose], camera: Camera, object_points: list[np.ndarray],
                      pixels: list[np.ndarray], sigmas: np.ndarray, refine: bool) -> tuple[np.ndarray, np.ndarray]:
    """(3,) mm and (3,) rad per base axis: the quadrature sum over intrinsics of the RMS (over views) move
    of the robot-predicted camera pose when X is solved again with that intrinsic one sigma off."""
    if sigmas.shape != camera.params.shape:
        raise ValueError(f"{sigmas.shape[0]} intrinsic sigmas for a camera of {camera.params.shape[0]} parameters")
    nominal = [x.inverse() @ b.inverse() for b in base_from_flange]
    pos_sq, rot_sq = np.zeros(3), np.zeros(3)
    for j in np.flatnonzero(np.isfinite(sigmas) & (sigmas > 0)):
        moved = camera.with_params(camera.params + np.eye(len(sigmas))[j] * sigmas[j])
        boards = [board_pose(moved, o, p) for o, p in zip(object_points, pixels)]
        x_j, _ = _solve(park_martin(base_from_flange, boards), base_from_flange, boards, refine)
        predicted = [x_j.inverse() @ b.inverse() for b in base_from_flange]
        pos_sq += np.mean([(p.centre - q.centre) ** 2 for p, q in zip(predicted, nominal)], axis=0)
        rot_sq += np.mean([matrix_to_rotvec(q.rotation.T @ p.rotation) ** 2
                           for p, q in zip(predicted, nominal)], axis=0)
    return np.sqrt(pos_sq), np.sqrt(rot_sq)


def park_martin(base_from_flange: list[Pose], cam_from_board: list[Pose]) -> Pose:
    """Closed-form flange_from_cam (Park & Martin 1994) from the motions of every pair of views.

    For views i, j the flange moves by ``A = base_from_flange[j]^-1 @ base_from_flange[i]`` and the camera by
    ``B = cam_from_board[j] @ cam_from_board[i]^-1``; ``A X = X B``. The rotation vectors satisfy
    ``a = R_X b``, so ``R_X`` is the orthogonal Procrustes fit of the b's onto the a's; then
    ``(R_A - I) t_X = R_X t_B - t_A`` is linear in ``t_X``."""
    a_vecs, b_vecs, lhs, motions = [], [], [], []
    n = len(base_from_flange)
    for i in range(n):
        for j in range(i + 1, n):
            a = base_from_flange[j].inverse() @ base_from_flange[i]
            b = cam_from_board[j] @ cam_from_board[i].inverse()
            a_vecs.append(matrix_to_rotvec(a.rotation))
            b_vecs.append(matrix_to_rotvec(b.rotation))
            motions.append((a, b))
    a_vecs, b_vecs = np.array(a_vecs), np.array(b_vecs)
    if np.linalg.matrix_rank(b_vecs, tol=1e-3) < 2:
        raise InputError("hand-eye: the views turn about one axis only; rotate the scope about two axes")
    u, _, vt = np.linalg.svd(b_vecs.T @ a_vecs)  # sum b a^T
    r_x = vt.T @ np.diag([1.0, 1.0, np.linalg.det(vt.T @ u.T)]) @ u.T
    for a, b in motions:
        lhs.append((a.rotation - np.eye(3), r_x @ b.translation - a.translation))
    m = np.concatenate([l for l, _ in lhs])
    rhs = np.concatenate([r for _, r in lhs])
    t_x = np.linalg.lstsq(m, rhs, rcond=None)[0]
    return Pose(r_x, t_x)


def _orthonormal(r: np.ndarray) -> np.ndarray:
    u, _, vt = np.linalg.svd(np.asarray(r, dtype=float))
    return u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt


def _mean_pose(poses: list[Pose]) -> Pose:
    """Chordal mean of the rotations, mean of the translations."""
    r = _orthonormal(np.mean([p.rotation for p in poses], axis=0))
    return Pose(r, np.mean([p.translation for p in poses], axis=0))


def _pack(x: Pose, y: Pose) -> np.ndarray:
    return np.concatenate([x.rotvec, x.translation, y.rotvec, y.translation])


def _unpack(v: np.ndarray) -> tuple[Pose, Pose]:
    return (Pose(rotvec_to_matrix(v[0:3]), v[3:6]), Pose(rotvec_to_matrix(v[6:9]), v[9:12]))


def _reprojection(x, y, base_from_flange, camera, object_points, pixels) -> np.ndarray:
    x_inv = x.inverse()
    out = []
    for b, obj, px in zip(base_from_flange, object_points, pixels):
        cam_from_board = x_inv @ b.inverse() @ y
        out.append(camera.project(cam_from_board.transform(obj)) - px)
    return np.concatenate(out).ravel()


def _loop_residuals(x: Pose, y: Pose, base_from_flange, cam_from_board) -> tuple[np.ndarray, np.ndarray]:
    """(n, 3) rotation vectors (rad) and (n, 3) centre differences (mm, base frame) between the camera pose
    predicted by the robot and the one seen through the board."""
    x_inv, y_inv = x.inverse(), y.inverse()
    rot, pos = [], []
    for b, c in zip(base_from_flange, cam_from_board):
        predicted = x_inv @ b.inverse()
        seen = c @ y_inv
        rot.append(matrix_to_rotvec(seen.rotation.T @ predicted.rotation))
        pos.append(predicted.centre - seen.centre)
    return np.array(rot), np.array(pos)


def _refine(x, y, base_from_flange, cam_from_board) -> tuple[Pose, Pose]:
    rot, pos = _loop_residuals(x, y, base_from_flange, cam_from_board)
    sigma_rad = max(float(np.sqrt(np.mean(rot ** 2))), 1e-9)
    sigma_mm = max(float(np.sqrt(np.mean(pos ** 2))), 1e-9)

    def fun(v):
        xv, yv = _unpack(v)
        r, p = _loop_residuals(xv, yv, base_from_flange, cam_from_board)
        return np.concatenate([(r / sigma_rad).ravel(), (p / sigma_mm).ravel()])

    sol = least_squares(fun, _pack(x, y), method="lm", x_scale="jac")
    return _unpack(sol.x)
