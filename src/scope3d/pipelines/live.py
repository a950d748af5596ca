"""The live map replayed from a recording, as ``scope3d live`` runs it (issue 36, reference sec. 9.3.2).

Method, one stage per function, run top to bottom by :func:`run`:

1. :func:`frame_times` — each frame's time: ``k / fps``, the rate given or the phantom video's own.
2. :func:`replay` — every frame, with its reported pose and tolerance, through one
   :class:`~scope3d.sfm.live_mapping.LiveMapper` in order, at the recording's real rate (the stream waits
   for each frame's time, so the keyframe worker has the wall time a live scope would give it) or as fast
   as possible; then :meth:`~scope3d.sfm.live_mapping.LiveMapper.finish`, the global BCBA.
3. :func:`evaluate` — where ground truth exists: per-frame errors of the fused pose, the robot's report and
   the image's own pose; the final map's ``surface_error_mm`` and its keyframes' ``pose_error``, the blocks
   ``scope3d map`` writes.
4. :func:`write_outputs` — ``poses.csv`` (every frame's fused pose, tolerance 3 sigma of its covariance),
   ``frames.csv`` (status, latency, inliers, errors), ``keyframes.csv`` (adjusted poses), ``map.ply``,
   ``keyframe_maps/NNN.ply`` (the map as it stood when keyframe NNN was kept),
   ``report.json`` (``latency_ms`` → ``median``, ``p99``, ``max``; statuses; the errors) and ``live.png``
   (error along the trajectory, latency histogram).
"""
from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path

import numpy as np

from scope3d.errors import InputError
from scope3d.estimators.kalman import covariance_to_tolerance
from scope3d.io.dataset import Dataset
from scope3d.io.ply import write_ply
from scope3d.io.poses_csv import format_poses_csv
from scope3d.metrology.evaluation import EvaluationOptions, pose_errors, surface_errors
from scope3d.mvs.surface_change import SurfaceChangeOptions, detect_surface_change
from scope3d.scene.mesh import PointCloud, SampledSurface
from scope3d.sensor.pose_tolerance import MeasuredPose
from scope3d.sfm.live_mapping import LIVE_STATUSES, LiveFrame, LiveMap, LiveMapper, LiveMapperOptions
from scope3d.utils.atomic import atomic_directory
from scope3d.utils.figures import new_figure, save_figure
from scope3d.utils.jsonio import write_json
from scope3d.utils.progress import Progress, advance, stage


@dataclass(frozen=True)
class LiveOptions:
    """mapper : :class:`~scope3d.sfm.live_mapping.LiveMapperOptions`.
    wait : bool, replay at the recording's rate (default True); False: as fast as possible.
    fps : float or None, the recording's frame rate (None: the phantom video's, from its ground truth).
    tolerance_sigmas : float, the tolerance written for a fused pose, in its standard deviations (3).
    evaluation : the surface errors' settings. figures : bool, write live.png (default True).
    change : tissue that changed (resected, moved) found by :func:`~scope3d.mvs.surface_change.detect_surface_change`
        with these options and dropped from the map (the mapper's ``change_test``), or None (default) to keep
        every point; a ``change_test`` already in ``mapper`` is kept. Off by default: on the loaded 2-core
        machine the test takes 0.5-1.5 s per keyframe, which pushes the worker past its one-second lag, so the
        stream waits (latency p99 1.7 s instead of 76 ms on the dome survey, benchmarks/results/live_resect.json).
    """

    mapper: LiveMapperOptions = field(default_factory=LiveMapperOptions)
    wait: bool = True
    fps: float | None = None
    tolerance_sigmas: float = 3.0
    evaluation: EvaluationOptions = field(default_factory=EvaluationOptions)
    figures: bool = True
    change: SurfaceChangeOptions | None = None

    def __post_init__(self) -> None:
        if self.fps is not None and not (np.isfinite(self.fps) and self.fps > 0):
            raise ValueError(f"fps must be positive, got {self.fps}")
        if not self.tolerance_sigmas > 0:
            raise ValueError(f"tolerance_sigmas must be positive, got {self.tolerance_sigmas}")


