"""The surgical-field map: a metric, textured, multimodal 3-D model of the field from a robot-held scope.

Method (reference chapters 3, 4 and 6), one stage per function, run top to bottom by :func:`run`:

1. :func:`detect_features` — SIFT on every reflectance frame, inside the scope's circular field.
2. :func:`match_frames` — frame pairs that overlap, found from the measured poses and a depth prior
   (itself estimated from a few exhaustively matched close pairs); then *feature position prediction*:
   each feature is searched only near the epipolar segment the poses predict, with a window sized by
   the pose tolerance; ratio test 0.8 and RANSAC. Poses whose tolerance makes that window wide are
   first adjusted by BCBA on a coarse pass (the reference's "combination algorithm", sec. 3.5).
3. :func:`reconstruct` — tracks by union-find, multi-view triangulation with the measured poses, then
   bundle adjustment in one of three pose modes: ``fixed`` (poses trusted, points refined — the
   reference's chapter 3-4 method), ``free`` (conventional BA, gauge fixed by the first camera and one
   coordinate of the farthest), ``bounded`` (BCBA, chapter 6: every pose scalar kept within its measured
   tolerance). Observations that still reproject badly are dropped and the adjustment is repeated once.
   Points that stand off their neighbours' surface (wrong matches along the epipolar line) are dropped.
4. :func:`build_surface` — a thin-plate-spline height field through the points, meshed on a grid and
   textured from each vertex's best view.
5. :func:`map_targets` — fluorescence thresholded and cleaned per frame, voted onto the surface,
   labelled and measured (centroid, area, star edge or disc diameter).
6. :func:`evaluate_map` — where ground truth exists: distances to the true surface, direct and after
   ICP from eight starts, pose errors, targets against the true ones.
7. :func:`write_outputs` — report.json, PLYs, COLMAP text model, targets CSV/JSON, figures.

Units: mm and radians inside; pixels with their origin at the top-left pixel's centre.
"""
from __future__ import annotations

import csv
import io
import json
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from scope3d.errors import InputError
from scope3d.estimators.averaging import gauge_centred_in_boxes, gauge_from_measurements
from scope3d.estimators.triangulation import TrackOptions, reprojection_errors, triangulate_tracks
from scope3d.feature.depth_prior import DepthPrior, window_radius_px
from scope3d.feature.detection import FEATURE_PRESETS, FeatureOptions, Features, detect
from scope3d.feature.matching import MatchOptions, PairMatches, match_exhaustive, match_pairs
from scope3d.feature.pairs import PairOptions, fov_samples, select_pairs
from scope3d.feature.tracks import build_tracks
from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import rotvec_to_matrix
from scope3d.io.dataset import Dataset
from scope3d.io.images import write_image
from scope3d.io.ply import write_ply
from scope3d.metrology.evaluation import (
    EvaluationOptions,
    distance_summary,
    icp_from_initial_poses,
    save_error_histogram_png,
    save_error_map_png,
)
from scope3d.metrology.fluorescence import FluorescenceOptions, Target, auto_threshold
from scope3d.metrology.fluorescence import map_targets as _targets_on_surface
from scope3d.metrology.fluorescence import match_targets, overlay, segment
from scope3d.scene.mesh import PointCloud, SampledSurface
from scope3d.scene.surface import Surface, SurfaceOptions, fit_surface, off_surface_points, save_depth_map_png, texture
from scope3d.scene.tracks import Tracks
from scope3d.sensor.camera import Camera
from scope3d.sensor.pose_tolerance import MeasuredPose, PoseTolerance
from scope3d.sfm.coarse_poses import CoarseOptions, CoarseResult, coarse_poses
from scope3d.sfm.depth_priors import box_depth_prior, estimate_depth_prior
from scope3d.utils.atomic import atomic_directory

POSE_MODES = ("fixed", "free", "bounded")
MATCHERS = ("guided", "exhaustive")


@dataclass(frozen=True)
class BundleStageOptions:
    """Bundle adjustment as the map uses it.

    max_iterations : int, LM iterations per adjustment (default 60: exact poses converge in a few,
        a robot's poses several mm off need ~50 in the first round).
    loss_scale_px : float, Huber loss scale (default 1.0 px: SIFT localisation ~0.3-0.5 px, so a
        residual beyond 1 px is downweighted as a likely wrong match).
    max_points : int, the adjustment uses at most this many tracks, the longest first (default 6000):
        poses are fixed by a few thousand well-spread points; the rest are re-triangulated with the
        adjusted poses, which is exact for them and costs nothing. It does not bound the map's points:
        every track is re-triangulated after the adjustment (500 or 100 000 give the same points).
    refine_intrinsics : bool, let the intrinsics move (default False: the scope is calibrated, and
        with a short-baseline survey focal length and depth trade off).
    align_gauge : bool, after free or bounded BA with inexact poses, move the map to the similarity
        frame that best fits all measured camera centres (:func:`align_gauge`; default True).
    settled_mm, settled_rad : no second adjustment round when no camera moved more than ``settled_mm``
        in the first and none turned more than ``settled_rad`` (defaults 0.02 mm, twice a micro-stage's
        tolerance, and 2e-4 rad, which moves a point by a tenth of a pixel at a focal length of 600 px).
    """

    max_iterations: int = 60
    loss_scale_px: float = 1.0
    max_points: int = 6000
    refine_intrinsics: bool = False
    align_gauge: bool = True
    settled_mm: float = 0.02
    settled_rad: float = 2e-4

    def __post_init__(self) -> None:
        if self.max_iterations < 0 or self.loss_scale_px <= 0 or self.max_points < 10:
            raise ValueError("need max_iterations >= 0, loss_scale_px > 0, max_points >= 10")


