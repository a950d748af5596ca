"""The live surgical map: the map grows while the scope moves, with the robot's poses fused in (reference
sec. 9.3.2, issue 36).

A :class:`LiveMapper` takes frames one at a time, as a video stream delivers them, each with the robot's
reported pose and its tolerance box::

    mapper = LiveMapper(camera, LiveMapperOptions())
    for image, reported, t in stream:
        frame = mapper.add_frame(image, reported, t)
        steer(frame.pose, frame.covariance)
    final = mapper.finish()

Per frame, on the caller's thread (the tracking path):

* **tracking** — the frame is localized against the *local map* (the points of the newest keyframes) by a
  :class:`~scope3d.sfm.localization.Localizer`: optical flow, guided or global SIFT matching, then PnP and
  the pose refined inside the robot's box (:func:`~scope3d.estimators.absolute_pose.estimate_absolute_pose`);
* **fusion** — a :class:`~scope3d.estimators.kalman.PoseKalmanFilter` predicts to the frame's time, then
  takes the robot's report (its box as a uniform error) and the image pose with its covariance. The fused
  pose and covariance are the frame's answer;
* **keyframes** — a frame becomes a keyframe when its view has moved a fifth of the image from the last
  keyframe's (phase correlation, :class:`~scope3d.feature.keyframes.KeyframeSelector`, the video import's
  rule: a wall point stays in about five keyframes), or when tracking holds fewer than
  ``min_inlier_fraction`` of the points it held at the last keyframe (or on the current local map's first
  frame, if later); either way only when the frame adds the baseline triangulation needs (its
  ``tracks.min_angle_deg`` of parallax at the map's depth) from the last keyframe. A frame that cannot be
  tracked and has no baseline stays ``lost``, not a keyframe.

Per keyframe, on a worker while tracking goes on (a child process by default, a thread or inline
if asked: ``LiveMapperOptions.worker``):

* SIFT on the keyframe, matched against the previous ``local_window - 1`` keyframes with pose-guided
  matching (:func:`~scope3d.feature.matching.match_guided_many`; the windows come from the fused poses'
  3-sigma boxes, so a frame tracked to 0.05 mm is searched in a few pixels) — the first pairs, before any
  depth is known, exhaustively;
* **local BCBA** over the newest ``local_window`` keyframes: tracks, triangulation and bundle adjustment
  with every keyframe kept inside the robot's box (:func:`~scope3d.sfm.guided_mapping.adjust_map`, the
  map's own stage), started from the keyframes' live poses; the tracks whose views span less than
  triangulation's angle with the point at the window's near depth are dropped (:func:`_with_parallax`);
  the window is then placed in the world that best fits every keyframe's robot report so far (``gauge``:
  the window's six alone leave it ~1.2 mm off). Its points (with their SIFT descriptors) become the
  tracking map, ``map_lag_frames`` frames after the keyframe: a fixed lag
  rather than "when done", so the output does not depend on the machine's load (the stream waits when the
  worker is late);
* **changed tissue** (with ``change_test``, e.g. ``scope3d live``'s ``LiveOptions.change``): after the local
  BCBA the newest three keyframes, adjusted together, are plane-swept (at half size) and tested against the
  window's points (:mod:`scope3d.mvs.surface_change`). Where they no longer agree (resected, moved), the
  older keyframes' features there are retired (no match uses them again, in a later window or the global
  BCBA), the window is adjusted again, and the new keyframes alone map the region.

:meth:`LiveMapper.finish` runs the **global BCBA**: pairs over all keyframes chosen from their adjusted
poses (:func:`~scope3d.feature.pairs.select_pairs`, which also closes loops: a serpentine survey's
neighbouring rows, a return to a mapped region), the missing pairs matched guided, then the map's
tracks-triangulation-bounded-adjustment stage over every keyframe with the robot's boxes. It is the same
stage ``scope3d map`` runs on the same frames, started from better poses; the tracks without parallax
leave it as they leave the local maps.

Statuses (:data:`LIVE_STATUSES`): ``tracked`` (image pose fused with the robot's), ``keyframe`` (as tracked
— or the robot's alone before the first map — and the frame was kept), ``relocalized`` (the image pose came
from global matching, or after a lost frame), ``lost`` (no image pose: the robot's report through the
filter, the covariance says so).

Units: mm and radians; ``time`` in seconds on any clock that only goes forward.
"""
from __future__ import annotations

import multiprocessing
import queue
import threading
import time
import traceback
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
from scipy.spatial import cKDTree

from scope3d.errors import InputError
from scope3d.estimators.kalman import KalmanOptions, PoseKalmanFilter, covariance_to_tolerance
from scope3d.estimators.triangulation import TrackOptions, ray_angles_deg
from scope3d.feature.depth_prior import DepthPrior
from scope3d.feature.detection import FEATURE_PRESETS, FeatureOptions, Features, detect
from scope3d.feature.keyframes import KeyframeOptions, KeyframeSelector
from scope3d.feature.matching import MatchOptions, PairMatches, match_exhaustive, match_guided_many
from scope3d.feature.pairs import PairOptions, select_pairs
from scope3d.feature.tracks import build_tracks, observation_descriptors, track_descriptors
from scope3d.estimators.gauge import gauge_from_measurements, moved_by
from scope3d.geometry.pose import Pose
from scope3d.geometry.similarity import Similarity, fit_similarity
from scope3d.io.map_points import MapPoints
from scope3d.scene.tracks import Tracks
from scope3d.sensor.camera import Camera
from scope3d.sensor.pose_tolerance import MeasuredPose, PoseTolerance
from scope3d.sfm.guided_mapping import BundleStageOptions, adjust_map
from scope3d.sfm.localization import LocalizationResult, Localizer, LocalizerOptions

LIVE_STATUSES = ("tracked", "keyframe", "relocalized", "lost")
LIVE_WORKERS = ("process", "thread", "inline")
LIVE_GAUGES = ("all", "window")


