"""Side-view thread metrology of a whole tapped hole (reference ch. 8), as one job.

Read top to bottom like the method section::

    quadrants  <- io.quadrants.read_quadrants         (frames of each 30° quadrant, stage angles)
    scan       <- metrology.measured_quadrant_scan    (each quadrant's step and side view read off its
                                                       poses; the scan plan's rule gives the frame gap)
    maps       <- sfm.quadrant_mapping.map_quadrant   (SIFT, matches, tracks, triangulation with the
                                                       stage's known axial poses), one per quadrant
    mount      <- sfm.estimate_mount_rotation         (the camera's rotation on its mount from every
                                                       quadrant's epipoles; the maps re-triangulated
                                                       with the corrected poses: sfm.retriangulate)
    panorama   <- registration.register_quadrants     (neighbours' 3-D-3-D feature correspondences,
                                                       RANSAC + SVD, joint solve with the loop closure)
    dense      <- mvs.plane_sweep.dense_quadrant     (plane sweep of each quadrant with its frames'
                                                       registered poses, straight into the registered
                                                       world; registration.registered_frame_poses)
    cloud      <- registration.statistical_inliers    (30 neighbours, 3 sigma) of the dense clouds (the
                                                       registered sparse ones without dense mapping)
    gauge      <- metrology.gauge_thread              (axis, D1, D, D2, P, flank angle, 6H verdict, defects)
    systematic <- metrology.registration_systematic   (the cloud re-placed by draws of the registration
                                                       from its covariance, re-measured: the spread is
                                                       the sizes' systematic uncertainty)
                  metrology.match_gap_systematic      (neighbours' matched points drawn apart along the
                                                       circle by their measured gap, the joint solve run
                                                       again, re-measured)
                  metrology.profile_bias_systematic   (each profile part's points offset by the sparse
                                                       reconstruction's measured bias, re-measured; both
                                                       in quadrature, the verdict judged again on the
                                                       combined uncertainty)
    errors     <- registration.registration_errors    (when the dataset has true poses)
    files      <- cloud.ply, quadrants/q??.ply (+ q??_dense.ply, registered), report.json,
                  registration.png, unwrapped.png

``run(options, dataset, out_dir) -> ThreadScanResult`` is what ``scope3d thread-scan`` calls.
"""
from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from scope3d.errors import InputError
from scope3d.geometry.iso_thread import THREAD_SIZES
from scope3d.geometry.pose import Pose
from scope3d.io.dataset import Dataset, check_jobs_take
from scope3d.io.ply import write_ply
from scope3d.io.quadrants import read_quadrant_thread, read_quadrants
from scope3d.metrology.thread_gauge import GaugeOptions, GaugeResult, gauge_thread, unmeasured_sizes
from scope3d.metrology.thread_scan_plan import (QuadrantScanPlan, ScanCoverage, measured_quadrant_scan,
                                                plan_quadrant_scan, scan_coverage)
from scope3d.metrology.thread_uncertainty import (MATCH_GAP_MM, SPARSE_POINT_BIAS_MM, combined_systematic,
                                                  match_gap_systematic, profile_bias_systematic,
                                                  registration_systematic, with_systematic)
from scope3d.registration.outliers import OutlierOptions, statistical_inliers
from scope3d.registration.panorama import (PanoramaOptions, PanoramaResult, QuadrantCloud, joint_solve,
                                           pairs_drawn_apart, register_quadrants, registered_frame_poses,
                                           registration_errors)
from scope3d.scene.mesh import PointCloud
from scope3d.mvs.plane_sweep import DenseQuadrantOptions, dense_quadrant
from scope3d.sfm.quadrant_mapping import (MountEstimate, MountOptions, QuadrantMapOptions, estimate_mount_rotation,
                                         map_quadrant, retriangulate)
from scope3d.utils.atomic import atomic_directory
from scope3d.utils.figures import new_figure, save_figure
from scope3d.utils.jsonio import write_json
from scope3d.utils.progress import Progress, advance, stage
from scope3d.utils.threads import check_threads, resolve_threads


# the thread gauged when neither the options nor the dataset name one
DEFAULT_THREAD = "M8x1.25"