@dataclass(frozen=True)
class MapOptions:
    """Everything the map pipeline can be told, with documented defaults per stage.

    pose_mode : "fixed" | "free" | "bounded" (default "bounded": BCBA, which reduces to "fixed" for
        exact poses and uses the tolerance otherwise).
    matcher : "guided" (feature position prediction, default) or "exhaustive" (the baseline).
    depth_prior : DepthPrior or None (default None: estimated from the data).
    surface, fluorescence : bool, build the surface / the targets (default True; a photograph ring
        around an object, like Middlebury's temple, is not a height field and turns them off).
    figures : bool, write PNG figures (default True).
    threads : int, threads for per-frame feature detection (default 2, the machine's cores).
    surface_prior : bool, two-pass guided matching with a coarse-surface depth band (default True;
        needs a scene that is a height field seen from one side, false for a ring around an object).
    surface_band_mm : float, added to the band around the coarse surface for the detail it smooths
        away (default 0.5 mm).
    use_bounding_box : bool, bounding_box_margin_mm : float, use the dataset's ``bounding_box_mm``
        (when its metadata has one) as the depth prior, enlarged by the margin (default True, 5 mm).
    refine_poses_for_matching : bool, when the pose tolerance widens the search window, find overlap
        and poses from the images first (the coarse pass, ``coarse``), adjust the poses by BCBA on its
        matches and predict the fine pass with them (:func:`_match_with_image_poses`; default True).
        False: the measured poses guide matching whatever their tolerance (the baseline).
    """

    pose_mode: str = "bounded"
    matcher: str = "guided"
    depth_prior: DepthPrior | None = None
    features: FeatureOptions = field(default_factory=FeatureOptions)
    pairs: PairOptions = field(default_factory=PairOptions)
    matching: MatchOptions = field(default_factory=MatchOptions)
    coarse: CoarseOptions = field(default_factory=CoarseOptions)
    tracks: TrackOptions = field(default_factory=TrackOptions)
    bundle: BundleStageOptions = field(default_factory=BundleStageOptions)
    surface_options: SurfaceOptions = field(default_factory=SurfaceOptions)
    fluorescence_options: FluorescenceOptions = field(default_factory=FluorescenceOptions)
    evaluation: EvaluationOptions = field(default_factory=EvaluationOptions)
    surface: bool = True
    fluorescence: bool = True
    figures: bool = True
    threads: int = 2
    surface_prior: bool = True
    surface_band_mm: float = 0.5
    use_bounding_box: bool = True
    bounding_box_margin_mm: float = 5.0
    refine_poses_for_matching: bool = True

    def __post_init__(self) -> None:
        if self.pose_mode not in POSE_MODES:
            raise ValueError(f"pose_mode must be one of {POSE_MODES}, got {self.pose_mode!r}")
        if self.matcher not in MATCHERS:
            raise ValueError(f"matcher must be one of {MATCHERS}, got {self.matcher!r}")
        if self.threads < 1:
            raise ValueError("threads must be >= 1")


#: Named presets. ``dim_endoscope``: CLAHE and a lower SIFT threshold for dark frames.
#: ``photograph``: calibrated photographs around an object (no circular mask, no height-field surface,
#: the nearest neighbour in each direction of motion only, a 1 px reprojection gate).
MAP_PRESETS: dict[str, MapOptions] = {
    "default": MapOptions(),
    "dim_endoscope": MapOptions(features=FEATURE_PRESETS["dim_endoscope"]),
    "photograph": MapOptions(features=FEATURE_PRESETS["photograph"], surface=False, fluorescence=False, surface_prior=False,
                             # one partner per direction, however dense the views: points then grow with the
                             # number of views (a fixed 4 partners lost them to glued tracks as views got
                             # denser, see PairOptions). 35 deg: SIFT still matches at 40-56 deg on the
                             # Middlebury temple, but the keypoints shift with the foreshortening (two-view
                             # error median 0.23-0.56 px there, 0.08-0.22 px up to 33 deg) and the 1 px gate
                             # then costs accuracy; the limit only binds when neighbours are farther apart
                             pairs=PairOptions(min_overlap=0.2, max_pairs_per_frame=0, max_pairs_per_direction=1,
                                               max_view_angle_deg=35.0),
                             # sharp calibrated photographs, no distortion-model error: 3 sigma of SIFT's ~0.3 px
                             tracks=TrackOptions(max_reprojection_error_px=1.0)),
}


# --- stage results ----------------------------------------------------------------------------


@dataclass
class MatchingResult:
    """pairs : (i, j, overlap) selected; matches : per pair; depth_prior : used for prediction.

    guide_poses : the poses (with the tolerance their windows used) that predicted the fine pass,
        when the coarse pass and :func:`refine_poses_for_matching` ran; None when the measured poses
        guided matching throughout.
    n_rematched : fine-pass pairs that the refined windows left empty and that were matched again
        exhaustively.
    coarse : the coarse pass's result, when it ran.
    """

    pairs: list
    matches: list[PairMatches]
    depth_prior: DepthPrior | None
    time_s: float
    depth_prior_time_s: float = 0.0
    guide_poses: list[MeasuredPose] | None = None
    n_rematched: int = 0
    coarse: CoarseResult | None = None

    @property
    def n_matches(self) -> int:
        return int(sum(len(m) for m in self.matches))


@dataclass
class SparseResult:
    """The adjusted sparse model: tracks (observations, points in mm world), poses, BA results.

    n_off_surface : points dropped for standing off their neighbours' surface (:func:`_on_surface`).
    """

    tracks: Tracks
    poses: list[Pose]
    camera: Camera
    bundle_results: list
    mean_reprojection_error_px: float
    time_s: float
    n_off_surface: int = 0


@dataclass
class SurfaceResult:
    surface: Surface
    colors: np.ndarray  # (GH, GW, 3) uint8 texture
    view_map: np.ndarray  # (GH, GW) best view per vertex
    time_s: float


@dataclass
class TargetResult:
    targets: list[Target]
    fluorescent: np.ndarray  # (GH, GW) bool
    labels: np.ndarray  # (GH, GW) int32
    threshold: int
    time_s: float


@dataclass
class MapResult:
    """What :func:`run` returns: the report (also in ``out_dir/report.json``) and the in-memory model."""

    report: dict
    out_dir: Path
    features: list[Features]
    matching: MatchingResult
    sparse: SparseResult
    surface: SurfaceResult | None
    targets: TargetResult | None

    def summary(self) -> str:
        r = self.report
        lines = [f"{r['n_frames']} frames, {r['n_points']} points ({r['n_points_off_surface_dropped']} off-surface "
                 f"dropped), {r['n_observations']} observations, "
                 f"mean reprojection error {r['mean_reprojection_error_px']:.3f} px, {r['time_s']:.2f} s"]
        if "surface_error_mm" in r:
            d, i = r["surface_error_mm"]["direct"], r["surface_error_mm"]["after_icp"]
            lines.append(f"surface error: direct mean {d['mean']:.3f} mm ({100 * d['within_1mm_fraction']:.1f} % "
                         f"within 1 mm), after ICP mean {i['mean']:.3f} mm ({100 * i['within_1mm_fraction']:.1f} %)")
        if r.get("targets"):
            lines.append(f"targets: {len(r['targets'])} found")
        return "\n".join(lines)


# --- 1. features ------------------------------------------------------------------------------


def detect_features(options: MapOptions, dataset: Dataset, frames: list[np.ndarray], *, progress=None) -> list[Features]:
    """SIFT per frame (threads: OpenCV releases the GIL)."""
    def one(k):
        f = detect(frames[k], dataset.camera, options.features)
        if progress is not None:
            progress(1)
        return f

    with ThreadPoolExecutor(max_workers=options.threads) as pool:
        return list(pool.map(one, range(len(frames))))


# --- 2. matching ------------------------------------------------------------------------------