@dataclass(frozen=True)
class LiveMapperOptions:
    """How the live map is built.

    localizer : tracking against the local map (:class:`~scope3d.sfm.localization.LocalizerOptions`).
    keyframes : when the view has moved enough (:class:`~scope3d.feature.keyframes.KeyframeOptions`).
    min_inlier_fraction : float in (0, 1), a frame also becomes a keyframe when its tracking inliers fall
        below this fraction of what the last keyframe, or the first frame tracked on the current local map if
        later, had (default 0.5: the view has left half of the mapped points behind). Measured against the
        map's first frame alone, the rule held from the frame it fired until the next local map, one
        ``map_lag_frames`` later, and kept every frame in between (the dome survey's frames 268-275).
    local_window : int >= 2, keyframes in the local BCBA and in the tracking map (default 6: with a keyframe
        every fifth of the image a wall point is in about five, so the window holds every view of the
        points the newest keyframe sees).
    map_lag_frames : int >= 0, the local BCBA of a keyframe becomes the tracking map this many frames later
        (default 30, a second at 30 fps: the worker's budget for SIFT, matching and the adjustment, which
        took 0.3-0.9 s on a loaded 2-core machine with 320 px frames; benchmarks/results/live.json).
        0 computes it inline at the keyframe (the stream waits for it).
    worker : where the keyframe work runs: ``process`` (default: a spawned child process, which has its own
        GIL — on a thread the adjustment's Python parts stall tracking, whose every small NumPy call then
        waits for the GIL), ``thread``, or ``inline`` (when submitted, in the caller's thread). All three
        apply the result at the same frame, so they give the same output.
    min_keyframes : int >= 2, the first local map is built once this many keyframes are in (default 3: with
        the robot's box the only scale, two keyframes a few mm apart leave the scale loose. 2 gave the dome
        survey its first image pose at frame 53 instead of 73, but 126 lost frames instead of 128 and the
        fused error <= half the robot's on 31 % of the frames instead of 42 % (image box 1x; with 2x: 58 lost
        instead of 69, 16 % instead of 26 %): docs/live.md. A window whose
        adjustment mirrors the points behind the cameras or collapses them onto them is refused, and the
        map waits for the next keyframe).
    features : SIFT on keyframes (the map's default settings). matching : guided matching of keyframe pairs.
    pairs : the global BCBA's pair choice. tracks : triangulation gates. bundle : the adjustments.
    kalman : the fusion filter's motion model.
    guide_sigmas : float, a keyframe's search box for guided matching is this many standard deviations of
        its fused pose (default 3).
    image_box_scale : float >= 1, the tracking's image pose is refined inside the robot's box times this
        (default 2). The map's world is not the robot's: each local BCBA keeps its keyframes inside their
        boxes, so its world is off the robot's by up to one box, and a frame's image pose lies within its
        report's box plus that offset. Inside the box alone, 186 of the dome survey's pose attempts failed as
        ``outside_tolerance`` (the 1.1 mm gauge offset plus the report's error past 3 mm), each a lost frame
        and a relocalization on the tracking path.
    gauge : ``all`` (default) or ``window``: the robot's reports that place each local map in the world.
        ``window``: its own keyframes' (the local BCBA's gauge), off the truth by the mean of six reports'
        errors. ``all``: every keyframe's so far, the older ones carried into the window's world by the steps
        between successive local maps (:func:`_world_step`), so that the errors average down as the map grows
        (docs/live.md: the image pose's error was mostly this gauge; on the dome survey the gauge's shift at
        the camera fell from 1.47 to 1.23 mm median, the fused error from 1.95 to 1.56 mm, and the frames
        with the fused error at most half the robot's rose from 26 to 42 %; holding its scale at 1 did
        worse, 34 %: the windows' scales differ).
    change_test : the test of tissue that changed, or None (default) to keep every point: a function
        ``(camera, points, sigma_mm, images, poses, *, references) -> SurfaceChange``, in practice
        ``functools.partial(scope3d.mvs.surface_change.detect_surface_change, options=...)`` (``scope3d
        live`` passes it; ``mvs`` sits beside ``sfm``, so the mapper takes it as a function).
        change_keyframes : int >= 3, the newest keyframes (adjusted together) whose plane sweeps test the map
        (default 3: the sweep's reference and its two sources; the two newest are swept, the test's two
        views of a point). change_min_baseline : float, the test waits while two of them are nearer than this
        fraction of the depth prior's near end (default 0.05, half the sweep's baseline of choice, 0.1:
        keyframes kept in a burst when tracking was lost barely move). change_reach_neighbours : int, the
        footprint of a change in an older keyframe reaches as far as the median distance to a map point's
        this-th neighbour there (default 16, the test's vote). change_scale : int >= 1, the test runs on the
        keyframes reduced this many times (default 2: a sweep of three 320 px frames took 0.75-2 s on the
        loaded 2-core machine, more than the worker's second per keyframe; at 160 px a quarter of it, the
        depth still good to a tenth of a millimetre at the survey's 3-7 mm baselines).
    depth_margin : float, the depth prior is the local map's 2nd-98th depth percentiles widened by this
        fraction on each side (default 0.1, as :func:`~scope3d.sfm.depth_priors.estimate_depth_prior`).
    working_range_mm : (near, far), where the scene may lie before any point is known (default 2-100 mm, an
        endoscope's depth of field and more). It only widens the first triangulation's gate by what the
        robot's box can shift a point at ``near``; the first pairs are matched exhaustively and verified.
    """

    localizer: LocalizerOptions = field(default_factory=LocalizerOptions)
    keyframes: KeyframeOptions = field(default_factory=KeyframeOptions)
    min_inlier_fraction: float = 0.5
    local_window: int = 6
    map_lag_frames: int = 30
    worker: str = "process"
    min_keyframes: int = 3
    features: FeatureOptions = field(default_factory=FeatureOptions)
    matching: MatchOptions = field(default_factory=MatchOptions)
    pairs: PairOptions = field(default_factory=PairOptions)
    tracks: TrackOptions = field(default_factory=TrackOptions)
    bundle: BundleStageOptions = field(default_factory=BundleStageOptions)
    kalman: KalmanOptions = field(default_factory=KalmanOptions)
    guide_sigmas: float = 3.0
    image_box_scale: float = 2.0
    gauge: str = "all"
    change_test: Callable | None = None
    change_keyframes: int = 3
    change_scale: int = 2
    change_min_baseline: float = 0.05
    change_reach_neighbours: int = 16
    depth_margin: float = 0.1
    working_range_mm: tuple[float, float] = (2.0, 100.0)

    def __post_init__(self) -> None:
        if self.gauge not in LIVE_GAUGES:
            raise ValueError(f"gauge must be one of {LIVE_GAUGES}, got {self.gauge!r}")
        if not 0 < self.min_inlier_fraction < 1:
            raise ValueError(f"min_inlier_fraction must be in (0, 1), got {self.min_inlier_fraction}")
        if self.local_window < 2:
            raise ValueError(f"local_window must be >= 2, got {self.local_window}")
        if self.worker not in LIVE_WORKERS:
            raise ValueError(f"worker must be one of {LIVE_WORKERS}, got {self.worker!r}")
        if not 2 <= self.min_keyframes <= self.local_window:
            raise ValueError(f"min_keyframes must be 2..local_window, got {self.min_keyframes}")
        if self.map_lag_frames < 0:
            raise ValueError(f"map_lag_frames must be >= 0, got {self.map_lag_frames}")
        if not (self.guide_sigmas > 0 and self.depth_margin >= 0):
            raise ValueError("need guide_sigmas > 0 and depth_margin >= 0")
        if not self.image_box_scale >= 1:
            raise ValueError(f"image_box_scale must be >= 1, got {self.image_box_scale}")
        if self.change_scale < 1:
            raise ValueError(f"change_scale must be >= 1, got {self.change_scale}")
        if self.change_keyframes < 3 or self.change_reach_neighbours < 1 or not self.change_min_baseline > 0:
            raise ValueError("need change_keyframes >= 3 (a sweep's reference and its two sources), "
                             "change_reach_neighbours >= 1 and change_min_baseline > 0")
        DepthPrior(*self.working_range_mm)  # raises on a wrong range


