"""The surgical-field map: a metric, textured, multimodal 3-D model of the field from a robot-held scope.

Method (reference chapters 3, 4 and 6), one stage per function, run top to bottom by :func:`run`:

1. :func:`detect_features` — SIFT on every reflectance frame, inside the scope's circular field.
2. :func:`match_frames` — frame pairs that overlap, found from the measured poses and a depth prior
   (itself estimated from a few exhaustively matched close pairs); then *feature position prediction*:
   each feature is searched only near the epipolar segment the poses predict, with a window sized by
   the pose tolerance; ratio test 0.8 and RANSAC. Poses whose tolerance makes that window wide are
   first adjusted by BCBA on a coarse pass (the reference's "combination algorithm", sec. 3.5).
3. :func:`reconstruct` — tracks (connected components of the match graph), multi-view triangulation
   with the poses that guided matching, then bundle adjustment in one of three pose modes: ``fixed``
   (poses trusted, points refined — the reference's chapter 3-4 method), ``free`` (conventional BA, gauge
   fixed by the first camera and one coordinate of the farthest), ``bounded`` (BCBA, chapter 6: every
   pose scalar kept within its measured tolerance). Observations that still reproject badly are dropped
   and the adjustment is repeated once. Points that stand off their neighbours' surface (wrong matches
   along the epipolar line) are dropped, gross ones before every adjustment.
4. :func:`build_surface` — a thin-plate-spline height field through the points, meshed on a grid and
   textured from each vertex's best view. With ``MapOptions.dense`` (``map --surface dense``) also
   :func:`build_dense` — a depth map per frame from its best neighbours with the adjusted poses, fused
   where the views agree, and a Poisson mesh of the fused points that follows overhangs
   (:mod:`scope3d.mvs.dense_map`); its mesh is then the map's mesh.ply, the spline's is mesh_spline.ply.
5. :func:`locate_targets` — fluorescence thresholded and cleaned per frame, voted onto the surface,
   labelled and measured (centroid, area, star edge or disc diameter).
   :func:`check_reported_poses` — in ``bounded`` mode after the coarse pass, each reported pose tested
   against the images and the other reports (an exact leave-one-out adjustment per frame, tested at a
   stated false-alarm rate); a report
   found wrong beyond its box is replaced by what the images say, and matching and adjustment run again.
6. :func:`evaluate_map` — where ground truth exists: distances to the true surface, direct and after
   ICP from eight starts, pose errors, targets against the true ones.
7. :func:`write_outputs` — report.json, PLYs, COLMAP text model, map points with descriptors for
   localization (map_points.npz), targets CSV/JSON, figures. The figures are drawn in a child process
   (:class:`scope3d.utils.background.BackgroundCalls`): those of :func:`draw_figures` while the
   targets and the evaluation are computed, the error figures while the other files are written.

Units: mm and radians inside; pixels with their origin at the top-left pixel's centre.
"""
from __future__ import annotations

import json
import time
import zipfile
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from scope3d.errors import InputError
from scope3d.estimators.clock_offset import ClockOffset, estimate_clock_offset
from scope3d.estimators.triangulation import TrackOptions, reprojection_errors
from scope3d.feature.depth_prior import DepthPrior, window_radius_px
from scope3d.feature.detection import FEATURE_PRESETS, FeatureOptions, Features, detect
from scope3d.feature.figures import save_matches_png
from scope3d.feature.matching import MatchOptions, PairMatches, match_exhaustive, match_guided, match_pairs
from scope3d.feature.pairs import PairOptions, select_pairs, spanning_pairs
from scope3d.feature.tracks import build_tracks, observation_descriptors, track_descriptors
from scope3d.geometry.plane import plane_residuals, plane_rms
from scope3d.geometry.pose import Pose
from scope3d.io.colmap import SparseModel, write_colmap_text
from scope3d.io.dataset import Dataset
from scope3d.io.images import write_image
from scope3d.io.map_points import MAP_POINTS_FILE, MapPoints, write_map_points
from scope3d.io.ply import write_ply
from scope3d.io.poses_csv import format_poses_csv
from scope3d.metrology.evaluation import (
    EvaluationOptions,
    icp_from_initial_poses,
    mesh_errors,
    pose_errors,
    save_error_histogram_png,
    save_error_map_png,
    surface_errors,
    visible_true_points,
)
from scope3d.metrology.fluorescence import (
    FluorescenceOptions,
    Target,
    auto_threshold,
    match_targets,
    overlay,
    segment,
    targets_on_surface,
    write_targets,
)
from scope3d.mvs.dense_map import DenseMap, DenseOptions, build_dense_map
from scope3d.phantoms.lab import true_targets
from scope3d.scene.mesh import Mesh, PointCloud, SampledSurface
from scope3d.scene.surface import Surface, SurfaceOptions, enlarge_raster, fit_surface, save_depth_map_png, texture
from scope3d.scene.tracks import Tracks
from scope3d.sensor.camera import Camera
from scope3d.sensor.pose_tolerance import MeasuredPose, PoseTolerance
from scope3d.sfm.coarse_poses import CoarseOptions, CoarseResult, coarse_poses
from scope3d.sfm.depth_priors import box_depth_prior, estimate_depth_prior, surface_depth_prior
from scope3d.sfm.guided_mapping import (
    POSE_MODES,
    BundleStageOptions,
    adjust_map,
    adjusted_pose_sigmas,
    refine_poses_for_matching,
)
from scope3d.sfm.model_checks import check_model, model_checks_summary
from scope3d.sfm.pose_checks import PoseCheck, PoseCheckOptions, check_pose_reports
from scope3d.utils.atomic import atomic_directory, atomic_file
from scope3d.utils.background import BackgroundCalls
from scope3d.utils.jsonio import json_default, write_json
from scope3d.utils.progress import Progress, advance, stage
from scope3d.utils.threads import check_threads, resolve_threads

MATCHERS = ("guided", "exhaustive")
#: The adjusted poses in poses.csv form, in the map's folder (:func:`write_refined_poses`).
REFINED_POSES_FILE = "poses_refined.csv"