@dataclass(frozen=True)
class ThreadScanOptions:
    """designation : the nominal thread (one of ``THREAD_SIZES``; None, the default: the one the
    dataset's ``quadrants.json`` names, else :data:`DEFAULT_THREAD`); the gauge's other options
    come from ``gauge`` (its designation is replaced by this one). mapping, panorama, outliers, gauge :
    the stages' options. dense : the dense clouds' options, or None to gauge the sparse points. threads :
    quadrants mapped at once (OpenCV releases the GIL; default 0: every available core,
    :mod:`scope3d.utils.threads`). registration_draws : draws of the registration from its covariance whose
    re-measured sizes give the systematic uncertainty (default 24: the spread's own relative error is
    1/sqrt(2 (n - 1)), ~15 %; 0 leaves the registration out). point_bias_mm : standard uncertainty of
    the offset of one profile part's points (crest, each flank, root) from the true surface along its
    normal, propagated by :func:`scope3d.metrology.thread_uncertainty.profile_bias_systematic` (default
    :data:`SPARSE_POINT_BIAS_MM`; 0 leaves it out). match_gap_mm : standard uncertainty of the gap along
    the circle between neighbour quadrants' matched points, propagated by
    :func:`scope3d.metrology.thread_uncertainty.match_gap_systematic`
    (default :data:`MATCH_GAP_MM`; 0 leaves it out). frame_gap : each quadrant map matches frames up to
    this many steps apart (it replaces ``mapping.max_frame_gap``); None (default) takes each quadrant's
    from its own scan with the scan plan's rule (matched frames' views overlap by half:
    :func:`scope3d.metrology.thread_scan_plan.measured_quadrant_scan`). mount : options of the camera's
    mount rotation, measured from the quadrants' epipolar geometry and corrected before the quadrants are
    registered (:func:`scope3d.sfm.quadrant_mapping.estimate_mount_rotation`), or None to triangulate with
    the reported poses as they are. seed : RANSAC's and the draws' seeds."""

    designation: str | None = None
    mapping: QuadrantMapOptions = QuadrantMapOptions()
    panorama: PanoramaOptions = PanoramaOptions()
    outliers: OutlierOptions = OutlierOptions()
    gauge: GaugeOptions = GaugeOptions()
    # Off by default: on rendered M8 holes (400x320, 4-8 frames per quadrant, 45° view) the dense clouds
    # measure D1 to 0.01-0.025 mm but not D2 or D (one flank seen), and cost ~1 min of CPU per hole;
    # see docs/thread_metrology.md.
    dense: DenseQuadrantOptions | None = None
    threads: int = 0
    registration_draws: int = 24
    point_bias_mm: float = SPARSE_POINT_BIAS_MM
    match_gap_mm: float = MATCH_GAP_MM
    frame_gap: int | None = None
    mount: MountOptions | None = MountOptions()
    seed: int = 0

    def __post_init__(self) -> None:
        if self.designation is not None and self.designation not in THREAD_SIZES:
            raise InputError(f"unknown thread {self.designation!r} (use one of {', '.join(THREAD_SIZES)})")
        check_threads(self.threads)
        if self.registration_draws < 0 or self.point_bias_mm < 0 or self.match_gap_mm < 0:
            raise ValueError("registration_draws, point_bias_mm and match_gap_mm must be >= 0")
        if self.frame_gap is not None and self.frame_gap < 1:
            raise InputError(f"the frame gap must be at least 1, got {self.frame_gap}")


