"""The phantom lab: render a scene along a trajectory, with exact ground truth, and write it as a dataset.

Typical use (tests, benchmarks, pipelines)::

    from scope3d.phantoms import generate, write
    seq = generate("dome", seed=0, pose_noise_mm=0.25, size=(160, 160), n_frames=4)
    write(seq, "out/dome")          # dataset folder + contact_sheet.png

Pose reports. With ``pose_noise_mm = 0`` the reported poses are the true ones, with the tolerance of the
reference's micro-positioning stage (0.01 mm, sec. 7.3 and 8.3), because a real stage is never exactly
right and downstream code should see a non-zero box. With ``pose_noise_mm = MM > 0`` every reported camera
centre is off by a uniform error in [-MM, MM] per axis (the reference's noise model, sec. 6.3) and its
orientation by a uniform rotation in [-a, a] per axis with ``a = MM * 0.5°/mm``; the tolerance written is
exactly (MM, a), so the truth always lies inside the reported box.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from scope3d.errors import InputError
from scope3d.geometry.iso_thread import THREAD_SIZES
from scope3d.geometry.pose import Pose
from scope3d.io.dataset import write_dataset
from scope3d.io.scan_plan import PlanFile
from scope3d.phantoms.boards import LAB_BOARD, LAB_BOARD_OPTIONS, render_board_views
from scope3d.phantoms.lenses import ENDOSCOPE_MASK_FRACTION, PINHOLE, lens_named
from scope3d.phantoms.render import RenderOptions, render_frame, sequence_exposure, supersample_factor
from scope3d.phantoms.resection import Resection, resect
from scope3d.phantoms.scenes import SCENE_TRAJECTORIES, SCENES, Scene, build_scene
from scope3d.phantoms.tool import paint_tool, tool_mask
from scope3d.phantoms.trajectories import (SURVEY_VIDEO_SPEED_MM_S, TRAJECTORIES, Trajectory, build_trajectory,
                                           survey_video)
from scope3d.scene.mesh import Mesh
from scope3d.sensor.calibration import CAMERA_MODEL_OF
from scope3d.sensor.camera import Camera
from scope3d.sensor.pose_tolerance import MICRO_STAGE, MeasuredPose, perturb_poses_uniform
from scope3d.utils.progress import Progress, advance, stage

ORIENTATION_NOISE_DEG_PER_MM = 0.5
RESECTED_SURFACE_FILE = "surface_resected.ply"  # the true surface from the resection on; in ground_truth/
BOARDS_FOLDER = "boards"  # checkerboard views through the dataset's lens (generate's board_views); beside dataset.json
TOOL_MASK_FILE = "tool_mask.png"  # white where the tool hides the scene; beside dataset.json
SECONDS_PER_PLANNED_VIEW = 600.0 / 529.0  # the reference's 15 mm scan: about 10 min for 529 views (sec. 2.3.2)
ENDOSCOPE_SIZE_PX = (608, 608)  # scanning fibre endoscope (sec. 3.1)
BORESCOPE_SIZE_PX = (1280, 1024)  # Stryker rigid scope (sec. 8.3)
BORESCOPE_FOV_DEG = 60.0


@dataclass
class PhantomSequence:
    """A rendered sequence and everything that is known about it.

    camera : intrinsics of every frame. frames : list of (H, W, 3) uint8 RGB reflectance.
    fluorescence : list of (H, W, 3) uint8 (emission in green) or None when the scene has no targets.
    true_poses : list of true ``cam_from_world``. measured_poses : as the robot reports them, with tolerances.
    surface : the true surface (mm). depths : list of (H, W) float32 true z-depth (mm), NaN where none.
    target_ids : list of (H, W) int16 id of the target seen at each pixel (0 = none).
    scene_info : JSON-ready ground truth (scene parameters, targets, trajectory, rendering), written to
        ``ground_truth/scene.json``.
    """

    scene: Scene
    camera: Camera
    frames: list[np.ndarray]
    fluorescence: list[np.ndarray] | None
    true_poses: list[Pose]
    measured_poses: list[MeasuredPose]
    depths: list[np.ndarray]
    target_ids: list[np.ndarray]
    trajectory: Trajectory
    scene_info: dict = field(default_factory=dict)
    names: list[str] = field(default_factory=list)
    tool_mask: np.ndarray | None = None  # (H, W) bool, where a tool hides the scene (approach trajectories)
    boards: list[np.ndarray] = field(default_factory=list)  # (H, W) uint8 checkerboard views through the camera
    resected: Scene | None = None  # the scene from the resection's time on (scene_info["resection"]), or None

    def __len__(self) -> int:
        return len(self.frames)

    @property
    def surface(self) -> Mesh:
        """The true surface as the sequence starts (before any resection)."""
        return self.scene.mesh

    @property
    def times_s(self) -> np.ndarray | None:
        """(n,) each frame's time in seconds for a video, None for stills."""
        return self.trajectory.times_s


