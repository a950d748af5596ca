"""Where is the scope now? Localization of live frames against the surgical-field map (reference ch. 5).

A :class:`Localizer` holds the map (:class:`~scope3d.io.map_points.MapPoints`) and takes frames one at a
time, as a video stream delivers them::

    loc = Localizer(read_map_points(map_dir), camera)
    for image, reported in stream:
        result = loc.localize(image, reported, blocked=tool_mask)
        if result.ok: steer(result.pose)

Each frame is localized in one of three modes, the cheapest that works:

* ``tracking`` — the map points that were inliers in the previous frame are followed into this one by
  pyramidal Lucas-Kanade optical flow, started where the constant-velocity prediction of the pose
  projects them and checked forwards-backwards. No detection, no descriptor matching: the 3-D points stay
  the map's, so the pose does not drift, only the 2-D positions are followed (they are re-anchored to
  fresh SIFT keypoints every ``refresh_every`` frames, or when too few survive).
* ``guided`` — SIFT in the frame, and each map point is searched only near where the predicted pose (the
  previous pose, or the reported one when its tolerance is finite) projects it, with a radius from the
  pose's uncertainty (:func:`~scope3d.feature.depth_prior.pose_error_px`); the ratio test runs among those
  candidates only (feature position prediction, reference sec. 4.3.1, applied to map points).
* ``global`` — SIFT against every map descriptor, ratio test (relocalization: the first frame, or after
  tracking was lost and no finite reported pose narrows the search); when that gives no pose and the map
  holds every observation's descriptor, SIFT against those, the ratio test between the two nearest points.

Every mode ends in :func:`~scope3d.estimators.absolute_pose.estimate_absolute_pose` (PnP + RANSAC, then
the pose refined with the map fixed inside the reported pose's tolerance box). A frame that cannot be
localized gets a failure status and no pose; the next frame relocalizes.

``blocked`` : (H, W) bool, True where the tool hides the scene (the reference's tool covered a sector of
every frame, sec. 5.2). No feature is detected or followed there, nor within ``blocked_margin_px`` of it
(a descriptor straddling the tool's edge describes the tool).
"""
from __future__ import annotations

import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.spatial import cKDTree

from scope3d.estimators.absolute_pose import AbsolutePoseOptions, AbsolutePoseResult, estimate_absolute_pose
from scope3d.feature.depth_prior import DepthPrior, pose_error_px
from scope3d.feature.detection import FeatureOptions, detect, detection_mask, to_grey
from scope3d.feature.matching import MatchOptions, best_two_per_query, pair_squared_distances, two_nearest
from scope3d.geometry.pose import Pose
from scope3d.io.map_points import MapPoints
from scope3d.sensor.camera import Camera
from scope3d.sensor.pose_tolerance import MeasuredPose, PoseTolerance

LOCALIZATION_MODES = ("tracking", "guided", "global")
# squared descriptor distances held at once by the every-observation match (float32: 64 MB)
_DISTANCE_BLOCK_ENTRIES = 1 << 24