@dataclass
class ThreadScanResult:
    """clouds : the quadrants (stacked frame); panorama : the registration; dense : per quadrant its
    dense cloud (registered frame, (M_q, 3) mm; empty without dense mapping); points : (N, 3) mm the
    registered cloud the gauge measured, after outlier removal (dense, or the sparse points without); gauge : the measurement, or None when the cloud shows no
    gaugeable thread (gauge_message says why; the verdict is then ``indeterminate``); errors :
    registration errors against the truth or None; timings_s : per stage; systematic_mm : the sizes'
    systematic standard uncertainties (mm) by source, ``registration``, ``point_bias`` and ``match_gap`` (each keyed as
    :func:`scope3d.metrology.thread_gauge.remeasure`), empty when not computed. scans : per quadrant the
    scan read off its poses and the frame gap its map used; coverage : what the shortest of them shows
    of the thread against what the gauge needs (None when the rule cannot tell). mount : the camera's measured mount rotation
    (None when not estimated); the stacked frame is that of the reported poses so corrected."""

    clouds: list[QuadrantCloud]
    panorama: PanoramaResult
    dense: list[np.ndarray]
    points: np.ndarray
    gauge: GaugeResult | None
    errors: dict | None
    timings_s: dict = field(default_factory=dict)
    gauge_message: str = ""
    systematic_mm: dict = field(default_factory=dict)
    scans: list[QuadrantScanPlan] = field(default_factory=list)
    mount: MountEstimate | None = None
    coverage: ScanCoverage | None = None

    def report(self) -> dict:
        g = self.gauge
        registration = {
            "loop_closure_residual_deg": self.panorama.loop_closure_deg,
            "loop_closure_residual_mm": self.panorama.loop_closure_mm,
            "pair_residual_rms_mm": self.panorama.residual_rms_mm,
            "pairs": [{"i": p.i, "j": p.j, "matches": p.n_matches, "inliers": len(p.points_i), "rms_mm": p.rms_mm}
                      for p in self.panorama.pairs],
            "time_s": self.timings_s.get("registration"),
        }
        if self.mount is not None:
            registration["mount_rotation"] = self.mount.to_dict()
        if self.errors:
            registration.update(self.errors)
        gauge = g.to_dict() if g is not None else {"verdict": "indeterminate", "message": self.gauge_message,
                                                   "defects": []}
        if g is not None and self.gauge_message:
            gauge["message"] = self.gauge_message
        if self.systematic_mm:
            gauge["systematic_by_source_mm"] = self.systematic_mm
        return {
            "gauge": gauge,
            "registration": registration,
            "points": {"per_quadrant": [len(c.points) for c in self.clouds],
                       "dense_per_quadrant": [len(d) for d in self.dense], "registered": len(self.points)},
            "scan": {"step_mm": [s.step_mm for s in self.scans], "frame_gap": [s.frame_gap for s in self.scans],
                     "view_extent_mm": [s.view_extent_mm for s in self.scans],
                     **({"coverage": {"pitches": self.coverage.pitches, "views_per_point": self.coverage.views_per_point,
                                      "needed_pitches": self.coverage.needed_pitches,
                                      "needed_views_per_point": self.coverage.needed_views,
                                      "short": self.coverage.short, "below_plan": self.coverage.below_plan,
                                      "plan": self.coverage.plan.to_dict(),
                                      "message": self.coverage.message()}} if self.coverage else {})},
            "timings_s": self.timings_s,
        }

    def summary(self) -> str:
        lines = [self.gauge.summary() if self.gauge is not None else
                 f"thread gauge: INDETERMINATE ({self.gauge_message})"]
        if self.gauge is not None and self.gauge_message:
            lines.append(f"not measured: {self.gauge_message}")
        if self.gauge is not None and self.gauge.verdict == "indeterminate" and self.coverage and self.coverage.below_plan:
            lines.append(f"scan below the plan: {self.coverage.message()}")
        p = self.panorama
        if p.loop_closure_deg is not None:
            lines.append(f"registration: loop closure {p.loop_closure_deg:.3f}° / {p.loop_closure_mm:.4f} mm "
                         f"before the joint solve; pair residuals {np.median(p.residual_rms_mm):.4f} mm (median)")
        if self.errors:
            lines.append(f"against the truth: rotation error {self.errors['rotation_error_deg']:.3f}° (max), "
                         f"offset error {self.errors['offset_error_mm']:.4f} mm (max over quadrants)")
        lines.append(f"points: {sum(len(c.points) for c in self.clouds)} sparse and {sum(map(len, self.dense))} "
                     f"dense in {len(self.clouds)} quadrants, "
                     f"{len(self.points)} after outlier removal; time "
                     + ", ".join(f"{k} {v:.1f} s" for k, v in self.timings_s.items()))
        return "\n".join(lines)


