"""The uncertainty budget of a gauged thread (reference sec. 8.4; docs/thread_metrology.md): the gauge's
statistical uncertainty (from the fit's residuals, :mod:`.thread_gauge`) and the systematic terms no point
residual shows, each found by moving the cloud the way the error would and re-fitting the profile
(:func:`~scope3d.metrology.thread_gauge.remeasure`):

    registration  <- draws of the quadrants' registration from its covariance   (:func:`registration_systematic`)
    match gap     <- neighbours' matched points drawn apart along the circle     (:func:`match_gap_systematic`)
    point bias    <- each profile part's points offset along the surface normal (:func:`profile_bias_systematic`)
    combined      <- the terms in quadrature with the statistical one, the verdict judged again
                     (:func:`combined_systematic`, :func:`with_systematic`)

The registration's draws and re-solved placements come from :mod:`scope3d.registration.panorama`; here they
are plain lists of ``world_from_stacked`` poses, one per quadrant.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from scope3d.geometry.pose import Pose
from scope3d.metrology.thread_gauge import (PROFILE_PARTS, GaugeOptions, GaugeResult, Measured, judge, profile_parts,
                                           remeasure)

# The sparse points' per-part offsets from the true surface, mapped with the TRUE poses (no registration)
# on the 90° scans of docs/thread_metrology.md (400x320 px): medians per part (crest, flank towards +z,
# flank towards -z, root) -0.0005 / +0.0010 / -0.0032 / -0.0014 mm on an M8 (0.5 mm steps) and -0.0005 /
# +0.0007 / -0.0022 / -0.0030 mm on an M6 (0.25 mm steps); their RMS over the parts, 0.0018 and 0.0019 mm,
# rounded up, is the standard uncertainty of one part's offset. Measured against the truth, not fitted to
# the sizes' errors.
SPARSE_POINT_BIAS_MM = 0.002

# Matched keypoints of neighbour quadrants are not quite the same point of the wall. Each quadrant's map and
# its neighbour's triangulated with the TRUE poses (docs/thread_metrology.md, "The negative diameter
# bias"), the first quadrant's point of an inlier correspondence lies, on average, short of its match
# along the circle by 0.0034 / 0.0030 / 0.0025 mm (standard error 0.0013-0.0015 mm; 1,457 / 1,196 / 1,141
# correspondences; M8 / M10 / M6 mid-class holes, 90° view, 400x320 px): each keypoint a little nearer
# its own frame's centre along the crest. Rounded, it is the standard uncertainty of that gap; measured
# against the truth, not fitted to the sizes' errors.
MATCH_GAP_MM = 0.003


def moved_by_quadrant(points: np.ndarray, quadrant_of: np.ndarray, placed: list[Pose],
                      estimated: list[Pose]) -> np.ndarray:
    """``points`` (N, 3) mm registered with the ``estimated`` ``world_from_stacked`` of their quadrants
    (``quadrant_of`` (N,)), moved to where the ``placed`` ones put them: each quadrant by ``G_placed G_est^-1``."""
    moved = points.copy()
    for q, (g_placed, g_est) in enumerate(zip(placed, estimated)):
        sel = quadrant_of == q
        moved[sel] = (g_placed @ g_est.inverse()).transform(points[sel])
    return moved


def registration_systematic(gauge: GaugeResult, draws: list[list[Pose]], estimated: list[Pose], points: np.ndarray,
                            quadrant_of: np.ndarray, noise_mm: float = 0.01) -> dict:
    """The sizes' systematic standard uncertainty (mm) from the registration's: each draw of the quadrants'
    ``world_from_stacked`` from the joint solve's covariance (``draws``, e.g.
    :meth:`scope3d.registration.panorama.PanoramaResult.sample_world_from_stacked`; ``estimated`` the
    solution) moves every quadrant's registered points by ``G_draw G_est^-1``; the gauge re-fits its profile
    to the moved cloud (warm-started, same points); the spread (standard deviation) of the re-measured sizes
    over the draws is the registration's share. It acts on the whole hole at once (a quadrant placed off
    moves its crests and roots together), which the fit's statistical uncertainty, from independent point
    residuals, cannot see. points : (N, 3) mm the gauged cloud; quadrant_of : (N,) its points' quadrants.
    Empty with fewer than two draws (no covariance)."""
    if len(draws) < 2:
        return {}
    sizes = [remeasure(gauge, moved_by_quadrant(points, quadrant_of, drawn, estimated), noise_mm) for drawn in draws]
    return {key: float(np.std([m[key] for m in sizes], ddof=1)) for key in sizes[0]}


def match_gap_systematic(gauge: GaugeResult, placed: list[Pose], estimated: list[Pose], points: np.ndarray,
                         quadrant_of: np.ndarray, noise_mm: float = 0.01) -> dict:
    """The sizes' systematic standard uncertainty (mm; keys as
    :func:`~scope3d.metrology.thread_gauge.remeasure`'s) from a gap along the circle between neighbour
    quadrants' matched points: ``placed`` is the joint solve run again on the pairs so drawn apart
    (:func:`scope3d.registration.panorama.pairs_drawn_apart`), ``estimated`` the solution; every quadrant's
    registered points are moved by ``G_placed G_est^-1``, the profile re-fitted; the size changes are the
    term. Such a gap moves every quadrant radially at once (by ~gap / (2 sin 15°) for 30° quadrants: every
    diameter by ~3.9 gap), which neither the fit's residuals nor the joint solve's covariance show.
    points : (N, 3) mm the gauged cloud; quadrant_of : (N,) its quadrants."""
    moved = moved_by_quadrant(points, quadrant_of, placed, estimated)
    base, sizes = remeasure(gauge, points, noise_mm), remeasure(gauge, moved, noise_mm)
    return {key: float(abs(sizes[key] - base[key])) for key in base}


def profile_bias_systematic(result: GaugeResult, points: np.ndarray, bias_mm: float, noise_mm: float = 0.01) -> dict:
    """The sizes' systematic standard uncertainty (mm; keys as :func:`~scope3d.metrology.thread_gauge.remeasure`'s) from a bias of the
    cloud's points along the surface normal that differs between the parts of the profile (crest, each
    flank, root): a reconstruction places its points on a flank seen obliquely, or on a root seen past a
    crest, a little off the surface, each part by its own amount, and the fit turns that into a size
    error no point residual shows. Each part's points are moved by ``bias_mm`` (a standard uncertainty of
    a part's offset) into the material and the profile re-fitted (:func:`~scope3d.metrology.thread_gauge.remeasure`); the four size
    changes, taken as independent, add in quadrature."""
    base = remeasure(result, points, noise_mm)
    part, normal = profile_parts(result, points)
    index = result.fit_state["index"]
    shifts = []
    for k in range(len(PROFILE_PARTS)):
        sel = part == k
        if not sel.any():
            continue
        moved = np.array(points, float, copy=True)
        moved[index[sel]] += bias_mm * normal[sel]
        sizes = remeasure(result, moved, noise_mm)
        shifts.append({key: sizes[key] - base[key] for key in base})
    return {key: float(np.sqrt(sum(s[key] ** 2 for s in shifts))) for key in base} if shifts else {}


def with_systematic(result: GaugeResult, systematic_mm: dict, *, options: GaugeOptions) -> GaugeResult:
    """``result`` with a systematic standard uncertainty (mm; keys as :func:`~scope3d.metrology.thread_gauge.remeasure`'s, missing = 0)
    added in quadrature to each size's statistical one, and the verdict judged again on the combined
    uncertainties (:func:`~scope3d.metrology.thread_gauge.judge`)."""
    def comb(m: Measured, key: str) -> Measured:
        stat = m.statistical if m.statistical is not None else m.uncertainty
        sys_ = float(systematic_mm.get(key, 0.0))
        return replace(m, uncertainty=float(np.hypot(stat, sys_)), statistical=stat, systematic=sys_)

    d1, d2 = comb(result.minor_diameter_mm, "minor_diameter"), comb(result.pitch_diameter_mm, "pitch_diameter")
    d, p = comb(result.major_diameter_mm, "major_diameter"), comb(result.pitch_mm, "pitch")
    u_d2v_stat = result.fit_state.get("u_d2v_statistical", result.virtual_pitch_diameter_uncertainty_mm)
    u_d2v = float(np.hypot(u_d2v_stat, systematic_mm.get("virtual_pitch_diameter", 0.0)))
    verdict, checks = judge(result.limits, options, d1.value, d1.uncertainty, d2.value, d2.uncertainty,
                             result.virtual_pitch_diameter_mm, u_d2v, d.value, d.uncertainty, result.defects,
                             bool(result.fit_state.get("at_bound", False)), result.unseen_parts)
    state = dict(result.fit_state, u_d2v_statistical=u_d2v_stat)
    return replace(result, minor_diameter_mm=d1, pitch_diameter_mm=d2, major_diameter_mm=d, pitch_mm=p,
                    virtual_pitch_diameter_uncertainty_mm=u_d2v, verdict=verdict, checks=checks, fit_state=state)


def combined_systematic(systematic: dict[str, dict]) -> dict:
    """The systematic terms by source (each a dict of sizes, mm) in quadrature: one dict of sizes."""
    keys = set().union(*systematic.values())
    return {k: float(np.sqrt(sum(v.get(k, 0.0) ** 2 for v in systematic.values()))) for k in keys}