@dataclass(frozen=True)
class LocalizerOptions:
    """How frames are localized against the map.

    features : SIFT settings for guided and global matching (default 2000 features: a frame sees a few
        hundred map points, and fewer features halve the detection time).
    matching : :class:`~scope3d.feature.matching.MatchOptions`, of which the localizer reads three:
        ``ratio``, Lowe's ratio test (0.8, the reference's); ``base_radius_px``, the search radius around a
        map point's predicted position when the prediction is the previous frame's pose (default here 20 px:
        the scope moves by well under a millimetre between video frames, ~20 px at 15 mm with f ~ 600 px),
        plus what the reported pose's tolerance allows when that predicts; ``max_radius_px``, beyond which
        the prediction carries little information and the frame is matched globally (default here 120 px,
        a fifth of a 608 px frame). A frame's matches are verified by its absolute pose, not by the pair
        RANSAC the other fields set.
    tracking : bool, follow last frame's inliers by optical flow (default True).
    refresh_every : int, re-anchor the tracked points on fresh SIFT keypoints every this many frames
        (default 10: optical flow drifts by ~0.05 px a frame, 0.5 px after ten).
    min_tracked : int, fewer points surviving the flow triggers a guided frame (default 60: four times
        the absolute pose's minimum of inliers, so a tool moving into view does not starve the pose) —
        unless they are still at least ``min_tracked_fraction`` of what the last SIFT association gave.
    min_tracked_fraction : float in (0, 1], where the map is sparse (a close-up of a patch the survey saw
        from afar) SIFT itself finds fewer than ``min_tracked`` inliers, and a SIFT frame would bring back
        no more points than tracking holds: tracking goes on while at least this fraction of the last
        association's points survive (default 0.5: the pose's sigma, growing as 1/sqrt(points), is then
        within sqrt(2) of a fresh SIFT frame's), never below the pose's ``min_inliers``.
    max_tracked : int, at most this many inliers are followed into the next frame, evenly through the
        list (default 250: the flow's cost grows with the count, a pose's precision only as its square
        root; 250 points hold the centre to ~0.02 mm on the dome).
    flow_window_px : int, Lucas-Kanade window side (default 21 px); flow_levels : pyramid levels of the
        forward flow (3; the backward check needs none).
    max_flow_error_px : float, forwards-backwards disagreement beyond which a followed point is dropped
        (default 0.5 px, the keypoints' own error).
    blocked_margin_px : float, pixels next to the tool that are treated as blocked (default 8 px, half a
        descriptor window at the finest scale, as FeatureOptions.mask_margin_px).
    refresh_lag_frames : int, 0 (default): the frame due for a refresh is localized by SIFT itself, and the
        stream waits for it (a SIFT frame costs ~10 tracking frames). L >= 1: the frame due is tracked like
        the others, its SIFT association (guided by its tracked pose) is computed alongside, and L frames
        later the tracked points are replaced by the refreshed ones, followed by optical flow from the
        refresh frame straight into that frame. The merge happens at that frame whatever the timing (the
        stream waits for a late refresh), so the outputs do not depend on the machine's load.
    refresh_in_thread : bool, with ``refresh_lag_frames >= 1``, compute the refresh on a worker thread
        (default True: OpenCV's SIFT releases the GIL, so it runs on the second core while the first keeps
        tracking). False computes it inline when submitted; the results are identical either way.
    refresh_image_scale : float in (0, 1], the lagged refresh's SIFT runs on the frame resized by this
        factor (default 1; 0.5 costs about a quarter: SIFT's cost grows with the pixels). Its keypoints,
        scaled back, only re-anchor the optical flow; their precision shrinks with the factor.
    sift_image_scale : float in (0, 1], the SIFT of a guided or global frame (the first frame, a
        relocalization, a synchronous refresh) runs on the frame resized by this factor (default 1). At 1 Mpx
        SIFT is three quarters of a relocalization's CPU, and 0.5 cuts it to a quarter: on the Strecha
        fountain's views 0.42 -> 0.13 s per relocalization, errors alike (the map limits them), the
        tracked frames' orientation 0.015 -> 0.022 deg (docs/localization.md, "Speed at 1 Mpx"). The
        keypoints' precision shrinks with the factor, so a small frame (640 px) keeps 1.
    pose : :class:`~scope3d.estimators.absolute_pose.AbsolutePoseOptions`.
    """

    features: FeatureOptions = field(default_factory=lambda: FeatureOptions(max_features=2000))
    matching: MatchOptions = field(default_factory=lambda: MatchOptions(base_radius_px=20.0, max_radius_px=120.0))
    tracking: bool = True
    refresh_every: int = 10
    min_tracked: int = 60
    min_tracked_fraction: float = 0.5
    max_tracked: int = 250
    flow_window_px: int = 21
    flow_levels: int = 3
    max_flow_error_px: float = 0.5
    blocked_margin_px: float = 8.0
    refresh_lag_frames: int = 0
    refresh_in_thread: bool = True
    refresh_image_scale: float = 1.0
    sift_image_scale: float = 1.0
    pose: AbsolutePoseOptions = field(default_factory=AbsolutePoseOptions)

    def __post_init__(self) -> None:
        if self.refresh_every < 1 or not self.pose.min_inliers <= self.min_tracked <= self.max_tracked:
            raise ValueError("need refresh_every >= 1 and pose.min_inliers <= min_tracked <= max_tracked")
        if not 0 < self.min_tracked_fraction <= 1:
            raise ValueError(f"min_tracked_fraction must be in (0, 1], got {self.min_tracked_fraction}")
        if self.flow_window_px < 5 or self.flow_levels < 0 or self.max_flow_error_px <= 0:
            raise ValueError("need flow_window_px >= 5, flow_levels >= 0 and max_flow_error_px > 0")
        if self.blocked_margin_px < 0:
            raise ValueError("blocked_margin_px must be >= 0")
        if self.refresh_lag_frames < 0:
            raise ValueError(f"refresh_lag_frames must be >= 0, got {self.refresh_lag_frames}")
        if not 0 < self.refresh_image_scale <= 1:
            raise ValueError(f"refresh_image_scale must be in (0, 1], got {self.refresh_image_scale}")
        if not 0 < self.sift_image_scale <= 1:
            raise ValueError(f"sift_image_scale must be in (0, 1], got {self.sift_image_scale}")