def check_dataset(options: ThreadScanOptions, dataset: Dataset) -> None:
    """What the job refuses before any work (``scope3d check --for thread-scan`` runs it too): the quadrants'
    layout (quadrants.json) and each quadrant's scan read off its poses, as :func:`run` reads them first.
    Raises InputError."""
    check_jobs_take(dataset.camera, dataset.root / "camera.json", "thread-scan")
    quadrant_scans(options, dataset)


def with_designation(options: ThreadScanOptions, dataset: Dataset) -> ThreadScanOptions:
    """``options`` with the nominal thread set: its own, else the one ``quadrants.json`` names, else
    :data:`DEFAULT_THREAD`."""
    if options.designation is not None:
        return options
    return replace(options, designation=read_quadrant_thread(dataset.root) or DEFAULT_THREAD)


def shortest_coverage(dataset: Dataset, designation: str, scans: list[QuadrantScanPlan]) -> ScanCoverage:
    """What the quadrant scan showing the fewest pitches shows of the thread (see
    :func:`scope3d.metrology.thread_scan_plan.scan_coverage`)."""
    covers = [scan_coverage(dataset.camera, designation, s.side_view_deg, s.step_mm, s.frames_per_quadrant)
              for s in scans]
    return min(covers, key=lambda c: (c.pitches, c.views_per_point))


def quadrant_scans(options: ThreadScanOptions, dataset: Dataset) -> list[QuadrantScanPlan]:
    """Per quadrant, its scan read off the stage's poses and the frame gap its map matches over
    (``options.frame_gap`` when given)."""
    options = with_designation(options, dataset)
    scans = []
    for q in read_quadrants(dataset.root, dataset.names):
        try:
            scan = measured_quadrant_scan(dataset.camera, [dataset.poses[i].pose for i in q.frames], options.designation)
        except ValueError as exc:
            raise InputError(f"{dataset.root}: quadrant {q.index} ({q.angle_deg:.1f}°): {exc}") from None
        scans.append(scan if options.frame_gap is None else replace(scan, frame_gap=options.frame_gap))
    return scans


def map_quadrants(options: ThreadScanOptions, dataset: Dataset, scans: list[QuadrantScanPlan] | None = None,
                  progress: Progress | None = None) -> tuple[list[QuadrantCloud], MountEstimate | None]:
    """Each quadrant's sparse map in the stacked frame, matching frames up to its scan's frame gap apart
    (``scans``: :func:`quadrant_scans`, computed when None): triangulated with the stage's reported poses,
    then, with ``options.mount``, the camera's mount rotation measured and every map triangulated again
    with the corrected poses. Returns (clouds, mount estimate or None)."""
    layout = read_quadrants(dataset.root, dataset.names)
    scans = quadrant_scans(options, dataset) if scans is None else scans
    stage(progress, "mapping quadrants", len(layout))
    reported = [[dataset.poses[i].pose for i in q.frames] for q in layout]

    def one(q, scan, poses):
        m = map_quadrant([dataset.frame(i) for i in q.frames], dataset.camera, poses,
                         options=replace(options.mapping, max_frame_gap=scan.frame_gap))
        advance(progress)
        return m

    with ThreadPoolExecutor(max_workers=resolve_threads(options.threads)) as pool:
        maps = list(pool.map(one, layout, scans, reported))
    mount = None
    if options.mount is not None:
        try:
            mount = estimate_mount_rotation(dataset.camera, maps, reported, options=options.mount)
        except ValueError as exc:
            raise InputError(f"{dataset.root}: {exc}") from None
        maps = [retriangulate(dataset.camera, m, [mount.corrected(p) for p in poses]) for m, poses in zip(maps, reported)]
    clouds = [QuadrantCloud(q.index, q.angle_deg, m.points, m.descriptors, m.colors, m.observation_point,
                            m.observation_frame, m.observation_descriptors) for q, m in zip(layout, maps)]
    for c in clouds:
        if len(c.points) < options.panorama.min_correspondences:
            raise InputError(f"{dataset.root}: quadrant {c.index} ({c.angle_deg:.1f}°): only {len(c.points)} 3-D points "
                             "reconstructed (too few features or matches)")
    return clouds, mount


