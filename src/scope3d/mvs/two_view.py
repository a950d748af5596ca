"""Dense depth from one axial-stereo pair: resample, match, mask, triangulate (reference ch. 7).

:func:`reconstruct_pair` is the whole two-view method as one call on arrays; the pipeline
(:mod:`scope3d.pipelines.axial`) adds files and evaluation around it, and :mod:`scope3d.mvs.multiview`
fuses many of its results.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np

from scope3d.geometry.grid import grid_faces
from scope3d.geometry.pose import Pose
from scope3d.mvs.axial import AxialPair, PolarGridOptions, aligned_poses, make_axial_pair
from scope3d.mvs.confidence import ConfidenceOptions, Reliability, reliability
from scope3d.mvs.dense_matching import Disparity, SadOptions, SgmOptions, sad_disparity, sgm_disparity
from scope3d.sensor.camera import Camera

METHODS = ("sgm", "sad")


@dataclass(frozen=True)
class TwoViewOptions:
    """How one pair is reconstructed.

    method : "sgm" (semi-global matching + sub-pixel refinement) or "sad" (the reference's 7x7 SAD).
    min_depth_mm : float, nearest surface expected, along the motion, from the front camera; it sets the
        disparity search range ``log(1 + step / min_depth) / log_rho_step`` columns.
    assume_aligned : bool, ignore the poses' relative rotation and axis tilt and use the reference's
        aligned model (eqs. 7.3-7.4, :func:`~scope3d.mvs.axial.aligned_poses`); for comparisons only.
    max_axis_angle_deg, min_step_mm : limits of :func:`~scope3d.mvs.axial.make_axial_pair`.
    """

    method: str = "sgm"
    min_depth_mm: float = 1.0
    assume_aligned: bool = False
    max_axis_angle_deg: float = 15.0
    min_step_mm: float = 1e-3
    grid: PolarGridOptions = field(default_factory=PolarGridOptions)
    sgm: SgmOptions = field(default_factory=SgmOptions)
    sad: SadOptions = field(default_factory=SadOptions)
    confidence: ConfidenceOptions = field(default_factory=ConfidenceOptions)

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"unknown two-view method {self.method!r} (use one of {', '.join(METHODS)})")
        if not self.min_depth_mm > 0:
            raise ValueError("TwoViewOptions.min_depth_mm must be positive")


@dataclass(frozen=True)
class PairResult:
    """One pair's reconstruction on the polar grid of ``pair`` (arrays (n_angles, n_radii)).

    front_polar, rear_polar : uint8 resampled grey images.
    disparity : :class:`~scope3d.mvs.dense_matching.Disparity` (columns).
    reliability : :class:`~scope3d.mvs.confidence.Reliability`.
    range_mm : float64, distance from the front camera centre along each grid ray, NaN where masked.
    time_s : dict stage -> seconds.
    """

    pair: AxialPair
    front_polar: np.ndarray
    rear_polar: np.ndarray
    disparity: Disparity
    reliability: Reliability
    range_mm: np.ndarray
    time_s: dict

    @property
    def n_points(self) -> int:
        return int(np.count_nonzero(np.isfinite(self.range_mm)))

    def points_world(self) -> np.ndarray:
        """(n_angles, n_radii, 3) world points (mm), NaN where masked."""
        rho = self.pair.grid.radii()[None, :]
        return self.pair.points_world(self.range_mm / np.sqrt(1.0 + rho * rho))


def reconstruct_pair(
    camera: Camera,
    image_a: np.ndarray,
    image_b: np.ndarray,
    pose_a: Pose,
    pose_b: Pose,
    *,
    options: TwoViewOptions = TwoViewOptions(),
) -> PairResult:
    """Axial-stereo depth of one pair of grey frames.

    image_a, image_b : (H, W) uint8 grey frames at ``pose_a``, ``pose_b`` (cam_from_world, mm); either
    may be the front one. Raises InputError for a zero step or non-axial poses.
    """
    t0 = time.perf_counter()
    if options.assume_aligned:
        # Order the pair by the measured poses first, then replace the rear pose by the aligned model's.
        probe = make_axial_pair(camera, pose_a, pose_b, grid_options=options.grid,
                                min_step_mm=options.min_step_mm, max_axis_angle_deg=options.max_axis_angle_deg)
        rear, front = aligned_poses(probe.pose_rear, probe.pose_front)
        swapped = probe.swapped
        pair = make_axial_pair(camera, rear, front, grid_options=options.grid,
                               min_step_mm=options.min_step_mm, max_axis_angle_deg=180.0)
    else:
        pair = make_axial_pair(camera, pose_a, pose_b, grid_options=options.grid,
                               min_step_mm=options.min_step_mm, max_axis_angle_deg=options.max_axis_angle_deg)
        swapped = pair.swapped
    img_rear, img_front = (image_b, image_a) if swapped else (image_a, image_b)
    for img in (img_rear, img_front):
        if img.ndim != 2 or img.shape != (camera.height, camera.width):
            raise ValueError(f"expected a {camera.width}x{camera.height} grey image, got shape {img.shape}")
    front_polar = pair.to_polar(img_front, pair.pose_front)
    rear_polar = pair.to_polar(img_rear, pair.pose_rear)
    valid = pair.valid_polar(pair.pose_front) & pair.valid_polar(pair.pose_rear)
    t1 = time.perf_counter()
    max_disparity = np.log1p(pair.baseline_mm / options.min_depth_mm) / pair.grid.log_rho_step
    num = int(np.ceil((max_disparity + 2) / 16.0) * 16)
    if options.method == "sgm":
        disparity = sgm_disparity(front_polar, rear_polar, options=replace(options.sgm, num_disparities=num,
                                                                           wrap_rows=True))
    else:
        disparity = sad_disparity(front_polar, rear_polar, options=replace(options.sad, num_disparities=num))
    t2 = time.perf_counter()
    rel = reliability(front_polar, rear_polar, disparity.disparity, disparity.cost, disparity.sigma, pair, valid,
                      options=options.confidence)
    range_mm = pair.range_from_disparity(disparity.disparity, where=rel.mask)
    t3 = time.perf_counter()
    times = {"resample": t1 - t0, "match": t2 - t1, "triangulate": t3 - t2, "total": t3 - t0}
    return PairResult(pair, front_polar, rear_polar, disparity, rel, range_mm, times)


@dataclass(frozen=True)
class ImageDepth:
    """A polar result resampled on the front camera's pixel grid (arrays (H, W)).

    z_depth_mm : float32, z-depth in the front camera frame, NaN = none. range_mm : float32.
    points_world : (H, W, 3) float64 mm, NaN = none. confidence : float32 in [0, 1], 0 = none.
    pose : the front camera's pose.
    """

    z_depth_mm: np.ndarray
    range_mm: np.ndarray
    points_world: np.ndarray
    confidence: np.ndarray
    pose: Pose

    @property
    def valid(self) -> np.ndarray:
        return np.isfinite(self.z_depth_mm)


def to_image(pair: AxialPair, range_polar_mm: np.ndarray, confidence_polar: np.ndarray | None = None) -> ImageDepth:
    """Resample a polar range map (n_angles, n_radii) mm onto the front camera's pixels."""
    rng = pair.from_polar(range_polar_mm, pair.pose_front)
    rays_cam = pair.camera_rays().reshape(rng.shape + (3,))
    with np.errstate(invalid="ignore"):
        z = (rng * rays_cam[..., 2]).astype(np.float32)
    pts = pair.pose_front.centre + (rays_cam * rng[..., None]) @ pair.pose_front.rotation
    conf = np.zeros(rng.shape, np.float32)
    if confidence_polar is not None:
        c = pair.from_polar(np.where(np.isfinite(range_polar_mm), confidence_polar, np.nan), pair.pose_front)
        conf = np.nan_to_num(c, nan=0.0).astype(np.float32)
    return ImageDepth(z, rng, pts, conf, pair.pose_front)


def grid_mesh_faces(points: np.ndarray, range_mm: np.ndarray, *, max_edge_ratio: float = 0.05) -> np.ndarray:
    """Triangles between grid neighbours (the reference: "neighbour points along the X and Y directions").

    points : (H, W, 3) float mm, NaN = no point; range_mm : (H, W) float, distance of each point from the
    camera. Each 2x2 block of valid points gives two triangles, except across depth jumps: an edge longer
    than ``max_edge_ratio`` times its end points' range is not surface (one pixel spans ``range / f``,
    about 0.004 range for a 600-pixel image, and ~0.02 range on a wall seen at 80 deg incidence).
    Returns (F, 3) int64 indices into ``points.reshape(-1, 3)``.
    """
    h, w = points.shape[:2]
    ok = np.all(np.isfinite(points), axis=-1) & np.isfinite(range_mm)
    rng = np.nan_to_num(range_mm)

    def short(a_sl, b_sl):
        edge = np.linalg.norm(np.nan_to_num(points[a_sl] - points[b_sl]), axis=-1)
        return edge <= max_edge_ratio * np.maximum(rng[a_sl], rng[b_sl])

    # Each edge is tested once: horizontal edges serve as the top of one row of cells and the bottom of
    # the row above, vertical edges as the right of one cell and the left of the next, and the diagonal
    # is shared by both triangles (the test is symmetric in its end points).
    everything, head, tail = slice(None), slice(None, -1), slice(1, None)
    horizontal = short((everything, head), (everything, tail))  # (h, w-1)
    vertical = short((head, everything), (tail, everything))  # (h-1, w)
    diagonal = short((head, tail), (tail, head))  # tr-bl, (h-1, w-1)
    tl, tr = (head, head), (head, tail)
    bl, br = (tail, head), (tail, tail)
    quad_ok = ok[tl] & ok[tr] & ok[bl] & ok[br]
    t1 = quad_ok & horizontal[:-1] & diagonal & vertical[:, :-1]
    t2 = quad_ok & vertical[:, 1:] & horizontal[1:] & diagonal
    # cells split along the top-right/bottom-left diagonal: (tl, bl, tr) and (tr, bl, br)
    return grid_faces(h, w, anti_diagonal=True, clockwise=True, keep=(t1, t2))