@dataclass
class LiveResult:
    """What :func:`run` returns: the report (also in ``out_dir/report.json``), every frame, the final map."""

    report: dict
    out_dir: Path
    frames: list[LiveFrame]
    map: LiveMap

    def summary(self) -> str:
        r = self.report
        lat = r["latency_ms"]
        line = (f"{r['n_frames']} frames, {r['n_keyframes']} keyframes, {r['n_points']} map points; latency "
                f"median {lat['median']:.1f} ms, p99 {lat['p99']:.1f} ms")
        err = r.get("tracking_error")
        if err:
            line += (f"; camera error median {err['fused']['position_mm_median']:.3f} mm "
                     f"(robot {err['robot']['position_mm_median']:.3f} mm)")
        surf = r.get("surface_error_mm")
        if surf:
            line += (f"; map {surf['direct']['mean']:.3f} mm from the surface "
                     f"({surf['after_icp']['mean']:.3f} after ICP)")
        return line


def frame_times(options: LiveOptions, dataset: Dataset) -> np.ndarray:
    """(m,) seconds: ``k / fps``, with ``options.fps`` or the phantom video's rate."""
    fps = options.fps
    if fps is None and dataset.ground_truth is not None:
        fps = (dataset.ground_truth.scene.get("trajectory") or {}).get("fps")
    if fps is None:
        raise InputError(f"{dataset.root}: the frame rate is not recorded; give it (--fps)")
    return np.arange(len(dataset)) / float(fps)


def mapper_options(options: LiveOptions) -> LiveMapperOptions:
    """The mapper's options with the change test of ``options.change`` (a function that pickles: the mapper's
    worker is a spawned process)."""
    if options.change is None or options.mapper.change_test is not None:
        return options.mapper
    return replace(options.mapper, change_test=partial(detect_surface_change, options=options.change))


def replay(options: LiveOptions, dataset: Dataset, times: np.ndarray, *, progress: Progress | None = None,
           on_frame: Callable[[LiveFrame, LiveMapper], None] | None = None,
           ) -> tuple[list[LiveFrame], LiveMap, float, list[LiveMap]]:
    """Every frame through one mapper, at the recorded rate when ``options.wait``; then the global BCBA.
    Returns the frames, the final map, the global BCBA's wall time (s) and the map as it stood at each
    keyframe (:meth:`~scope3d.sfm.live_mapping.LiveMapper.current_map`, taken after the frame's answer).
    A frame is read before its time comes (a live stream delivers decoded frames). ``on_frame(frame,
    mapper)`` is called after each frame's answer (a benchmark's look at the map as it grows)."""
    frames: list[LiveFrame] = []
    snapshots: list[LiveMap] = []
    stage(progress, "live", len(dataset))
    with LiveMapper(dataset.camera, mapper_options(options)) as mapper:
        start = time.perf_counter()
        for k in range(len(dataset)):
            image = dataset.frame(k)
            if options.wait:
                late = start + times[k] - time.perf_counter()
                if late > 0:
                    time.sleep(late)
            frames.append(mapper.add_frame(image, dataset.poses[k], float(times[k])))
            if on_frame is not None:
                on_frame(frames[-1], mapper)
            if frames[-1].keyframe is not None:
                snapshots.append(mapper.current_map())
            advance(progress)
        t0 = time.perf_counter()
        final = mapper.finish()
    return frames, final, time.perf_counter() - t0, snapshots