@dataclass(frozen=True)
class MapOptions:
    """Everything the map pipeline can be told, with documented defaults per stage.

    pose_mode : "fixed" | "free" | "bounded" (default "bounded": BCBA, which reduces to "fixed" for
        exact poses and uses the tolerance otherwise).
    matcher : "guided" (feature position prediction, default) or "exhaustive" (the baseline).
    depth_prior : DepthPrior or None (default None: estimated from the data).
    surface : SurfaceOptions or None, the surface stage (None: no surface; a photograph ring around an
        object, like Middlebury's temple, is not a height field). fluorescence : FluorescenceOptions or
        None, the targets stage (None: no targets; it also needs the surface and fluorescence frames).
    figures : bool, write PNG figures (default True).
    threads : int, threads for per-frame feature detection (default 0: every available core,
        :mod:`scope3d.utils.threads`).
    surface_prior : bool, two-pass guided matching with a coarse-surface depth band (default True;
        needs a scene that is a height field seen from one side, false for a ring around an object).
    surface_band_mm : float, added to the band around the coarse surface for the detail it smooths
        away (default 0.5 mm).
    use_bounding_box : bool, bounding_box_margin_mm : float, use the dataset's ``bounding_box_mm``
        (when its metadata has one) as the depth prior, enlarged by the margin (default True, 5 mm).
    refine_poses_for_matching : bool, when the pose tolerance widens the search window, find overlap
        and poses from the images first (the coarse pass, ``coarse``), adjust the poses by BCBA on its
        matches and predict the fine pass with them (:func:`match_with_image_poses`; default True).
        False: the measured poses guide matching whatever their tolerance (the baseline).
    dense : DenseOptions or None, the dense stage (default None: none; ``map --surface dense``). It needs the
        surface stage's camera and poses only, and writes dense.ply; its mesh becomes mesh.ply.
    pose_check : PoseCheckOptions or None, in ``bounded`` mode, when the reports' tolerance was wide enough
        for the coarse pass to run, test every reported pose against the images and the other reports
        after the adjustment, and map again with the reports found wrong replaced by what the images say
        (:func:`check_reported_poses`). Default None (every report trusted to lie in its box): with its local
        exact test no clean map measured had a frame flagged, but it costs 0.45-1.2 s CPU on a clean 30-frame
        map (median 0.6 s, ~9 % of the map; +11-26 % measured on whole maps at load 10) and finds 2 of 26
        glitches fewer than the check before it, both at the edge of what the geometry sees
        (docs/reliability.md section 5, "the local round"), so it is opt-in (``PoseCheckOptions()``).
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
    surface: SurfaceOptions | None = field(default_factory=SurfaceOptions)
    fluorescence: FluorescenceOptions | None = field(default_factory=FluorescenceOptions)
    evaluation: EvaluationOptions = field(default_factory=EvaluationOptions)
    figures: bool = True
    threads: int = 0
    surface_prior: bool = True
    surface_band_mm: float = 0.5
    use_bounding_box: bool = True
    bounding_box_margin_mm: float = 5.0
    refine_poses_for_matching: bool = True
    pose_check: PoseCheckOptions | None = None
    dense: DenseOptions | None = None

    def __post_init__(self) -> None:
        if self.pose_mode not in POSE_MODES:
            raise ValueError(f"pose_mode must be one of {POSE_MODES}, got {self.pose_mode!r}")
        if self.matcher not in MATCHERS:
            raise ValueError(f"matcher must be one of {MATCHERS}, got {self.matcher!r}")
        check_threads(self.threads)


#: Named presets. ``dim_endoscope``: CLAHE and a lower SIFT threshold for dark frames.
#: ``photograph``: calibrated photographs around an object (no circular mask, no height-field surface,
#: the nearest neighbour in each direction of motion only, a 1 px reprojection gate).
MAP_PRESETS: dict[str, MapOptions] = {
    "default": MapOptions(),
    "dim_endoscope": MapOptions(features=FEATURE_PRESETS["dim_endoscope"]),
    "photograph": MapOptions(features=FEATURE_PRESETS["photograph"], surface=None, fluorescence=None, surface_prior=False,
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
        when the coarse pass and
        :func:`scope3d.sfm.guided_mapping.refine_poses_for_matching` ran; None when the measured poses
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

    off_surface_points : (K, 3) mm world, points dropped for standing off their neighbours' surface
        (:func:`scope3d.sfm.guided_mapping.on_surface`; only when the map has a surface stage).
    matched : every matched observation as tracks, untriangulated (what the adjustment started from; the pose
        check tests the reports against all of them, not only those the map kept).
    pose_sigmas : (m, 6) what is left of each adjusted pose's uncertainty, standard deviations (rotation rad,
        centre mm; :func:`scope3d.sfm.guided_mapping.adjusted_pose_sigmas`), None when not computed.
    """

    tracks: Tracks
    poses: list[Pose]
    camera: Camera
    bundle_results: list
    mean_reprojection_error_px: float
    time_s: float
    off_surface_points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    matched: Tracks | None = None
    pose_sigmas: np.ndarray | None = None

    @property
    def n_off_surface(self) -> int:
        return len(self.off_surface_points)


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
    """What :func:`run` returns: the report (also in ``out_dir/report.json``) and the in-memory model.

    The model as arrays: :attr:`points`, :attr:`colors`, :attr:`cam_from_world`, :attr:`pose_sigmas`,
    :attr:`mesh` (the textured surface) and :attr:`names` (the frames, in the order of the poses).
    :meth:`save` writes them (and the tracks, the camera and the surface grid) to one ``.npz`` that
    :meth:`load` reads back; the stages' intermediates (features, matches, bundle logs, fluorescence rasters)
    are not saved: a loaded result has ``features == []``, ``matching is None``, ``targets is None`` (the
    targets are in its report and in targets.csv), and ``dense is None`` (the dense map, with ``MapOptions.dense``,
    is in dense.ply and mesh.ply). The whole result also pickles.
    """

    report: dict
    out_dir: Path
    features: list[Features]
    matching: MatchingResult | None
    sparse: SparseResult
    surface: SurfaceResult | None
    targets: TargetResult | None
    names: list[str] = field(default_factory=list)
    dense: DenseMap | None = None

    @property
    def points(self) -> np.ndarray:
        """(N, 3) mm world, the map's points."""
        return self.sparse.tracks.points

    @property
    def colors(self) -> np.ndarray:
        """(N, 3) uint8 RGB, each point's colour."""
        return self.sparse.tracks.colors

    @property
    def poses(self) -> list[Pose]:
        """The adjusted ``cam_from_world`` poses, one per frame."""
        return self.sparse.poses

    @property
    def cam_from_world(self) -> np.ndarray:
        """(m, 4, 4) the adjusted poses as matrices (mm)."""
        return np.stack([p.matrix for p in self.sparse.poses])

    @property
    def pose_sigmas(self) -> np.ndarray | None:
        """(m, 6) each adjusted pose's remaining standard deviations (rotation rad, centre mm), as in
        poses_refined.csv."""
        return self.sparse.pose_sigmas

    @property
    def mesh(self) -> Mesh | None:
        """The surface as a triangle mesh with its texture's vertex colours (mesh_reflectance.ply), or None."""
        return None if self.surface is None else self.surface.surface.mesh(self.surface.colors)

    def save(self, path: str | Path) -> Path:
        """Write the model's arrays and the report to ``path`` (one ``.npz``, written atomically); returns it."""
        tr, camera = self.sparse.tracks, self.sparse.camera
        arrays = {"report": np.array(json.dumps(self.report, default=json_default)), "out_dir": np.array(str(self.out_dir)),
                  "names": np.array(self.names, dtype=str), "camera": np.array(json.dumps(asdict(camera), default=json_default)),
                  "track": tr.track, "frame": tr.frame, "feature": tr.feature, "pixels": tr.pixels,
                  "colors": tr.colors, "points": tr.points, "cam_from_world": self.cam_from_world,
                  "off_surface_points": self.sparse.off_surface_points}
        if self.pose_sigmas is not None:
            arrays["pose_sigmas"] = self.pose_sigmas
        if self.surface is not None:
            s = self.surface.surface
            arrays.update(surface_origin=s.origin, surface_axes=s.axes, surface_s=s.s, surface_t=s.t,
                          surface_height=s.height, surface_colors=self.surface.colors,
                          surface_view_map=self.surface.view_map)
        path = Path(path)
        with atomic_file(path, "wb") as fh:
            np.savez_compressed(fh, **arrays)
        return path

    @classmethod
    def load(cls, path: str | Path) -> "MapResult":
        """The result :meth:`save` wrote to ``path``. Raises InputError if it is not such a file."""
        path = Path(path)
        try:
            with np.load(path, allow_pickle=False) as z:
                a = {k: z[k] for k in z.files}
        except (OSError, ValueError, zipfile.BadZipFile) as exc:
            raise InputError(f"{path}: not a saved map result ({exc})") from None
        missing = [k for k in ("report", "names", "camera", "track", "points", "cam_from_world") if k not in a]
        if missing:
            raise InputError(f"{path}: not a saved map result (no {', '.join(missing)})")
        report = json.loads(str(a["report"]))
        timings = report.get("timings_s", {})
        tracks = Tracks(a["track"], a["frame"], a["feature"], a["pixels"], a["colors"], a["points"])
        poses = [Pose(m[:3, :3], m[:3, 3]) for m in a["cam_from_world"]]
        sparse = SparseResult(tracks, poses, Camera(**json.loads(str(a["camera"]))), [],
                              float(report["mean_reprojection_error_px"]), float(timings.get("bundle", 0.0)),
                              a["off_surface_points"], None, a.get("pose_sigmas"))
        surface = None
        if "surface_height" in a:
            grid = Surface(a["surface_origin"], a["surface_axes"], a["surface_s"], a["surface_t"], a["surface_height"])
            surface = SurfaceResult(grid, a["surface_colors"], a["surface_view_map"], float(timings.get("surface", 0.0)))
        return cls(report, Path(str(a["out_dir"])), [], None, sparse, surface, None, [str(n) for n in a["names"]])

    def summary(self) -> str:
        r = self.report
        lines = [f"{r['n_frames']} frames, {r['n_points']} points ({r['n_points_off_surface_dropped']} off-surface "
                 f"dropped), {r['n_observations']} observations, "
                 f"mean reprojection error {r['mean_reprojection_error_px']:.3f} px, {r['time_s']:.2f} s"]
        if "model_checks" in r:
            lines.append(model_checks_summary(r["model_checks"]))
        lines += [f"{why} (stage skipped)" for why in r.get("stages_skipped", {}).values()]
        if "note" in r.get("surface", {}):
            lines.append(f"surface: {r['surface']['note']}")
        if "surface_error_mm" in r:
            d, i = r["surface_error_mm"]["direct"], r["surface_error_mm"]["after_icp"]
            lines.append(f"surface error: direct mean {d['mean']:.3f} mm ({100 * d['within_1mm_fraction']:.1f} % "
                         f"within 1 mm), after ICP mean {i['mean']:.3f} mm ({100 * i['within_1mm_fraction']:.1f} %)")
        if r.get("clock_offset", {}).get("significant"):
            lines.append(clock_offset_summary(r["clock_offset"]))
        if "targets" in r:  # an empty fluorescence channel (no residual tumour) is a result, not an error
            lines.append(f"targets: {len(r['targets'])} found" if r["targets"] else
                         f"targets: no targets (no fluorescence above {r['fluorescence_threshold']})")
        return "\n".join(lines)