def default_camera(
    scene: Scene, trajectory: str, *, size: tuple[int, int] | None = None, fov_deg: float | None = None,
    k1: float = 0.0, k2: float = 0.0, lens: str = PINHOLE.name,
) -> Camera:
    """The camera the reference used for this scene and trajectory, through ``lens`` (:mod:`.lenses`).

    Endoscope (SFE): 608 x 608, circular field of radius 300 px (scaled with ``size``), FOV 53° for the
    dome and sheet (the dome experiment), 70° elsewhere (sec. 3.1). Borescope for ``quadrants``: 1280 x 1024,
    60° FOV, no mask (sec. 8.3). size : (width, height) px; fov_deg : across the width (the pinhole's; a
    distorting lens has its own field). ValueError for an unknown lens or one given k1, k2 or a FOV.
    """
    chosen = lens_named(lens)
    if chosen is not PINHOLE and (k1 or k2 or fov_deg):
        raise ValueError(f"the {lens} lens has its own distortion and field of view; k1, k2 and the FOV "
                         "apply to the pinhole")
    if trajectory == "quadrants":
        camera = borescope_camera(size=size, fov_deg=fov_deg, k1=k1, k2=k2)
    else:
        w, h = size or ENDOSCOPE_SIZE_PX
        camera = Camera.from_fov(w, h, fov_deg or scene.fov_deg, k1=k1, k2=k2,
                                 mask_radius_px=ENDOSCOPE_MASK_FRACTION * min(w, h))
    if chosen is PINHOLE:
        return camera
    return chosen.camera(camera.width, camera.height, fov_deg=camera.fov_deg, mask_radius_px=camera.mask_radius_px)


def borescope_camera(*, size: tuple[int, int] | None = None, fov_deg: float | None = None,
                     k1: float = 0.0, k2: float = 0.0) -> Camera:
    """The ``quadrants`` borescope: 1280 x 1024, 60° FOV, no mask (sec. 8.3); size (width, height) px and
    fov_deg (across the width) adjust it."""
    w, h = size or BORESCOPE_SIZE_PX
    return Camera.from_fov(w, h, fov_deg or BORESCOPE_FOV_DEG, k1=k1, k2=k2)


def measure_poses(true_poses: list[Pose], pose_noise_mm: float, *, seed: int) -> list[MeasuredPose]:
    """Reported poses (see the module docstring for the noise model and the tolerances)."""
    if not np.isfinite(pose_noise_mm) or pose_noise_mm < 0:
        raise InputError(f"pose noise must be a non-negative number of mm, got {pose_noise_mm}")
    if pose_noise_mm == 0:
        return [MeasuredPose(p, MICRO_STAGE) for p in true_poses]
    orientation_rad = np.deg2rad(pose_noise_mm * ORIENTATION_NOISE_DEG_PER_MM)
    # A seed stream apart from the sensor noise's, so changing one never changes the other.
    return perturb_poses_uniform(true_poses, pose_noise_mm, orientation_rad, seed=seed + 7919)