def stacked_poses(dataset: Dataset, frames: tuple[int, ...], mount: MountEstimate | None) -> list[Pose]:
    """The ``cam_from_world`` of ``frames`` in the stacked frame: as reported, corrected for the mount."""
    poses = [dataset.poses[i].pose for i in frames]
    return poses if mount is None else [mount.corrected(p) for p in poses]


def dense_clouds(options: ThreadScanOptions, dataset: Dataset, panorama: PanoramaResult, clouds: list[QuadrantCloud],
                 mount: MountEstimate | None = None, progress: Progress | None = None) -> list[np.ndarray]:
    """Each quadrant's dense cloud in the registered world, swept with its frames' registered poses."""
    layout = read_quadrants(dataset.root, dataset.names)
    stage(progress, "dense quadrants", len(layout))

    def one(q):
        g = panorama.world_from_stacked[q.index]
        poses = registered_frame_poses(g, stacked_poses(dataset, q.frames, mount), len(q.frames) // 2)
        points, _ = dense_quadrant([dataset.frame(i) for i in q.frames], dataset.camera, poses,
                                   g.transform(clouds[q.index].points), options=options.dense)
        advance(progress)
        return points

    with ThreadPoolExecutor(max_workers=resolve_threads(options.threads)) as pool:
        return list(pool.map(one, layout))


def true_world_from_stacked(dataset: Dataset, mount: MountEstimate | None = None) -> list[Pose] | None:
    """Per quadrant, the transform taking its stacked frame (the reported poses, corrected for the
    ``mount`` when given) to the true world: at the quadrant's middle frame, ``true world_from_cam @
    stacked cam_from_world``. None without true poses. (With the reported poses of a camera tilted on its
    mount this differs from frame to frame of a quadrant; with a mount corrected exactly it does not.)"""
    gt = dataset.ground_truth
    if gt is None or gt.poses is None:
        return None
    out = []
    for q in read_quadrants(dataset.root, dataset.names):
        i = q.frames[len(q.frames) // 2]
        out.append(gt.poses[i].inverse() @ stacked_poses(dataset, (i,), mount)[0])
    return out


def unseen_message(gauge, dataset: Dataset, designation: str, scans: list[QuadrantScanPlan]) -> str:
    """One line: the profile parts the cloud did not show, the sizes left unmeasured, and the scan that
    shows them (the scan plan's at a 90° side view, which looks at the wall square on: both flanks and the
    root of every tooth)."""
    views = sorted({round(s.side_view_deg) for s in scans})
    sizes = unmeasured_sizes(gauge.unseen_parts)
    line = (f"{' and '.join(gauge.unseen_parts)} not in the cloud: {' and '.join(sizes)} not measured "
            f"(a {'/'.join(map(str, views))}° side view")
    try:
        plan = plan_quadrant_scan(dataset.camera, designation, 90.0)
    except ValueError:
        return line + ")"
    return (line + f"); a 90° side view shows them: the scan plan's {plan.frames_per_quadrant} frames per "
            f"quadrant {plan.step_mm:g} mm apart, frame gap {plan.frame_gap}")


def run(options: ThreadScanOptions, dataset: Dataset, out_dir: str | Path, *,
        progress: Progress | None = None) -> ThreadScanResult:
    """Measure a tapped hole from a side-view quadrant scan and write the run folder ``out_dir``."""
    timings = {}
    t0 = time.perf_counter()
    options = with_designation(options, dataset)
    scans = quadrant_scans(options, dataset)
    try:
        coverage = shortest_coverage(dataset, options.designation, scans)
    except ValueError:  # a view the plan's rule cannot take (looking down the hole): nothing to say
        coverage = None
    clouds, mount = map_quadrants(options, dataset, scans, progress)
    timings["mapping"] = time.perf_counter() - t0

    # From here on the work is numpy's on one thread (the registration's RANSAC, the profile fits and the
    # systematic terms' re-fits: many small products and SVDs), and OpenBLAS's own threads only spin against
    # the other processes on a shared machine: 3000 3x3 and 20 200x200 SVDs took 1.5-10.8 s wall with
    # OpenBLAS's 2 threads, 0.20-0.22 s on one (2 cores at load 3). The limit holds for this job's stages
    # alone, not the process.
    with threadpool_limits(limits=1, user_api="blas"):
        t0 = time.perf_counter()
        panorama = register_quadrants(clouds, options=options.panorama, seed=options.seed, progress=progress)
        registered = panorama.apply(clouds)
        timings["registration"] = time.perf_counter() - t0

        dense = [np.zeros((0, 3)) for _ in clouds]
        if options.dense is not None:
            t0 = time.perf_counter()
            dense = dense_clouds(options, dataset, panorama, clouds, mount, progress)
            registered = dense
            timings["dense"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        merged = np.concatenate(registered)
        quadrant_of = np.repeat(np.arange(len(registered)), [len(r) for r in registered])
        keep = statistical_inliers(merged, options=options.outliers)
        points = merged[keep]
        timings["outliers"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        # The stage's rotation axis (world z, nominal) is the gauge's hint for the hole axis.
        gauge_options = replace(options.gauge, designation=options.designation, axis_hint=(0.0, 0.0, 1.0))
        gauge, gauge_message = None, ""
        try:
            gauge = gauge_thread(points, options=gauge_options)
        except ValueError as exc:  # no thread in the cloud: a result to report, not a crash
            gauge_message = str(exc) + (f"; {coverage.message()}" if coverage is not None else "")
        if gauge is not None and unmeasured_sizes(gauge.unseen_parts):
            gauge_message = unseen_message(gauge, dataset, options.designation, scans)
        timings["gauge"] = time.perf_counter() - t0
        systematic = {}
        if gauge is not None and (options.registration_draws or options.point_bias_mm or options.match_gap_mm):
            t0 = time.perf_counter()
            if options.registration_draws:
                draws = panorama.sample_world_from_stacked(options.registration_draws, options.seed)
                systematic["registration"] = registration_systematic(gauge, draws, panorama.world_from_stacked, points,
                                                                     quadrant_of[keep], gauge_options.noise_mm)
            if options.point_bias_mm:
                systematic["point_bias"] = profile_bias_systematic(gauge, points, options.point_bias_mm,
                                                                   gauge_options.noise_mm)
            if options.match_gap_mm:
                drawn_apart = pairs_drawn_apart(panorama.pairs, options.match_gap_mm)
                placed = joint_solve(drawn_apart, [c.angle_deg for c in clouds], options=options.panorama)[0]
                systematic["match_gap"] = match_gap_systematic(gauge, placed, panorama.world_from_stacked, points,
                                                               quadrant_of[keep], gauge_options.noise_mm)
            systematic = {k: v for k, v in systematic.items() if v}
            if systematic:
                gauge = with_systematic(gauge, combined_systematic(systematic), options=gauge_options)
            timings["systematic"] = time.perf_counter() - t0

        errors = None
        truth = true_world_from_stacked(dataset, mount)
        if truth is not None:
            rot, off = registration_errors(panorama.world_from_stacked, truth, clouds)
            rot0, off0 = registration_errors([Pose.identity()] * len(clouds), truth, clouds)
            errors = {"rotation_error_deg": float(rot.max()), "offset_error_mm": float(off.max()),
                      "rotation_error_per_quadrant_deg": rot.tolist(), "offset_error_per_quadrant_mm": off.tolist(),
                      "stacked_rotation_error_deg": float(rot0.max()), "stacked_offset_error_mm": float(off0.max())}
            made = (dataset.ground_truth.scene.get("thread") or {}).get("as_made")
            if made and gauge is not None:
                errors["gauge_errors_mm"] = {
                    "minor_diameter": gauge.minor_diameter_mm.value - made["minor_diameter_mm"],
                    "major_diameter": gauge.major_diameter_mm.value - made["major_diameter_mm"],
                    "pitch_diameter": gauge.pitch_diameter_mm.value - made["pitch_diameter_mm"],
                    "pitch": gauge.pitch_mm.value - dataset.ground_truth.scene["thread"]["pitch_mm"]}
    result = ThreadScanResult(clouds, panorama, dense, points, gauge, errors, timings, gauge_message, systematic, scans,
                              mount, coverage)
    write_outputs(result, out_dir)
    return result


def write_outputs(result: ThreadScanResult, out_dir: str | Path) -> None:
    """cloud.ply (registered, outliers removed), quadrants/qNN.ply (stacked frame), report.json,
    registration.png (top and side views before and after), unwrapped.png (radius vs angle and depth)."""
    with atomic_directory(out_dir) as tmp:
        write_ply(tmp / "cloud.ply", PointCloud(result.points))
        (tmp / "quadrants").mkdir()
        for c in result.clouds:
            write_ply(tmp / "quadrants" / f"q{c.index:02d}.ply", PointCloud(c.points, c.colors))
        for c, d in zip(result.clouds, result.dense):
            if len(d):
                write_ply(tmp / "quadrants" / f"q{c.index:02d}_dense.ply", PointCloud(d))
        write_json(tmp / "report.json", result.report())
        _registration_figure(result, tmp / "registration.png")
        if result.gauge is not None:
            _unwrapped_figure(result, tmp / "unwrapped.png")


def _registration_figure(result: ThreadScanResult, path: Path) -> None:
    fig = new_figure((10, 9))
    before = [c.points for c in result.clouds]
    after = result.panorama.apply(result.clouds)
    import matplotlib

    colours = [matplotlib.colormaps["hsv"](q / len(before)) for q in range(len(before))]
    for col, (name, clouds) in enumerate((("stacked (stage poses)", before), ("registered", after))):
        top = fig.add_subplot(2, 2, 1 + col)
        side = fig.add_subplot(2, 2, 3 + col)
        for q, pts in enumerate(clouds):
            sub = pts[:: max(1, len(pts) // 1500)]
            top.scatter(sub[:, 0], sub[:, 1], s=0.5, color=colours[q])
            side.scatter(sub[:, 0], sub[:, 2], s=0.5, color=colours[q])
        top.set_title(f"top view, {name}")
        side.set_title(f"side view (x-z), {name}")
        top.set_aspect("equal")
        side.set_aspect("equal")
        for ax in (top, side):
            ax.set_xlabel("x (mm)")
        top.set_ylabel("y (mm)")
        side.set_ylabel("z (mm)")
    save_figure(fig, path)


def _unwrapped_figure(result: ThreadScanResult, path: Path) -> None:
    g = result.gauge
    local = result.points - g.axis_point_mm
    d = g.axis_direction
    ref = np.array([1.0, 0.0, 0.0]) if abs(d[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    ex = ref - (ref @ d) * d
    ex /= np.linalg.norm(ex)
    ey = np.cross(d, ex)
    x, y, z = local @ ex, local @ ey, local @ d
    angle = np.degrees(np.mod(np.arctan2(y, x), 2 * np.pi))
    radius = np.hypot(x, y)
    fig = new_figure((10, 5))
    ax = fig.add_subplot(1, 1, 1)
    lo, hi = g.minor_diameter_mm.value / 2 - 0.05, g.major_diameter_mm.value / 2 + 0.05
    sc = ax.scatter(angle, z, c=radius, s=1.0, cmap="viridis", vmin=lo, vmax=hi)
    fig.colorbar(sc, ax=ax, label="radius from the fitted axis (mm)")
    for defect in g.defects:
        ax.plot(defect.angle_deg, defect.axial_mm, "o", mfc="none", mec="red", ms=18, mew=2)
        ax.annotate(f"{defect.depth_mm:.2f} mm", (defect.angle_deg, defect.axial_mm), color="red",
                    xytext=(12, 12), textcoords="offset points")
    ax.axhspan(*g.zone_mm, color="0.9", zorder=-1)
    ax.set_xlim(0, 360)
    ax.set_xlabel("angle about the axis (deg)")
    ax.set_ylabel("along the axis (mm)")
    ax.set_title(f"{g.limits.designation}-{g.limits.tolerance_class} unwrapped: {g.verdict}, "
                 f"{len(g.defects)} defect(s) (circles); grey band = gauged zone")
    save_figure(fig, path)