# --- 1. features ------------------------------------------------------------------------------


def detect_features(options: MapOptions, dataset: Dataset, frames: list[np.ndarray], *,
                    progress: Progress | None = None) -> list[Features]:
    """SIFT per frame (threads: OpenCV releases the GIL)."""
    def one(k):
        f = detect(frames[k], dataset.camera, options=options.features)
        advance(progress)
        return f

    with ThreadPoolExecutor(max_workers=resolve_threads(options.threads)) as pool:
        return list(pool.map(one, range(len(frames))))


# --- 2. matching ------------------------------------------------------------------------------


def match_frames(options: MapOptions, dataset: Dataset, features: list[Features], *,
                 progress: Progress | None = None) -> MatchingResult:
    """Overlapping pairs and their matches, guided by the poses as far as their tolerance allows.

    Poses good enough to predict (a micro-stage: every search window at most twice what exact poses
    give) select the pairs from their frusta at a depth prior and guide the matcher directly. With
    ``options.surface_prior`` the guided matcher runs in two passes: each frame's best partner and a
    spanning forest first, with the global depth range; a coarse thin-plate surface through those points
    then narrows every other pair's depth range to a band around it (the reference predicted with a
    single plane; a surface predicts a curved cavity as well).

    Poses whose tolerance widens the search (a tracker, a surgical arm) go through the reference's
    "combination algorithm" (sec. 3.5) instead, :func:`match_with_image_poses`.
    """
    t0 = time.perf_counter()
    camera, measured = dataset.camera, dataset.poses
    depth_prior = options.depth_prior
    box = dataset.metadata.get("bounding_box_mm") if options.use_bounding_box else None
    if depth_prior is None and box is not None:  # a calibrated object's box is the tightest prior there is
        depth_prior = box_depth_prior(box[0], box[1], [m.pose for m in measured], margin_mm=options.bounding_box_margin_mm)
    guided = options.matcher == "guided" and len(dataset) >= 3
    if guided and options.refine_poses_for_matching and not all(m.tolerance.is_exact for m in measured):
        estimate = depth_prior or _estimate_depth_prior_or_none(options, dataset, features)
        if estimate is None or not _poses_predict_matches(options, dataset, estimate):
            return match_with_image_poses(options, dataset, features, depth_prior, progress=progress, t0=t0)
        depth_prior = estimate
    if depth_prior is None:
        depth_prior = estimate_depth_prior(camera, features, measured, options=options.matching)
    t_depth = time.perf_counter() - t0
    # the depth prior also places the frusta for pair selection, so both matchers see the same pairs
    pairs = select_pairs(camera, [m.pose for m in measured], depth_prior, options=options.pairs)
    if options.matcher != "guided" or len(pairs) < 4 or not options.surface_prior:
        matches = match_pairs(camera, features, measured, pairs, depth_prior, options=options.matching,
                              method=options.matcher, progress=progress)
        return MatchingResult(pairs, matches, depth_prior, time.perf_counter() - t0, t_depth)
    first = spanning_pairs(pairs, len(dataset))
    rest = sorted(set(range(len(pairs))) - set(first))
    matches: list = [None] * len(pairs)
    for k, m in zip(first, match_pairs(camera, features, measured, [pairs[k] for k in first], depth_prior,
                                       options=options.matching, progress=progress)):
        matches[k] = m
    band = surface_depth_prior(camera, features, [matches[k] for k in first], depth_prior, measured, options.tracks,
                               options.surface or SurfaceOptions(), options.surface_band_mm)
    for k, m in zip(rest, match_pairs(camera, features, measured, [pairs[k] for k in rest], band or depth_prior,
                                      options=options.matching, progress=progress)):
        matches[k] = m
    return MatchingResult(pairs, matches, band or depth_prior, time.perf_counter() - t0, t_depth)