def generate(
    scene: str = "dome",
    trajectory: str | None = None,
    *,
    seed: int = 0,
    pose_noise_mm: float = 0.0,
    camera: Camera | None = None,
    thread: str = "M8x1.25",
    n_frames: int | None = None,
    size: tuple[int, int] | None = None,
    fov_deg: float | None = None,
    side_view_deg: float = 45.0,
    axis_offset_mm: float = 0.0,
    axis_tilt_deg: float = 0.0,
    dome_radius_mm: float = 17.5,
    texture_seed: int = 0,
    options: RenderOptions = RenderOptions(),
    progress: Progress | None = None,
    target: int | None = None,
    thread_offsets_mm: tuple = (0.0, 0.0, 0.0),
    thread_defect: tuple | None = None,
    quadrant_mount: tuple | None = None,
    quadrant_step_mm: float | None = None,
    bladder: dict | None = None,
    plan: PlanFile | None = None,
    video_fps: float | None = None,
    seconds_per_view: float = SECONDS_PER_PLANNED_VIEW,
    lens: str = PINHOLE.name,
    board_views: int = 0,
    scan_speed_mm_s: float = SURVEY_VIDEO_SPEED_MM_S,
    resection: Resection | None = None,
) -> PhantomSequence:
    """Render ``scene`` along ``trajectory`` (the scene's default when None).

    seed : sensor noise (``default_rng([seed, frame])``) and pose noise. The phantom itself (texture,
        targets) depends only on ``texture_seed``, like a physical phantom that is imaged many times.
    pose_noise_mm : half-width of the uniform error on reported camera centres (see module docstring).
    camera : overrides :func:`default_camera`; else ``size`` (width, height) px and ``fov_deg`` adjust it.
    thread : one of ``geometry.iso_thread.THREAD_SIZES`` (``M5x0.8`` to ``M12x1.75``) for the ``thread`` scene.
    n_frames : limit or length of the trajectory (see :func:`~scope3d.phantoms.trajectories.build_trajectory`).
    side_view_deg : borescope side-view angle for ``quadrants`` (45 or 90 in the reference).
    axis_offset_mm, axis_tilt_deg : misalignment of the ``axial`` trajectory (lateral offset of the scope
        from the hole axis, mm; tilt of its optical axis from the motion, degrees); recorded in scene.json.
    options : rendering settings; ``options.supersample`` None takes the scene's anti-aliasing default
        (2 x 2 rays per pixel for the thread, 1 elsewhere); the value used is recorded in scene.json.
    progress : tqdm-like or None (:mod:`scope3d.utils.progress`), advanced by one per frame rendered.
    target : the ``approach`` trajectory's target id (1..n of the scene's targets); the approach starts
        towards azimuth ``72 * (target - 1)`` degrees, so five targets give five directions. A tool
        (:mod:`scope3d.phantoms.tool`) hides part of every approach frame.
    thread_offsets_mm : (minor, pitch, major) diameter deviations of the thread as made (mm);
        thread_defect : (angle_deg, width_deg, depth_mm) chipped crest or None (see
        :func:`~scope3d.phantoms.scenes.build_thread`).
    quadrant_mount : (offset_x_mm, offset_y_mm, tilt_deg) of the ``quadrants`` camera from the rotation
        axis (None: the trajectory's default). For ``quadrants`` the reported poses are the stage's
        nominal ones (camera on the axis, untilted: what the stage knows), with a tolerance box that covers
        the mount's offset and tilt; the true poses go to the ground truth, and ``quadrants.json`` maps
        frames to quadrants (:func:`write`). quadrant_step_mm : the ``quadrants`` advance per frame (None:
        0.1 mm).
    bladder : keyword arguments of :func:`~scope3d.phantoms.scenes.build_bladder` (``semi_axes_mm``,
        ``shape_seed``, ``vessel_density``, ``wet``) for the ``bladder`` scene.
    plan : a scan plan (:func:`scope3d.io.scan_plan.read_scan_plan`) rendered instead of a named trajectory,
        with its field of view unless ``fov_deg`` is given. video_fps : render the continuous path through the
        plan's views at this frame rate, ``seconds_per_view`` apart (poses interpolated; the reference's
        scan took about 10 min for 529 views, 1.1 s each), instead of one frame per view; without a plan,
        a grid survey's stops flown at ``scan_speed_mm_s`` (:func:`~scope3d.phantoms.trajectories.survey_video`),
        ``n_frames`` then keeping the video's first frames. Either way each frame's time (i / video_fps) is
        the trajectory's ``times_s``, written as ``poses.csv``'s ``time_s`` column.
    resection : the dome only, with a video: from ``resection.time_s`` on the frames see a pit cut into the
        wall (:mod:`scope3d.phantoms.resection`, placed from ``seed`` unless given); the depth maps are of
        the surface each frame saw, ``scene_info["resection"]`` holds the pit and its time and the frames
        from it, and :func:`write` adds the surface after it as ``ground_truth/surface_resected.ply``.
    lens : the lens the scene is seen through (:data:`~scope3d.phantoms.lenses.LENSES`: ``pinhole``,
        ``fisheye-140``, ``barrel-70``), on the scene's sensor; its vignetting applies unless
        ``options.vignetting`` is set. The camera written (camera.json) is that lens's model.
    board_views : also render this many views of the lab's checkerboard (:data:`~scope3d.phantoms.boards.LAB_BOARD`,
        9 x 6 inner corners, 2 mm squares) through the same camera, for ``scope3d calibrate`` (:func:`write`
        puts them in ``boards/``); their poses are drawn from ``seed``.
    """
    try:
        chosen = lens_named(lens)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    if camera is not None and chosen is not PINHOLE:
        raise InputError("give either a camera or a lens, not both")
    if options.vignetting is None:
        options = replace(options, vignetting=chosen.vignetting)
    if thread not in THREAD_SIZES:
        raise InputError(f"unknown thread size {thread!r} (use one of {', '.join(THREAD_SIZES)})")
    if scene not in SCENES:
        raise InputError(f"unknown scene {scene!r} (use one of {', '.join(SCENES)})")
    if bladder and scene != "bladder":
        raise InputError(f"cavity shape, vessel density and wetness apply to the bladder only, not {scene!r}")
    built = build_scene(scene, thread=thread, dome_radius_mm=float(dome_radius_mm), texture_seed=int(texture_seed),
                        thread_offsets_mm=tuple(float(v) for v in thread_offsets_mm),
                        thread_defect=None if thread_defect is None else tuple(float(v) for v in thread_defect),
                        bladder=tuple(sorted((k, tuple(v) if isinstance(v, (list, np.ndarray)) else v)
                                             for k, v in (bladder or {}).items())))
    if plan is not None:
        if trajectory is not None:
            raise InputError("give either a trajectory or a plan, not both")
        traj = plan_trajectory(plan, video_fps=video_fps, seconds_per_view=seconds_per_view, n_frames=n_frames)
        name = traj.name
        fov_deg = fov_deg or plan.fov_deg
    else:
        name = trajectory or built.default_trajectory
        if video_fps is not None and not name.startswith("grid"):
            raise InputError(f"a video runs along a grid survey or a plan (--plan), not the {name!r} trajectory")
        if name not in TRAJECTORIES:
            raise InputError(f"unknown trajectory {name!r} (use one of {', '.join(TRAJECTORIES)})")
        if name not in built.trajectories:
            raise InputError(f"trajectory {name!r} does not fit scene {scene!r} (use one of {', '.join(built.trajectories)})")
        target_mm = None
        if name == "approach":
            ids = [t.id for t in built.targets]
            if target not in ids:
                raise InputError(f"the approach needs --target, one of {', '.join(map(str, ids))} (the scene's targets)")
            target_mm = next(t for t in built.info["targets"] if t["id"] == target)["centroid_mm"]
        try:
            traj = build_trajectory(name, n_frames=n_frames, side_view_deg=side_view_deg,
                                    axis_offset_mm=float(axis_offset_mm), axis_tilt_deg=float(axis_tilt_deg),
                                    target_mm=target_mm, azimuth_deg=72.0 * ((target or 1) - 1),
                                    quadrant_mount=quadrant_mount, quadrant_step_mm=quadrant_step_mm)
        except ValueError as exc:
            raise InputError(str(exc)) from None
        if video_fps is not None:
            # the video flies the whole survey; n_frames keeps its first frames, not the first stops
            traj = survey_video(build_trajectory(name), video_fps, speed_mm_s=scan_speed_mm_s)
            if n_frames is not None:
                traj = traj.first(n_frames)
            name = traj.name
    resected, change = None, None
    if resection is not None:
        if traj.times_s is None:
            raise InputError("a resection happens at a time: it needs a video (--video FPS)")
        resected, change = resect(built, resection, seed=seed)
        after = np.flatnonzero(traj.times_s >= resection.time_s)
        if len(after) == 0:
            raise InputError(f"the resection at {resection.time_s:g} s comes after the video's last frame "
                             f"({traj.times_s[-1]:.3f} s)")
        change.update({"first_frame": int(after[0]), "surface": f"ground_truth/{RESECTED_SURFACE_FILE}",
                       "surface_before": "ground_truth/surface.ply"})
    if camera is None:
        try:
            camera = default_camera(built, name, size=size, fov_deg=fov_deg, lens=lens)
        except ValueError as exc:
            raise InputError(str(exc)) from None
    if board_views < 0:
        raise InputError(f"the number of board views must be zero or positive, got {board_views}")
    boards = []
    if board_views:
        stage(progress, f"boards through the {lens} lens", board_views)
        boards = render_board_views(camera, LAB_BOARD, n_views=board_views, seed=seed + 104729,
                                    options=LAB_BOARD_OPTIONS).images
        advance(progress, board_views)
    poses = traj.poses
    # a live approach auto-exposes every frame (the light at the tip is 6x brighter at the stop than at the
    # start), and so does a survey of a deep cavity (Scene.auto_exposure); other surveys keep one setting
    exposure = (None if name == "approach" or built.auto_exposure
                else sequence_exposure(built, camera, poses, options=options))
    frames, fluo, depths, tids = [], [], [], []
    stage(progress, f"phantom {scene}/{name}", len(poses))
    for i, pose in enumerate(poses):
        seen = resected if resected is not None and i >= change["first_frame"] else built
        out = render_frame(seen, camera, pose, seed=seed, frame_index=i, exposure=exposure, options=options)
        advance(progress)
        frames.append(out.image)
        fluo.append(out.fluorescence)
        depths.append(out.depth_mm)
        tids.append(out.target_id)
    blocked = None
    if name == "approach":
        blocked = tool_mask(camera)
        frames = [paint_tool(f, blocked, seed=seed, frame_index=i) for i, f in enumerate(frames)]
        fluo = [np.where(blocked[..., None], 0, f).astype(np.uint8) for f in fluo]
        depths = [np.where(blocked, np.nan, d).astype(np.float32) for d in depths]
        tids = [np.where(blocked, 0, t).astype(t.dtype) for t in tids]
    if name == "quadrants":
        measured = _stage_reported_quadrant_poses(traj, pose_noise_mm, seed)
    else:
        measured = measure_poses(poses, pose_noise_mm, seed=seed)
    info = dict(built.info)
    info.update({
        "trajectory": {"name": name, **traj.params},
        "camera": {"kind": "borescope" if name == "quadrants" else "endoscope (scanning fibre endoscope)",
                   "lens": lens, "model": camera.model, "params": camera.params.tolist(),
                   "width": camera.width, "height": camera.height, "fov_deg": camera.fov_deg,
                   "mask_radius_px": camera.mask_radius_px,
                   **({"side_view_deg": side_view_deg} if name == "quadrants" else {})},
        "lighting": "point light at the camera centre; Lambert cos/d^2 plus Blinn-Phong specular",
        "render": {**options.to_dict(), "supersample": supersample_factor(built, options=options), "exposure_gain": exposure if exposure is not None else "per frame (auto-exposure)", "seed": seed, "texture_seed": texture_seed},
        "pose_noise": {
            "position_mm": pose_noise_mm,
            "orientation_deg": pose_noise_mm * ORIENTATION_NOISE_DEG_PER_MM,
            "model": "uniform per axis within the tolerance (reference sec. 6.3)" if pose_noise_mm > 0
            else "exact poses reported with the micro-positioning stage tolerance (0.01 mm)",
        },
    })
    if change is not None:
        info["resection"] = change
    if boards:
        board = f"{LAB_BOARD.cols}x{LAB_BOARD.rows}"
        info["boards"] = {"folder": BOARDS_FOLDER, "count": len(boards), "inner_corners": [LAB_BOARD.cols, LAB_BOARD.rows],
                          "square_mm": LAB_BOARD.square_mm,
                          "calibrate": f"scope3d calibrate {BOARDS_FOLDER}/*.png --board {board} --square "
                                       f"{LAB_BOARD.square_mm:g} --model {calibration_model(camera.model)}"}
    if blocked is not None:
        info["tool"] = {"mask": "tool_mask.png", "fraction_of_view": float(blocked[camera.mask()].mean()),
                        "model": "rigid with the scope: the same pixels in every frame (scope3d.phantoms.tool)"}
    return PhantomSequence(
        built, camera, frames, fluo if built.targets else None, list(poses), measured, depths, tids, traj, info,
        [f"{i:04d}.png" for i in range(len(poses))], blocked, boards, resected,
    )


