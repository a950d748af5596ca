"""Image-only 3-D organ panorama (reference sec. 2.4), ``scope3d panorama``. :func:`run` reads as the method::

    features  <- SIFT in every frame's circular field (a pale wall: every frame equalised, a lower threshold)
    map       <- pairs by capture order and retrieval, relative poses chosen by the wall's shape, rotation
                 averaging, centres from baselines scaled by the wall's distance; the pairs this start says
                 overlap matched too, tracks from every geometrically verified pair, centres from their
                 rays; bundle adjustment, points outside the anatomical shell dropped (sfm.cavity_mapping;
                 planned poses with finite tolerances add the pairs they say overlap, and start and bound
                 the poses)
    scale     <- the 6 mm star targets in the fluorescence frames (metrology.star_scale), unless not asked
    wall      <- a star-shaped cavity mesh: the convex hull of the points' directions from the cavity's centre,
                 textured from the registered frames (mvs.texturing: a cube-map atlas, each texel from the
                 frames that see it best, seams blended, the tip light divided out)
    organ map <- the 2-D map of the whole cavity (mvs.organ_map): the ellipsoid the points describe (or the
                 cameras' centroid sphere where it is ill-conditioned) with a smooth radial correction, every
                 frame projected onto it and unwrapped (equirectangular), blended; coverage, uncovered
                 regions and the scope's path
    truth     <- where the dataset has it: the wall error after a 7-DoF similarity fitted to the tracks'
                 true positions, the scale error of the stars, and the organ map's alignment (atlas px, against
                 the true poses and depths) and true coverage
    files     <- report.json, sparse/ (COLMAP text), points.ply, mesh.ply, wall.obj/.mtl/.png (the textured
                 wall), organ_map.png and organ_coverage.png, panorama_3d.png (atomic folder)

Any camera model of :mod:`scope3d.sensor.camera_models` (issue 32): every stage works on the frames as they
are, through the dataset camera's model, and none resamples a frame to rectify it. The start's bearings,
the triangulation and the truth's track points are unit rays (``Camera.unproject``); the relative poses'
five-point RANSAC and the star fits work on normalised coordinates x/z, so there a fisheye's rays past
90 deg are not used (the phantom's fisheye-140 sees 70 deg).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np
from scipy.spatial import ConvexHull

from scope3d.errors import InputError
from scope3d.feature.detection import FeatureOptions, Features
from scope3d.feature.matching import MatchOptions
from scope3d.io.colmap import SparseModel, write_colmap_text
from scope3d.io.dataset import Dataset
from scope3d.io.images import write_image
from scope3d.io.obj import write_textured_obj
from scope3d.io.ply import write_ply
from scope3d.metrology.evaluation import errors_after_similarity, true_track_points
from scope3d.metrology.star_scale import StarScaleOptions, star_scale
from scope3d.mvs.organ_map import (OrganMap, OrganMapOptions, alignment_error, draw_organ_map, fit_cavity_surface,
                                   organ_map)
from scope3d.mvs.texturing import TextureOptions, texture_mesh
from scope3d.pipelines.surgical_map import MapOptions, detect_features
from scope3d.scene.mesh import Mesh, PointCloud, SampledSurface
from scope3d.sensor.camera import Camera
from scope3d.sfm.cavity_map_choice import MAX_OFF_CENTRE, cameras_off_centre
from scope3d.sfm.cavity_mapping import CavityMap, CavityOptions, knows_poses, map_cavity
from scope3d.sfm.scan_planning import coverage
from scope3d.sfm.depth_consistency import MAX_INCONSISTENT_FRACTION, N_SIGMA, frame_depth_inconsistency, inconsistent_frames
from scope3d.utils.atomic import atomic_directory
from scope3d.utils.figures import new_figure, save_figure
from scope3d.utils.jsonio import write_json
from scope3d.utils.progress import Progress, stage


@dataclass(frozen=True)
class Panorama3dOptions:
    """features, matching, cavity : the stages' options. pale_features, min_median_features : when
    the frames give fewer than ``min_median_features`` SIFT features (median over frames) with
    ``features``, every frame is detected again with ``pale_features`` (None: never), see
    :func:`panorama_features`. stars : the scale targets, or None for an unscaled
    model (``scale_source: none``; or the plan's scale when the poses are planned). use_planned_poses :
    planned poses with finite tolerances start and bound the adjustment (default True); False ignores them
    (image-only). evaluation_step_mm : sample spacing of the true surface for the wall error (default 0.25).
    figures : write panorama_3d.png (default True). texture : the textured wall's options, or None for no
    wall.obj. refuse_implausible : a map failing :func:`self_check` raises InputError instead of being
    written (default True); False writes it with the check's problems in report.json. organ_map : the 2-D
    map of the whole cavity's options, or None for no organ_map.png."""

    features: FeatureOptions = field(default_factory=FeatureOptions)
    pale_features: FeatureOptions | None = field(
        default_factory=lambda: FeatureOptions(contrast_threshold=0.01, clahe_clip_limit=2.0))
    min_median_features: int = 1000
    matching: MatchOptions = field(default_factory=MatchOptions)
    cavity: CavityOptions = field(default_factory=CavityOptions)
    stars: StarScaleOptions | None = field(default_factory=StarScaleOptions)
    use_planned_poses: bool = True
    evaluation_step_mm: float = 0.25
    figures: bool = True
    texture: TextureOptions | None = field(default_factory=TextureOptions)
    refuse_implausible: bool = True
    organ_map: OrganMapOptions | None = field(default_factory=OrganMapOptions)

    def __post_init__(self) -> None:
        if self.evaluation_step_mm <= 0 or self.min_median_features < 0:
            raise ValueError("evaluation_step_mm must be > 0 and min_median_features >= 0")


@dataclass
class Panorama3dResult:
    """report : report.json as written; cavity : the map (poses, points, tracks, the wall's sphere)."""

    report: dict
    cavity: CavityMap

    @property
    def points(self) -> np.ndarray:
        """(N, 3) mm, the wall's points (mm when the scale is known, see the report's ``scale_source``)."""
        return self.cavity.tracks.points

    @property
    def colors(self) -> np.ndarray:
        """(N, 3) uint8 RGB, each point's colour."""
        return self.cavity.tracks.colors

    @property
    def cam_from_world(self) -> np.ndarray:
        """(m, 4, 4) every frame's pose as a matrix (meaningful where ``cavity.registered``)."""
        return np.stack([p.matrix for p in self.cavity.poses])

    def summary(self) -> str:
        r = self.report
        line = (f"{r['n_registered']}/{r['n_frames']} frames registered, {r['n_points']} points, "
                f"scale from {r['scale_source']}"
                + (f" (± {r['scale_uncertainty_fraction']:.2%})" if r.get("scale_uncertainty_fraction") else "")
                + f", {r['time_s']:.1f} s")
        disagreement = (r["self_check"]["map_choice"] or {}).get("disagreement")
        if disagreement:  # image-only: how far the two candidate maps are apart (both right: ~0.003 of the radius)
            line += (f"; the two image-only maps disagree by {disagreement['median']:.1%} of the wall's radius "
                     f"(p95 {disagreement['p95']:.1%})")
        lines = [line]
        err = r.get("surface_error_mm", {}).get("after_similarity")
        if err:
            lines.append(f"wall error after similarity: mean {err['mean']:.3f}, median {err['median']:.3f}, "
                         f"p95 {err['p95']:.3f} mm" + (f"; scale error {r['scale_error_fraction']:+.2%}"
                                                      if "scale_error_fraction" in r else ""))
        if "texture_texel_mm" in r:
            lines.append(f"textured wall: {r['texture_texel_mm']:.3f} mm per texel, atlas "
                         f"{r['texture_atlas_px'][0]} x {r['texture_atlas_px'][1]} px, "
                         f"{r['textured_fraction']:.0%} of the wall seen")
        organ = r.get("organ_map")
        if organ:
            line = (f"organ map: {organ['coverage_fraction']:.1%} of the wall covered, "
                    f"{len(organ['uncovered_regions'])} uncovered region(s), on the {organ['surface']['kind']}")
            if organ.get("alignment"):
                line += (f"; alignment against the truth {organ['alignment']['mean_px']:.2f} px mean, "
                         f"{organ['alignment']['p95_px']:.2f} px p95, true coverage "
                         f"{organ['true_coverage_fraction']:.1%}")
            lines.append(line)
        lines += [f"self-check WARNING: {w}" for w in r["self_check"]["warnings"]]
        if not r["self_check"]["passed"]:
            lines.append("self-check FAILED, the map is kept as asked: " + "; ".join(r["self_check"]["problems"]))
        return "\n".join(lines)


def panorama_features(options: Panorama3dOptions, dataset: Dataset, *, progress: Progress | None = None) -> list[Features]:
    """SIFT in every frame; on a pale wall (median features per frame below ``options.min_median_features``)
    every frame again with ``options.pale_features`` (CLAHE, which flattens the tip light's falloff and
    the wet glint, and a contrast threshold of 0.01, half of COLMAP's SIFT peak threshold).

    Why all frames or none: a frame equalised and its neighbour not describe the same wall differently (on
    the dry spiral, equalising only the frames under 1000 features took the image-only map from 0.175 to
    2.59 mm). Why 1000: consecutive key frames share 35-65 % of their field, so 1000 features leave ~350
    in common, several times the 15 matches a pair needs. Measured on the pale wet wall (vessels at 0.25 of
    the default density, 608 px): 9-280 features per frame and no match between most consecutive frames
    at the default threshold; 1370-1780 features and 15-182 matches per pair (3-9 % wrong but one pair)
    with CLAHE at 0.01; at 0.01 without CLAHE 126-805 features, up to 26 % wrong."""
    frames = [dataset.frame(k) for k in range(len(dataset))]
    features = detect_features(MapOptions(features=options.features), dataset, frames, progress=progress)
    if options.pale_features is not None and np.median([len(f) for f in features]) < options.min_median_features:
        stage(progress, "panorama: features (pale wall)", len(frames))
        features = detect_features(MapOptions(features=options.pale_features), dataset, frames, progress=progress)
    return features


def cavity_mesh(points: np.ndarray, centre: np.ndarray, colors: np.ndarray | None = None) -> Mesh:
    """A closed mesh through the points (N, 3) of a cavity seen from inside: the convex hull of their unit
    directions from ``centre`` (a star-shaped cavity's triangulation), faces turned to face the centre."""
    rel = np.asarray(points, float) - centre
    hull = ConvexHull(rel / np.linalg.norm(rel, axis=1, keepdims=True))
    faces = hull.simplices.copy()
    v = rel[faces]
    outward = np.einsum("ij,ij->i", np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), v.mean(axis=1)) > 0
    faces[outward] = faces[outward][:, ::-1]  # normals towards the centre: the wall seen from inside
    return Mesh(np.asarray(points, float), faces, colors)