def _estimate_depth_prior_or_none(options: MapOptions, dataset: Dataset, features) -> DepthPrior | None:
    """The data's depth prior, or None when the measured poses are too far off to triangulate the
    closest pairs at all (then they certainly cannot predict matches)."""
    try:
        return estimate_depth_prior(dataset.camera, features, dataset.poses, options=options.matching)
    except ValueError:
        return None


def _poses_predict_matches(options: MapOptions, dataset: Dataset, depth_prior: DepthPrior) -> bool:
    """True when every frame's search window is at most twice what exact poses give (a micro-stage):
    beyond that the window holds many look-alike candidates, and adjusting the poses first pays."""
    base = options.matching.base_radius_px
    radius = max(window_radius_px(dataset.camera, m.tolerance, m.tolerance, depth_prior, base) for m in dataset.poses)
    return radius <= 2.0 * base


def match_with_image_poses(options: MapOptions, dataset: Dataset, features: list[Features],
                           depth_prior: DepthPrior | None, *, progress: Progress | None = None,
                           t0: float | None = None) -> MatchingResult:
    """The combination algorithm for poses whose tolerance widens the search window.

    1. :func:`scope3d.sfm.coarse_poses.coarse_poses`: pairs by image similarity, exhaustive matching
       verified by the essential matrix, poses by rotation and position averaging anchored to the
       measurements;
    2. :func:`scope3d.sfm.guided_mapping.refine_poses_for_matching`: BCBA on those tracks inside the
       measured boxes, and the tolerance the images leave each adjusted pose;
    3. the depth prior from the adjusted points (unless the dataset gave one), pairs from the adjusted
       frusta, and guided matching of every pair in the narrow windows the adjusted poses allow, with the
       coarse surface's depth band. A pair the narrow windows leave empty is matched exhaustively; a
       verified coarse pair the frusta did not select is kept.
    """
    t0 = time.perf_counter() if t0 is None else t0
    camera = dataset.camera
    coarse = coarse_poses(camera, features, dataset.poses, match_options=options.matching, options=options.coarse,
                          progress=progress)
    guide, points_prior = refine_poses_for_matching(camera, dataset.poses, features, coarse.matches, coarse.poses,
                                                    track_options=options.tracks, options=options.bundle,
                                                    where=str(dataset.root))
    depth_prior = depth_prior or points_prior
    t_depth = time.perf_counter() - t0
    pairs = select_pairs(camera, [m.pose for m in guide], depth_prior, options=options.pairs)
    band = None
    if options.surface_prior:
        band = surface_depth_prior(camera, features, coarse.matches, depth_prior, guide, options.tracks,
                                   options.surface or SurfaceOptions(), options.surface_band_mm)
    matches = match_pairs(camera, features, guide, pairs, band or depth_prior, options=options.matching,
                          progress=progress)
    lost = [k for k, m in enumerate(matches) if len(m) == 0]
    if lost:
        again = match_pairs(camera, features, guide, [pairs[k] for k in lost], depth_prior, options=options.matching,
                            method="exhaustive")
        for k, m in zip(lost, again):
            matches[k] = m
    selected = {(i, j) for i, j, _ in pairs}
    for m in coarse.matches:
        if (m.i, m.j) not in selected:
            pairs.append((m.i, m.j, float(coarse.similarity[m.i, m.j])))
            matches.append(m)
    return MatchingResult(pairs, matches, band or depth_prior, time.perf_counter() - t0, t_depth, guide, len(lost),
                          coarse)


# --- 3. tracks, triangulation, bundle adjustment ------------------------------------------------