def match_frames(options: MapOptions, dataset: Dataset, features: list[Features], *, progress=None) -> MatchingResult:
    """Overlapping pairs and their matches, guided by the poses as far as their tolerance allows.

    Poses good enough to predict (a micro-stage; :func:`_poses_predict_matches`) select the pairs from
    their frusta at a depth prior and guide the matcher directly. With ``options.surface_prior`` the
    guided matcher runs in two passes: each frame's best partner first, with the global depth range; a
    coarse thin-plate surface through those points then narrows every other pair's depth range to a band
    around it (the reference predicted with a single plane; a surface predicts a curved cavity as well).

    Poses whose tolerance widens the search (a tracker, a surgical arm) go through the reference's
    "combination algorithm" (sec. 3.5) instead, :func:`_match_with_image_poses`: overlap and poses from
    the images first, BCBA inside the measured boxes, then guided matching around the adjusted poses.
    """
    t0 = time.perf_counter()
    # a scene bounding box (a calibrated object's, from the dataset) is the tightest prior there is
    depth = options.depth_prior
    box = dataset.metadata.get("bounding_box_mm") if options.use_bounding_box else None
    if depth is None and box is not None:
        depth = box_depth_prior(box[0], box[1], [m.pose for m in dataset.poses], margin_mm=options.bounding_box_margin_mm)
    guided = options.matcher == "guided" and len(dataset) >= 3
    if guided and options.refine_poses_for_matching and not all(m.tolerance.is_exact for m in dataset.poses):
        estimate = depth or _depth_prior_if_poses_predict(options, dataset, features)
        if estimate is None or not _poses_predict_matches(options, dataset, estimate):
            return _match_with_image_poses(options, dataset, features, depth, progress, t0)
        depth = estimate
    if depth is None:
        depth = estimate_depth_prior(dataset.camera, features, dataset.poses, options.matching)
    t_depth = time.perf_counter() - t0
    # the depth prior also places the frusta for pair selection, so both matchers see the same pairs
    pairs = select_pairs(dataset.camera, [m.pose for m in dataset.poses], depth, options.pairs)
    if options.matcher != "guided" or len(pairs) < 4 or not options.surface_prior:
        matches = match_pairs(dataset.camera, features, dataset.poses, pairs, depth, options.matching,
                              method=options.matcher, progress=progress)
        return MatchingResult(pairs, matches, depth, time.perf_counter() - t0, t_depth)
    first = _first_pass_pairs(pairs, len(dataset))
    rest = [k for k in range(len(pairs)) if k not in set(first)]
    m1 = match_pairs(dataset.camera, features, dataset.poses, [pairs[k] for k in first], depth, options.matching,
                     progress=progress)
    depth2 = _surface_depth_prior(options, dataset, features, m1, depth, dataset.poses)
    m2 = match_pairs(dataset.camera, features, dataset.poses, [pairs[k] for k in rest], depth2 or depth,
                     options.matching, progress=progress)
    matches: list = [None] * len(pairs)
    for k, m in zip(first, m1):
        matches[k] = m
    for k, m in zip(rest, m2):
        matches[k] = m
    return MatchingResult(pairs, matches, depth2 or depth, time.perf_counter() - t0, t_depth)


def _depth_prior_if_poses_predict(options: MapOptions, dataset: Dataset, features) -> DepthPrior | None:
    """The data's depth prior (:func:`estimate_depth_prior`), or None when the measured poses are too far
    off to triangulate the closest pairs at all (then they certainly cannot predict matches)."""
    try:
        return estimate_depth_prior(dataset.camera, features, dataset.poses, options.matching)
    except ValueError:
        return None


def _poses_predict_matches(options: MapOptions, dataset: Dataset, depth: DepthPrior) -> bool:
    """True when every frame's search window is at most twice what exact poses give (a micro-stage):
    beyond that the window holds many look-alike candidates, and adjusting the poses first pays."""
    radius = max(window_radius_px(dataset.camera, m.tolerance, m.tolerance, depth, options.matching.base_radius_px)
                 for m in dataset.poses)
    return radius <= 2.0 * options.matching.base_radius_px


def _match_with_image_poses(options: MapOptions, dataset: Dataset, features, depth: DepthPrior | None, progress,
                            t0: float) -> MatchingResult:
    """The combination algorithm for poses whose tolerance widens the search window.

    1. :func:`scope3d.sfm.coarse_poses.coarse_poses`: pairs by image similarity, exhaustive matching verified
       by the essential matrix, poses by rotation and position averaging anchored to the measurements;
    2. :func:`refine_poses_for_matching`: BCBA on those tracks inside the measured boxes, and the tolerance
       the images leave each adjusted pose;
    3. the depth prior from the adjusted points (unless the dataset gave one), pairs from the adjusted
       frusta, and guided matching of every pair in the narrow windows the adjusted poses allow, with the
       coarse surface's depth band. A pair the narrow windows leave empty is matched exhaustively; a
       verified coarse pair the frusta did not select is kept.
    """
    camera = dataset.camera
    coarse = coarse_poses(camera, features, dataset.poses, options.matching, options.coarse, progress=progress)
    guide, points_depth = refine_poses_for_matching(options, dataset, features, coarse.matches, coarse.poses)
    depth = depth or points_depth
    t_depth = time.perf_counter() - t0
    pairs = select_pairs(camera, [m.pose for m in guide], depth, options.pairs)
    band = _surface_depth_prior(options, dataset, features, coarse.matches, depth, guide) if options.surface_prior else None
    matches = match_pairs(camera, features, guide, pairs, band or depth, options.matching, progress=progress)
    lost = [k for k, m in enumerate(matches) if len(m) == 0]
    if lost:
        again = match_pairs(camera, features, guide, [pairs[k] for k in lost], depth, options.matching,
                            method="exhaustive")
        for k, m in zip(lost, again):
            matches[k] = m
    selected = {(i, j) for i, j, _ in pairs}
    for m in coarse.matches:
        if (m.i, m.j) not in selected:
            pairs.append((m.i, m.j, float(coarse.similarity[m.i, m.j])))
            matches.append(m)
    return MatchingResult(pairs, matches, band or depth, time.perf_counter() - t0, t_depth, guide, len(lost), coarse)


def _first_pass_pairs(pairs: list, n_frames: int) -> list[int]:
    """Indices of the first pass's pairs: each frame's best partner, plus the best-scored pairs that
    join what those leave apart (a maximum spanning forest, Kruskal), so that one adjustment of the
    first pass's tracks ties every frame to every other. Pairs come sorted best first."""
    chosen = set(_first_neighbour_pairs(pairs, n_frames, per_frame=1))
    parent = list(range(n_frames))

    def root(x):
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    for k in sorted(chosen):
        parent[root(pairs[k][0])] = root(pairs[k][1])
    for k, (i, j, _) in enumerate(pairs):
        if root(i) != root(j):
            parent[root(i)] = root(j)
            chosen.add(k)
    return sorted(chosen)


def _first_neighbour_pairs(pairs: list, n_frames: int, per_frame: int) -> list[int]:
    """Indices of each frame's ``per_frame`` best-scored pairs (pairs come sorted best first)."""
    count = np.zeros(n_frames, int)
    chosen = []
    for k, (i, j, _) in enumerate(pairs):
        if count[i] < per_frame or count[j] < per_frame:
            chosen.append(k)
            count[i] += 1
            count[j] += 1
    return chosen


