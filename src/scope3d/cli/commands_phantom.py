"""``scope3d phantom``: render a phantom scene along a trajectory and write it as a dataset with ground truth."""
from __future__ import annotations

import argparse
import time
from pathlib import Path

from scope3d.cli.job_output import add_job_arguments, dataset_report_writer, finish_job, show_progress
from scope3d.cli.lazy import LazyChoices
from scope3d.errors import InputError


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must be WIDTHxHEIGHT in pixels, e.g. 160x160, got {text!r}") from None
    if w < 8 or h < 8:
        raise argparse.ArgumentTypeError(f"size must be at least 8x8 pixels, got {text!r}")
    return w, h


def _floats(text: str, n: int, option: str, form: str) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in text.split(":"))
    except ValueError:
        values = ()
    if len(values) != n or not all(abs(v) < float("inf") for v in values):
        raise InputError(f"{option} must be {form}, got {text!r}")
    return values


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "phantom",
        help="render a phantom (dome, sheet, bladder, thread, cavity) with exact ground truth",
        description="Render an image sequence of a phantom with exact ground truth (true poses, surface mesh, "
                    "depth maps, scene.json; lengths in mm) and write it as a scope3d dataset folder, plus "
                    "contact_sheet.png, report.json and report.html.",
    )
    p.add_argument("scene", nargs="?", choices=LazyChoices("scope3d.phantoms.scenes", "SCENES"), metavar="SCENE",
                   help="phantom to render: %(choices)s")
    p.add_argument("--out", metavar="DIR", help="dataset folder to write (replaced if it exists)")
    p.add_argument("--list", action="store_true", help="list scenes and trajectories with their parameters")
    p.add_argument("--seed", type=int, default=0, help="seed of sensor and pose noise (default 0)")
    p.add_argument("--trajectory", metavar="NAME", help="trajectory, see --list (default: the scene's)")
    p.add_argument("--pose-noise", type=float, default=0.0, metavar="MM",
                   help="reported camera centres are off by up to ±MM per axis (orientation ±0.5°/mm), "
                        "written as their tolerance; 0 = exact, with the micro-stage tolerance 0.01 mm (default)")
    p.add_argument("--thread", default="M8x1.25", metavar="SIZE",
                   help="ISO thread size (default M8x1.25; the sizes: see --list)")
    p.add_argument("--frames", type=int, metavar="N", help="number of frames (limits grids; quadrants: total, "
                   "default the scan plan's for the thread size, lens and side view)")
    p.add_argument("--fov", type=float, metavar="DEG", help="camera field of view across the width, degrees "
                   "(the pinhole lens's)")
    p.add_argument("--lens", default="pinhole", choices=LazyChoices("scope3d.phantoms.lenses", "LENSES"),
                   metavar="LENS", help="the scope's lens, %(choices)s (default pinhole): fisheye-140 a capsule-like "
                   "OPENCV_FISHEYE with a circular field and vignetting, barrel-70 a rigid scope with strong barrel "
                   "distortion (OPENCV); camera.json is written of that model (docs/phantoms.md)")
    p.add_argument("--boards", type=int, default=0, metavar="N",
                   help="also render N checkerboard views (9x6 inner corners, 2 mm squares) through the same lens "
                        "into DIR/boards/, for `scope3d calibrate` (scene.json gives its command line)")
    p.add_argument("--size", type=_size, metavar="WxH", help="image size in pixels (e.g. 160x160 for tests)")
    p.add_argument("--side-view", type=float, default=45.0, metavar="DEG",
                   help="borescope side-view angle for quadrants (45 or 90 in the reference)")
    p.add_argument("--axis-offset", type=float, default=0.0, metavar="MM",
                   help="axial trajectory: scope centre offset from the hole axis along +x, mm (default 0)")
    p.add_argument("--axis-tilt", type=float, default=0.0, metavar="DEG",
                   help="axial trajectory: optical axis tilted from the motion about the camera x axis, "
                        "degrees, within ±15 (default 0)")
    p.add_argument("--supersample", type=int, metavar="K",
                   help="anti-aliasing: K x K rays per pixel (default: the scene's, 2 for thread, 1 elsewhere)")
    p.add_argument("--dome-radius", type=float, default=17.5, metavar="MM", help="dome radius, 15-17.5 mm")
    p.add_argument("--blur", type=float, default=0.0, metavar="PX", help="optical blur sigma in pixels")
    p.add_argument("--defect", metavar="ANGLE_DEG:WIDTH_DEG:DEPTH_MM[:Z_MM]",
                   help="thread: a chipped crest on the middle turn (or the crest turn nearest height Z, mm, "
                        "negative into the hole), centred at ANGLE about +z from +x, WIDTH degrees wide, cut "
                        "back DEPTH mm")
    p.add_argument("--pitch-diameter-offset", type=float, default=0.0, metavar="MM",
                   help="thread: pitch diameter D2 above its basic size, mm (6H: 0 to TD2)")
    p.add_argument("--minor-diameter-offset", type=float, default=0.0, metavar="MM",
                   help="thread: minor diameter D1 above its basic size, mm (6H: 0 to TD1)")
    p.add_argument("--major-diameter-offset", type=float, default=0.0, metavar="MM",
                   help="thread: major diameter D above nominal, mm (6H: >= 0)")
    p.add_argument("--mount", metavar="DX_MM:DY_MM:TILT_DEG",
                   help="quadrants: the camera's unknown offset from the rotation axis (mm) and tilt about its "
                        "image rows (degrees); default 0.08:-0.05:0")
    p.add_argument("--quadrant-step", type=float, metavar="MM",
                   help="quadrants: the scope's advance per frame, mm (default: the scan plan's for the thread "
                        "size, lens and side view, docs/thread_metrology.md)")
    p.add_argument("--target", type=int, metavar="N",
                   help="approach trajectory: the target to approach (dome: 1-8); a tool hides part of the view, "
                        "its mask written as tool_mask.png")
    bl = p.add_argument_group("bladder and scan plans (reference ch. 2)")
    bl.add_argument("--plan", metavar="PLAN_JSON", help="render the views of a scan plan (scope3d plan-scan) "
                    "instead of a trajectory, with its field of view unless --fov is given")
    bl.add_argument("--seconds-per-view", type=float, default=600.0 / 529.0, metavar="S",
                    help="with --video: time from one planned view to the next (default 1.13 s, the reference's "
                         "10 min for 529 views)")
    bl.add_argument("--cavity-mm", type=_semi_axes, metavar="A,B,C", help="bladder semi-axes in mm (default 45,38,32)")
    bl.add_argument("--shape-seed", type=int, default=0, metavar="N",
                    help="bladder irregularity: 0 the default shape, else a random one of the same size")
    bl.add_argument("--vessel-density", type=float, default=1.0, metavar="F",
                    help="bladder vessels and capillary dots as a fraction of the default (1); 0.25 is pale")
    bl.add_argument("--wet", action="store_true", help="bladder: specular glints of wet mucosa at the tip's light")
    vid = p.add_argument_group("videos: a continuous path with frame times, tissue that changes (docs/phantoms.md)")
    vid.add_argument("--video", type=float, metavar="FPS", help="render a continuous path at FPS frames per second "
                     "(poses interpolated; poses.csv gets each frame's time_s, frame i at i / FPS): with --plan the "
                     "path through the planned views; without, a grid survey (dome, sheet, cavity) flown from stop "
                     "to stop at --scan-speed (grid5x6 at 10 mm/s: 436 frames at 30 fps); --frames keeps the first N")
    vid.add_argument("--mp4", action="store_true", help="with --video: also write the frames as DIR/video.mp4 "
                     "(MPEG-4, at FPS), a real video file for `scope3d import video`")
    vid.add_argument("--resect", metavar="T_S[:RADIUS_MM:DEPTH_MM[:X_MM:Y_MM]]",
                     help="dome with --video: from T seconds on, a pit is cut into the dome's wall (default radius "
                          "3 mm, depth 1.5 mm, centred on the wall below (X, Y), drawn from --seed unless given); "
                          "ground_truth/ holds the surface before (surface.ply) and after (surface_resected.ply), "
                          "scene.json the pit, its time and first frame (docs/phantoms.md)")
    raw = p.add_argument_group("a lab's raw recording (docs/own_data.md)")
    raw.add_argument("--raw-recording", action="store_true",
                     help="dome only: write what a lab would bring instead of a dataset: checkerboard views, "
                          "hand-eye stills with the robot's log, a scan video with its 250 Hz robot log (metres, "
                          "x-y-z-w quaternions, the robot's own clock) and the hidden truth (--size, --seed apply)")
    raw.add_argument("--scan-speed", type=float, metavar="MM_S",
                     help="with --raw-recording or a grid --video: the scan's speed between raster points (default "
                          "25 mm/s for a raw recording, 10 mm/s for a video)")
    raw.add_argument("--robot-error", type=float, default=0.2, metavar="MM",
                     help="with --raw-recording: the controller's smooth pose error along the path, at most MM "
                          "per axis and MM x 0.5 deg (default 0.2; 0 = an exact robot)")
    add_job_arguments(p)
    p.set_defaults(func=run)