#: Named settings. ``dim_endoscope``: CLAHE and a lower SIFT threshold on keyframes and for tracking (the
#: map's preset of the same name; on the 320 px dome 1,100 features instead of 200).
LIVE_PRESETS: dict[str, LiveMapperOptions] = {
    "default": LiveMapperOptions(),
    "dim_endoscope": LiveMapperOptions(
        features=FEATURE_PRESETS["dim_endoscope"],
        localizer=LocalizerOptions(features=replace(FEATURE_PRESETS["dim_endoscope"], max_features=2000))),
}


@dataclass
class LiveFrame:
    """One frame's answer.

    index : the frame's number in the stream (from 0). time_s : its time. status : one of
        :data:`LIVE_STATUSES`. pose : fused ``cam_from_world`` (mm). covariance : (6, 6) of ``(w rad, C mm)``.
    image_pose, image_covariance : the tracking's own pose before fusion, or None when the image gave none.
    n_inliers : tracking inliers (0 without an image pose). keyframe : the keyframe's number when the frame
    became one, else None. latency_ms : wall time of :meth:`LiveMapper.add_frame`. waited_ms : the part of it
    spent waiting for a local map due at this frame that the worker had not finished (0 when it was ready).
    dropped_points : map points the change test found changed in the local map that became the tracking map
    at this frame (their tissue was re-mapped from the newest keyframes).
    """

    index: int
    time_s: float
    status: str
    pose: Pose
    covariance: np.ndarray
    image_pose: Pose | None
    image_covariance: np.ndarray | None
    n_inliers: int
    keyframe: int | None
    latency_ms: float
    waited_ms: float = 0.0
    dropped_points: int = 0


@dataclass
class LiveMap:
    """The map as it stands.

    keyframe_frames : (K,) the stream index of each keyframe. keyframe_poses : their adjusted poses (the
    live fused pose for a keyframe no adjustment has reached yet). measured : the robot's reports for them.
    points : (N, 3) mm world. colors : (N, 3) uint8. tracks : the observations (frame = keyframe number),
    None before any adjustment. final : True after the global BCBA.
    """

    keyframe_frames: np.ndarray
    keyframe_poses: list[Pose]
    measured: list[MeasuredPose]
    points: np.ndarray
    colors: np.ndarray
    tracks: Tracks | None
    final: bool = False


@dataclass
class _LocalMap:
    """A local BCBA's outcome: its keyframes, their adjusted poses, its tracks and its tracking map; the
    points the change test dropped before it was adjusted ((N, 3) mm, its world)."""

    keyframes: list[int]
    poses: list[Pose]
    tracks: Tracks
    points: MapPoints
    dropped: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))