def _surface_depth_prior(options: MapOptions, dataset: Dataset, features, matches, depth: DepthPrior,
                         poses: list[MeasuredPose]) -> DepthPrior | None:
    """A per-ray depth band around a coarse surface through the first-pass matches, triangulated with
    ``poses`` (the ones the second pass predicts with); None if too few points."""
    camera = dataset.camera
    tracks = build_tracks(features, matches)
    if tracks.n_tracks < 50:
        return None
    tracks = triangulate_tracks(camera, [m.pose for m in poses], tracks, _tolerant_gate(options, camera, poses, depth))
    if tracks.n_tracks < 50:
        return None
    coarse = SurfaceOptions(grid_step_mm=max(4 * options.surface_options.grid_step_mm, 0.5),
                            control_cell_mm=2 * options.surface_options.control_cell_mm, max_control_points=800,
                            max_extrapolation_mm=3.0)
    towards = -np.mean([m.pose.optical_axis for m in dataset.poses], axis=0)
    try:
        surface = fit_surface(tracks.points, coarse, towards=towards)
    except ValueError:
        return None
    stn = surface.to_plane(tracks.points)
    resid = stn[:, 2] - surface.height_at(stn[:, :2])
    resid = resid[np.isfinite(resid)]
    # band: the spread of the points about the coarse surface (robust, 4 sigma), what a measured pose
    # may be off along the normal, and the shape detail the coarse fit smooths away
    pos_tol = max(float(np.linalg.norm(m.tolerance.position_mm)) for m in poses)
    band = 4.0 * 1.4826 * float(np.median(np.abs(resid - np.median(resid)))) + pos_tol + options.surface_band_mm
    if not np.isfinite(band):
        return None
    return DepthPrior(depth.near_mm, depth.far_mm, per_ray=surface.depth_band(band))


def _tolerant_gate(options: MapOptions, camera: Camera, poses: list[MeasuredPose], depth: DepthPrior) -> TrackOptions:
    """The track options with the reprojection gate widened by what the poses' tolerance can cause
    (capped at 200 px), for triangulating with poses that are not yet adjusted."""
    slack = max(_pose_error_px(camera, m.tolerance, depth) for m in poses)
    return replace(options.tracks, max_reprojection_error_px=options.tracks.max_reprojection_error_px + min(slack, 200.0))


def refine_poses_for_matching(options: MapOptions, dataset: Dataset, features: list[Features],
                              matches: list[PairMatches], start: list[Pose]) -> tuple[list[MeasuredPose], DepthPrior]:
    """Poses for predicting the fine matching pass: BCBA on the coarse pass's tracks.

    The reference's "combination algorithm" (sec. 3.5): treat the robot's poses as constrained unknowns
    rather than truth. The coarse tracks are triangulated with the ``start`` poses (the coarse pass's
    averaging), with a reprojection gate of 3 robust sigma of their own errors (the start is good to a
    fraction of a millimetre, not to a pixel); BCBA inside the measured boxes, starting there, adjusts
    poses and points; the tracks are triangulated again with the strict gate and adjusted once more.

    Each adjusted pose carries the tolerance the images leave it: its covariance relative to the other
    cameras (:func:`scope3d.estimators.bundle.covariance.relative_pose_covariances`; a frame tied to the rest by one
    small patch reprojects well and is still poorly fixed) carried into the image
    (:func:`_projection_sigma_px`), 3 sigma, expressed as the camera shift that moves a point at the
    nearest depth that far; at most the measured tolerance. Frames the coarse pass did not reach keep
    their measurement.
    Returns the guide poses and the depth prior of the adjusted points (2nd-98th depth percentile of
    every observation, widened by 10 %). Raises InputError when the coarse pass left too few points.
    """
    from scope3d.estimators.bundle.covariance import relative_pose_covariances

    camera, measured = dataset.camera, dataset.poses
    tracks = build_tracks(features, matches, min_track_length=options.tracks.min_track_length)
    loose = replace(options.tracks, max_reprojection_error_px=1e6, min_angle_deg=0.5 * options.tracks.min_angle_deg)
    tracks = triangulate_tracks(camera, start, tracks, loose)
    if tracks.n_tracks >= 50:
        err = reprojection_errors(camera, start, tracks)
        gate = max(options.tracks.max_reprojection_error_px, 3.0 * float(np.median(err)) / 1.1774)
        tracks = triangulate_tracks(camera, start, tracks, replace(loose, max_reprojection_error_px=gate))
    if tracks.n_tracks < 50:
        raise InputError(f"{dataset.root}: the frames share too few features to map "
                         f"({tracks.n_tracks} points from {len(matches)} verified pairs)")
    fixed_intrinsics = replace(options, bundle=replace(options.bundle, refine_intrinsics=False))
    poses = start
    for strict in (False, True):
        if strict:
            tracks = triangulate_tracks(camera, poses, tracks, replace(options.tracks, min_angle_deg=loose.min_angle_deg))
        problem, result = _adjust(fixed_intrinsics, "bounded", measured, camera, tracks, poses)
        poses = result.poses
    tracks = triangulate_tracks(camera, poses, tracks, replace(options.tracks, min_angle_deg=loose.min_angle_deg))
    z = np.einsum("mi,mi->m", np.stack([p.rotation[2] for p in poses])[tracks.frame], tracks.points[tracks.track]) \
        + np.stack([p.translation[2] for p in poses])[tracks.frame]
    z = z[z > 0]
    near, far = np.percentile(z, [2.0, 98.0])
    depth = DepthPrior(max(0.9 * near, 1e-3), 1.1 * far)
    # what the images leave each pose free to do relative to the others, as pixels of reprojection
    covariances = relative_pose_covariances(problem, result.parameters, loss_scale_px=options.bundle.loss_scale_px)
    f = max(camera.fx, camera.fy)
    guide = []
    for m, pose, cov in zip(measured, poses, covariances):
        if m.tolerance.is_exact or not np.all(np.isfinite(cov)):
            guide.append(m)
            continue
        # the camera shift that moves a point at the nearest depth by 3 sigma (per axis, so that the box's
        # half-diagonal is the shift: f * |dp| / z_near = 3 sigma); the orientation is then part of it
        shift = 3.0 * _projection_sigma_px(camera, pose, cov, depth) * depth.near_mm / f / np.sqrt(3.0)
        guide.append(MeasuredPose(pose, PoseTolerance(np.minimum(shift, m.tolerance.position_mm),
                                                      np.zeros(3))))
    return guide, depth


