"""Where the tissue changed: the map points that new frames no longer see, and the image regions to map
again (issue 36: a surgeon resects tissue while the scope films; the live map must drop the old surface
there, not average the new one into it).

The new frames (with poses: the tracker's) measure the surface as it is now: each reference frame gets a
dense depth map from a plane sweep against two of the other new frames (:func:`scope3d.mvs.plane_sweep.sweep`,
the sources chosen for a baseline of about ``baseline_ratio`` times the depth, with each pixel's
predicted depth error). A map point that projects into a reference frame where the sweep kept a depth is
*observed* there: its residual is the measured depth minus its own, over the two errors added
(``hypot(sweep sigma, the point's sigma)``). Where the tissue is unchanged these normalised residuals
follow one distribution whose scale the models only approximate (the sweep's ``match_sigma_px`` was
measured on another texture; a map's sigma comes from its own noise model), so the scale is measured on
the data: the robust standard deviation (MAD) of every observation's normalised residual, about zero, the
*noise factor* (a variance factor: 1 when the models are right). Changed tissue is a minority of the
observations, so the MAD sees the unchanged part. A point is flagged when it is observed in at least
``min_views`` frames and the median over them of its absolute normalised residual exceeds ``n_sigma``
noise factors (a Gaussian exceeds 3 sigma with probability 0.27 %, and the median of several views
still less often; a stray wrong sweep depth in one view does not move the median). The sweep's errors
have heavier tails than that (on the dome, 1.8 % of the points on unchanged wall are flagged), but they
are scattered, while tissue is removed or moved as a region: a flagged point stays changed only when at
least half of its ``vote_neighbours`` nearest judged map points are flagged too (a majority of 16
independent false alarms at 2 % each has a probability below 1e-9; the change must span more than that
neighbourhood, 0.26 mm on a dense map, a few mm on a sparse one).

The region to map again in a reference frame: its pixels whose measured depth departs by more than the
same threshold from the map's surface there (the least-squares plane, depth against pixel, through the
``neighbours`` nearest map points in that image, as ``sfm.depth_consistency`` fits it; its error that
of a three-parameter fit, ``sqrt(3 / k)`` times the neighbours' RMS sigma), among the pixels the map
covers (the nearest map point within twice the map's median point spacing in that image) and near a
changed point (as close): the points' decision rests on several views, a pixel's on one sweep, whose
stray depths would otherwise mark isolated specks all over the view; a 3 x 3 median on the sweep's grid
removes the isolated pixels left. To these the changed points' own footprint is added (the pixels within
twice the spacing of their projections): where this frame's sweep kept no depth, other views found the
change; and a morphological closing fills the gaps narrower than the vote's neighbourhood in the image (the
median distance of a map point's ``vote_neighbours``-th neighbour there), which a change found by that
vote spans anyway. The test is two-sided: tissue moved towards the scope is a
change too. A view in which other tissue hides a map point would flag it; the dome and a cavity seen from
inside hide none of their own wall.

The new frames' poses must be good relative to each other: the sweep's error model holds the matching
noise only, so pose errors show as a larger noise factor and a higher threshold. On the dome (2.2 mm
baselines at 22 mm), independent per-frame errors of +-0.05 mm and +-0.025 deg raise it from 1.2 to 4.2 and
find 39 % of the points moved 1 mm or more; +-0.1 mm blinds it (factor 7.1). It then misses change but does
not drop unchanged tissue; feed it poses refined together (a local bundle adjustment of the new frames).
A sparse map works the same way: every tenth or thirtieth point of the test's map (1001 or 334 points)
finds every point moved 1 mm or more and drops none off the pit.

Units: mm, pixels. Tested against the phantom lab's resection (``tests/test_surface_change.py``).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.spatial import cKDTree

from scope3d.geometry.pose import Pose
from scope3d.mvs.plane_sweep import PlaneSweepOptions, sweep
from scope3d.sensor.camera import Camera
from scope3d.utils.robust import robust_sigma


@dataclass(frozen=True)
class SurfaceChangeOptions:
    """sweep : the plane sweep's options (its ``min_sources`` source frames per reference).
    baseline_ratio : sources are the frames whose baseline over the map's median depth in the reference
        is nearest this (default 0.1: 1.5 mm at the survey's 15 mm, 1.2 px of parallax per mm of depth at
        320 px across 53°, where the sweep's matches still overlap).
    depth_margin : the sweep searches the map's depths in the reference widened by this fraction each way
        (default 0.3: a pit or a swelling of up to 30 % of the distance is measured).
    n_sigma : the threshold, in noise factors (default 3, the module docstring).
    min_views : reference frames a point must be observed in to be judged (default 2).
    neighbours : map points through which the map's local depth plane is fitted (default 8, as
        ``sfm.depth_consistency``: three parameters leave five degrees of freedom).
    vote_neighbours : a point stays changed only when at least half of this many nearest judged map
        points (in 3-D) are changed too (default 16; the module docstring).
    """

    sweep: PlaneSweepOptions = field(default_factory=PlaneSweepOptions)
    baseline_ratio: float = 0.1
    depth_margin: float = 0.3
    n_sigma: float = 3.0
    min_views: int = 2
    neighbours: int = 8
    vote_neighbours: int = 16

    def __post_init__(self) -> None:
        if not (self.baseline_ratio > 0 and 0 < self.depth_margin < 1 and self.n_sigma > 0):
            raise ValueError("need baseline_ratio > 0, depth_margin in (0, 1) and n_sigma > 0")
        if self.min_views < 1 or self.neighbours < 3 or self.vote_neighbours < 1:
            raise ValueError("need min_views >= 1, neighbours >= 3 and vote_neighbours >= 1")


@dataclass
class SurfaceChange:
    """changed : (N,) bool, the map points to drop. score : (N,) the median absolute normalised residual
    over the frames that observed the point, in noise factors (NaN where fewer than ``min_views``).
    n_views : (N,) frames that observed each point. references : the frames (indices into the frames
    given) used as sweep references; regions : per reference, (H, W) bool, the pixels to map again.
    noise_factor : the measured scale of the normalised residuals (module docstring)."""

    changed: np.ndarray
    score: np.ndarray
    n_views: np.ndarray
    references: list[int]
    regions: list[np.ndarray]
    noise_factor: float

    def summary(self) -> str:
        return (f"{int(self.changed.sum())} of {len(self.changed)} map points changed "
                f"({int(np.sum(self.n_views >= 1))} observed), noise factor {self.noise_factor:.2f}, "
                f"{sum(int(r.sum()) for r in self.regions)} px to map again in {len(self.regions)} frames")


def detect_surface_change(camera: Camera, map_points: np.ndarray, map_sigma_mm: np.ndarray | float,
                          images: list[np.ndarray], poses: list[Pose], *, references: list[int] | None = None,
                          options: SurfaceChangeOptions = SurfaceChangeOptions()) -> SurfaceChange:
    """The map points (N, 3) mm, each with its standard deviation ``map_sigma_mm`` (N,) or one for all,
    that the new ``images`` with their ``poses`` (``cam_from_world``) no longer see, and the regions to map
    again (module docstring). references : the frames to sweep (default all; each needs
    ``options.sweep.min_sources`` others)."""
    points = np.asarray(map_points, float).reshape(-1, 3)
    sigma_map = np.broadcast_to(np.asarray(map_sigma_mm, float), (len(points),))
    if len(images) != len(poses):
        raise ValueError(f"{len(images)} images but {len(poses)} poses")
    if len(images) < options.sweep.min_sources + 1:
        raise ValueError(f"need at least {options.sweep.min_sources + 1} frames")
    refs = list(range(len(images))) if references is None else [int(r) for r in references]
    centres = np.array([p.centre for p in poses])
    observations = [[] for _ in range(len(points))]
    per_frame = []
    field_mask = camera.mask()
    for r in refs:
        z_map, px, seen = _project(camera, poses[r], points, field_mask)
        if seen.sum() < options.neighbours + 1:
            per_frame.append(None)
            continue
        depth = float(np.median(z_map[seen]))
        baseline = np.linalg.norm(centres - centres[r], axis=1) / depth
        order = np.argsort(np.abs(baseline - options.baseline_ratio) + np.where(np.arange(len(poses)) == r, np.inf, 0))
        sources = order[:options.sweep.min_sources]
        near = (1.0 - options.depth_margin) * float(z_map[seen].min())
        far = (1.0 + options.depth_margin) * float(z_map[seen].max())
        measured = sweep(camera, images[r], poses[r], [images[s] for s in sources], [poses[s] for s in sources],
                         (near, far), options=options.sweep)
        ij = np.round(px[seen]).astype(int)
        z_obs = measured.depth_mm[ij[:, 1], ij[:, 0]]
        s_obs = measured.sigma_mm[ij[:, 1], ij[:, 0]]
        ok = np.isfinite(z_obs)
        ids = np.flatnonzero(seen)[ok]
        for i, z in zip(ids, (z_obs[ok] - z_map[ids]) / np.hypot(s_obs[ok], sigma_map[ids])):
            observations[i].append(z)
        per_frame.append((measured, px[seen], z_map[seen], sigma_map[seen], np.flatnonzero(seen)))
    flat = np.concatenate([np.asarray(o) for o in observations if o] or [np.zeros(0)])
    noise = robust_sigma(flat, about=0.0) if len(flat) else float("nan")
    n_views = np.array([len(o) for o in observations])
    score = np.full(len(points), np.nan)
    judged = n_views >= options.min_views
    score[judged] = [np.median(np.abs(observations[i])) / noise for i in np.flatnonzero(judged)]
    changed = _vote(points, judged, np.nan_to_num(score, nan=0.0) > options.n_sigma, options.vote_neighbours)
    regions = [np.zeros(field_mask.shape, bool) if f is None else
               _region(camera, *f[:4], changed[f[4]], noise * options.n_sigma, options) for f in per_frame]
    return SurfaceChange(changed, score, n_views, refs, regions, noise)


def _vote(points: np.ndarray, judged: np.ndarray, flagged: np.ndarray, k: int) -> np.ndarray:
    """The flagged points at least half of whose ``k`` nearest judged points (themselves excluded) are
    flagged too."""
    ids = np.flatnonzero(judged)
    out = np.zeros(len(points), bool)
    if len(ids) < 2:
        return out
    k = min(k, len(ids) - 1)
    candidates = ids[flagged[ids]]
    if len(candidates) == 0:
        return out
    _, nb = cKDTree(points[ids]).query(points[candidates], k + 1)
    out[candidates] = flagged[ids[nb[:, 1:]]].mean(axis=1) >= 0.5
    return out


def _project(camera: Camera, pose: Pose, points: np.ndarray, field_mask: np.ndarray):
    """z-depth, pixel and whether each point lies in front of the camera and inside its field."""
    cam = pose.transform(points)
    z = cam[:, 2]
    px = np.full((len(points), 2), -1.0)
    front = z > 0
    px[front] = camera.project(cam[front])
    ij = np.round(px).astype(int)
    inside = front & (ij[:, 0] >= 0) & (ij[:, 1] >= 0) & (ij[:, 0] < camera.width) & (ij[:, 1] < camera.height)
    inside[inside] = field_mask[ij[inside, 1], ij[inside, 0]]
    return z, px, inside


def _region(camera: Camera, measured, px_map: np.ndarray, z_map: np.ndarray, sigma_map: np.ndarray,
            changed: np.ndarray, threshold: float, options: SurfaceChangeOptions) -> np.ndarray:
    """(H, W) bool: the pixels near a changed map point whose measured depth departs from the map's local
    plane by more than ``threshold`` of its error (module docstring)."""
    k = options.neighbours
    tree = cKDTree(px_map)
    spacing = float(np.median(tree.query(px_map, 2)[0][:, 1]))
    if not changed.any():
        return np.zeros((camera.height, camera.width), bool)
    near_change = cKDTree(px_map[changed]).query(measured.pixels, 1)[0] <= 2.0 * spacing
    dist, nb = tree.query(measured.pixels, k)
    covered = (dist[:, 0] <= 2.0 * spacing) & near_change
    q = measured.pixels[covered]
    nb = nb[covered]
    # the plane in pixel offsets from the query: its depth there is the constant term (pseudo-inverse:
    # neighbours along one line leave the tilt across it free)
    A = np.concatenate([px_map[nb] - q[:, None], np.ones(nb.shape + (1,))], axis=2)
    plane = (np.linalg.pinv(A) @ z_map[nb][..., None])[:, 2, 0]
    plane_sigma = np.sqrt(3.0 / k * np.mean(sigma_map[nb] ** 2, axis=1))
    ij = q.astype(int)
    z_obs = measured.depth_mm[ij[:, 1], ij[:, 0]]
    s_obs = measured.sigma_mm[ij[:, 1], ij[:, 0]]
    off = np.abs(z_obs - plane) > threshold * np.hypot(s_obs, plane_sigma)
    stride = options.sweep.stride_px
    grid = np.zeros(((camera.height + stride - 1) // stride, (camera.width + stride - 1) // stride), np.uint8)
    grid[ij[off, 1] // stride, ij[off, 0] // stride] = 255
    grid = cv2.medianBlur(grid, 3)
    full = np.repeat(np.repeat(grid, stride, axis=0), stride, axis=1)[:camera.height, :camera.width] > 0
    # and the changed points' own footprint: where the sweep kept no depth they still say what changed
    seeds = np.full((camera.height, camera.width), 255, np.uint8)
    ij = np.round(px_map[changed]).astype(int)
    seeds[ij[:, 1], ij[:, 0]] = 0
    footprint = cv2.distanceTransform(seeds, cv2.DIST_L2, 5) <= 2.0 * spacing
    region = (full | footprint).astype(np.uint8)
    # close gaps narrower than the vote's neighbourhood (a change spans at least that much)
    reach = float(np.median(tree.query(px_map, options.vote_neighbours + 1)[0][:, -1]))
    size = 2 * int(np.ceil(reach)) + 1
    region = cv2.morphologyEx(region, cv2.MORPH_CLOSE, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size)))
    return (region > 0) & camera.mask()