def calibration_model(model: str) -> str:
    """The ``calibrate --model`` that fits a camera of this model (``radial`` for scope3d's own)."""
    return next(name for name, fitted in CAMERA_MODEL_OF.items() if fitted == model)


def _stage_reported_quadrant_poses(traj: Trajectory, pose_noise_mm: float, seed: int) -> list[MeasuredPose]:
    """What the rotation stage reports for a quadrant scan: its nominal poses (camera on the rotation axis,
    untilted), with the stage's noise if any, and a tolerance covering the unknown mount."""
    from scope3d.phantoms.trajectories import quadrant_trajectory
    from scope3d.sensor.pose_tolerance import PoseTolerance

    p = traj.params
    nominal = quadrant_trajectory(p["frames_per_quadrant"], step_mm=p["step_mm"], quadrants=p["quadrants"],
                                  angle_step_deg=p["angle_step_deg"], side_view_deg=p["side_view_deg"],
                                  start_z_mm=p["start_z_mm"], axis_offset_mm=(0.0, 0.0), axis_tilt_deg=0.0)
    reported = measure_poses(nominal.poses, pose_noise_mm, seed=seed)
    mount_mm = float(np.hypot(*p["axis_offset_mm"]))
    mount_rad = float(np.deg2rad(abs(p["axis_tilt_deg"])))
    return [MeasuredPose(m.pose, PoseTolerance(m.tolerance.position_mm + mount_mm,
                                               m.tolerance.orientation_rad + mount_rad)) for m in reported]