def evaluate(options: LiveOptions, dataset: Dataset, frames: list[LiveFrame], final: LiveMap) -> dict:
    """Errors against the ground truth (empty when there is none): per frame (``rows``), their summary after
    the first second, the keyframes' ``pose_error`` and the map's ``surface_error_mm``."""
    gt = dataset.ground_truth
    out: dict = {}
    if gt is None:
        return out
    if gt.poses is not None:
        rows = []
        for f in frames:
            truth = gt.poses[f.index]
            row = {"fused": f.pose.distance_to(truth), "robot": dataset.poses[f.index].pose.distance_to(truth),
                   "image": f.image_pose.distance_to(truth) if f.image_pose is not None else (np.nan, np.nan)}
            rows.append(row)
        out["rows"] = rows
        settled = [r for f, r in zip(frames, rows) if f.time_s >= frames[0].time_s + 1.0] or rows
        out["tracking_error"] = {key: _error_summary([r[key] for r in settled]) for key in ("fused", "robot", "image")}
        # on the frames the image posed: fusion against the image's own pose, like for like
        imaged = [r for r in settled if np.isfinite(r["image"][0])]
        out["tracking_error"]["on_imaged_frames"] = {key: _error_summary([r[key] for r in imaged])
                                                     for key in ("fused", "robot", "image")}
        out["tracking_error"]["frames_after_s"] = 1.0
        out["tracking_error"]["fused_at_most_half_robot_fraction"] = float(np.mean(
            [r["fused"][0] <= 0.5 * r["robot"][0] for r in settled]))
        kf = final.keyframe_frames
        out["pose_error"] = pose_errors(final.keyframe_poses, final.measured, [gt.poses[k] for k in kf])
    if gt.surface_path is not None and len(final.points):
        truth = SampledSurface(gt.surface(), options.evaluation.sample_step_mm)
        out["surface_error_mm"], _, _ = surface_errors(final.points, truth, options=options.evaluation)
    return out


def _error_summary(errors: list[tuple[float, float]]) -> dict:
    e = np.array(errors, float).reshape(-1, 2)
    ok = np.isfinite(e[:, 0])
    if not ok.any():
        return {"n": 0}
    d, a = e[ok, 0], np.degrees(e[ok, 1])
    return {"n": int(ok.sum()), "position_mm_median": float(np.median(d)), "position_mm_mean": float(np.mean(d)),
            "position_mm_max": float(np.max(d)), "orientation_deg_median": float(np.median(a)),
            "orientation_deg_max": float(np.max(a))}


def write_outputs(options: LiveOptions, dataset: Dataset, out_dir: Path, frames: list[LiveFrame], final: LiveMap,
                  errors: dict, times: np.ndarray, finish_s: float, snapshots: list[LiveMap]) -> dict:
    """poses.csv, frames.csv, keyframes.csv, map.ply, keyframe_maps/NNN.ply, report.json and live.png into
    ``out_dir``."""
    names = dataset.names
    fused = [MeasuredPose(f.pose, covariance_to_tolerance(f.covariance, options.tolerance_sigmas)) for f in frames]
    (out_dir / "poses.csv").write_text(format_poses_csv([names[f.index] for f in frames], fused))
    (out_dir / "keyframes.csv").write_text(format_poses_csv([names[k] for k in final.keyframe_frames],
                                                            [MeasuredPose(p) for p in final.keyframe_poses]))
    rows = errors.get("rows")
    lines = ["frame,time_s,status,keyframe,latency_ms,waited_ms,inliers,dropped_points,fused_error_mm,robot_error_mm,"
             "image_error_mm"]
    for k, f in enumerate(frames):
        e = (f"{rows[k]['fused'][0]:.6f},{rows[k]['robot'][0]:.6f},{rows[k]['image'][0]:.6f}" if rows else ",,")
        lines.append(f"{names[f.index]},{f.time_s:.6f},{f.status},{'' if f.keyframe is None else f.keyframe},"
                     f"{f.latency_ms:.3f},{f.waited_ms:.3f},{f.n_inliers},{f.dropped_points},{e}")
    (out_dir / "frames.csv").write_text("\n".join(lines) + "\n")
    write_ply(out_dir / "map.ply", PointCloud(final.points, final.colors))
    (out_dir / "keyframe_maps").mkdir()
    for k, snapshot in enumerate(snapshots):  # the local map tracking used when keyframe k was kept
        write_ply(out_dir / "keyframe_maps" / f"{k:03d}.ply", PointCloud(snapshot.points, snapshot.colors))
    latency = np.array([f.latency_ms for f in frames])
    own = latency - np.array([f.waited_ms for f in frames])
    interval_ms = 1000.0 * float(np.median(np.diff(times))) if len(times) > 1 else float("inf")
    report = {
        "dataset": str(dataset.root), "n_frames": len(frames), "n_keyframes": len(final.keyframe_frames),
        "n_points": int(len(final.points)), "replayed_at_rate": options.wait,
        "fps": 1000.0 / interval_ms if np.isfinite(interval_ms) else None,
        "statuses": {s: sum(f.status == s for f in frames) for s in LIVE_STATUSES},
        "latency_ms": {"median": float(np.median(latency)), "p99": float(np.percentile(latency, 99)),
                       "max": float(latency.max()), "over_frame_interval": int(np.sum(latency > interval_ms)),
                       "frames_waiting_for_the_worker": int(sum(f.waited_ms > 0 for f in frames)),
                       "without_waits": {"median": float(np.median(own)), "p99": float(np.percentile(own, 99)),
                                         "max": float(own.max())}},
        "global_bcba_s": finish_s,
        "changed_tissue": {"points_dropped": int(sum(f.dropped_points for f in frames)),
                           "at_frames": [f.index for f in frames if f.dropped_points]},
        "keyframe_frames": final.keyframe_frames.tolist(),
    }
    report.update({k: v for k, v in errors.items() if k != "rows"})
    write_json(out_dir / "report.json", report)
    if options.figures:
        save_live_figure(out_dir / "live.png", frames, rows)
    return report


