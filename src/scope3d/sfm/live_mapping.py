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
  ``min_inlier_fraction`` of the points the current local map first gave.

Per keyframe, on one worker thread (``concurrent.futures``) while tracking goes on:

* SIFT on the keyframe, matched against the previous ``local_window - 1`` keyframes with pose-guided
  matching (:func:`~scope3d.feature.matching.match_guided_many`; the windows come from the fused poses'
  3-sigma boxes, so a frame tracked to 0.05 mm is searched in a few pixels) — the first pairs, before any
  depth is known, exhaustively;
* **local BCBA** over the newest ``local_window`` keyframes: tracks, triangulation and bundle adjustment
  with every keyframe kept inside the robot's box (:func:`~scope3d.sfm.guided_mapping.adjust_map`, the
  map's own stage), started from the keyframes' live poses. Its points (with their SIFT descriptors)
  become the tracking map, ``map_lag_frames`` frames after the keyframe: a fixed lag rather than "when
  done", so the output does not depend on the machine's load (the stream waits when the worker is late).

:meth:`LiveMapper.finish` runs the **global BCBA**: pairs over all keyframes chosen from their adjusted
poses (:func:`~scope3d.feature.pairs.select_pairs`, which also closes loops: a serpentine survey's
neighbouring rows, a return to a mapped region), the missing pairs matched guided, then the map's
tracks-triangulation-bounded-adjustment stage over every keyframe with the robot's boxes. It is the same
stage ``scope3d map`` runs on the same frames, started from better poses.

Statuses (:data:`LIVE_STATUSES`): ``tracked`` (image pose fused with the robot's), ``keyframe`` (as tracked
— or the robot's alone before the first map — and the frame was kept), ``relocalized`` (the image pose came
from global matching, or after a lost frame), ``lost`` (no image pose: the robot's report through the
filter, the covariance says so).