def evaluate(dataset: Dataset, cavity: CavityMap, step_mm: float) -> dict:
    """Wall error after a 7-DoF similarity fitted to the tracks' true positions (true depth maps and poses),
    in mm of the truth; {} without ground truth."""
    gt = dataset.ground_truth
    if gt is None or gt.poses is None or gt.surface_path is None or not gt.depth_paths:
        return {}
    tr = cavity.tracks
    true_points = true_track_points(dataset.camera, gt.poses, gt.depth, tr.frame, tr.track, tr.pixels, tr.n_tracks)
    summary, distances, sim = errors_after_similarity(tr.points, true_points, SampledSurface(gt.surface(), step_mm))
    return {"surface_error_mm": {"after_similarity": summary}, "scale_error_fraction": summary["scale"] - 1.0,
            "_distances": distances, "_similarity": sim}


def build_organ_map(options: OrganMapOptions, videos: Sequence[tuple[Dataset, CavityMap]]) -> OrganMap:
    """The whole cavity's 2-D map from the registered frames of one or more videos' maps in one frame
    (:mod:`scope3d.mvs.organ_map`; each video's own coverage in ``group_coverage``); the surface fitted to all
    their points, the pole towards the wall the first registered frame looks at."""
    poses, cameras, frames, groups, points = [], [], [], [], []
    for g, (dataset, cavity) in enumerate(videos):
        poses += [p if ok else None for p, ok in zip(cavity.poses, cavity.registered)]
        cameras += [dataset.camera] * len(dataset)
        frames += [(dataset, k) for k in range(len(dataset))]
        groups += [g] * len(dataset)
        points.append(cavity.tracks.points)
    first = next(p for p in poses if p is not None)
    centres = np.stack([p.centre for p in poses if p is not None])
    surface = fit_cavity_surface(np.concatenate(points), centres,
                                 first.centre + videos[0][1].radius_mm * first.optical_axis, options=options)
    return organ_map(surface, cameras, poses, lambda k: frames[k][0].frame(frames[k][1]), options=options,
                     groups=groups)