def _semi_axes(text: str) -> tuple[float, float, float]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 3 or not all(v > 0 for v in values):
        raise argparse.ArgumentTypeError(f"--cavity-mm takes three positive lengths A,B,C in mm, got {text!r}")
    return values


def run(args) -> int:
    from scope3d.cli.progress import progress_bar
    from scope3d.phantoms import catalogue, generate, write
    from scope3d.phantoms.render import RenderOptions

    if args.list:
        print(catalogue())
        return 0
    if not args.scene:
        raise InputError("name a scene (dome, sheet, bladder, thread, cavity) or use --list")
    if not args.out:
        raise InputError("--out DIR is required")
    if args.raw_recording:
        if args.lens != "pinhole" or args.boards:
            raise InputError("--lens and --boards apply to a dataset; a raw recording is rendered through the "
                             "pinhole with its own boards")
        return _run_raw_recording(args)
    if args.blur < 0:
        raise InputError(f"--blur must be non-negative, got {args.blur}")
    if args.lens != "pinhole" and args.fov is not None:
        raise InputError(f"--fov sets the pinhole's field; the {args.lens} lens has its own")
    if args.supersample is not None and not 1 <= args.supersample <= 8:
        raise InputError(f"--supersample must be from 1 to 8, got {args.supersample}")
    defect = None
    if args.defect:
        form = "ANGLE_DEG:WIDTH_DEG:DEPTH_MM[:Z_MM]"
        defect = _floats(args.defect, 4 if args.defect.count(":") == 3 else 3, "--defect", form)
    mount = _floats(args.mount, 3, "--mount", "DX_MM:DY_MM:TILT_DEG") if args.mount else None
    offsets = (args.minor_diameter_offset, args.pitch_diameter_offset, args.major_diameter_offset)
    if (defect or any(offsets)) and args.scene != "thread":
        raise InputError("--defect and the diameter offsets apply to the thread scene only")
    bladder = {}
    if args.cavity_mm is not None:
        bladder["semi_axes_mm"] = args.cavity_mm
    if args.shape_seed:
        bladder["shape_seed"] = args.shape_seed
    if args.vessel_density != 1.0:
        bladder["vessel_density"] = args.vessel_density
    if args.wet:
        bladder["wet"] = True
    plan = None
    if args.plan:
        from scope3d.io.scan_plan import read_scan_plan

        plan = read_scan_plan(args.plan)
    if args.mp4 and args.video is None:
        raise InputError("--mp4 needs --video FPS")
    if args.scan_speed is not None and (args.video is None or args.plan):
        raise InputError("--scan-speed applies to --raw-recording and to a grid survey's --video")
    resection = None
    if args.resect:
        from scope3d.phantoms.resection import Resection

        if args.video is None:
            raise InputError("--resect needs --video FPS (the pit is cut at a time)")
        form = "T_S[:RADIUS_MM:DEPTH_MM[:X_MM:Y_MM]]"
        n = args.resect.count(":") + 1
        if n not in (1, 3, 5):
            raise InputError(f"--resect must be {form}, got {args.resect!r}")
        values = _floats(args.resect, n, "--resect", form)
        resection = Resection(values[0], *values[1:3], **({"centre_xy_mm": values[3:5]} if n == 5 else {}))
    n_frames, step, scan_plan = args.frames, args.quadrant_step, None
    if args.scene == "thread" and args.trajectory == "quadrants" and not args.plan:
        n_frames, step, scan_plan = _planned_quadrant_scan(args)
    started = time.perf_counter()
    with progress_bar(show_progress(args), "frame") as progress:
        seq = generate(
            args.scene, args.trajectory, seed=args.seed, pose_noise_mm=args.pose_noise, thread=args.thread,
            n_frames=n_frames, size=args.size, fov_deg=args.fov, side_view_deg=args.side_view,
            axis_offset_mm=args.axis_offset, axis_tilt_deg=args.axis_tilt,
            dome_radius_mm=args.dome_radius, options=RenderOptions(blur_sigma_px=args.blur, supersample=args.supersample),
            progress=progress, target=args.target, thread_offsets_mm=offsets, thread_defect=defect,
            quadrant_mount=mount, quadrant_step_mm=step, bladder=bladder or None, plan=plan, video_fps=args.video,
            seconds_per_view=args.seconds_per_view, lens=args.lens, board_views=args.boards,
            resection=resection,
            **({"scan_speed_mm_s": args.scan_speed} if args.scan_speed is not None else {}),
        )
    report = {"job": "phantom", "scene": args.scene, "trajectory": seq.trajectory.name, "seed": args.seed,
              "pose_noise_mm": args.pose_noise, **({"scan_plan": scan_plan} if scan_plan else {})}
    out = write(seq, args.out, mp4=args.mp4, finish=dataset_report_writer(report, Path(args.out).name, started))
    return finish_job(args, None, report, [
        f"wrote {len(seq)} frames of {args.scene}/{seq.trajectory.name} ({seq.camera.width}x{seq.camera.height}) "
        f"to {out}", f"wrote {Path(out) / 'report.html'}"])