def save_live_figure(path: Path, frames: list[LiveFrame], rows: list[dict] | None) -> None:
    """The camera error along the trajectory (fused, robot, image) with the keyframes marked, and the
    latency histogram."""
    fig = new_figure((12.0, 4.2), dpi=100)
    ax, hist = fig.subplots(1, 2)
    t = np.array([f.time_s for f in frames])
    if rows:
        for key, style in (("robot", "-"), ("image", "-"), ("fused", "-")):
            ax.plot(t, [r[key][0] for r in rows], style, lw=1, label=f"{key} pose")
        ax.set_ylabel("camera centre error (mm)")
    kf = [f.time_s for f in frames if f.keyframe is not None]
    for x in kf:
        ax.axvline(x, color="0.85", lw=0.6, zorder=0)
    lost = [f.time_s for f in frames if f.status == "lost"]
    if lost:
        ax.plot(lost, np.zeros(len(lost)), "rx", ms=3, label="lost (robot only)")
    ax.set_xlabel("time (s); grey lines: keyframes")
    ax.set_title("error along the trajectory", fontsize=9)
    ax.legend(fontsize=7)
    latency = np.array([f.latency_ms for f in frames])
    hist.hist(latency, bins=40, color="0.4")
    for q, style in ((50, "--"), (99, ":")):
        hist.axvline(np.percentile(latency, q), color="r", ls=style, label=f"p{q} {np.percentile(latency, q):.1f} ms")
    hist.set_xlabel("latency per frame (ms)")
    hist.set_ylabel("frames")
    hist.set_title("latency", fontsize=9)
    hist.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, path)


def run(options: LiveOptions, dataset: Dataset, out_dir: str | Path, *, progress: Progress | None = None) -> LiveResult:
    """Replay ``dataset`` through the live mapper; write ``out_dir`` atomically."""
    t0 = time.perf_counter()
    times = frame_times(options, dataset)
    frames, final, finish_s, snapshots = replay(options, dataset, times, progress=progress)
    errors = evaluate(options, dataset, frames, final)
    with atomic_directory(Path(out_dir)) as tmp:
        report = write_outputs(options, dataset, tmp, frames, final, errors, times, finish_s, snapshots)
        report["time_s"] = time.perf_counter() - t0
        write_json(tmp / "report.json", report)
    return LiveResult(report, Path(out_dir), frames, final)