def _projection_sigma_px(camera: Camera, pose: Pose, covariance: np.ndarray, depth: DepthPrior, *,
                         samples_per_side: int = 5) -> float:
    """The largest standard deviation (px) with which a pose of covariance (6, 6) over ``(w, centre)``
    (w: a left rotation ``exp(w) R``) moves the image of a point, over a grid of pixels at the depth
    prior's near and far ends. Correlated rotation and translation errors partly cancel in the image,
    which is what matters to a matcher; their separate sigmas would not say so."""
    pix = fov_samples(camera, samples_per_side)
    world = np.concatenate([(camera.unproject(pix, np.full(len(pix), z)) - pose.translation) @ pose.rotation
                            for z in (depth.near_mm, depth.far_mm)])
    base = camera.project_world(pose, world)
    step = 1e-6
    jac = np.empty((len(world), 2, 6))
    for a in range(6):  # central differences along each pose scalar
        ends = []
        for sign in (1.0, -1.0):
            d = np.zeros(6)
            d[a] = sign * step
            moved = Pose.from_centre(rotvec_to_matrix(d[:3]) @ pose.rotation, pose.centre + d[3:])
            ends.append(camera.project_world(moved, world))
        jac[:, :, a] = (ends[0] - ends[1]) / (2 * step)
    cov_px = jac @ covariance @ np.swapaxes(jac, 1, 2)
    ok = np.all(np.isfinite(base), axis=1)
    return float(np.sqrt(np.linalg.eigvalsh(cov_px[ok])[:, -1].max())) if ok.any() else np.inf


# --- 3. tracks, triangulation, bundle adjustment ------------------------------------------------


def _pose_error_px(camera: Camera, tolerance: PoseTolerance, depth: DepthPrior | None) -> float:
    """Reprojection error (px) that a pose error within ``tolerance`` can cause at the nearest depth."""
    if depth is None or tolerance.is_exact:
        return 0.0
    f = max(camera.fx, camera.fy)
    dp, dw = np.linalg.norm(tolerance.position_mm), np.linalg.norm(tolerance.orientation_rad)
    return float(2.0 * (f * dp / depth.near_mm + f * dw)) if np.isfinite(dp + dw) else np.inf


def _bundle_problem(mode: str, measured: list[MeasuredPose], camera: Camera, tracks: Tracks, refine_intrinsics: bool,
                    start: list[Pose] | None = None):
    """The bundle problem of ``mode`` on ``tracks``.

    bounded : the measured boxes, starting from ``start`` (clipped into them) when given;
    free : conventional BA from ``start`` (default: the measured poses), gauge fixed on the start;
    fixed : the measured poses held.
    """
    from scope3d.estimators.bundle import BundleProblem

    pts = tracks.points
    if mode == "bounded":
        problem = BundleProblem.from_measured_poses(
            measured, camera, pts, tracks.pixels, tracks.frame, tracks.track, refine_intrinsics=refine_intrinsics)
        if all(not np.isfinite(m.tolerance.position_mm).all() for m in measured):
            _fix_gauge(problem, [m.pose for m in measured])
        if start is not None:
            problem.start_from(start)
        return problem
    base = [m.pose for m in measured] if mode == "fixed" or start is None else start
    rot = np.stack([p.rotation for p in base])
    trans = np.stack([p.translation for p in base])
    problem = BundleProblem(tracks.pixels, tracks.frame, tracks.track, rot, trans, pts, camera.intrinsics)
    if not refine_intrinsics:
        problem.fix("intrinsics")
    if mode == "fixed":
        problem.fix("pose")
    else:
        _fix_gauge(problem, base)
    return problem


def _fix_gauge(problem, poses: list[Pose]) -> None:
    """Conventional BA's gauge: the first camera's pose, and the scale through one position coordinate
    of the camera farthest from it (along the axis where they differ most)."""
    problem.fix("pose", [0])
    centres = np.stack([p.centre for p in poses])
    d = np.abs(centres - centres[0])
    far = int(np.argmax(d.max(axis=1)))
    if far != 0:
        problem.fix("pose", [far], [("px", "py", "pz")[int(np.argmax(d[far]))]])


def _adjust(options: MapOptions, mode: str, measured: list[MeasuredPose], camera: Camera, tracks: Tracks,
            start: list[Pose]):
    """One bundle adjustment of the strongest tracks in ``mode`` from ``start``; returns (problem, result)."""
    from scope3d.estimators.bundle import SolverOptions, solve

    solver = SolverOptions(max_iterations=options.bundle.max_iterations, loss="huber",
                           loss_scale_px=options.bundle.loss_scale_px)
    problem = _bundle_problem(mode, measured, camera, _strongest_tracks(tracks, options.bundle.max_points),
                              options.bundle.refine_intrinsics, start)
    return problem, solve(problem, solver)


def reconstruct(options: MapOptions, dataset: Dataset, features: list[Features], matching: MatchingResult) -> SparseResult:
    """Tracks, triangulation, bundle adjustment in ``options.pose_mode``.

    Triangulation and the adjustment start from the poses that guided matching (the coarse pass's
    adjusted poses when the tolerance was wide, else the measured ones; always the measured ones in
    ``fixed`` mode); the bounds are always the measured boxes.
    """

    t0 = time.perf_counter()
    camera = dataset.camera
    measured = dataset.poses
    tracks = build_tracks(features, matching.matches, min_track_length=options.tracks.min_track_length)
    if tracks.n_tracks == 0:
        raise InputError(f"{dataset.root}: no feature could be matched between frames (do they overlap?)")
    movable = options.pose_mode != "fixed"
    start = matching.guide_poses if movable and matching.coarse is not None else measured
    # with inexact poses and a mode that may move them, keep the observations their error can explain
    slack = max((_pose_error_px(camera, m.tolerance, matching.depth_prior) for m in start), default=0.0) if movable else 0.0
    if options.pose_mode == "free" and not np.isfinite(slack):
        slack = 50.0
    first = replace(options.tracks, max_reprojection_error_px=options.tracks.max_reprojection_error_px + min(slack, 200.0),
                    min_angle_deg=0.5 * options.tracks.min_angle_deg if movable else options.tracks.min_angle_deg)
    poses = [m.pose for m in start]
    tracks = triangulate_tracks(camera, poses, tracks, first)
    if tracks.n_tracks == 0:
        raise InputError(f"{dataset.root}: no point could be triangulated (poses inconsistent with the images?)")
    results = []
    for round_ in range(2):
        before = poses
        _, result = _adjust(options, options.pose_mode, measured, camera, tracks, poses)
        results.append(result)
        poses = result.poses
        if movable and options.bundle.align_gauge and not all(m.tolerance.is_exact for m in measured):
            poses = align_gauge(poses, measured, bounded=options.pose_mode == "bounded")
        if options.bundle.refine_intrinsics:
            camera = camera.with_intrinsics(result.intrinsics[0])
        tracks = Tracks(tracks.track, tracks.frame, tracks.feature, tracks.pixels, tracks.colors, None)
        tracks = triangulate_tracks(camera, poses, tracks, options.tracks)
        if tracks.n_tracks == 0:
            raise InputError(f"{dataset.root}: bundle adjustment left no consistent point")
        if not movable or (options.pose_mode == "bounded" and all(m.tolerance.is_exact for m in measured)):
            break  # poses cannot move: one adjustment of the points is all there is
        moved = max(p.distance_to(q)[0] for p, q in zip(poses, before))
        turned = max(p.distance_to(q)[1] for p, q in zip(poses, before))
        if moved < options.bundle.settled_mm and turned < options.bundle.settled_rad:
            break  # the poses barely moved (a micro-stage's 0.01 mm box): a second round would change nothing
    n_off_surface = 0
    if options.surface:  # the surface stage's assumption: a height field seen from one side
        keep = _on_surface(tracks, poses)
        n_off_surface = int((~keep).sum())
        tracks = tracks.subset(keep[tracks.track])
    err = reprojection_errors(camera, poses, tracks)
    return SparseResult(tracks, poses, camera, results, float(np.mean(err)), time.perf_counter() - t0, n_off_surface)