def _planned_quadrant_scan(args) -> tuple[int, float, dict]:
    """(total frames, step mm, what was planned) of a thread's quadrant scan: the scan plan's for the thread
    size, the lens and the side view (``metrology.thread_scan_plan``), ``--frames`` and ``--quadrant-step``
    overriding it. A scan too short to gauge is refused with the least it needs."""
    from scope3d.geometry.iso_thread import THREAD_SIZES
    from scope3d.metrology.thread_scan_plan import minimum_frames, plan_quadrant_scan, scan_coverage
    from scope3d.phantoms.lab import borescope_camera
    from scope3d.phantoms.trajectories import QUADRANT_COUNT

    if args.thread not in THREAD_SIZES:
        raise InputError(f"unknown thread size {args.thread!r} (use one of {', '.join(THREAD_SIZES)})")
    if args.quadrant_step is not None and not args.quadrant_step > 0:
        raise InputError(f"the quadrant step must be a positive length in mm, got {args.quadrant_step}")
    if args.frames is not None and args.frames < 1:
        raise InputError(f"number of frames must be at least 1, got {args.frames}")
    try:
        camera = borescope_camera(size=args.size, fov_deg=args.fov)
        plan = plan_quadrant_scan(camera, args.thread, args.side_view, step_mm=args.quadrant_step)
        frames = plan.frames_per_quadrant if args.frames is None else max(1, args.frames // QUADRANT_COUNT)
        coverage = scan_coverage(camera, args.thread, args.side_view, plan.step_mm, frames)
        least = minimum_frames(camera, args.thread, args.side_view, plan.step_mm)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    if coverage.short:
        fix = (f"at {plan.step_mm:g} mm per frame it needs at least {least} frames per quadrant "
               f"(--frames {least * QUADRANT_COUNT})" if coverage.views_per_point >= 2 or frames < 2 else
               f"the step must be at most {plan.view_extent_mm / 2:.2f} mm (half the view's extent)")
        raise InputError(f"too short to gauge: {coverage.message()}; {fix}")
    return frames * QUADRANT_COUNT, plan.step_mm, {**plan.to_dict(), "frames_per_quadrant": frames,
                                                  "designation": args.thread,
                                                  "overridden": [o for o, v in (("--frames", args.frames),
                                                                                ("--quadrant-step", args.quadrant_step))
                                                                 if v is not None]}


def _run_raw_recording(args) -> int:
    from scope3d.cli.progress import progress_bar
    from scope3d.phantoms.recording import RecordingOptions, write_recording

    if args.scene != "dome":
        raise InputError(f"--raw-recording renders the dome phantom, not {args.scene!r}")
    speed = RecordingOptions.speed_mm_s if args.scan_speed is None else args.scan_speed
    if not speed > 0:
        raise InputError(f"--scan-speed must be positive, got {args.scan_speed}")
    if not args.robot_error >= 0:
        raise InputError(f"--robot-error must be zero or positive, got {args.robot_error}")
    out = Path(args.out)
    if out.exists() and not (out / "README.txt").is_file() and any(out.iterdir()):
        raise InputError(f"{out}: exists and is not a recording; choose another --out")
    started = time.perf_counter()
    with progress_bar(show_progress(args), "image") as progress:
        write_recording(RecordingOptions(size=args.size, speed_mm_s=speed, seed=args.seed,
                                         robot_error_mm=args.robot_error), out,
                        progress=progress)
    report = {"job": "phantom", "scene": "dome", "raw_recording": str(out), "seed": args.seed,
              "time_s": round(time.perf_counter() - started, 3)}
    return finish_job(args, None, report, [f"wrote a raw recording to {out} (README.txt says what is in it)"])