#: Named settings. ``threaded``: the SIFT refresh every 5 frames on a worker thread, at half size, merged 2
#: frames later (docs/localization.md: the stream's thread then only tracks; same accuracy within noise).
LOCALIZER_PRESETS: dict[str, LocalizerOptions] = {
    "default": LocalizerOptions(),
    "threaded": LocalizerOptions(refresh_every=5, refresh_lag_frames=2, refresh_image_scale=0.5),
}


@dataclass
class LocalizationResult:
    """One frame's outcome.

    status : "ok" or a failure of :data:`~scope3d.estimators.absolute_pose.POSE_STATUSES`.
    mode : one of :data:`LOCALIZATION_MODES`, the last one tried.
    pose : ``cam_from_world`` (mm) when ok. n_matches : 2-D/3-D correspondences given to the pose.
    n_inliers : final inliers. covariance : (6, 6) of ``(w rad, centre mm)`` when ok.
    time_s : wall time of :meth:`Localizer.localize`; cpu_s : process CPU time.
    """

    status: str
    mode: str
    pose: Pose | None
    n_matches: int
    n_inliers: int
    covariance: np.ndarray | None
    rms_px: float
    time_s: float
    cpu_s: float

    @property
    def ok(self) -> bool:
        return self.status == "ok"


@dataclass
class _Track:
    """What tracking carries from one frame to the next."""

    grey: np.ndarray
    point_ids: np.ndarray
    pixels: np.ndarray


@dataclass
class _PendingRefresh:
    """A refresh submitted at one frame (``grey``), merged ``refresh_lag_frames`` tracking frames later.
    ``outcome`` is a Future when it runs on the worker thread, else its value: the refreshed ``(point ids,
    pixels in grey)`` or None when the refresh frame could not be matched."""

    grey: np.ndarray
    outcome: object
    age: int = 0