def reconstruct(options: MapOptions, dataset: Dataset, features: list[Features], matching: MatchingResult) -> SparseResult:
    """Tracks, triangulation, bundle adjustment in ``options.pose_mode`` (:func:`scope3d.sfm.guided_mapping.adjust_map`),
    then, when a surface will be fitted, points off their neighbours' surface dropped.

    The adjustment starts from the poses that guided matching (the coarse pass's adjusted poses when the
    tolerance was wide, else the measured ones; always the measured ones in ``fixed`` mode); the bounds
    are always the measured boxes.
    """
    t0 = time.perf_counter()
    tracks = build_tracks(features, matching.matches, min_track_length=options.tracks.min_track_length,
                          split_inconsistent=options.tracks.split_inconsistent)
    if tracks.n_tracks == 0:
        raise InputError(f"{dataset.root}: no feature could be matched between frames (do they overlap?)")
    movable = options.pose_mode != "fixed"
    start = matching.guide_poses if movable and matching.coarse is not None else dataset.poses
    # the surface stage's assumption, a height field seen from one side, lets wrong matches be dropped
    adjusted = adjust_map(options.pose_mode, dataset.poses, dataset.camera, tracks, start, matching.depth_prior,
                          track_options=options.tracks, options=options.bundle,
                          height_field=options.surface is not None, where=str(dataset.root))
    err = reprojection_errors(adjusted.camera, adjusted.poses, adjusted.tracks)
    sigmas = adjusted_pose_sigmas(options.pose_mode, dataset.poses, adjusted.camera, adjusted.tracks, adjusted.poses,
                                  options=options.bundle)
    return SparseResult(adjusted.tracks, adjusted.poses, adjusted.camera, adjusted.bundle_results, float(np.mean(err)),
                        time.perf_counter() - t0, adjusted.off_surface_points, tracks, sigmas)


def check_reported_poses(options: MapOptions, dataset: Dataset, matching: MatchingResult,
                         sparse: SparseResult) -> PoseCheck | None:
    """Each reported pose tested against the images and the other frames
    (:func:`scope3d.sfm.pose_checks.check_pose_reports`: every frame's pose estimated again from its
    observations of the points the other frames triangulate at the bounded map's poses); None when there
    is nothing to test: not ``bounded``, or reports so tight that they guided matching themselves (no
    coarse pass: a micro-stage's 0.01 mm, which the images cannot improve on; there a false alarm would
    only replace a good report by a worse estimate)."""
    if options.pose_check is None or options.pose_mode != "bounded" or matching.coarse is None:
        return None
    return check_pose_reports(sparse.camera, dataset.poses, sparse.matched, sparse.poses, options.tracks,
                              options.pose_check)


# --- 4. surface -------------------------------------------------------------------------------


class StageSkipped(Exception):
    """A stage that cannot run on this input; its message is the one-line reason (report.json's
    ``stages_skipped``, the summary): the map is written without what the stage would have added."""


def build_surface(options: MapOptions, dataset: Dataset, sparse: SparseResult, frames: list[np.ndarray]) -> SurfaceResult:
    """Thin-plate-spline surface through the points, textured from each vertex's best view. Raises
    :class:`StageSkipped` when the points cannot carry a surface (fewer than 10)."""
    t0 = time.perf_counter()
    towards = -np.mean([p.optical_axis for p in sparse.poses], axis=0)
    if sparse.tracks.n_tracks < 10:
        raise StageSkipped(f"surface: {sparse.tracks.n_tracks} points, a surface needs at least 10")
    surface = fit_surface(sparse.tracks.points, options=options.surface or SurfaceOptions(), towards=towards)
    colors, view_map = texture(surface, sparse.camera, sparse.poses, frames)
    return SurfaceResult(surface, colors, view_map, time.perf_counter() - t0)


def build_dense(options: MapOptions, sparse: SparseResult, frames: list[np.ndarray], *,
                progress: Progress | None = None) -> DenseMap:
    """The dense map (:mod:`scope3d.mvs.dense_map`) from the adjusted camera, poses and points."""
    return build_dense_map(sparse.camera, frames, sparse.poses, sparse.tracks.points,
                           options=options.dense or DenseOptions(), progress=progress)


# What a mesh vertex may stand off a frame's depth beyond the depth's own error: the Poisson surface smooths
# over about one octree cell (0.08 mm over the 40 mm plate at the default depth 9).
_POISSON_SMOOTHING_MM = 0.1


def dense_fluorescence(dataset: Dataset, sparse: SparseResult, dense: DenseMap, threshold: int, *,
                       options: FluorescenceOptions) -> np.ndarray:
    """(V,) bool: the dense mesh's vertices that glow. A vertex votes in each frame whose consistent depth at
    its projection lies within ``3 x`` the depth's standard deviation of it (the frame sees it, not what
    hides it); it glows when at least half of at least two such votes fall in the frame's segmented mask."""
    v = dense.mesh.vertices
    seen = np.zeros(len(v), int)
    lit = np.zeros(len(v), int)
    camera = sparse.camera
    for k, depth in enumerate(dense.depths):
        if depth is None:
            continue
        mask = segment(dataset.fluorescence_frame(k), threshold, options=options, mask=camera.mask())
        idx, ij, z_vertex = camera.nearest_pixels(sparse.poses[k], v)
        z = np.where(dense.fused.consistent[k], depth.depth_mm, np.nan)[ij[:, 1], ij[:, 0]]
        s = depth.sigma_mm[ij[:, 1], ij[:, 0]]
        ok = np.isfinite(z) & (np.abs(z - z_vertex) <= 3.0 * s + _POISSON_SMOOTHING_MM)
        seen[idx[ok]] += 1
        lit[idx[ok]] += mask[ij[ok, 1], ij[ok, 0]]
    return (seen >= 2) & (2 * lit >= seen)


# --- 5. fluorescence --------------------------------------------------------------------------


def locate_targets(options: MapOptions, dataset: Dataset, sparse: SparseResult, surface: SurfaceResult) -> TargetResult:
    """Segment each fluorescence frame, vote onto the surface, label and measure the targets."""
    t0 = time.perf_counter()
    fl = options.fluorescence or FluorescenceOptions()
    images = [dataset.fluorescence_frame(k) for k in range(len(dataset))]
    threshold = auto_threshold(images, options=fl)
    valid = sparse.camera.mask()
    masks = [segment(img, threshold, options=fl, mask=valid) for img in images]
    targets, on, labels = targets_on_surface(surface.surface, sparse.camera, sparse.poses, masks, options=fl)
    return TargetResult(targets, on, labels, threshold, time.perf_counter() - t0)


# --- 6. evaluation ----------------------------------------------------------------------------