def quadrant_layout(trajectory: Trajectory, names: list[str], thread: str | None = None) -> dict:
    """The ``quadrants.json`` of a quadrant scan: per quadrant its stage angle (degrees) and frames in
    order of advance, plus the stage's nominal step and side-view angle, and the hole's nominal ``thread``
    (the drawing's designation, which ``thread-scan`` gauges against) when given."""
    p = trajectory.params
    m = p["frames_per_quadrant"]
    return {**({"thread": thread} if thread else {}),
            "angle_step_deg": p["angle_step_deg"], "step_mm": p["step_mm"], "side_view_deg": p["side_view_deg"],
            "rotation_axis": "world z through the origin (nominal)",
            "quadrants": [{"index": q, "angle_deg": q * p["angle_step_deg"], "frames": names[q * m:(q + 1) * m]}
                          for q in range(p["quadrants"])]}


def plan_trajectory(plan: PlanFile, *, video_fps: float | None = None,
                    seconds_per_view: float = SECONDS_PER_PLANNED_VIEW, n_frames: int | None = None) -> Trajectory:
    """A plan's views as a trajectory: one frame per view, or with ``video_fps`` the continuous path through
    them (``round(video_fps * seconds_per_view)`` frames from each view to the next, poses interpolated:
    centres linearly, orientations by slerp). ``n_frames`` keeps the first frames. The frame's section
    (spiral turn) is in ``params["sections"]``."""
    poses, sections = list(plan.poses), list(int(k) for k in plan.sections)
    params = {"kind": "plan", "views": len(poses), "plan": {k: v for k, v in plan.info.items() if k != "camera"}}
    if video_fps is not None:
        if not (np.isfinite(video_fps) and video_fps > 0 and np.isfinite(seconds_per_view) and seconds_per_view > 0):
            raise InputError(f"video frame rate and seconds per view must be positive, got {video_fps}, "
                             f"{seconds_per_view}")
        steps = max(1, int(round(video_fps * seconds_per_view)))
        path, path_sections = [], []
        for a, b, k in zip(poses[:-1], poses[1:], sections[:-1]):
            path.extend(a.interpolate(b, j / steps) for j in range(steps))
            path_sections.extend([k] * steps)
        poses, sections = path + poses[-1:], path_sections + sections[-1:]
        params.update({"kind": "plan video", "fps": float(video_fps), "seconds_per_view": float(seconds_per_view),
                       "frames_per_view": steps})
    if n_frames is not None:
        poses, sections = poses[:n_frames], sections[:n_frames]
    params["sections"] = sections
    times = None if video_fps is None else np.arange(len(poses)) / float(video_fps)
    return Trajectory("plan" if video_fps is None else "plan_video", poses, params, times)