def evaluate_organ_map(videos: Sequence[tuple[Dataset, CavityMap, object]], organ: OrganMap) -> dict:
    """The organ map against the truth, for videos (dataset, map, the similarity from the map's frame to the
    truth's: the wall error's gauge) with ground truth: ``alignment`` (atlas px over every video's frames;
    :func:`scope3d.mvs.organ_map.alignment_error`) and the true covered fraction of the first video's true wall
    (the true poses of every frame taken, :func:`scope3d.sfm.scan_planning.coverage`: the same rule as the
    map's). {} when a video has no ground truth."""
    parts = []
    for dataset, cavity, truth_from_map in videos:
        gt = dataset.ground_truth
        if gt is None or gt.poses is None or gt.surface_path is None or not gt.depth_paths or truth_from_map is None:
            return {}
        poses = [p if ok else None for p, ok in zip(cavity.poses, cavity.registered)]
        parts.append(alignment_error(organ.surface, dataset.camera, poses, gt.poses, gt.depth, truth_from_map,
                                     organ.width, organ.height))
    alignment = parts[0] if len(parts) == 1 else _pooled_alignment(parts)
    wall = videos[0][0].ground_truth.surface()
    seen = np.zeros(len(wall.faces), bool)
    for dataset, _, _ in videos:
        seen |= coverage(wall, dataset.camera, dataset.ground_truth.poses).seen_faces
    tri = wall.vertices[wall.faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    true_fraction = float(area[seen].sum() / area.sum())
    return {"alignment": alignment, "true_coverage_fraction": true_fraction,
            "coverage_error_fraction": organ.coverage_fraction - true_fraction}


def _pooled_alignment(parts: list[dict]) -> dict:
    """Several videos' alignment figures as one: means weighted by their pixels, the worst p95 and max (a pooled
    percentile needs the pixels themselves), each video's own figures kept."""
    parts = [p for p in parts if p]
    if not parts:
        return {}
    n = np.array([p["n_pixels"] for p in parts], float)
    return {"mean_px": float(np.average([p["mean_px"] for p in parts], weights=n)),
            "p95_px": max(p["p95_px"] for p in parts), "max_px": max(p["max_px"] for p in parts),
            "on_wall_mean": float(np.average([p["on_wall_mean"] for p in parts], weights=n)),
            "on_wall_p95": max(p["on_wall_p95"] for p in parts), "n_pixels": int(n.sum()),
            "p95_is": "the worst video's", "videos": parts}


def self_check(cavity: CavityMap, options: CavityOptions, scaled: bool, camera: Camera) -> dict:
    """Whether the map can be a cavity seen from inside, from the map alone (no truth): the cameras' centroid
    within :data:`MAX_OFF_CENTRE` of the wall's radius from its centre (:func:`cameras_off_centre`), and,
    when the map has a physical scale (stars or plan), the wall's fitted radius within the anatomical shell
    (``options.min_radius_mm``-``max_radius_mm``, the prior's own range). Returns the measures, the
    ``problems`` found (sentences), ``passed``, the image-only map's choice (``map_choice``: both candidates'
    figures, why one was kept, their disagreement) and ``warnings``.

    Measured (docs/panorama.md, "A wrong map reported as a map"): the unseen wet cavity's broken map had
    its cameras 0.97 radii off centre and, from the stars, a 107 mm wall radius (the truth: 29-38 mm
    semi-axes); the maps kept on the phantoms (dry, wet, unseen shapes), 0.02-0.07 and 34-41 mm.

    The warning: the two image-only candidate maps (:func:`scope3d.sfm.cavity_mapping.map_cavity`) come from
    different starts and pair sets; when 5 % of the points they share lie more than :data:`MAX_OFF_CENTRE` of
    the wall's radius apart after a similarity (:func:`scope3d.sfm.cavity_map_choice.map_disagreement`), they
    cannot both be the cavity, and the kept one is not confirmed. A warning, not a refusal: the kept map may
    be the right one (docs/panorama.md, "Which image-only map").

    The second warning: frames whose points do not form one wall in their own view
    (:func:`scope3d.sfm.depth_consistency.frame_depth_inconsistency`: more than a tenth of a frame's points
    off the depth plane through their image neighbours by more than 3 standard deviations of the keypoint
    noise), a wrong surface inside a map that is otherwise a cavity seen from inside (the pale wet wall at a
    tenth of the vessels with planned poses: 2.5 mm, 21 frames flagged; docs/panorama.md, "A wrong surface
    inside a right map"). A warning: the rest of the map may be right, and the frames are named."""
    off = cameras_off_centre(cavity.tracks.points, cavity.poses)
    problems = []
    if not off <= MAX_OFF_CENTRE:
        problems.append(f"the cameras' centroid is {off:.2f} of the wall's radius from its centre "
                        f"(a scope inside a cavity: at most {MAX_OFF_CENTRE:g})")
    radius = float(cavity.radius_mm) if scaled else None
    if radius is not None and not options.min_radius_mm <= radius <= options.max_radius_mm:
        problems.append(f"the wall's radius is {radius:.1f} mm, outside the anatomical "
                        f"{options.min_radius_mm:g}-{options.max_radius_mm:g} mm")
    warnings = []
    disagreement = cavity.choice.get("disagreement", {})
    if disagreement.get("p95", 0.0) > MAX_OFF_CENTRE:  # NaN (no common points) does not warn
        kept = "all-pair" if cavity.choice["kept"] == "all pairs" else "chain's"
        warnings.append(f"the two image-only maps disagree: 5 % of their common points are "
                        f"{disagreement['p95']:.2f} of the wall's radius apart or more (median "
                        f"{disagreement['median']:.2f}), so at least one is wrong; kept the "
                        f"{kept} map: {cavity.choice['reason']}")
    inconsistency = frame_depth_inconsistency(camera, cavity.poses, cavity.tracks, cavity.registered)
    flagged = inconsistent_frames(inconsistency)
    if flagged:
        worst = int(np.nanargmax(inconsistency))
        warnings.append(f"{len(flagged)} frame(s) {flagged} see points that are no single wall: more than "
                        f"{MAX_INCONSISTENT_FRACTION:.0%} of each one's points lie off the depth of their image "
                        f"neighbours by over {N_SIGMA:g} standard deviations of the keypoint noise (frame {worst}: "
                        f"{inconsistency[worst]:.0%}), so the map holds a wrong surface there")
    return {"cameras_off_centre": off, "max_off_centre": MAX_OFF_CENTRE, "wall_radius_mm": radius,
            "anatomical_radius_mm": [options.min_radius_mm, options.max_radius_mm], "problems": problems,
            "passed": not problems, "map_choice": cavity.choice or None,
            "frame_depth_inconsistency": [None if np.isnan(v) else float(v) for v in inconsistency],
            "inconsistent_frames": flagged, "warnings": warnings}


def save_panorama_png(path: Path, cavity: CavityMap, distances: np.ndarray | None) -> None:
    """Three orthogonal views of the points (coloured by their wall error when known, else their colour)
    with the camera centres."""
    pts = cavity.tracks.points
    centres = np.stack([p.centre for p in cavity.poses])
    fig = new_figure(figsize=(12, 4.2))
    for k, (a, b, name) in enumerate([(0, 1, "x-y"), (0, 2, "x-z"), (1, 2, "y-z")]):
        ax = fig.add_subplot(1, 3, k + 1)
        if distances is not None:
            sc = ax.scatter(pts[:, a], pts[:, b], c=distances, s=2, cmap="viridis", vmin=0,
                            vmax=max(float(np.percentile(distances, 95)), 1e-3))
        else:
            ax.scatter(pts[:, a], pts[:, b], c=cavity.tracks.colors / 255.0, s=2)
        ax.plot(centres[:, a], centres[:, b], "r.-", lw=0.8, ms=3)
        ax.set_aspect("equal")
        ax.set_title(f"{name} (mm)")
    if distances is not None:
        fig.colorbar(sc, ax=fig.axes, label="distance to the true wall after similarity, mm", shrink=0.8)
    save_figure(fig, path)


def check_dataset(options: Panorama3dOptions, dataset: Dataset) -> None:
    """What :func:`run` refuses before any work (``scope3d check --for panorama`` runs it too): raises
    InputError."""
    if len(dataset) < 2:
        raise InputError(f"{dataset.root}: need at least 2 frames for a panorama, found {len(dataset)}")
    if options.stars is not None and dataset.fluorescence_paths is None:
        raise InputError(f"{dataset.root}: no fluorescence frames, so no star targets to set the scale "
                         "(use --no-scale for an unscaled model)")


def check_videos(options: Panorama3dOptions, datasets: Sequence[Dataset]) -> None:
    """Several videos share one organ map only in the frame their planned poses share: raises InputError
    naming the first dataset without planned poses (or when they are ignored), or with fewer than 2 frames."""
    for ds in datasets:
        if len(ds) < 2:
            raise InputError(f"{ds.root}: need at least 2 frames for a panorama, found {len(ds)}")
        if not (options.use_planned_poses and knows_poses(ds.poses)):
            raise InputError(f"{ds.root}: several videos go on one organ map only in the frame their planned poses "
                             "share (finite tolerances in poses.csv, without --ignore-poses): images-only maps of "
                             "two videos are not registered to each other")


def map_video(options: Panorama3dOptions, dataset: Dataset, scale: float, *,
              progress: Progress | None = None) -> CavityMap:
    """A further video's map for the combined organ map: its planned poses bound it in the plan's frame, scaled
    by the first video's star scale (the same factor about the same origin keeps both in one frame). A map
    failing :func:`self_check` raises InputError unless ``options.refuse_implausible`` is off."""
    stage(progress, f"panorama: features of {dataset.root.name}", len(dataset))
    features = panorama_features(options, dataset, progress=progress)
    cavity = map_cavity(dataset.camera, features, dataset.poses, options.cavity, options.matching,
                        where=str(dataset.root), progress=progress).scaled(scale)
    check = self_check(cavity, options.cavity, True, dataset.camera)
    if options.refuse_implausible and not check["passed"]:
        raise InputError(f"{dataset.root}: the map is no cavity seen from inside, so it is not combined: "
                         + "; ".join(check["problems"]) + " (keep it anyway with --keep-implausible)")
    return cavity


def run(options: Panorama3dOptions, dataset: Dataset, out_dir: str | Path, *,
        progress: Progress | None = None, more: Sequence[Dataset] = ()) -> Panorama3dResult:
    """The 3-D panorama of ``dataset`` into ``out_dir`` (written atomically). more : further videos of the same
    cavity (planned poses, like ``dataset``'s, see :func:`check_videos`), mapped each on its own and drawn with
    ``dataset`` on one organ map; the 3-D files are ``dataset``'s."""
    t0, c0 = time.perf_counter(), time.process_time()
    check_dataset(options, dataset)
    if more:
        check_videos(options, [dataset, *more])
    n = len(dataset)
    timings, cpu = {}, {}  # wall and CPU seconds per stage (CPU: every thread of the process)
    stage(progress, "panorama: features", n)
    features = panorama_features(options, dataset, progress=progress)
    timings["features_s"] = time.perf_counter() - t0
    cpu["features_s"] = time.process_time() - c0
    stage(progress, "panorama: pairs", None)
    measured = dataset.poses if options.use_planned_poses else None
    cavity = map_cavity(dataset.camera, features, measured, options.cavity, options.matching,
                        where=str(dataset.root), progress=progress)
    timings.update(cavity.time_s)
    cpu["map_s"] = time.process_time() - c0 - sum(cpu.values())
    scale_info = None
    if options.stars is not None:
        t1, c1 = time.perf_counter(), time.process_time()
        fluorescence = [dataset.fluorescence_frame(k) for k in range(n)]
        scale_info = star_scale(dataset.camera, cavity.poses, cavity.tracks, fluorescence, options=options.stars,
                                where=str(dataset.root))
        cavity = cavity.scaled(scale_info.scale)
        timings["scale_s"], cpu["scale_s"] = time.perf_counter() - t1, time.process_time() - c1
    scale_source = "stars" if scale_info is not None else ("plan" if cavity.scale_known else "none")
    check = self_check(cavity, options.cavity, scale_source != "none", dataset.camera)
    if options.refuse_implausible and not check["passed"]:
        raise InputError(f"{dataset.root}: the map is no cavity seen from inside, so it is not written: "
                         + "; ".join(check["problems"]) + " (keep it anyway with --keep-implausible)")
    evaluation = evaluate(dataset, cavity, options.evaluation_step_mm)
    distances = evaluation.pop("_distances", None)
    truth_from_map = evaluation.pop("_similarity", None)
    if scale_source == "none":
        evaluation.pop("scale_error_fraction", None)
    tr = cavity.tracks
    report = {
        "job": "panorama", "dataset": str(dataset.root),  # the report page reads the frames and truth from it
        "n_frames": n,
        "n_registered": int(cavity.registered.sum()),
        "n_points": int(tr.n_tracks),
        "n_observations": int(tr.n_observations),
        "n_pairs": len(cavity.matches),
        "n_pairs_tried": cavity.n_pairs_tried,
        "poses": "planned (bounded)" if cavity.scale_known else "images only",
        "scale_source": scale_source,
        "stars": None if scale_info is None else scale_info.to_dict(),
        "scale_uncertainty_fraction": None if scale_info is None else scale_info.uncertainty,
        "cavity_radius": cavity.radius_mm,
        "length_unit": "mm" if scale_source != "none" else "map units (no physical scale)",
        "stages": cavity.stages,
        "self_check": check,
        **evaluation,
        "timings_s": timings,
        "cpu_by_stage_s": cpu,
        "time_s": time.perf_counter() - t0,
        "cpu_s": time.process_time() - c0,
    }
    with atomic_directory(out_dir) as tmp:
        write_ply(tmp / "points.ply", PointCloud(tr.points, tr.colors))
        if tr.n_tracks >= 4:
            wall = cavity_mesh(tr.points, cavity.centre_mm, tr.colors)
            write_ply(tmp / "mesh.ply", wall)
            if options.texture is not None:
                t1, c1 = time.perf_counter(), time.process_time()
                poses = [p if ok else None for p, ok in zip(cavity.poses, cavity.registered)]
                textured = texture_mesh(wall, cavity.centre_mm, dataset.camera, poses, dataset.frame,
                                        options=options.texture)
                write_textured_obj(tmp / "wall.obj", textured.mesh.vertices, textured.mesh.faces, textured.uv,
                                   textured.face_uv, textured.image)
                report.update({"texture_texel_mm": textured.texel_mm, "textured_fraction": textured.textured_fraction,
                               "texture_atlas_px": list(textured.image.shape[1::-1])})
                timings["texture_s"], cpu["texture_s"] = time.perf_counter() - t1, time.process_time() - c1
        if options.organ_map is not None and tr.n_tracks >= 9:
            t1, c1 = time.perf_counter(), time.process_time()
            videos = [(dataset, cavity, truth_from_map)]
            for extra in more:
                video = map_video(options, extra, 1.0 if scale_info is None else scale_info.scale, progress=progress)
                videos.append((extra, video, evaluate(extra, video, options.evaluation_step_mm).get("_similarity")))
            organ = build_organ_map(options.organ_map, [(d, m) for d, m, _ in videos])
            picture, mask = draw_organ_map(organ)
            write_image(tmp / "organ_map.png", picture)
            write_image(tmp / "organ_coverage.png", mask)
            report["organ_map"] = {**organ.summary(), **evaluate_organ_map(videos, organ)}
            if more:  # each video's own coverage on the same surface: what combining them adds
                report["organ_map"]["videos"] = [
                    {"dataset": str(d.root), "n_frames": len(d), "n_registered": int(m.registered.sum()),
                     "coverage_fraction": f} for (d, m, _), f in zip(videos, organ.group_coverage)]
            timings["organ_map_s"], cpu["organ_map_s"] = time.perf_counter() - t1, time.process_time() - c1
        model = SparseModel.from_observations(dataset.camera, dataset.names, cavity.poses, tr.points, tr.frame,
                                              tr.track, tr.pixels, colors=tr.colors)
        write_colmap_text(model, tmp / "sparse")
        if options.figures:
            save_panorama_png(tmp / "panorama_3d.png", cavity, distances)
        report["time_s"], report["cpu_s"] = time.perf_counter() - t0, time.process_time() - c0
        cpu["rest_s"] = report["cpu_s"] - sum(cpu.values())  # evaluation, mesh, files
        write_json(tmp / "report.json", report)
    return Panorama3dResult(report, cavity)