class LiveMapper:
    """Simultaneous tracking and mapping with the robot's poses (see the module docstring).

    camera : the frames' intrinsics. Unless ``options.worker`` is ``inline`` the mapper owns a worker (a
    child process or a thread, started here): call :meth:`finish` or :meth:`close` (or use it as a context
    manager) when done.
    """

    def __init__(self, camera: Camera, options: LiveMapperOptions = LiveMapperOptions()):
        self.camera = camera
        self.options = options
        self._filter = PoseKalmanFilter(options.kalman)
        self._selector = KeyframeSelector(options.keyframes, field_radius_px=camera.mask_radius_px)
        self._localizer: Localizer | None = None
        self._keyframes: list[_KeyframeInfo] = []
        self._pending: list[int] = []  # the due frame of each submitted keyframe's local map, in order
        self._worker = _start_worker(camera, options)
        self._frames = 0
        self._last_time: float | None = None
        self._last_status = "lost"
        self._reference_inliers = 0  # inliers of the last keyframe, or of the first frame tracked on a new local map
        self._last_keyframe_pose: Pose | None = None  # its fused pose, in the tracking's current world
        self._map_depth_mm: float | None = None  # the tracking map's median depth in its newest keyframe
        self._local: _LocalMap | None = None
        self._final: LiveMap | None = None

    # --- the stream -----------------------------------------------------------------------------
    def add_frame(self, image: np.ndarray, measured_pose: MeasuredPose, time: float) -> LiveFrame:
        """Track one frame, fuse it with the robot's report, keep it as a keyframe when the view moved.

        image : (H, W, 3) uint8 RGB or (H, W) uint8, the camera's size. measured_pose : the robot's pose
        for this frame with its tolerance box. time : seconds, not before the previous frame's.
        """
        t0 = _clock()
        if self._final is not None:
            raise ValueError("the live map is finished: start a new LiveMapper")
        if self._last_time is not None and not time >= self._last_time:
            raise ValueError(f"frame time {time} s is before the previous frame's {self._last_time} s")
        index = self._frames
        t_wait = _clock()
        dropped = 0
        while self._pending and self._pending[0] <= index:
            self._pending.pop(0)
            dropped += self._apply(self._worker.result())
        waited_ms = 1000.0 * (_clock() - t_wait) if self._worker.was_late() else 0.0
        if self._filter.initialised:
            self._filter.predict(time - self._last_time)
        self._filter.update_measured(measured_pose)
        result: LocalizationResult | None = None
        if self._localizer is not None:
            tol = measured_pose.tolerance
            box = PoseTolerance(self.options.image_box_scale * tol.position_mm,
                                self.options.image_box_scale * tol.orientation_rad)
            result = self._localizer.localize(image, MeasuredPose(measured_pose.pose, box))
        ok = result is not None and result.ok
        status = "lost"
        if ok:
            self._filter.update(result.pose, result.covariance)
            status = "relocalized" if result.mode == "global" or self._last_status == "lost" else "tracked"
            if self._reference_inliers == 0:
                self._reference_inliers = result.n_inliers
        decision = self._selector.measure(image)
        thinned = ok and result.n_inliers < self.options.min_inlier_fraction * self._reference_inliers
        keep = (decision.keep or thinned) and self._adds_baseline(self._filter.pose)
        keyframe = None
        if keep:
            # both rules measure from the frame kept: the view's shift from it, tracking's inliers against
            # its own (left at the map's first frame's, the thinned rule held until the next local map
            # arrived, map_lag_frames later, and kept every frame of a slow stretch: 8 keyframes 0.15 mm apart)
            self._selector.keep()
            if ok:
                self._reference_inliers = result.n_inliers
            self._last_keyframe_pose = self._filter.pose
            keyframe = len(self._keyframes)
            guide = MeasuredPose(self._filter.pose, covariance_to_tolerance(self._filter.pose_covariance,
                                                                             self.options.guide_sigmas))
            self._keyframes.append(_KeyframeInfo(index, measured_pose, guide))
            self._worker.submit(keyframe, np.ascontiguousarray(image), measured_pose, guide)
            self._pending.append(index + self.options.map_lag_frames)
            status = "keyframe"
        self._frames += 1
        self._last_time = time
        self._last_status = status if ok else "lost"
        return LiveFrame(index, float(time), status, self._filter.pose, self._filter.pose_covariance,
                         result.pose if ok else None, result.covariance if ok else None,
                         result.n_inliers if ok else 0, keyframe, 1000.0 * (_clock() - t0), waited_ms, dropped)

    def current_map(self) -> LiveMap:
        """The map now: every keyframe (adjusted where a local BCBA reached it) and the local map's points;
        after :meth:`finish`, the global map."""
        if self._final is not None:
            return self._final
        local = self._local
        poses = [k.guide.pose for k in self._keyframes]
        points, colors, tracks = np.zeros((0, 3)), np.zeros((0, 3), np.uint8), None
        if local is not None:
            for k, pose in zip(local.keyframes, local.poses):
                poses[k] = pose
            # the window's frames are its own positions; the map's are keyframe numbers
            points, colors = local.points.xyz_mm, local.points.colors
            tracks = replace(local.tracks, frame=np.asarray(local.keyframes)[local.tracks.frame])
        return LiveMap(self._keyframe_frames(), poses, [k.measured for k in self._keyframes], points, colors, tracks)

    def finish(self) -> LiveMap:
        """Wait for the keyframe work, then the global BCBA over every keyframe (see the module docstring).
        Raises InputError when the keyframes hold no consistent point."""
        if self._final is not None:
            return self._final
        for _ in self._pending:
            self._apply(self._worker.result())
        self._pending = []
        if len(self._keyframes) < 2:
            self.close()
            raise InputError(f"{len(self._keyframes)} keyframe(s): the scope did not move enough to map anything")
        try:
            self._final = self._worker.finish(self._keyframe_frames())
        finally:
            self.close()
        return self._final

    def close(self) -> None:
        """Stop the worker (work under way is finished first)."""
        self._worker.close()

    def __enter__(self) -> "LiveMapper":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def n_keyframes(self) -> int:
        return len(self._keyframes)

    def _apply(self, outcome: "_LocalMap | None") -> int:
        """Track on a new local map; returns how many points the change test dropped from it."""
        if outcome is None:
            return 0
        before, self._local = self._local, outcome
        if self._localizer is None:
            self._localizer = Localizer(outcome.points, self.camera, self.options.localizer)
        else:
            moved = _new_from_old(before, outcome)
            self._localizer.replace_map(outcome.points, moved)
            if moved is not None:
                self._filter.change_world(moved)
                self._last_keyframe_pose = self._last_keyframe_pose @ moved.inverse()
        self._reference_inliers = 0
        depth = outcome.poses[-1].transform(outcome.points.xyz_mm)[:, 2]
        self._map_depth_mm = float(np.median(depth[depth > 0])) if np.any(depth > 0) else None
        return len(outcome.dropped)

    def _adds_baseline(self, pose: Pose) -> bool:
        """Whether a keyframe at ``pose`` would add the baseline triangulation needs: from the last keyframe,
        ``tracks.min_angle_deg`` of parallax at the tracking map's median depth (before any map, at
        ``working_range_mm``'s near end: the robot's poses alone measure no finer). A frame kept without it
        adds points that only the adjustment's drift places, millimetres off the wall."""
        if self._last_keyframe_pose is None:
            return True
        depth = self._map_depth_mm or self.options.working_range_mm[0]
        baseline = float(np.linalg.norm(pose.centre - self._last_keyframe_pose.centre))
        return baseline >= depth * np.tan(np.radians(self.options.tracks.min_angle_deg))

    def _keyframe_frames(self) -> np.ndarray:
        return np.array([k.frame for k in self._keyframes], np.int64)