def contact_sheet(images: list[np.ndarray], *, columns: int | None = None, thumb_px: int = 160,
                  gap_px: int = 2) -> np.ndarray:
    """Tile images (each (H, W, 3) or (H, W) uint8) as thumbnails ``thumb_px`` wide. -> (H', W', 3) uint8."""
    import cv2

    if not images:
        raise ValueError("contact sheet needs at least one image")
    n = len(images)
    cols = columns or int(np.ceil(np.sqrt(n * 1.3)))
    rows = int(np.ceil(n / cols))
    h0, w0 = images[0].shape[:2]
    tw, th = thumb_px, max(1, int(round(thumb_px * h0 / w0)))
    sheet = np.full((rows * (th + gap_px) + gap_px, cols * (tw + gap_px) + gap_px, 3), 40, np.uint8)
    for k, img in enumerate(images):
        thumb = cv2.resize(img, (tw, th), interpolation=cv2.INTER_AREA)
        if thumb.ndim == 2:
            thumb = np.repeat(thumb[..., None], 3, axis=2)
        r, c = divmod(k, cols)
        y, x = gap_px + r * (th + gap_px), gap_px + c * (tw + gap_px)
        sheet[y:y + th, x:x + tw] = thumb
    return sheet


def write(sequence: PhantomSequence, out_dir: str | Path, *, contact_sheet_px: int = 160, mp4: bool = False,
          finish=None) -> Path:
    """Write the dataset folder (see :mod:`scope3d.io.dataset`), ground truth included, and
    ``contact_sheet.png`` (plus ``contact_sheet_fluorescence.png`` when the scene has targets).
    mp4 : also write the frames as ``video.mp4`` at the trajectory's frame rate (a plan video's).
    finish : see :func:`scope3d.io.dataset.write_dataset` (a job's report, written with the dataset)."""
    if mp4 and "fps" not in sequence.trajectory.params:
        raise InputError("an MP4 needs a video-rate trajectory (a plan or a grid survey rendered with a frame rate)")
    out_dir = Path(out_dir)
    # the contact sheets go into the dataset's atomic write: a kill never leaves a dataset without them
    sheets = {"contact_sheet.png": contact_sheet(sequence.frames, thumb_px=contact_sheet_px)}
    if sequence.fluorescence is not None:
        sheets["contact_sheet_fluorescence.png"] = contact_sheet(sequence.fluorescence, thumb_px=contact_sheet_px)
    if sequence.tool_mask is not None:
        sheets[TOOL_MASK_FILE] = np.where(sequence.tool_mask, 255, 0).astype(np.uint8)
    write_dataset(
        out_dir, sequence.camera, sequence.frames, sequence.measured_poses, names=sequence.names,
        fluorescence=sequence.fluorescence, true_poses=sequence.true_poses, true_surface=sequence.surface,
        true_depths=sequence.depths, scene=sequence.scene_info,
        metadata={"source": "scope3d phantom lab", "scene_name": sequence.scene.name,
                  "trajectory": sequence.trajectory.name},
        extra_images=sheets, finish=lambda folder: _complete(sequence, folder, mp4, finish),
        times_s=sequence.times_s,
    )
    return out_dir