def evaluate_map(options: MapOptions, dataset: Dataset, sparse: SparseResult, targets: TargetResult | None,
                 dense: DenseMap | None = None, surface: SurfaceResult | None = None) -> dict:
    """Accuracy against the dataset's ground truth (empty dict when it has none). With a dense map and the
    true depth maps, its mesh and the spline's are both measured (:func:`mesh_errors`: accuracy and
    completeness, direct)."""
    gt = dataset.ground_truth
    out: dict = {}
    if gt is None:
        return out
    t0 = time.perf_counter()
    if gt.poses is not None:
        out["pose_error"] = pose_errors(sparse.poses, dataset.poses, gt.poses)
    if gt.surface_path is not None:
        truth = SampledSurface(gt.surface(), options.evaluation.sample_step_mm)
        summary, direct, aligned = surface_errors(sparse.tracks.points, truth, options=options.evaluation)
        out["surface_error_mm"] = summary
        out["_distances"] = (direct, aligned)
        if dense is not None and gt.depth_paths and gt.poses is not None:
            # completeness over all the surface the frames see, and over what three frames see (the dense
            # stage needs a frame and two others that agree)
            visible = visible_true_points(dataset.camera, gt.poses, gt.depth)
            multi = visible_true_points(dataset.camera, gt.poses, gt.depth, min_views=3)
            meshes = {"dense_error_mm": dense.mesh}
            if surface is not None:
                meshes["spline_error_mm"] = surface.surface.mesh(surface.colors)
            for key, mesh in meshes.items():
                out[key] = mesh_errors(mesh, truth, visible)
                out[key]["completeness_seen_by_3"] = mesh_errors(mesh, truth, multi)["completeness"]
                # and after a rigid ICP of the mesh's vertices to the truth (as the sparse points): a common
                # offset of all the poses is unobservable from the images and stays in the direct error
                best, _ = icp_from_initial_poses(mesh.vertices, truth, options=options.evaluation)
                moved = Mesh(best.apply(mesh.vertices), mesh.faces)
                out[key]["after_icp"] = mesh_errors(moved, truth, visible)
                out[key]["after_icp"]["completeness_seen_by_3"] = mesh_errors(moved, truth, multi)["completeness"]
    if targets is not None and true_targets(gt.scene):
        out["targets_vs_truth"] = match_targets(targets.targets, true_targets(gt.scene))
    out["time_s"] = time.perf_counter() - t0
    return out


# --- 7. outputs -------------------------------------------------------------------------------


def write_outputs(
    options: MapOptions, dataset: Dataset, out_dir: Path, frames: list[np.ndarray], features: list[Features],
    matching: MatchingResult, sparse: SparseResult, surface: SurfaceResult | None, targets: TargetResult | None,
    evaluation: dict, timings: dict, pose_check: PoseCheck | None = None, *,
    background: BackgroundCalls | None = None, figure_pair: dict | None = None, skipped: dict | None = None,
    dense: DenseMap | None = None, dense_glow: np.ndarray | None = None,
) -> dict:
    """Write every output file into ``out_dir`` (already a temporary folder) and return the report.

    background : where the figures that need the evaluation are drawn (default: here); it is waited for
    before the report is written. figure_pair : what :func:`draw_figures` returned, for the report.
    skipped : stage name -> why it could not run (:class:`StageSkipped`), the report's ``stages_skipped``.
    """
    t0 = time.perf_counter()
    background = background or BackgroundCalls(enabled=False)
    tr = sparse.tracks
    err = reprojection_errors(sparse.camera, sparse.poses, tr)
    write_ply(out_dir / "points.ply", PointCloud(tr.points, tr.colors))
    per_point_err = np.bincount(tr.track, err, tr.n_tracks) / np.maximum(tr.lengths(), 1)
    model = SparseModel.from_observations(sparse.camera, dataset.names, sparse.poses, tr.points, tr.frame, tr.track,
                                          tr.pixels, colors=tr.colors, errors=per_point_err)
    write_colmap_text(model, out_dir / "sparse")
    write_refined_poses(out_dir / REFINED_POSES_FILE, dataset.names, sparse)
    # what localization against this map needs (scope3d localize): points, one descriptor each, track lengths,
    # and every observation's descriptor (a new view may resemble one observation and not the representative)
    write_map_points(out_dir / MAP_POINTS_FILE, MapPoints(tr.points, track_descriptors(features, tr),
                                                          tr.lengths(), tr.colors, observation_descriptors(features, tr),
                                                          tr.track))
    prior = matching.depth_prior
    report: dict = {
        "dataset": str(dataset.root), "n_frames": len(dataset), "pose_mode": options.pose_mode, "matcher": options.matcher,
        "n_features": int(sum(len(f) for f in features)), "n_pairs": len(matching.pairs), "n_matches": matching.n_matches,
        "depth_prior_mm": None if prior is None else [prior.near_mm, prior.far_mm],
        "n_points": int(tr.n_tracks), "n_observations": int(tr.n_observations),
        "n_points_off_surface_dropped": sparse.n_off_surface,
        "matching": {"poses_refined_for_matching": matching.guide_poses is not None,
                     "pairs_rematched_exhaustively": matching.n_rematched},
        "mean_track_length": float(tr.n_observations / max(tr.n_tracks, 1)),
        "mean_reprojection_error_px": float(np.mean(err)), "median_reprojection_error_px": float(np.median(err)),
        "bundle": [_bundle_summary(r) for r in sparse.bundle_results],
        "camera_adjusted": {"intrinsics": dict(zip(sparse.camera.param_names, sparse.camera.params.tolist())),
                            "fov_deg": sparse.camera.fov_deg, "fov_deg_dataset": dataset.camera.fov_deg},
        "model_checks": check_model(dataset.names, dataset.poses, sparse.poses, tr).as_dict(),
    }
    clock = clock_offset_report(dataset, sparse)
    if clock is not None:
        report["clock_offset"] = clock
    if pose_check is not None:
        report["model_checks"]["reported_pose_test"] = pose_check.as_dict(dataset.names, dataset.poses)
    if skipped:
        report["stages_skipped"] = dict(skipped)
    fl = options.fluorescence or FluorescenceOptions()
    if surface is not None:
        s = surface.surface
        colors = surface.colors
        if targets is not None:
            colors = overlay(colors, targets.fluorescent, None, options=fl, draw_outlines=False)
        spline = "mesh_spline.ply" if dense is not None else "mesh.ply"
        write_ply(out_dir / spline, s.mesh(colors))
        if dense is None:
            write_ply(out_dir / "mesh_reflectance.ply", s.mesh(surface.colors))
        d = s.height[s.valid]
        report["surface"] = {"grid": list(s.height.shape), "step_mm": s.step_mm, "n_vertices": int(s.valid.sum()),
                             "height_range_mm": float(np.ptp(d)),
                             "flatness_rms_mm": plane_rms(s.vertices()[s.valid]),
                             "points_flatness_rms_mm": plane_rms(tr.points),
                             "points_flatness_median_mm": float(np.median(np.abs(plane_residuals(tr.points))))}
        requested = (options.surface or SurfaceOptions()).grid_step_mm
        if s.step_mm > requested * (1 + 1e-9):
            report["surface"]["note"] = (f"grid step raised from {requested:g} to {s.step_mm:.3g} mm to keep the grid "
                                         f"within {(options.surface or SurfaceOptions()).max_grid_vertices:,} vertices")
        if options.figures:
            write_image(out_dir / "texture_mosaic.png", enlarge_raster(surface.colors))
    if dense is not None:
        write_ply(out_dir / "dense.ply", dense.fused.cloud)
        m = dense.mesh
        colors = m.vertex_colors
        if dense_glow is not None and colors is not None:
            colors = np.where(dense_glow[:, None], np.array([40, 255, 40], np.uint8), colors)
        write_ply(out_dir / "mesh.ply", Mesh(m.vertices, m.faces, colors, m.vertex_normals))
        write_ply(out_dir / "mesh_reflectance.ply", m)
        report["dense"] = {**dense.summary(), "glowing_vertices": None if dense_glow is None else int(dense_glow.sum())}
    if targets is not None:
        report["fluorescence_threshold"] = targets.threshold
        report["targets"] = [t.as_dict() for t in targets.targets]
        write_targets(out_dir, targets.targets, evaluation.get("targets_vs_truth"))
        if options.figures and surface is not None:
            write_image(out_dir / "multimodal_mosaic.png",
                        overlay(enlarge_raster(surface.colors), enlarge_raster(targets.fluorescent),
                                enlarge_raster(targets.labels), options=fl))
    if evaluation:
        report.update({k: v for k, v in evaluation.items() if not k.startswith("_") and k != "time_s"})
        if options.figures and "_distances" in evaluation:
            direct, aligned = evaluation["_distances"]
            background.submit(save_error_histogram_png, out_dir / "error_histogram.png", aligned,
                              title="distance to the true surface after ICP")
            background.submit(save_error_map_png, out_dir / "error_map.png", tr.points, aligned,
                              title="error map after ICP (mm)")
    if options.figures:
        report["figure_pair"] = figure_pair
    background.wait()
    timings["outputs"] = time.perf_counter() - t0
    report["timings_s"] = {k: round(v, 4) for k, v in timings.items()}
    report["time_s"] = round(sum(v for k, v in timings.items() if k != "evaluation"), 4)
    write_json(out_dir / "report.json", report)
    return report