@dataclass
class _KeyframeInfo:
    frame: int
    measured: MeasuredPose  # the robot's report
    guide: MeasuredPose  # the fused pose with its guide_sigmas box, at the time it was kept


class _KeyframeWork:
    """The keyframe work and all it keeps (features, matches, adjusted poses, depth prior): one per mapper,
    fed one keyframe at a time, in order, wherever it runs (the mapper's thread, a worker thread or a child
    process)."""

    def __init__(self, camera: Camera, options: LiveMapperOptions):
        self.camera = camera
        self.options = options
        self.measured: list[MeasuredPose] = []
        self.guides: list[MeasuredPose] = []
        self.features: list[Features] = []
        self.matches: dict[tuple[int, int], PairMatches] = {}
        self.adjusted: dict[int, Pose] = {}
        self.depth_prior: DepthPrior | None = None
        # the change test's state: per keyframe and feature, whether it saw tissue that has changed since (its
        # matches are no longer used); the newest keyframes' images; every adjusted keyframe's pose in the
        # newest local map's world
        self.retired: list[np.ndarray] = []
        self.images: dict[int, np.ndarray] = {}
        self.posed: dict[int, Pose] = {}
        self.last: _LocalMap | None = None

    def add(self, keyframe: int, image: np.ndarray, measured: MeasuredPose, guide: MeasuredPose) -> _LocalMap | None:
        """A new keyframe: its SIFT, its matches to the window's other keyframes, the local BCBA over the
        window, then the change test (tissue the newest keyframes no longer see as the map has it is dropped
        and the window adjusted again without it). None when the window holds too little to adjust."""
        o = self.options
        if keyframe != len(self.features):
            raise ValueError(f"keyframe {keyframe} out of order (expected {len(self.features)})")
        self.measured.append(measured)
        self.guides.append(guide)
        self.features.append(detect(image, self.camera, options=o.features))
        self.retired.append(np.zeros(len(self.features[-1].keypoints), bool))
        if o.change_test is not None:
            self.images[keyframe] = _reduced(image, o.change_scale)
            self.images.pop(keyframe - o.change_keyframes, None)
        window = list(range(max(0, keyframe - o.local_window + 1), keyframe + 1))
        for i in window[:-1]:
            if self.depth_prior is None:
                m = match_exhaustive(self.camera, self.features[i], self.features[keyframe], o.matching,
                                     i=i, j=keyframe)
            else:
                m = match_guided_many(self.camera, [self.features[i], self.features[keyframe]],
                                      [self.guide(i), self.guide(keyframe)], [(0, 1, 1.0)], self.depth_prior,
                                      options=o.matching, frame_ids=[i, keyframe])[0]
            self.matches[(i, keyframe)] = m
        if len(window) < o.min_keyframes:
            return None
        outcome = self._adjust_window(window)
        if outcome is None:
            return None
        self._move_world(outcome)
        if o.change_test is not None and len(window) > o.change_keyframes:
            dropped = self._drop_changed(outcome)
            if len(dropped):
                again = self._adjust_window(window)
                if again is not None:
                    self._move_world(again)
                    outcome = again
                outcome.dropped = dropped
        if o.gauge == "all":
            outcome = self._anchored(outcome)
        return outcome

    def _anchored(self, local: _LocalMap) -> _LocalMap:
        """The local map moved into the world that best fits every keyframe's robot report so far
        (:func:`~scope3d.estimators.gauge.gauge_from_measurements` over the keyframes' poses in this map's
        world, each weighed by its box)."""
        ks = sorted(self.posed)
        step = gauge_from_measurements([self.posed[k] for k in ks], [self.measured[k] for k in ks])
        poses = moved_by(local.poses, step)
        self.posed = dict(zip(ks, moved_by([self.posed[k] for k in ks], step)))
        for k, pose in zip(local.keyframes, poses):
            self.adjusted[k] = pose
        tracks = replace(local.tracks, points=step.apply(local.tracks.points))
        points = replace(local.points, xyz_mm=step.apply(local.points.xyz_mm))
        moved = _LocalMap(local.keyframes, poses, tracks, points, local.dropped)
        self.last = moved
        return moved

    def _adjust_window(self, window: list[int]) -> _LocalMap | None:
        """The local BCBA over ``window`` (keyframe numbers) from its usable matches; None when too little
        survives or the solution is no map (see :meth:`_depth_prior`)."""
        o = self.options
        local = {k: n for n, k in enumerate(window)}
        matches = [_renumbered(self._usable(m), local[i], local[j]) for (i, j), m in self.matches.items()
                   if i in local and j in local and len(m)]
        features = [self.features[k] for k in window]
        tracks = build_tracks(features, [m for m in matches if len(m)], min_track_length=o.tracks.min_track_length)
        if tracks.n_tracks < o.localizer.pose.min_inliers:
            return None
        try:
            adjusted = adjust_map("bounded", [self.measured[k] for k in window], self.camera, tracks,
                                  [self.guide(k) for k in window], self.depth_prior or DepthPrior(*o.working_range_mm),
                                  track_options=o.tracks, options=o.bundle, height_field=True, where="live map")
        except InputError:
            return None
        prior = self._depth_prior(adjusted.poses, adjusted.tracks)
        if prior is None:
            return None
        t = _with_parallax(self.camera, adjusted.poses, adjusted.tracks, prior.near_mm, o.tracks.min_angle_deg)
        if t.n_tracks < o.localizer.pose.min_inliers:
            return None
        for k, pose in zip(window, adjusted.poses):
            self.adjusted[k] = pose
        self.depth_prior = prior
        points = MapPoints(t.points, track_descriptors(features, t), t.lengths(), t.colors,
                           observation_descriptors(features, t), t.track.copy())
        return _LocalMap(window, list(adjusted.poses), t, points)

    def _usable(self, m: PairMatches) -> PairMatches:
        """The matches of a keyframe pair without the features retired as changed tissue."""
        keep = ~(self.retired[m.i][m.idx_i] | self.retired[m.j][m.idx_j])
        return m if keep.all() else PairMatches(m.i, m.j, m.idx_i[keep], m.idx_j[keep])

    def _move_world(self, new: _LocalMap) -> None:
        """Every keyframe's pose in ``new``'s world: its own keyframes' adjusted poses, the older ones moved by
        the gauge step between the last local map and this one (:func:`_world_step`)."""
        old, self.last = self.last, new
        if old is not None:
            new_from_old = _world_step(old, new, self.depth_prior.near_mm)
            if new_from_old is not None:
                self.posed = dict(zip(self.posed, moved_by(list(self.posed.values()), new_from_old)))
        self.posed.update(zip(new.keyframes, new.poses))

    def _drop_changed(self, local: _LocalMap) -> np.ndarray:
        """The change test (``change_test``, ``mvs.surface_change``): the plane sweeps of the newest
        ``change_keyframes``, adjusted together, against the local map's points. The changed points, and those
        in a swept view's region to map again (``SurfaceChange.regions``), lose their observations in the
        older keyframes, and so does every older keyframe's feature within their footprint there (the reach
        of the test's vote in that image: the median distance to a map point's ``change_reach_neighbours``-th
        neighbour; never triangulated, or in a track the test did not judge, such a feature could still bring
        the old surface back in a later window or the global BCBA). Returns the changed points ((N, 3) mm,
        this local map's world).

        Only the window's points are tested: a map left behind is in its own window's world. Carried into the
        newest one by the chain of gauge steps it was 0.5-2.5 mm off within a few windows on the dome survey
        (the test's noise factor rose to 3.6 and it flagged points off the pit), far above the 0.1-0.3 mm the
        test resolves. Tissue changed while the scope looked elsewhere needs a loop closure first."""
        o = self.options
        newest = local.keyframes[-o.change_keyframes:]
        if not _sweepable(self.camera, [self.posed[k] for k in newest], self.depth_prior, o.change_min_baseline):
            return np.zeros((0, 3))
        t = local.tracks
        found = o.change_test(_reduced_camera(self.camera, o.change_scale), t.points,
                              _point_sigma(self.camera, local.poses, t), [self.images[k] for k in newest],
                              [self.posed[k] for k in newest], references=list(range(len(newest)))[-2:])
        # the changed points, and every point in the region to map again of a swept view: most points over a
        # change are judged in too few views to be tested themselves (the sweep keeps a depth only where the
        # texture has contrast), and left in, the old surface stays in the map beside the new one
        changed = found.changed.copy()
        small = _reduced_camera(self.camera, o.change_scale)
        for r, region in zip(found.references, found.regions):
            px = _in_view(small, self.posed[newest[r]], t.points, region)
            changed |= ~np.isnan(px[:, 0])
        if not changed.any():
            return np.zeros((0, 3))
        older = np.array([k for k in self.posed if k < newest[0]], np.int64)
        frames = np.asarray(local.keyframes)[t.frame]
        own = changed[t.track] & np.isin(frames, older)
        for k, f in zip(frames[own], t.feature[own]):
            self.retired[k][f] = True
        field_mask = self.camera.mask()
        for k in older:
            seen_px = _in_view(self.camera, self.posed[int(k)], t.points, field_mask)
            visible = ~np.isnan(seen_px[:, 0])
            hit = changed & visible
            if hit.sum() == 0 or visible.sum() < 2:
                continue
            seen = seen_px[visible]
            k_reach = min(o.change_reach_neighbours, len(seen) - 1)
            reach = float(np.median(cKDTree(seen).query(seen, k_reach + 1)[0][:, -1]))
            self.retired[k] |= cKDTree(seen_px[hit]).query(self.features[k].keypoints, 1)[0] <= reach
        return t.points[changed]

    def guide(self, keyframe: int) -> MeasuredPose:
        """A keyframe's pose for guided matching and to start an adjustment: the adjusted one once a local
        BCBA reached it, with the box its fused covariance gave when it was kept."""
        pose = self.adjusted.get(keyframe)
        return self.guides[keyframe] if pose is None else MeasuredPose(pose, self.guides[keyframe].tolerance)

    def finish(self, frames: np.ndarray) -> LiveMap:
        """The global BCBA over every keyframe (see the module docstring)."""
        n = len(self.features)
        prior = self.depth_prior
        if prior is None:
            raise InputError("no local map was built: the keyframes could not be matched")
        guides = [self.guide(k) for k in range(n)]
        pairs = select_pairs(self.camera, [g.pose for g in guides], prior, options=self.options.pairs)
        todo = [(i, j, ov) for i, j, ov in pairs if (i, j) not in self.matches]
        for m in match_guided_many(self.camera, self.features, guides, todo, prior, options=self.options.matching):
            self.matches[(m.i, m.j)] = m
        matches = [u for u in (self._usable(m) for m in self.matches.values()) if len(u)]
        tracks = build_tracks(self.features, matches, min_track_length=self.options.tracks.min_track_length)
        if tracks.n_tracks == 0:
            raise InputError("no feature could be matched between keyframes")
        adjusted = adjust_map("bounded", self.measured, self.camera, tracks, guides, prior,
                              track_options=self.options.tracks, options=self.options.bundle, height_field=True,
                              where="live map")
        near = (self._depth_prior(adjusted.poses, adjusted.tracks) or prior).near_mm
        t = _with_parallax(self.camera, adjusted.poses, adjusted.tracks, near, self.options.tracks.min_angle_deg)
        return LiveMap(frames, adjusted.poses, list(self.measured), t.points, t.colors, t, final=True)

    def _depth_prior(self, poses: list[Pose], tracks: Tracks) -> DepthPrior | None:
        """The depth range of the newest local map's points in their keyframes (2nd-98th percentile,
        widened): the window's own, not joined with older ones (the first windows' scale is the least
        certain, their range the least right). None when more than 2 % of the observed points lie behind
        their keyframe, or 98 % nearer than ``working_range_mm``'s near end: a mirrored or collapsed
        solution (two keyframes a few mm apart can give one), not a map."""
        depth = np.concatenate([poses[f].transform(tracks.points[tracks.track[tracks.frame == f]])[:, 2]
                                for f in np.unique(tracks.frame)])
        lo, hi = np.percentile(depth, [2.0, 98.0])
        if lo <= 0 or hi < self.options.working_range_mm[0]:
            return None
        m = self.options.depth_margin
        return DepthPrior(float(max(lo * (1 - m), 1e-3)), float(hi * (1 + m)))