Units: mm and radians; ``time`` in seconds on any clock that only goes forward.
"""
from __future__ import annotations

import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from scope3d.errors import InputError
from scope3d.estimators.kalman import KalmanOptions, PoseKalmanFilter, covariance_to_tolerance
from scope3d.estimators.triangulation import TrackOptions
from scope3d.feature.depth_prior import DepthPrior
from scope3d.feature.detection import FeatureOptions, Features, detect
from scope3d.feature.keyframes import KeyframeOptions, KeyframeSelector
from scope3d.feature.matching import MatchOptions, PairMatches, match_exhaustive, match_guided_many
from scope3d.feature.pairs import PairOptions, select_pairs
from scope3d.feature.tracks import build_tracks, observation_descriptors, track_descriptors
from scope3d.geometry.pose import Pose
from scope3d.io.map_points import MapPoints
from scope3d.scene.tracks import Tracks
from scope3d.sensor.camera import Camera
from scope3d.sensor.pose_tolerance import MeasuredPose
from scope3d.sfm.guided_mapping import BundleStageOptions, adjust_map
from scope3d.sfm.localization import LocalizationResult, Localizer, LocalizerOptions

LIVE_STATUSES = ("tracked", "keyframe", "relocalized", "lost")


@dataclass(frozen=True)
class LiveMapperOptions:
    """How the live map is built.

    localizer : tracking against the local map (:class:`~scope3d.sfm.localization.LocalizerOptions`).
    keyframes : when the view has moved enough (:class:`~scope3d.feature.keyframes.KeyframeOptions`).
    min_inlier_fraction : float in (0, 1), a frame also becomes a keyframe when its tracking inliers fall
        below this fraction of what the first frame tracked on the current local map had (default 0.5: the
        view has left half of the mapped points behind).
    local_window : int >= 2, keyframes in the local BCBA and in the tracking map (default 6: with a keyframe
        every fifth of the image a wall point is in about five, so the window holds every view of the
        points the newest keyframe sees).
    map_lag_frames : int >= 0, the local BCBA of a keyframe becomes the tracking map this many frames later
        (default 15, half a second at 30 fps: the worker's budget for SIFT, matching and the adjustment).
        0 computes it inline at the keyframe (the stream waits for it).
    in_thread : bool, run the keyframe work on a worker thread (default True; False runs it inline when
        submitted, with the same lag: the results are identical).
    features : SIFT on keyframes (the map's default settings). matching : guided matching of keyframe pairs.
    pairs : the global BCBA's pair choice. tracks : triangulation gates. bundle : the adjustments.
    kalman : the fusion filter's motion model.
    guide_sigmas : float, a keyframe's search box for guided matching is this many standard deviations of
        its fused pose (default 3).
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
    map_lag_frames: int = 15
    in_thread: bool = True
    features: FeatureOptions = field(default_factory=FeatureOptions)
    matching: MatchOptions = field(default_factory=MatchOptions)
    pairs: PairOptions = field(default_factory=PairOptions)
    tracks: TrackOptions = field(default_factory=TrackOptions)
    bundle: BundleStageOptions = field(default_factory=BundleStageOptions)
    kalman: KalmanOptions = field(default_factory=KalmanOptions)
    guide_sigmas: float = 3.0
    depth_margin: float = 0.1
    working_range_mm: tuple[float, float] = (2.0, 100.0)

    def __post_init__(self) -> None:
        if not 0 < self.min_inlier_fraction < 1:
            raise ValueError(f"min_inlier_fraction must be in (0, 1), got {self.min_inlier_fraction}")
        if self.local_window < 2:
            raise ValueError(f"local_window must be >= 2, got {self.local_window}")
        if self.map_lag_frames < 0:
            raise ValueError(f"map_lag_frames must be >= 0, got {self.map_lag_frames}")
        if not (self.guide_sigmas > 0 and self.depth_margin >= 0):
            raise ValueError("need guide_sigmas > 0 and depth_margin >= 0")
        DepthPrior(*self.working_range_mm)  # raises on a wrong range


@dataclass
class LiveFrame:
    """One frame's answer.

    index : the frame's number in the stream (from 0). time_s : its time. status : one of
        :data:`LIVE_STATUSES`. pose : fused ``cam_from_world`` (mm). covariance : (6, 6) of ``(w rad, C mm)``.
    image_pose, image_covariance : the tracking's own pose before fusion, or None when the image gave none.
    n_inliers : tracking inliers (0 without an image pose). keyframe : the keyframe's number when the frame
    became one, else None. latency_ms : wall time of :meth:`LiveMapper.add_frame`.
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
class _Keyframe:
    frame: int
    image: np.ndarray
    measured: MeasuredPose  # the robot's report
    guide: MeasuredPose  # the fused pose with its guide_sigmas box, at the time it was kept
    features: Features | None = None  # detected by the worker


@dataclass
class _LocalMap:
    """A local BCBA's outcome: its keyframes, their adjusted poses, its tracks and its tracking map."""

    keyframes: list[int]
    poses: list[Pose]
    tracks: Tracks
    points: MapPoints


@dataclass
class _Pending:
    due: int  # the frame index at which the outcome is applied
    outcome: object  # a Future, or the _LocalMap / None itself


class LiveMapper:
    """Simultaneous tracking and mapping with the robot's poses (see the module docstring).

    camera : the frames' intrinsics. With ``options.in_thread`` the mapper owns one worker thread: call
    :meth:`finish` or :meth:`close` (or use it as a context manager) when done.
    """

    def __init__(self, camera: Camera, options: LiveMapperOptions = LiveMapperOptions()):
        self.camera = camera
        self.options = options
        self._filter = PoseKalmanFilter(options.kalman)
        self._selector = KeyframeSelector(options.keyframes, field_radius_px=camera.mask_radius_px)
        self._localizer: Localizer | None = None
        self._keyframes: list[_Keyframe] = []
        self._pending: list[_Pending] = []
        self._executor: ThreadPoolExecutor | None = None
        self._frames = 0
        self._last_time: float | None = None
        self._last_status = "lost"
        self._reference_inliers = 0  # inliers of the first frame tracked on the current local map
        self._local: _LocalMap | None = None
        # the worker's own state: only the keyframe jobs (run one at a time, in order) touch it
        self._matches: dict[tuple[int, int], PairMatches] = {}
        self._adjusted: dict[int, Pose] = {}
        self._depth_prior: DepthPrior | None = None
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
        self._apply_due(index)
        if self._filter.initialised:
            self._filter.predict(time - self._last_time)
        self._filter.update_measured(measured_pose)
        result: LocalizationResult | None = None
        if self._localizer is not None:
            result = self._localizer.localize(image, measured_pose)
        status = "lost"
        if result is not None and result.ok:
            self._filter.update(result.pose, result.covariance)
            status = "relocalized" if result.mode == "global" or self._last_status == "lost" else "tracked"
            if self._reference_inliers == 0:
                self._reference_inliers = result.n_inliers
        decision = self._selector.offer(image)
        keep = decision.keep or (status != "lost" and self._reference_inliers > 0
                                 and result.n_inliers < self.options.min_inlier_fraction * self._reference_inliers)
        keyframe = None
        if keep:
            keyframe = len(self._keyframes)
            guide = MeasuredPose(self._filter.pose, covariance_to_tolerance(self._filter.pose_covariance,
                                                                             self.options.guide_sigmas))
            self._keyframes.append(_Keyframe(index, np.ascontiguousarray(image), measured_pose, guide))
            self._submit(keyframe, index)
            status = "keyframe"
        self._frames += 1
        self._last_time = time
        self._last_status = "lost" if result is None or not result.ok else status
        ok = result is not None and result.ok
        return LiveFrame(index, float(time), status, self._filter.pose, self._filter.pose_covariance,
                         result.pose if ok else None, result.covariance if ok else None,
                         result.n_inliers if ok else 0, keyframe, 1000.0 * (_clock() - t0))

    def current_map(self) -> LiveMap:
        """The map now: every keyframe (adjusted where a local BCBA reached it) and the local map's points;
        after :meth:`finish`, the global map."""
        if self._final is not None:
            return self._final
        local = self._local
        poses = [self._adjusted_pose(k) for k in range(len(self._keyframes))]
        if local is None:
            return LiveMap(self._keyframe_frames(), poses, [k.measured for k in self._keyframes], np.zeros((0, 3)),
                           np.zeros((0, 3), np.uint8), None)
        return LiveMap(self._keyframe_frames(), poses, [k.measured for k in self._keyframes], local.points.xyz_mm,
                       local.points.colors, local.tracks)

    def finish(self) -> LiveMap:
        """Wait for the keyframe work, then the global BCBA over every keyframe (see the module docstring).
        Raises InputError when the keyframes hold no consistent point."""
        if self._final is not None:
            return self._final
        for p in self._pending:
            self._apply(p)
        self._pending = []
        self.close()
        kfs = self._keyframes
        if len(kfs) < 2:
            raise InputError(f"{len(kfs)} keyframe(s): the scope did not move enough to map anything")
        for k in kfs:
            if k.features is None:
                k.features = detect(k.image, self.camera, options=self.options.features)
        guides = [self._guide(k) for k in range(len(kfs))]
        prior = self._depth_prior
        if prior is None:
            raise InputError("no local map was built: the keyframes could not be matched")
        pairs = select_pairs(self.camera, [g.pose for g in guides], prior, options=self.options.pairs)
        todo = [(i, j, ov) for i, j, ov in pairs if (i, j) not in self._matches]
        features = [k.features for k in kfs]
        for m in match_guided_many(self.camera, features, guides, todo, prior, options=self.options.matching):
            self._matches[(m.i, m.j)] = m
        matches = [m for m in self._matches.values() if len(m)]
        tracks = build_tracks(features, matches, min_track_length=self.options.tracks.min_track_length)
        if tracks.n_tracks == 0:
            raise InputError("no feature could be matched between keyframes")
        adjusted = adjust_map("bounded", [k.measured for k in kfs], self.camera, tracks, guides, prior,
                              track_options=self.options.tracks, options=self.options.bundle, height_field=True,
                              where="live map")
        self._final = LiveMap(self._keyframe_frames(), adjusted.poses, [k.measured for k in kfs],
                              adjusted.tracks.points, adjusted.tracks.colors, adjusted.tracks, final=True)
        for k in kfs:
            k.image = None  # the frames are no longer needed
        return self._final

    def close(self) -> None:
        """Stop the worker thread (pending keyframe work is finished first)."""
        if self._executor is not None:
            self._executor.shutdown(wait=True)
            self._executor = None

    def __enter__(self) -> "LiveMapper":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def n_keyframes(self) -> int:
        return len(self._keyframes)

    # --- keyframe work ----------------------------------------------------------------------------
    def _submit(self, keyframe: int, index: int) -> None:
        due = index + self.options.map_lag_frames
        if not self.options.in_thread:
            self._pending.append(_Pending(due, self._local_map(keyframe)))
            return
        if self._executor is None:
            self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="scope3d-live")
        self._pending.append(_Pending(due, self._executor.submit(self._local_map, keyframe)))

    def _apply_due(self, index: int) -> None:
        while self._pending and self._pending[0].due <= index:
            self._apply(self._pending.pop(0))

    def _apply(self, pending: _Pending) -> None:
        outcome = pending.outcome.result() if isinstance(pending.outcome, Future) else pending.outcome
        if outcome is None:
            return
        self._local = outcome
        if self._localizer is None:
            self._localizer = Localizer(outcome.points, self.camera, self.options.localizer)
        else:
            self._localizer.replace_map(outcome.points)
        self._reference_inliers = 0

    def _local_map(self, keyframe: int) -> _LocalMap | None:
        """The worker's job for a new keyframe: its SIFT, its matches to the window's other keyframes, and
        the local BCBA over the window. None when the window holds too little to adjust."""
        o = self.options
        kfs = self._keyframes
        new = kfs[keyframe]
        new.features = detect(new.image, self.camera, options=o.features)
        window = list(range(max(0, keyframe - o.local_window + 1), keyframe + 1))
        for i in window[:-1]:
            if self._depth_prior is None:
                m = match_exhaustive(self.camera, kfs[i].features, new.features, o.matching, i=i, j=keyframe)
            else:
                m = match_guided_many(self.camera, [kfs[i].features, new.features],
                                      [self._guide(i), self._guide(keyframe)], [(0, 1, 1.0)], self._depth_prior,
                                      options=o.matching, frame_ids=[i, keyframe])[0]
            self._matches[(i, keyframe)] = m
        if len(window) < 2:
            return None
        local = {k: n for n, k in enumerate(window)}
        matches = [_renumbered(m, local[m.i], local[m.j]) for (i, j), m in self._matches.items()
                   if i in local and j in local and len(m)]
        features = [kfs[k].features for k in window]
        tracks = build_tracks(features, matches, min_track_length=o.tracks.min_track_length)
        if tracks.n_tracks < o.localizer.pose.min_inliers:
            return None
        try:
            adjusted = adjust_map("bounded", [kfs[k].measured for k in window], self.camera, tracks,
                                  [self._guide(k) for k in window],
                                  self._depth_prior or DepthPrior(*o.working_range_mm), track_options=o.tracks,
                                  options=o.bundle, height_field=True, where="live map")
        except InputError:
            return None
        t = adjusted.tracks
        if t.n_tracks < o.localizer.pose.min_inliers:
            return None
        for k, pose in zip(window, adjusted.poses):
            self._adjusted[k] = pose
        self._depth_prior = self._widened_prior(adjusted.poses, t)
        points = MapPoints(t.points, track_descriptors(features, t), t.lengths(), t.colors,
                           observation_descriptors(features, t), t.track.copy())
        return _LocalMap(window, list(adjusted.poses), t, points)

    def _guide(self, keyframe: int) -> MeasuredPose:
        """A keyframe's pose for guided matching and to start the adjustment: the adjusted one once a local
        BCBA reached it, with the box its fused covariance gave when it was kept."""
        k = self._keyframes[keyframe]
        pose = self._adjusted.get(keyframe)
        return k.guide if pose is None else MeasuredPose(pose, k.guide.tolerance)

    def _adjusted_pose(self, keyframe: int) -> Pose:
        local = self._local
        if local is not None and keyframe in local.keyframes:
            return local.poses[local.keyframes.index(keyframe)]
        return self._guide(keyframe).pose

    def _widened_prior(self, poses: list[Pose], tracks: Tracks) -> DepthPrior:
        """The depth range of the adjusted points in their keyframes (2nd-98th percentile, widened), joined
        with the range known before (the scope may come closer again)."""
        depth = np.concatenate([poses[f].transform(tracks.points[tracks.track[tracks.frame == f]])[:, 2]
                                for f in np.unique(tracks.frame)])
        lo, hi = np.percentile(depth, [2.0, 98.0])
        m = self.options.depth_margin
        near, far = max(lo * (1 - m), 1e-3), hi * (1 + m)
        if self._depth_prior is not None:
            near, far = min(near, self._depth_prior.near_mm), max(far, self._depth_prior.far_mm)
        return DepthPrior(float(near), float(far))

    def _keyframe_frames(self) -> np.ndarray:
        return np.array([k.frame for k in self._keyframes], np.int64)


def _renumbered(m: PairMatches, i: int, j: int) -> PairMatches:
    return PairMatches(i, j, m.idx_i, m.idx_j)


def _clock() -> float:
    return time.perf_counter()