def _on_surface(tracks: Tracks, poses: list[Pose]) -> np.ndarray:
    """Mask (n_tracks,) of points consistent with their neighbours' local surface.

    A wrong match that happens to lie on the epipolar line passes RANSAC and the reprojection gate
    and triangulates millimetres off the surface (on the dome: 2 % of the points, all two-view tracks,
    2-13 mm off); :func:`scope3d.scene.surface.off_surface_points` finds them.
    """
    towards = -np.mean([p.optical_axis for p in poses], axis=0)
    return ~off_surface_points(tracks.points, towards=towards)


def align_gauge(poses: list[Pose], measured: list[MeasuredPose], *, bounded: bool = False) -> list[Pose]:
    """Express adjusted poses in the similarity frame that best fits the measured poses.

    Images fix a reconstruction only up to a similarity (rotation, translation, scale: the gauge).
    Free BA pins it to one camera's measurement; bounded BA keeps it inside the tolerance boxes, but
    where the boxes are wide compared with the trajectory, LM drifts along the scale (on the
    cable-driven-robot test the map shrank by 9 %, as the reference's Fig. 6.4 shows BA doing).
    Moving to the similarity that best fits every measured centre and orientation
    (:func:`scope3d.estimators.averaging.gauge_from_measurements`) changes no reprojection error — it is the same
    map — but uses every measurement, so their random errors average out (a common bias cannot: it is
    unobservable).

    bounded : the poses (in their boxes) must stay in their boxes. Then the placement is the
        least-squares one among those that keep every camera well inside its box
        (:func:`scope3d.estimators.averaging.gauge_centred_in_boxes`): with uniform errors the boxes' intersection
        says more than a least-squares fit alone (on the dome at +-3 mm the centres' least-squares scale
        was 7 % off); and only as much of it is applied (:meth:`scope3d.geometry.similarity.Similarity.fraction`)
        as keeps every pose inside.
    """
    if not bounded:
        return _moved(poses, gauge_from_measurements(poses, measured))
    similarity = gauge_centred_in_boxes(poses, measured)
    if not _all_in_boxes(_moved(poses, similarity), measured):
        lo, hi = 0.0, 1.0  # the identity keeps them inside; bisect for the largest step that does
        for _ in range(30):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if _all_in_boxes(_moved(poses, similarity.fraction(mid)), measured) else (lo, mid)
        similarity = similarity.fraction(lo)
    return _moved(poses, similarity)


def _moved(poses: list[Pose], similarity) -> list[Pose]:
    return [Pose(*similarity.apply_to_cam_from_world(p.rotation, p.translation)) for p in poses]


def _all_in_boxes(poses: list[Pose], measured: list[MeasuredPose]) -> bool:
    return all(m.contains(p) for p, m in zip(poses, measured))


def _strongest_tracks(tracks: Tracks, max_points: int) -> Tracks:
    """The ``max_points`` longest tracks (ties: lowest id), all their observations."""
    if tracks.n_tracks <= max_points:
        return tracks
    lengths = tracks.lengths()
    keep_ids = np.argsort(-lengths, kind="stable")[:max_points]
    keep = np.zeros(tracks.n_tracks, bool)
    keep[keep_ids] = True
    return tracks.subset(keep[tracks.track])


# --- 4. surface -------------------------------------------------------------------------------


def build_surface(options: MapOptions, dataset: Dataset, sparse: SparseResult, frames: list[np.ndarray]) -> SurfaceResult:
    """Thin-plate-spline surface through the points, textured from each vertex's best view."""
    t0 = time.perf_counter()
    towards = -np.mean([p.optical_axis for p in sparse.poses], axis=0)
    surface = fit_surface(sparse.tracks.points, options.surface_options, towards=towards)
    colors, view_map = texture(surface, sparse.camera, sparse.poses, frames)
    return SurfaceResult(surface, colors, view_map, time.perf_counter() - t0)


# --- 5. fluorescence --------------------------------------------------------------------------


def map_targets(options: MapOptions, dataset: Dataset, sparse: SparseResult, surface: SurfaceResult) -> TargetResult:
    """Segment each fluorescence frame, vote onto the surface, label and measure the targets."""
    t0 = time.perf_counter()
    fl = options.fluorescence_options
    images = [dataset.fluorescence_frame(k) for k in range(len(dataset))]
    threshold = auto_threshold(images, fl)
    valid = sparse.camera.mask()
    masks = [segment(img, threshold, fl, mask=valid) for img in images]
    targets, on, labels = _targets_on_surface(surface.surface, sparse.camera, sparse.poses, masks, fl)
    return TargetResult(targets, on, labels, threshold, time.perf_counter() - t0)


# --- 6. evaluation ----------------------------------------------------------------------------


def true_targets(scene: dict) -> list[dict]:
    """Ground-truth targets from a phantom's scene description, as ``{name, centre_mm, size_mm, shape}``."""
    out = []
    for k, t in enumerate(scene.get("targets", []) or []):
        sizes = t.get("size", {}) if isinstance(t.get("size"), dict) else {}
        centre = next((t[key] for key in ("centroid_mm", "centre_mm", "center_mm", "position_mm") if key in t), None)
        size = next((sizes[key] for key in ("edge_mm", "diameter_mm") if key in sizes), t.get("size_mm"))
        if centre is None or size is None:
            continue
        out.append({"name": t.get("name", f"#{t.get('id', k + 1)} {t.get('shape', '')}".strip()), "centre_mm": centre, "size_mm": float(size), "shape": t.get("shape"),
                    "area_mm2": t.get("area_mm2"), "projection_normal": (t.get("projection") or {}).get("n")})
    return out