class _InlineWorker:
    """The keyframe work done in the caller's thread when submitted; results handed out in order."""

    def __init__(self, camera: Camera, options: LiveMapperOptions):
        self._work = _KeyframeWork(camera, options)
        self._results: list = []

    def submit(self, keyframe, image, measured, guide) -> None:
        self._results.append(self._work.add(keyframe, image, measured, guide))

    def result(self):
        return self._results.pop(0)

    def was_late(self) -> bool:
        """Whether the results taken at this frame had to be waited for (never, inline: the work was done
        at the keyframe)."""
        return False

    def finish(self, frames: np.ndarray) -> LiveMap:
        return self._work.finish(frames)

    def close(self) -> None:
        pass


class _ThreadWorker(_InlineWorker):
    """The keyframe work on one worker thread (the GIL is shared with tracking: see ``LiveMapperOptions``)."""

    def __init__(self, camera: Camera, options: LiveMapperOptions):
        super().__init__(camera, options)
        self._executor: ThreadPoolExecutor | None = ThreadPoolExecutor(max_workers=1, thread_name_prefix="scope3d-live")
        self._late = False

    def submit(self, keyframe, image, measured, guide) -> None:
        self._results.append(self._executor.submit(self._work.add, keyframe, image, measured, guide))

    def result(self):
        future = self._results.pop(0)
        self._late = not future.done()
        return future.result()

    def was_late(self) -> bool:
        late, self._late = self._late, False
        return late

    def close(self) -> None:
        if self._executor is not None:
            self._executor.shutdown(wait=True)
            self._executor = None