def clock_offset_report(dataset: Dataset, sparse: SparseResult) -> dict | None:
    """report.json's ``clock_offset`` when the dataset records its frames' times on the robot's clock
    (``scope3d import frames``: dataset.json's ``source.frame_times_s``), else None.

    ``s``, ``sigma_s``: :func:`scope3d.estimators.clock_offset.estimate_clock_offset` (None with ``reason``
    when it cannot be told). ``significant``: beyond 3 sigma *and* the shift it implies (``|s|`` times the
    median speed) beyond the map's own pose precision (the median adjusted centre's 3D sigma), so that an
    offset too small to move a pose past what the map knows of it is not reported as a fault.
    ``clock_offset_s_used``: what the import added to the frame times; ``clock_offset_s_corrected`` what to add
    instead."""
    source = dataset.metadata.get("source")
    times = source.get("frame_times_s") if isinstance(source, dict) else None
    if not isinstance(times, dict):
        return None
    keep = [k for k, n in enumerate(dataset.names) if n in times]
    measured = np.array([dataset.poses[k].pose.centre for k in keep]).reshape(-1, 3)
    adjusted = np.array([sparse.poses[k].centre for k in keep]).reshape(-1, 3)
    fit = estimate_clock_offset(measured, adjusted, np.array([times[dataset.names[k]] for k in keep], dtype=float))
    if not isinstance(fit, ClockOffset):
        return {"s": None, "sigma_s": None, "significant": False, "reason": fit}
    used = (source.get("frame_times") or {}).get("clock_offset_s") or 0.0
    precision = (None if sparse.pose_sigmas is None else
                 float(np.median(np.linalg.norm(sparse.pose_sigmas[keep, 3:], axis=1))))
    shift = abs(fit.offset_s) * fit.speed_mm_s
    significant = abs(fit.offset_s) > 3.0 * fit.sigma_s and (precision is None or shift > precision)
    return {"s": fit.offset_s, "sigma_s": fit.sigma_s, "significant": bool(significant),
            "implied_shift_mm": shift, "pose_precision_mm": precision, "median_speed_mm_s": fit.speed_mm_s,
            "residual_mm": fit.residual_mm, "n_frames": fit.n_frames,
            "clock_offset_s_used": float(used), "clock_offset_s_corrected": float(used) - fit.offset_s}


def clock_offset_summary(clock: dict) -> str:
    """The summary's line for a significant clock offset (:func:`clock_offset_report`)."""
    late = "late" if clock["s"] > 0 else "early"
    return (f"clock offset: the camera and robot clocks disagree by {1e3 * clock['s']:+.2f} ms "
            f"(sigma {1e3 * clock['sigma_s']:.2f} ms; the frame times run {late}, each pose "
            f"{clock['implied_shift_mm']:.3g} mm off along the scan): re-import with `scope3d import frames ... "
            f"--clock-offset {clock['clock_offset_s_corrected']:.6g}`")


def write_refined_poses(path: Path, names: list[str], sparse: SparseResult) -> None:
    """``poses_refined.csv``: the adjusted poses in the dataset's own poses.csv form, each with a box of 3 of
    its remaining standard deviations as its tolerance (as ``import rosbag`` reads a covariance) and the
    standard deviations themselves in the extra :data:`scope3d.io.poses_csv.SIGMA_COLUMNS`: a dataset whose
    poses.csv is this file maps again from the refined poses."""
    sigmas = sparse.pose_sigmas if sparse.pose_sigmas is not None else np.full((len(sparse.poses), 6), np.inf)
    boxes = [PoseTolerance(3.0 * s[3:], 3.0 * s[:3]) for s in sigmas]
    path.write_text(format_poses_csv(names, [MeasuredPose(p, b) for p, b in zip(sparse.poses, boxes)], sigmas))