def evaluate_map(options: MapOptions, dataset: Dataset, sparse: SparseResult, targets: TargetResult | None) -> dict:
    """Accuracy against the dataset's ground truth (empty dict when it has none)."""
    gt = dataset.ground_truth
    out: dict = {}
    if gt is None:
        return out
    t0 = time.perf_counter()
    if gt.poses is not None:
        dc = [np.linalg.norm(p.centre - q.centre) for p, q in zip(sparse.poses, gt.poses)]
        dr = [np.degrees(p.distance_to(q)[1]) for p, q in zip(sparse.poses, gt.poses)]
        dm = [np.linalg.norm(m.pose.centre - q.centre) for m, q in zip(dataset.poses, gt.poses)]
        out["pose_error"] = {"position_mm_mean": float(np.mean(dc)), "position_mm_max": float(np.max(dc)),
                             "orientation_deg_mean": float(np.mean(dr)), "orientation_deg_max": float(np.max(dr)),
                             "measured_position_mm_mean": float(np.mean(dm))}
    if gt.surface_path is not None:
        truth = SampledSurface(gt.surface(), options.evaluation.sample_step_mm)
        pts = sparse.tracks.points
        direct = truth.distances(pts)
        best, spread = icp_from_initial_poses(pts, truth, options.evaluation)
        aligned = truth.distances(best.apply(pts))
        out["surface_error_mm"] = {
            "direct": distance_summary(direct), "after_icp": distance_summary(aligned),
            "icp_mean_from_8_starts_mm": [round(v, 6) for v in spread],
            "icp_rotation_deg": float(np.degrees(np.linalg.norm(_rotvec(best.rotation)))),
            "icp_translation_mm": [float(v) for v in best.translation],
        }
        out["_distances"] = (direct, aligned)
    if targets is not None:
        truth_t = true_targets(gt.scene)
        if truth_t:
            out["targets_vs_truth"] = match_targets(targets.targets, truth_t)
    out["time_s"] = time.perf_counter() - t0
    return out


def _rotvec(R: np.ndarray) -> np.ndarray:
    from scope3d.geometry.rotation import matrix_to_rotvec

    return matrix_to_rotvec(R)


# --- 7. outputs -------------------------------------------------------------------------------


def write_outputs(
    options: MapOptions, dataset: Dataset, out_dir: Path, frames: list[np.ndarray], features: list[Features],
    matching: MatchingResult, sparse: SparseResult, surface: SurfaceResult | None, targets: TargetResult | None,
    evaluation: dict, timings: dict,
) -> dict:
    """Write every output file into ``out_dir`` (already a temporary folder) and return the report."""
    from scope3d.io.colmap import SparseModel, write_colmap_text

    t0 = time.perf_counter()
    tr = sparse.tracks
    err = reprojection_errors(sparse.camera, sparse.poses, tr)
    write_ply(out_dir / "points.ply", PointCloud(tr.points, tr.colors))
    per_point_err = np.bincount(tr.track, err, tr.n_tracks) / np.maximum(tr.lengths(), 1)
    model = SparseModel.from_observations(sparse.camera, dataset.names, sparse.poses, tr.points, tr.frame, tr.track,
                                          tr.pixels, colors=tr.colors, errors=per_point_err)
    write_colmap_text(model, out_dir / "sparse")
    report: dict = {
        "dataset": str(dataset.root), "n_frames": len(dataset), "pose_mode": options.pose_mode, "matcher": options.matcher,
        "n_features": int(sum(len(f) for f in features)), "n_pairs": len(matching.pairs), "n_matches": matching.n_matches,
        "depth_prior_mm": None if matching.depth_prior is None else [matching.depth_prior.near_mm, matching.depth_prior.far_mm],
        "n_points": int(tr.n_tracks), "n_observations": int(tr.n_observations),
        "n_points_off_surface_dropped": sparse.n_off_surface,
        "matching": {"poses_refined_for_matching": matching.guide_poses is not None,
                     "pairs_rematched_exhaustively": matching.n_rematched},
        "mean_track_length": float(tr.n_observations / max(tr.n_tracks, 1)),
        "mean_reprojection_error_px": float(np.mean(err)), "median_reprojection_error_px": float(np.median(err)),
        "bundle": [_bundle_summary(r) for r in sparse.bundle_results],
    }
    if surface is not None:
        s = surface.surface
        colors = surface.colors
        if targets is not None:
            colors = overlay(colors, targets.fluorescent, None, options.fluorescence_options, draw_outlines=False)
        write_ply(out_dir / "mesh.ply", s.mesh(colors))
        write_ply(out_dir / "mesh_reflectance.ply", s.mesh(surface.colors))
        d = s.height[s.valid]
        report["surface"] = {"grid": list(s.height.shape), "step_mm": s.step_mm, "n_vertices": int(s.valid.sum()),
                             "height_range_mm": float(np.ptp(d)),
                             "flatness_rms_mm": _flatness_rms(s.vertices()[s.valid]),
                             "points_flatness_rms_mm": _flatness_rms(tr.points),
                             "points_flatness_median_mm": _flatness_median(tr.points)}
        if options.figures:
            write_image(out_dir / "texture_mosaic.png", _upsample(surface.colors))
            save_depth_map_png(out_dir / "depth_map.png", s)
    if targets is not None:
        report["fluorescence_threshold"] = targets.threshold
        report["targets"] = [t.as_dict() for t in targets.targets]
        _write_targets(out_dir, targets.targets, evaluation.get("targets_vs_truth"))
        if options.figures and surface is not None:
            write_image(out_dir / "multimodal_mosaic.png",
                        overlay(_upsample(surface.colors), _upsample(targets.fluorescent), _upsample(targets.labels),
                                options.fluorescence_options))
    if evaluation:
        report.update({k: v for k, v in evaluation.items() if not k.startswith("_") and k != "time_s"})
        if "targets_vs_truth" in evaluation:
            report["targets_vs_truth"] = evaluation["targets_vs_truth"]
        if options.figures and "_distances" in evaluation:
            direct, aligned = evaluation["_distances"]
            save_error_histogram_png(out_dir / "error_histogram.png", aligned, title="distance to the true surface after ICP")
            save_error_map_png(out_dir / "error_map.png", tr.points, aligned, title="error map after ICP (mm)")
    if options.figures:
        if sparse.bundle_results:
            sparse.bundle_results[0].plot_convergence(out_dir / "ba_convergence.png",
                                                      title=f"bundle adjustment ({options.pose_mode})")
        _matches_figure(options, dataset, frames, features, matching, out_dir / "matches_with_without_prediction.png", report)
    timings["outputs"] = time.perf_counter() - t0
    report["timings_s"] = {k: round(v, 4) for k, v in timings.items()}
    report["time_s"] = round(sum(v for k, v in timings.items() if k != "evaluation"), 4)
    (out_dir / "report.json").write_text(json.dumps(report, indent=2, default=_json_default) + "\n")
    return report


def _json_default(obj):
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (np.floating, np.integer)):
        return obj.item()
    raise TypeError(f"cannot serialise {type(obj).__name__}")


def _bundle_summary(result) -> dict:
    d = result.to_dict()
    d.pop("iteration_log", None)
    d["rms_initial_px"] = float(np.sqrt(2 * result.initial_cost / max(result.problem.num_observations, 1)))
    d["rms_final_px"] = float(np.sqrt(2 * result.final_cost / max(result.problem.num_observations, 1)))
    return d