class _ProcessWorker:
    """The keyframe work in a child process (its own GIL): jobs and answers through a pipe, in order. The
    child is spawned, not forked: a fork copies OpenCV's and the BLAS's thread pools in whatever state the
    parent's threads left them. A sender and a reader thread move the jobs and the answers, so the stream
    never blocks on the pipe (a frame and a local map both exceed a pipe's buffer: sent from the stream's
    thread, a frame waits until the child reads it, a second or more while the child is still starting).
    The child ends when the pipe closes (the mapper closed, or its process died)."""

    def __init__(self, camera: Camera, options: LiveMapperOptions):
        context = multiprocessing.get_context("spawn")
        self._conn, child = context.Pipe(duplex=True)
        self._process = context.Process(target=_serve, args=(child, camera, options), daemon=True,
                                        name="scope3d-live")
        self._process.start()
        child.close()
        self._answers: queue.SimpleQueue = queue.SimpleQueue()
        self._late = False
        self._reader = threading.Thread(target=_read_answers, args=(self._conn, self._answers), daemon=True,
                                        name="scope3d-live-reader")
        self._reader.start()
        self._jobs: queue.SimpleQueue = queue.SimpleQueue()
        self._sender = threading.Thread(target=_send_jobs, args=(self._conn, self._jobs), daemon=True,
                                        name="scope3d-live-sender")
        self._sender.start()

    def submit(self, keyframe, image, measured, guide) -> None:
        self._jobs.put(("add", (keyframe, image, measured, guide)))

    def result(self):
        self._late = self._late or self._answers.empty()
        return self._answer()

    def was_late(self) -> bool:
        late, self._late = self._late, False
        return late

    def finish(self, frames: np.ndarray) -> LiveMap:
        self._jobs.put(("finish", (frames,)))
        return self._answer()

    def _answer(self):
        ok, value = self._answers.get()
        if not ok:
            if isinstance(value, InputError):
                raise value
            raise RuntimeError(f"the live mapper's worker failed:\n{value}")
        return value

    def close(self) -> None:
        if self._process is not None:
            self._jobs.put(None)  # the child ends its loop, then the sender
            self._sender.join()
            self._process.join()
            self._reader.join()
            self._conn.close()
            self._process = None


def _send_jobs(conn, jobs: queue.SimpleQueue) -> None:
    """The parent's sender thread: every job to the child, in order; None (sent too) ends it."""
    while True:
        job = jobs.get()
        try:
            conn.send(job)
        except OSError:
            return
        if job is None:
            return


def _read_answers(conn, answers: queue.SimpleQueue) -> None:
    """The parent's reader thread: every answer into ``answers``; the child's end as a failure."""
    while True:
        try:
            answers.put(conn.recv())
        except (EOFError, OSError):
            answers.put((False, "the worker process ended"))
            return


def _serve(conn, camera: Camera, options: LiveMapperOptions) -> None:
    """The child's loop: keyframes in, local maps out, until ``finish`` or the parent's end."""
    work = _KeyframeWork(camera, options)
    while True:
        try:
            job = conn.recv()
        except EOFError:
            return
        if job is None:
            conn.close()
            return
        what, args = job
        try:
            if what == "add":
                answer = (True, work.add(*args))
            else:
                answer = (True, work.finish(*args))
        except InputError as exc:
            answer = (False, exc)
        except Exception:  # noqa: BLE001 - carried to the parent, which raises it
            answer = (False, traceback.format_exc())
        conn.send(answer)


def _start_worker(camera: Camera, options: LiveMapperOptions):
    workers = {"inline": _InlineWorker, "thread": _ThreadWorker, "process": _ProcessWorker}
    return workers[options.worker](camera, options)


def _new_from_old(old: _LocalMap, new: _LocalMap) -> Pose | None:
    """How the new local map's world sits in the old one's: each adjustment aligns its window to the
    robot's reports, so the gauge moves by a fraction of the robot's error from one window to the next.
    Taken at the newest keyframe both adjusted (the one tracking has just followed)."""
    common = sorted(set(old.keyframes) & set(new.keyframes))
    if not common:
        return None
    k = common[-1]
    return new.poses[new.keyframes.index(k)].inverse() @ old.poses[old.keyframes.index(k)]