def _bundle_summary(result) -> dict:
    d = result.to_dict()
    d.pop("iteration_log", None)
    d["rms_initial_px"], d["rms_final_px"] = result.rms_initial_px, result.rms_final_px
    return d


def draw_figures(options: MapOptions, dataset: Dataset, out_dir: Path, frames: list[np.ndarray], features: list[Features],
                 matching: MatchingResult, sparse: SparseResult, surface: SurfaceResult | None,
                 background: BackgroundCalls) -> dict | None:
    """Submit to ``background`` the figures that do not need the evaluation (the depth map, the bundle
    adjustment's convergence, the matches with and without prediction); returns the matches figure's
    summary for the report (None without figures or pairs)."""
    if not options.figures:
        return None
    if surface is not None:
        background.submit(save_depth_map_png, out_dir / "depth_map.png", surface.surface)
    if sparse.bundle_results:
        background.submit(sparse.bundle_results[0].plot_convergence, out_dir / "ba_convergence.png",
                          title=f"bundle adjustment ({options.pose_mode})")
    return _matches_figure(options, dataset, frames, features, matching, out_dir / "matches_with_without_prediction.png",
                           background)


def _matches_figure(options, dataset, frames, features, matching, path, background) -> dict | None:
    """Matches of the best-overlapping pair with and without prediction (reference Fig. 3.4 / 4.5)."""
    if not matching.pairs:
        return None
    # the pair with the most matches among those with a real baseline (a ring can hold two views from
    # one place: they match perfectly and show nothing)
    centres = np.stack([m.pose.centre for m in dataset.poses])
    spread = float(np.ptp(centres, axis=0).max())
    moved = [m for m in matching.matches if np.linalg.norm(centres[m.i] - centres[m.j]) > 0.01 * spread]
    best = max(moved or matching.matches, key=len)
    i, j = best.i, best.j
    exh = match_exhaustive(dataset.camera, features[i], features[j], options.matching, i=i, j=j)
    guided = best if options.matcher == "guided" else match_guided(
        dataset.camera, features[i], features[j], dataset.poses[i], dataset.poses[j], matching.depth_prior,
        options=options.matching, i=i, j=j)
    background.submit(save_matches_png, path, frames[i], frames[j], features[i], features[j], [exh, guided],
                      [f"without prediction: {len(exh)} matches", f"with prediction: {len(guided)} matches"])
    return {"frames": [i, j], "matches_with_prediction": len(guided), "matches_without_prediction": len(exh)}


# --- the pipeline -----------------------------------------------------------------------------


def run(options: MapOptions, dataset: Dataset, out_dir: str | Path, *, progress: Progress | None = None) -> MapResult:
    """Map the surgical field of ``dataset`` into ``out_dir`` (written atomically). See the module docstring.

    progress : tqdm-like or None (:mod:`scope3d.utils.progress`): one stage after another, counted in
    frames (features) and pairs (matching).
    """
    # the stages run frames and pairs on threads of their own; BLAS's threads on their small products only
    # spin against those (measured on the 30-frame dome: 37.1 -> 32.8 s CPU, matching 12.4 -> 8.8 s CPU)
    with threadpool_limits(limits=1, user_api="blas"):
        return _run_stages(options, dataset, out_dir, progress)


def check_dataset(options: MapOptions, dataset: Dataset) -> None:
    """What :func:`run` refuses before any work (``scope3d check`` runs it too): raises InputError."""
    if len(dataset) < 2:
        raise InputError(f"{dataset.root}: need at least 2 frames to map, found {len(dataset)}")


def _run_stages(options: MapOptions, dataset: Dataset, out_dir: str | Path, progress: Progress | None) -> MapResult:
    check_dataset(options, dataset)
    timings: dict = {}
    tick = time.perf_counter()

    def lap(name):
        nonlocal tick
        now = time.perf_counter()
        timings[name] = now - tick
        tick = now

    frames = [dataset.frame(k) for k in range(len(dataset))]
    lap("load")
    stage(progress, "features", len(frames))
    features = detect_features(options, dataset, frames, progress=progress)
    lap("features")
    stage(progress, "matching")
    matching = match_frames(options, dataset, features, progress=progress)
    lap("matching")
    stage(progress, "bundle adjustment")
    sparse = reconstruct(options, dataset, features, matching)
    lap("bundle")
    stage(progress, "pose check")
    pose_check = check_reported_poses(options, dataset, matching, sparse)
    if pose_check is not None and pose_check.flagged:  # reports wrong beyond their boxes: map again without trusting them
        released = replace(dataset, poses=pose_check.released(dataset.poses))
        matching = match_frames(options, released, features, progress=progress)
        sparse = reconstruct(options, released, features, matching)
    if pose_check is not None:
        lap("pose check")
    surface, skipped = None, {}
    if options.surface is not None:
        try:
            surface = build_surface(options, dataset, sparse, frames)
        except StageSkipped as why:
            skipped["surface"] = str(why)
    lap("surface")
    dense = None
    if options.dense is not None:
        dense = build_dense(options, sparse, frames, progress=progress)
        lap("dense")
    # matplotlib holds the GIL: the figures are drawn in a child process while the targets and the
    # evaluation are computed (the child's ~3 s of drawing outlast the evaluation alone)
    with atomic_directory(Path(out_dir)) as tmp, BackgroundCalls(enabled=options.figures) as background:
        figure_pair = draw_figures(options, dataset, tmp, frames, features, matching, sparse, surface, background)
        background.start()
        targets = None
        if options.fluorescence is not None and surface is not None and dataset.fluorescence_paths:
            targets = locate_targets(options, dataset, sparse, surface)
        dense_glow = None
        if targets is not None and dense is not None:
            dense_glow = dense_fluorescence(dataset, sparse, dense, targets.threshold,
                                            options=options.fluorescence or FluorescenceOptions())
        lap("fluorescence")
        evaluation = evaluate_map(options, dataset, sparse, targets, dense, surface)
        lap("evaluation")
        stage(progress, "writing outputs")
        report = write_outputs(options, dataset, tmp, frames, features, matching, sparse, surface, targets, evaluation,
                               timings, pose_check, background=background, figure_pair=figure_pair, skipped=skipped,
                               dense=dense, dense_glow=dense_glow)
    return MapResult(report, Path(out_dir), features, matching, sparse, surface, targets, list(dataset.names), dense)