def _flatness_rms(points: np.ndarray) -> float:
    """RMS distance (mm) of points (N, 3) from their best-fit plane (0 for a perfectly flat sheet)."""
    c = points - points.mean(axis=0)
    return float(np.linalg.svd(c, compute_uv=False)[-1] / np.sqrt(len(points)))


def _flatness_median(points: np.ndarray) -> float:
    """Median distance (mm) of the points from their best-fit plane (robust to the odd wrong track)."""
    c = points - points.mean(axis=0)
    n = np.linalg.svd(c, full_matrices=False)[2][-1]
    return float(np.median(np.abs(c @ n)))


def _upsample(img: np.ndarray, factor: int = 3) -> np.ndarray:
    """Surface rasters (one pixel per 0.2 mm grid vertex) enlarged for viewing: colours bilinear,
    masks and labels nearest."""
    import cv2

    a = np.asarray(img)
    size = (a.shape[1] * factor, a.shape[0] * factor)
    if a.dtype == bool:
        return cv2.resize(a.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST).astype(bool)
    if a.dtype != np.uint8:
        return cv2.resize(a.astype(np.int32), size, interpolation=cv2.INTER_NEAREST)
    return cv2.resize(a, size, interpolation=cv2.INTER_LINEAR)


def _write_targets(out_dir: Path, targets: list[Target], vs_truth: list | None) -> None:
    rows = [t.as_dict() for t in targets]
    (out_dir / "targets.json").write_text(json.dumps({"targets": rows, "vs_truth": vs_truth}, indent=2) + "\n")
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["label", "shape", "x_mm", "y_mm", "z_mm", "area_mm2", "size_mm"])
    for t in targets:
        w.writerow([t.label, t.shape, *(f"{v:.4f}" for v in t.centroid_mm), f"{t.area_mm2:.4f}", f"{t.size_mm:.4f}"])
    (out_dir / "targets.csv").write_text(buf.getvalue())


def _matches_figure(options, dataset, frames, features, matching, path, report) -> None:
    """Matches of the best-overlapping pair with and without prediction (reference Fig. 3.4 / 4.5)."""
    if not matching.pairs:
        return
    # the pair with the most matches among those with a real baseline (a ring can hold two views from
    # one place: they match perfectly and show nothing)
    centres = np.stack([m.pose.centre for m in dataset.poses])
    spread = float(np.ptp(centres, axis=0).max())
    moved = [m for m in matching.matches if np.linalg.norm(centres[m.i] - centres[m.j]) > 0.01 * spread]
    best = max(moved or matching.matches, key=len)
    i, j = best.i, best.j
    exh = match_exhaustive(dataset.camera, features[i], features[j], options.matching, i=i, j=j)
    guided = best if options.matcher == "guided" else None
    if guided is None:
        from scope3d.feature.matching import match_guided

        guided = match_guided(dataset.camera, features[i], features[j], dataset.poses[i], dataset.poses[j],
                              matching.depth_prior, options.matching, i=i, j=j)
    report["figure_pair"] = {"frames": [i, j], "matches_with_prediction": len(guided), "matches_without_prediction": len(exh)}
    save_matches_png(path, frames[i], frames[j], features[i], features[j], [exh, guided],
                     [f"without prediction: {len(exh)} matches", f"with prediction: {len(guided)} matches"])


def save_matches_png(path, img_i, img_j, feat_i, feat_j, match_sets, titles, *, max_lines: int = 80) -> None:
    """Side-by-side pairs with lines for (a random subset of) matches, one row per match set."""
    import cv2

    rows = []
    rng = np.random.default_rng(0)
    for m, title in zip(match_sets, titles):
        canvas = np.concatenate([img_i, img_j], axis=1).copy()
        if canvas.ndim == 2:
            canvas = np.repeat(canvas[..., None], 3, axis=2)
        w = img_i.shape[1]
        idx = np.arange(len(m))
        if len(idx) > max_lines:
            idx = rng.choice(idx, max_lines, replace=False)
        for k in idx:
            p = tuple(int(v) for v in np.rint(feat_i.keypoints[m.idx_i[k]]))
            q = tuple(int(v) for v in np.rint(feat_j.keypoints[m.idx_j[k]] + [w, 0]))
            color = tuple(int(c) for c in rng.integers(60, 255, 3))
            cv2.line(canvas, p, q, color, 1, cv2.LINE_AA)
            cv2.circle(canvas, p, 3, color, 1)
            cv2.circle(canvas, q, 3, color, 1)
        cv2.putText(canvas, title, (10, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (255, 255, 0), 2, cv2.LINE_AA)
        rows.append(canvas)
    write_image(path, np.concatenate(rows, axis=0))


# --- the pipeline -----------------------------------------------------------------------------


def run(options: MapOptions, dataset: Dataset, out_dir: str | Path, *, progress=None) -> MapResult:
    """Map the surgical field of ``dataset`` into ``out_dir`` (written atomically). See the module docstring.

    progress : optional factory ``progress(total, desc)`` returning an object with ``update(n)`` and
    ``close()`` (tqdm fits), for per-frame and per-pair progress.
    """
    if len(dataset) < 2:
        raise InputError(f"{dataset.root}: need at least 2 frames to map, found {len(dataset)}")
    out_dir = Path(out_dir)
    timings: dict = {}
    tick = time.perf_counter()

    def lap(name):
        nonlocal tick
        now = time.perf_counter()
        timings[name] = now - tick
        tick = now

    frames = [dataset.frame(k) for k in range(len(dataset))]
    lap("load")
    with _progress(progress, len(frames), "features") as bar:
        features = detect_features(options, dataset, frames, progress=bar)
    lap("features")
    with _progress(progress, None, "matching") as bar:
        matching = match_frames(options, dataset, features, progress=bar)
    lap("matching")
    sparse = reconstruct(options, dataset, features, matching)
    lap("bundle")
    surface = build_surface(options, dataset, sparse, frames) if options.surface else None
    lap("surface")
    targets = None
    if options.fluorescence and surface is not None and dataset.fluorescence_paths:
        targets = map_targets(options, dataset, sparse, surface)
    lap("fluorescence")
    evaluation = evaluate_map(options, dataset, sparse, targets)
    lap("evaluation")
    with atomic_directory(out_dir) as tmp:
        report = write_outputs(options, dataset, tmp, frames, features, matching, sparse, surface, targets, evaluation, timings)
    return MapResult(report, out_dir, features, matching, sparse, surface, targets)


class _NullBar:
    def update(self, n=1):
        pass

    def close(self):
        pass

    def __call__(self, n=1):
        pass


class _progress:
    """Context manager around an optional progress-bar factory; yields a callable ``bar(n)``."""

    def __init__(self, factory, total, desc):
        self.bar = factory(total, desc) if factory is not None else _NullBar()

    def __enter__(self):
        return self.bar.update

    def __exit__(self, *exc):
        self.bar.close()
        return False