class Localizer:
    """Streaming localization against one map (see the module docstring).

    map_points : the map. camera : the live frames' intrinsics (those of the map's dataset).

    With ``options.refresh_lag_frames >= 1`` and ``options.refresh_in_thread`` the localizer owns one worker
    thread: call :meth:`close` (or use it as a context manager) when done.
    """

    def __init__(self, map_points: MapPoints, camera: Camera, options: LocalizerOptions = LocalizerOptions()):
        if len(map_points) < options.pose.min_inliers:
            raise ValueError(f"the map holds {len(map_points)} points, fewer than the {options.pose.min_inliers} "
                             "inliers a pose needs")
        self.map = map_points
        self.camera = camera
        self.options = options
        self._detect_mask = detection_mask(camera, options.features.mask_margin_px) > 0
        self._usable_cache: tuple[np.ndarray, np.ndarray] | None = None
        self._observations: tuple | None = None  # the observation descriptors by point, built on first use
        self._executor: ThreadPoolExecutor | None = None
        self.reset()

    def reset(self) -> None:
        """Forget the past: the next frame relocalizes."""
        self._poses: list[Pose] = []  # the last two poses, for the constant-velocity prediction
        self._track: _Track | None = None
        self._since_refresh = 0
        self._anchored = 0  # points the last SIFT association (a SIFT frame or a merged refresh) gave
        self._pending: _PendingRefresh | None = None  # a refresh still running is simply never merged

    def replace_map(self, map_points: MapPoints, new_from_old: Pose | None = None) -> None:
        """Localize against ``map_points`` from the next frame on (a live map grown or adjusted). The point ids
        of the old map mean nothing in the new one, so the followed points are dropped, but the last poses
        are kept, moved into the new map's frame by ``new_from_old`` (the new world from the old, when the
        adjustment moved the map): the next frame is matched guided by their prediction, not relocalized."""
        if len(map_points) < self.options.pose.min_inliers:
            raise ValueError(f"the map holds {len(map_points)} points, fewer than the {self.options.pose.min_inliers} "
                             "inliers a pose needs")
        self.map = map_points
        if new_from_old is not None:
            old_from_new = new_from_old.inverse()
            self._poses = [p @ old_from_new for p in self._poses]
        self._observations = None
        self._track = None
        self._since_refresh = 0
        self._anchored = 0
        self._pending = None

    def close(self) -> None:
        """Stop the refresh thread (if one was started). The localizer stays usable: it starts another."""
        if self._executor is not None:
            self._executor.shutdown(wait=True)
            self._executor = None

    def __enter__(self) -> "Localizer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # --- one frame ------------------------------------------------------------------------------
    def localize(self, image: np.ndarray, reported: MeasuredPose | None = None, *,
                 blocked: np.ndarray | None = None) -> LocalizationResult:
        """Localize one frame.

        image : (H, W, 3) uint8 RGB or (H, W) uint8, the camera's size.
        reported : the robot's pose for this frame with its tolerance, or None. A finite tolerance bounds
            the refinement and narrows the search when tracking is lost; an infinite one is ignored.
        blocked : (H, W) bool, True where the tool hides the scene, or None. The tool is rigid with the
            scope, so the mask is dilated once and reused while the same array is passed (pass a new array,
            not the old one edited in place, when it changes).
        """
        t0, c0 = time.perf_counter(), time.process_time()
        grey = to_grey(image)
        if grey.shape != (self.camera.height, self.camera.width):
            raise ValueError(f"frame is {grey.shape[1]}x{grey.shape[0]}, the camera {self.camera.width}x{self.camera.height}")
        usable = self._usable(blocked)
        if reported is not None and not np.all(np.isfinite(reported.tolerance.position_mm)):
            reported = None  # unknown tolerance: the image alone
        o = self.options
        result, mode = None, "global"
        predicted = self._predict()
        lagged = o.refresh_lag_frames > 0
        if o.tracking and self._track is not None and predicted is not None and (
                lagged or self._since_refresh < o.refresh_every):
            mode = "tracking"
            ids, px = self._merge_refresh(grey, predicted, usable)
            if ids is None:
                ids, px = self._follow(self._track, grey, predicted, usable)
            if len(ids) >= self._enough_tracked(self._anchored):
                result, used_ids, used_px = self._pose(ids, px, reported)
                self._since_refresh += 1
        if result is None or not result.ok:
            guide = predicted if predicted is not None else (reported.pose if reported is not None else None)
            tolerance = PoseTolerance.exact() if predicted is not None else (
                reported.tolerance if reported is not None else None)
            kp, desc = self._features(grey, usable, o.sift_image_scale)
            result = None
            if guide is not None:
                radius = self._guided_radius(guide, tolerance)
                if radius <= o.matching.max_radius_px:
                    mode = "guided"
                    ids, fidx = self._match_guided(guide, kp, desc, radius)
                    result, used_ids, used_px = self._pose(ids, kp[fidx], reported)
            if result is None or not result.ok:
                # relocalization: the prediction was wrong or too vague to narrow the search
                mode = "global"
                ids, fidx = self._match_global(desc)
                result, used_ids, used_px = self._pose(ids, kp[fidx], reported)
                if not result.ok and self.map.observation_point is not None:
                    # against every observation's descriptor: a view between two mapped ones may resemble
                    # the observation that is not the representative (2-4x the descriptors: tried second)
                    ids, fidx = self._match_every_observation(desc)
                    result, used_ids, used_px = self._pose(ids, kp[fidx], reported)
            self._since_refresh = 0
            self._pending = None  # this frame is fresher than any refresh still to come
        if result.ok:
            self._poses = (self._poses + [result.pose])[-2:]
            self._track = _Track(grey, *self._kept(result, used_ids, used_px))
            if mode != "tracking":
                self._anchored = len(self._track.point_ids)
            if lagged and mode == "tracking" and self._since_refresh >= o.refresh_every and self._pending is None:
                self._submit_refresh(grey, result.pose, reported, usable)
        else:
            self.reset()
        return LocalizationResult(result.status, mode, result.pose, len(result.inliers), result.n_inliers,
                                  result.covariance, result.rms_px, time.perf_counter() - t0,
                                  time.process_time() - c0)

    # --- pieces ---------------------------------------------------------------------------------
    def _usable(self, blocked: np.ndarray | None) -> np.ndarray:
        if blocked is None:
            return self._detect_mask
        if self._usable_cache is not None and self._usable_cache[0] is blocked:
            return self._usable_cache[1]  # a sequence-wide mask: dilated once
        key = blocked
        blocked = np.asarray(blocked, bool)
        if blocked.shape != (self.camera.height, self.camera.width):
            raise ValueError(f"blocked mask is {blocked.shape[1]}x{blocked.shape[0]}, the camera "
                             f"{self.camera.width}x{self.camera.height}")
        m = int(np.ceil(self.options.blocked_margin_px))
        if m:
            blocked = cv2.dilate(blocked.astype(np.uint8), np.ones((2 * m + 1, 2 * m + 1), np.uint8)) > 0
        usable = self._detect_mask & ~blocked
        self._usable_cache = (key, usable)
        return usable

    def _predict(self) -> Pose | None:
        """Constant velocity: the last motion applied once more (the previous pose when only one is known)."""
        if not self._poses:
            return None
        if len(self._poses) == 1:
            return self._poses[-1]
        a, b = self._poses
        return (b @ a.inverse()) @ b

    def _visible(self, pose: Pose) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Map points in front of ``pose`` and inside the frame: (ids, pixels (K, 2), depths (K,) mm)."""
        cam = pose.transform(self.map.xyz_mm)
        front = np.flatnonzero(cam[:, 2] > 1e-3)
        px = self.camera.project(cam[front])
        inside = self.camera.in_image(px)
        return front[inside], px[inside], cam[front[inside], 2]

    def _guided_radius(self, guide: Pose, tolerance: PoseTolerance) -> float:
        _, _, depth = self._visible(guide)
        if len(depth) == 0:
            return float("inf")
        prior = DepthPrior(float(np.percentile(depth, 1)), float(depth.max()))
        return self.options.matching.base_radius_px + pose_error_px(self.camera, tolerance, prior)

    def _features(self, grey: np.ndarray, usable: np.ndarray, scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
        """SIFT keypoints (K, 2) and descriptors (K, 128) of the frame (resized by ``scale`` for detection),
        those on usable pixels only."""
        if scale == 1.0:
            features = detect(grey, self.camera, options=self.options.features)
            keypoints = features.keypoints
        else:
            small = cv2.resize(grey, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
            features = detect(small, None, options=self.options.features)  # the usable mask below drops the rim
            # pixel centres: full-resolution u = (u_small + 0.5) / scale - 0.5
            keypoints = (features.keypoints + 0.5) / scale - 0.5
        keep = usable[np.clip(np.rint(keypoints[:, 1]).astype(int), 0, grey.shape[0] - 1),
                      np.clip(np.rint(keypoints[:, 0]).astype(int), 0, grey.shape[1] - 1)]
        return keypoints[keep], features.descriptors[keep]

    def _kept(self, result: AbsolutePoseResult, ids: np.ndarray, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The inliers to follow into the next frame: at most ``max_tracked``, evenly through the list."""
        keep = np.flatnonzero(result.inliers)
        if len(keep) > self.options.max_tracked:
            keep = keep[np.linspace(0, len(keep) - 1, self.options.max_tracked).round().astype(int)]
        return ids[keep], pixels[keep]

    def _enough_tracked(self, anchored: int) -> int:
        """Fewest followed points to go on tracking, after an association that gave ``anchored`` points."""
        o = self.options
        return max(o.pose.min_inliers, min(o.min_tracked, int(np.ceil(o.min_tracked_fraction * anchored))))

    def _refresh(self, grey: np.ndarray, guide: Pose, reported: MeasuredPose | None, usable: np.ndarray):
        """A refresh frame's fresh association: SIFT matched to the map points near where its tracked pose
        ``guide`` projects them, checked by a pose. Returns (point ids, pixels) to follow, or None. Reads
        nothing that changes, so it runs on the worker thread as well as inline."""
        kp, desc = self._features(grey, usable, self.options.refresh_image_scale)
        ids, fidx = self._match_guided(guide, kp, desc, self.options.matching.base_radius_px)
        result, ids, px = self._pose(ids, kp[fidx], reported)
        return self._kept(result, ids, px) if result.ok else None

    def _submit_refresh(self, grey: np.ndarray, guide: Pose, reported: MeasuredPose | None, usable: np.ndarray) -> None:
        self._since_refresh = 0  # the refresh frame starts the count to the next one
        if not self.options.refresh_in_thread:
            self._pending = _PendingRefresh(grey, self._refresh(grey, guide, reported, usable))
            return
        if self._executor is None:
            self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="scope3d-refresh")
        self._pending = _PendingRefresh(grey, self._executor.submit(self._refresh, grey, guide, reported, usable))

    def _merge_refresh(self, grey: np.ndarray, predicted: Pose, usable: np.ndarray):
        """When a pending refresh is due (``refresh_lag_frames`` frames old), its points followed from the
        refresh frame into ``grey``; (None, None) when none is due, or too few of its points survive."""
        pending = self._pending
        if pending is None:
            return None, None
        pending.age += 1
        if pending.age < self.options.refresh_lag_frames:
            return None, None
        self._pending = None
        outcome = pending.outcome.result() if isinstance(pending.outcome, Future) else pending.outcome
        if outcome is None:
            return None, None
        ids, px = self._follow(_Track(pending.grey, *outcome), grey, predicted, usable)
        if len(ids) < self._enough_tracked(len(outcome[0])):
            return None, None
        self._anchored = len(outcome[0])
        return ids, px

    def _follow(self, tr: _Track, grey: np.ndarray, predicted: Pose, usable: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The points of ``tr`` followed into ``grey`` by optical flow from their predicted positions."""
        o = self.options
        start = self.camera.project(predicted.transform(self.map.xyz_mm[tr.point_ids]))
        prev = tr.pixels.astype(np.float32).reshape(-1, 1, 2)
        guess = np.where(np.isfinite(start), start, tr.pixels).astype(np.float32).reshape(-1, 1, 2)
        win = (o.flow_window_px, o.flow_window_px)
        criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)
        nxt, st, _ = cv2.calcOpticalFlowPyrLK(tr.grey, grey, prev, guess, winSize=win, maxLevel=o.flow_levels,
                                              criteria=criteria, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
        # the backward flow starts where the point was, the answer of a consistent track, and any answer
        # farther than max_flow_error_px from it is rejected: a pyramid would only widen a capture range
        # the check does not use, and building it is a third of the flow's cost
        back, st2, _ = cv2.calcOpticalFlowPyrLK(grey, tr.grey, nxt, prev.copy(), winSize=win, maxLevel=0,
                                                criteria=criteria, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
        nxt, back = nxt.reshape(-1, 2).astype(float), back.reshape(-1, 2)
        ok = (st.ravel() == 1) & (st2.ravel() == 1)
        ok &= np.linalg.norm(back - tr.pixels, axis=1) <= o.max_flow_error_px
        ok &= self.camera.in_image(nxt)
        iu = np.clip(np.rint(nxt[:, 0]).astype(int), 0, grey.shape[1] - 1)
        iv = np.clip(np.rint(nxt[:, 1]).astype(int), 0, grey.shape[0] - 1)
        ok &= usable[iv, iu]
        return tr.point_ids[ok], nxt[ok]

    def _match_guided(self, guide: Pose, kp: np.ndarray, desc: np.ndarray, radius: float):
        """Each map point against the features within ``radius`` of where ``guide`` projects it: ratio test
        among those candidates, then one feature per map point and one map point per feature."""
        ids, px, _ = self._visible(guide)
        if len(ids) == 0 or len(kp) == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        # every (map point, feature) pair within the radius, found in C (a Python list per point cost ~20 ms)
        pairs = cKDTree(px).sparse_distance_matrix(cKDTree(kp), radius, output_type="ndarray")
        if len(pairs) == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        row, feat = pairs["i"].astype(np.int64), pairs["j"].astype(np.int64)
        d2 = pair_squared_distances(desc, self.map.descriptors, feat, ids[row])  # in place: no (pairs, 128) gathers
        # per map point its nearest feature (ties to the lower index, whatever the pairs' order) and the
        # second distance, in one pass (a lexsort of the ~2.5e5 pairs of a first frame cost ~90 ms)
        best, best_d2, second_d2 = best_two_per_query(row, feat, d2, len(ids))
        keep = np.flatnonzero((best >= 0) & (best_d2 < self.options.matching.ratio**2 * second_d2.astype(np.float64)))
        return _one_to_one(ids[keep], best[keep], best_d2[keep])

    def _match_global(self, desc: np.ndarray):
        """Every feature against every map descriptor, ratio test, one-to-one. The two nearest by one matrix
        product (BLAS: the same neighbours and distances as OpenCV's brute force, a fifth of its time on
        2,000 features against a 6,800-point map, where it was half of a relocalization at 1 Mpx)."""
        if len(desc) < 2:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        nearest, best, second = two_nearest(desc, self.map.descriptors)
        feat = np.flatnonzero(best.astype(np.float64) < self.options.matching.ratio * second.astype(np.float64))
        return _one_to_one(nearest[feat], feat.astype(np.int64), best[feat].astype(np.float64) ** 2)

    def _match_every_observation(self, desc: np.ndarray):
        """Every feature against every observation's descriptor: per map point the nearest of its
        observations, the ratio test between the two nearest points (a point's own observations are never
        each other's second), one-to-one."""
        empty = np.zeros(0, np.int64), np.zeros(0, np.int64)
        if self._observations is None:
            point = self.map.observation_point
            order = np.argsort(point, kind="stable")
            rows = np.ascontiguousarray(self.map.observation_descriptors[order], np.float32)
            starts = np.flatnonzero(np.r_[True, point[order][1:] != point[order][:-1]]) if len(order) else order
            self._observations = (rows, np.einsum("ij,ij->i", rows, rows), starts, point[order][starts])
        rows, rows2, starts, points = self._observations
        if len(desc) < 2 or len(points) < 2:
            return empty
        desc = np.ascontiguousarray(desc, np.float32)
        best, best_d2, second_d2 = (np.empty(len(desc), t) for t in (np.int64, np.float32, np.float32))
        chunk = max(1, _DISTANCE_BLOCK_ENTRIES // len(rows))  # features per block of squared distances
        for lo in range(0, len(desc), chunk):
            q = desc[lo:lo + chunk]
            d2 = rows2[None, :] - 2.0 * (q @ rows.T)  # + |q|^2 below: the same for every row
            per_point = np.minimum.reduceat(d2, starts, axis=1)
            two = np.argpartition(per_point, 1, axis=1)[:, :2]
            pair = np.take_along_axis(per_point, two, axis=1)
            first = np.argmin(pair, axis=1)
            q2 = np.einsum("ij,ij->i", q, q)
            best[lo:lo + chunk] = points[two[np.arange(len(q)), first]]
            best_d2[lo:lo + chunk] = np.maximum(pair[np.arange(len(q)), first] + q2, 0.0)
            second_d2[lo:lo + chunk] = np.maximum(pair[np.arange(len(q)), 1 - first] + q2, 0.0)
        keep = np.flatnonzero(best_d2 < self.options.matching.ratio**2 * second_d2)
        if len(keep) == 0:
            return empty
        return _one_to_one(best[keep], keep.astype(np.int64), best_d2[keep].astype(np.float64))

    def _pose(self, ids: np.ndarray, pixels: np.ndarray, reported: MeasuredPose | None
              ) -> tuple[AbsolutePoseResult, np.ndarray, np.ndarray]:
        """The pose from map points ``ids`` seen at ``pixels``; returns the result and the correspondences."""
        pixels = np.asarray(pixels, float).reshape(-1, 2)
        result = estimate_absolute_pose(self.camera, self.map.xyz_mm[ids], pixels, reported=reported,
                                        options=self.options.pose)
        return result, ids, pixels


def _one_to_one(ids: np.ndarray, feat: np.ndarray, cost: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Keep, for every map point and every feature, only its cheapest match."""
    order = np.argsort(cost, kind="stable")
    ids, feat = ids[order], feat[order]
    _, first = np.unique(ids, return_index=True)
    ids, feat = ids[first], feat[first]
    _, first = np.unique(feat, return_index=True)
    return ids[first], feat[first]