#: a SIFT keypoint's localisation error (px) in a map point's depth error; its scale matters little: the change
#: test measures the scale of its residuals (the noise factor), this only weighs a point's error against the sweep's
KEYPOINT_SIGMA_PX = 0.5


def _point_sigma(camera: Camera, poses: list[Pose], tracks: Tracks) -> np.ndarray:
    """(n_tracks,) mm: each point's depth error from its widest pair of views, ``z^2 sigma_px / (f b)``, z its
    distance from its first view's centre, b the longest baseline from that view among its observers."""
    centres = np.array([p.centre for p in poses])[tracks.frame]
    first = np.searchsorted(tracks.track, np.arange(tracks.n_tracks))
    baseline = np.zeros(tracks.n_tracks)
    np.maximum.at(baseline, tracks.track, np.linalg.norm(centres - centres[first][tracks.track], axis=1))
    depth = np.linalg.norm(tracks.points - centres[first], axis=1)
    return depth ** 2 * KEYPOINT_SIGMA_PX / (camera.fx * np.maximum(baseline, 1e-3))


def _sweepable(camera: Camera, poses: list[Pose], prior: DepthPrior, min_baseline: float) -> bool:
    """Whether the keyframes can be swept together: every two at least ``min_baseline`` times the near
    depth apart (keyframes kept in a burst when tracking was lost barely move: no parallax), and each one's
    view centre, at the near and the far depth, inside every other's image (a pose gone wrong looks away)."""
    centres = np.array([p.centre for p in poses])
    apart = np.linalg.norm(centres[:, None] - centres[None], axis=2)[np.triu_indices(len(poses), 1)]
    if apart.min() < min_baseline * prior.near_mm:
        return False
    centre_px = np.array([[(camera.width - 1) / 2.0, (camera.height - 1) / 2.0]])
    for a in poses:
        ends = np.concatenate([a.inverse().transform(camera.unproject(centre_px, z))
                               for z in (prior.near_mm, prior.far_mm)])
        for b in poses:
            if not (np.all(b.transform(ends)[:, 2] > 0) and np.all(np.isfinite(camera.project_world(b, ends)))):
                return False
    return True


def _reduced(image: np.ndarray, scale: int) -> np.ndarray:
    """The image reduced ``scale`` times (pixel areas averaged)."""
    if scale == 1:
        return image
    h, w = image.shape[:2]
    return cv2.resize(image, (w // scale, h // scale), interpolation=cv2.INTER_AREA)


def _reduced_camera(camera: Camera, scale: int) -> Camera:
    """The camera of :func:`_reduced` images: a reduced pixel's centre is the mean of the ``scale`` x ``scale``
    pixels it averages (pixel centres at integers: u' = (u + 0.5) / scale - 0.5)."""
    if scale == 1:
        return camera
    return replace(camera, width=camera.width // scale, height=camera.height // scale, fx=camera.fx / scale,
                   fy=camera.fy / scale, cx=(camera.cx + 0.5) / scale - 0.5, cy=(camera.cy + 0.5) / scale - 0.5,
                   mask_radius_px=None if camera.mask_radius_px is None else camera.mask_radius_px / scale)


def _in_view(camera: Camera, pose: Pose, points: np.ndarray, field_mask: np.ndarray) -> np.ndarray:
    """(N, 2) pixels of the points in front of the camera and inside its field, NaN for the others."""
    cam = pose.transform(points)
    out = np.full((len(points), 2), np.nan)
    front = cam[:, 2] > 0
    px = camera.project(cam[front])
    ij = np.round(px).astype(int)
    inside = (ij[:, 0] >= 0) & (ij[:, 1] >= 0) & (ij[:, 0] < camera.width) & (ij[:, 1] < camera.height)
    inside[inside] = field_mask[ij[inside, 1], ij[inside, 0]]
    out[np.flatnonzero(front)[inside]] = px[inside]
    return out


def _world_step(old: _LocalMap, new: _LocalMap, reach_mm: float) -> Similarity | None:
    """The rigid step from the old local map's world to the new one's, fitted to all the keyframes both
    adjusted (not one, as the tracking map's :func:`_new_from_old`: that one keyframe's own error would move
    every older pose by it): their centres and a point ``reach_mm`` along each optical axis (a survey's
    centres may lie on a line, which leaves the rotation about it free). None with fewer than two common
    keyframes."""
    common = sorted(set(old.keyframes) & set(new.keyframes))
    if len(common) < 2:
        return None

    def marks(m: _LocalMap) -> np.ndarray:
        poses = [m.poses[m.keyframes.index(k)] for k in common]
        return np.concatenate([[p.centre for p in poses], [p.centre + reach_mm * p.optical_axis for p in poses]])

    return fit_similarity(marks(old), marks(new), with_scale=False)


def _with_parallax(camera: Camera, poses: list[Pose], tracks: Tracks, near_mm: float, min_angle_deg: float) -> Tracks:
    """The triangulated tracks whose views span ``min_angle_deg`` (triangulation's gate) with the point at a
    depth the map can hold: a point nearer its views' mean centre than ``near_mm`` (the depth prior's near
    end) is judged as if moved out to it along that line. Triangulation judges a point where it lies, so
    views a few hundredths of a millimetre apart pass it with their point collapsed onto the cameras
    (the dome survey's keyframe burst left such points 16 mm off the wall)."""
    centres = np.array([p.centre for p in poses])[tracks.frame]
    mean = np.zeros((tracks.n_tracks, 3))
    np.add.at(mean, tracks.track, centres)
    mean /= np.bincount(tracks.track, minlength=tracks.n_tracks)[:, None]
    away = tracks.points - mean
    dist = np.linalg.norm(away, axis=1, keepdims=True)
    pushed = mean + away * np.maximum(dist, near_mm) / np.maximum(dist, 1e-12)
    angle = ray_angles_deg(camera, poses, replace(tracks, points=pushed))
    return tracks.subset((angle >= min_angle_deg)[tracks.track])


def _renumbered(m: PairMatches, i: int, j: int) -> PairMatches:
    return PairMatches(i, j, m.idx_i, m.idx_j)


def _clock() -> float:
    return time.perf_counter()