def _complete(sequence: PhantomSequence, folder: Path, mp4: bool, finish) -> None:
    """The files beside the dataset proper, written into the folder being built (a kill never leaves a
    thread dataset without its quadrant layout): quadrants.json, the surface after a resection, the
    boards, video.mp4, then the caller's ``finish``."""
    if sequence.trajectory.params.get("kind") == "quadrants":
        from scope3d.utils.jsonio import write_json

        write_json(folder / "quadrants.json", quadrant_layout(sequence.trajectory, sequence.names,
                                                              (sequence.scene_info.get("thread") or {}).get("designation")))
    if sequence.resected is not None:
        from scope3d.io.ply import write_ply

        write_ply(folder / "ground_truth" / RESECTED_SURFACE_FILE, sequence.resected.mesh)
    if sequence.boards:
        from scope3d.io.images import write_image

        (folder / BOARDS_FOLDER).mkdir()
        for i, image in enumerate(sequence.boards):
            write_image(folder / BOARDS_FOLDER / f"board_{i:02d}.png", image)
    if mp4:
        from scope3d.io.video import write_video

        write_video(folder / "video.mp4", sequence.frames, sequence.trajectory.params["fps"])
    if finish is not None:
        finish(folder)


def catalogue() -> str:
    """Human-readable list of scenes, trajectories and their parameters (``scope3d phantom --list``)."""
    lines = ["scenes (default trajectory first):"]
    for name, text in SCENES.items():
        lines.append(f"  {name:8s} {text}")
        lines.append(f"  {'':8s} trajectories: {', '.join(SCENE_TRAJECTORIES[name])}")
    lines.append(f"  thread sizes: {', '.join(THREAD_SIZES)} (ISO 68-1 basic profile)")
    lines.append("trajectories:")
    for name, (text, _) in TRAJECTORIES.items():
        lines.append(f"  {name:9s} {text}")
    lines.append("cameras: endoscope 608x608, circular field r = 300 px, FOV 53° (dome, sheet) or 70°; "
                 "borescope 1280x1024, FOV 60°, 45° side view (quadrants)")
    return "\n".join(lines)


def true_targets(scene: dict) -> list[dict]:
    """Ground-truth targets from a phantom's scene description (``ground_truth/scene.json``), as dicts
    ``{name, centre_mm, size_mm, shape, area_mm2, projection_normal}``; targets without a centre or size are skipped."""
    out = []
    for k, t in enumerate(scene.get("targets", []) or []):
        sizes = t.get("size", {}) if isinstance(t.get("size"), dict) else {}
        centre = next((t[key] for key in ("centroid_mm", "centre_mm", "center_mm", "position_mm") if key in t), None)
        size = next((sizes[key] for key in ("edge_mm", "diameter_mm") if key in sizes), t.get("size_mm"))
        if centre is None or size is None:
            continue
        name = t.get("name", f"#{t.get('id', k + 1)} {t.get('shape', '')}".strip())
        out.append({"name": name, "centre_mm": centre, "size_mm": float(size), "shape": t.get("shape"),
                    "area_mm2": t.get("area_mm2"), "projection_normal": (t.get("projection") or {}).get("n")})
    return out
