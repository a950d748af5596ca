"""Fluorescent targets (residual tumour) segmented in 2-D and carried onto the 3-D surface (reference
sec. 4.4.3 and 4.5, Fig. 4.4(d-f), Fig. 4.6(d)).

Steps, as in the reference: a grey-level threshold on each fluorescence frame, then morphological
opening (removes the speckle of a high-gain PMT) and closing (fills pin-holes inside a target). The
binary masks are carried onto the surface by projecting the surface's grid vertices into every frame
that sees them; a vertex is fluorescent when at least half of those views say so (a vote, so one
frame's noise or a slightly wrong pose does not paint the surface). The surface grid is a raster in
the plane of the field (:class:`scope3d.scene.surface.Surface`), so the targets are labelled there as
connected components, and measured in 3-D through the grid: centroid, area, and size — a disc's
diameter (from its area, ``2 sqrt(A / pi)``), a star's mean edge length (the polygon of its outline,
reference: "the average length of the edges was 6.2 mm").
"""
from __future__ import annotations

import csv
import io
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from scope3d.geometry.pose import Pose
from scope3d.scene.surface import Surface
from scope3d.sensor.camera import Camera
from scope3d.utils.jsonio import write_json


@dataclass(frozen=True)
class FluorescenceOptions:
    """Segmentation and measurement of fluorescent targets.

    threshold : int or None, grey level (0-255) above which a fluorescence pixel is "on". None
        (default) = Otsu's threshold on the pooled histogram of all frames, floored at ``min_threshold``
        (a frame with no target would otherwise split its own noise in two).
    min_threshold : int, floor of the automatic threshold (default 40).
    open_px, close_px : int, radius (px) of the opening and closing disc in each frame (default 1, 3;
        a wider opening rounds off sharp corners: a 36 deg star tip loses r / sin 18 deg = 3.2 r px).
    min_vote : float, fraction of the views seeing a vertex that must call it fluorescent (default 0.5).
    min_area_mm2 : float, smaller components on the surface are noise (default 0.5 mm²).
    star_solidity : float, a target whose area / convex-hull area is below this is a star (default
        0.8; a five-point star with inner/outer radius 0.4 has solidity ~0.6, a disc 1.0).
    star_points : int, points of the star; its outline polygon has twice as many edges (default 5).
    overlay_alpha : float, weight of the fluorescence green in the multimodal overlay (default 0.6).
    refine_factor : int, each target is re-measured on a grid this many times finer than the surface's
        (default 4: 0.05 mm cells on the 0.2 mm surface grid, so a 2 mm disc spans 40 cells).
    refine_margin_mm : float, margin around a target's coarse extent for its fine grid (default 1 mm).
    """

    threshold: int | None = None
    min_threshold: int = 40
    open_px: int = 1
    close_px: int = 3
    min_vote: float = 0.5
    min_area_mm2: float = 0.5
    star_solidity: float = 0.8
    star_points: int = 5
    overlay_alpha: float = 0.6
    refine_factor: int = 4
    refine_margin_mm: float = 1.0

    def __post_init__(self) -> None:
        if self.threshold is not None and not 0 <= self.threshold <= 255:
            raise ValueError(f"threshold must be in [0, 255], got {self.threshold}")
        if self.open_px < 0 or self.close_px < 0 or not 0 < self.min_vote <= 1:
            raise ValueError("open_px, close_px must be >= 0 and min_vote in (0, 1]")
        if self.min_area_mm2 < 0 or not 0 < self.star_solidity < 1 or self.star_points < 3:
            raise ValueError("min_area_mm2 >= 0, star_solidity in (0, 1), star_points >= 3 required")
        if not 0 <= self.overlay_alpha <= 1:
            raise ValueError("overlay_alpha must be in [0, 1]")
        if self.refine_factor < 1 or self.refine_margin_mm < 0:
            raise ValueError("refine_factor must be >= 1 and refine_margin_mm >= 0")


@dataclass
class Target:
    """One fluorescent target on the surface.

    label : int, 1-based. centroid_mm : (3,) world mm (area-weighted). area_mm2 : float.
    shape : "star", "triangle", "square" or "disc". size_mm : float, star: mean stroke (tip to the tip
    two along, the pentagram's edge); triangle / square: mean edge; disc: diameter.
    outline_mm : (K, 3) world mm, the outline polygon's vertices.
    """

    label: int
    centroid_mm: np.ndarray
    area_mm2: float
    shape: str
    size_mm: float
    outline_mm: np.ndarray
    cell_mm: float = 0.0

    def size_in_plane_mm(self, normal: np.ndarray) -> float:
        """Size measured after projecting the outline along ``normal`` (3,) onto a plane — how a
        target drawn flat and dropped onto a curved surface along ``normal`` is specified (a disc on
        a 40 deg slope is 1.3 times longer on the surface than on the drawing)."""
        n = np.asarray(normal, float) / np.linalg.norm(normal)
        helper = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        u = np.cross(helper, n)
        u /= np.linalg.norm(u)
        v = np.cross(n, u)
        uv = np.stack([self.outline_mm @ u, self.outline_mm @ v], axis=1)
        d = 0.5 * self.cell_mm
        if self.shape == "star":
            tips = uv[0::2]
            return float(np.linalg.norm(np.roll(tips, -2, axis=0) - tips, axis=1).mean())
        if self.shape in ("triangle", "square"):
            edges = np.linalg.norm(np.roll(uv, -1, axis=0) - uv, axis=1)
            return float(edges.mean() + (2.0 * np.sqrt(3.0) if self.shape == "triangle" else 2.0) * d)
        x, y = uv[:, 0], uv[:, 1]
        area = 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))
        perimeter = float(np.linalg.norm(np.roll(uv, -1, axis=0) - uv, axis=1).sum())
        return float(2.0 * np.sqrt((area + d * perimeter) / np.pi))

    def as_dict(self) -> dict:
        return {
            "label": self.label, "centroid_mm": [round(float(v), 4) for v in self.centroid_mm],
            "area_mm2": round(self.area_mm2, 4), "shape": self.shape, "size_mm": round(self.size_mm, 4),
        }


def _disc(radius: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))


def auto_threshold(images, *, options: FluorescenceOptions = FluorescenceOptions()) -> int:
    """Otsu's threshold on the pooled histogram of all frames (uint8), floored at ``min_threshold``."""
    if options.threshold is not None:
        return int(options.threshold)
    hist = np.zeros(256)
    for img in images:
        hist += np.bincount(np.asarray(img, np.uint8).ravel(), minlength=256)
    p = hist / max(hist.sum(), 1)
    omega = np.cumsum(p)
    mu = np.cumsum(p * np.arange(256))
    with np.errstate(divide="ignore", invalid="ignore"):
        between = (mu[-1] * omega - mu) ** 2 / (omega * (1 - omega))
    t = int(np.nanargmax(np.nan_to_num(between, nan=-1)))
    return max(t, options.min_threshold)


def segment(image: np.ndarray, threshold: int, *, options: FluorescenceOptions = FluorescenceOptions(),
            mask: np.ndarray | None = None) -> np.ndarray:
    """One fluorescence frame (H, W) uint8 -> (H, W) bool target mask: threshold, opening, closing.
    mask : optional (H, W) bool valid-image mask (outside is never a target)."""
    img = np.asarray(image)
    if img.ndim != 2:
        raise ValueError(f"fluorescence image must be (H, W), got {img.shape}")
    on = (img > threshold).astype(np.uint8)
    if options.open_px:
        on = cv2.morphologyEx(on, cv2.MORPH_OPEN, _disc(options.open_px))
    if options.close_px:
        on = cv2.morphologyEx(on, cv2.MORPH_CLOSE, _disc(options.close_px))
    out = on.astype(bool)
    if mask is not None:
        out &= mask
    return out


def carry_to_surface(
    surface: Surface, camera: Camera, poses: list[Pose], masks, *, options: FluorescenceOptions = FluorescenceOptions()
) -> np.ndarray:
    """Vote the frames' 2-D target masks onto the surface grid.

    masks : sequence or callable ``masks(k)`` -> (H, W) bool per frame. Returns (GH, GW) bool on the
    surface grid: vertices called fluorescent by at least ``min_vote`` of the frames that see them.
    """
    get = masks if callable(masks) else (lambda k: masks[k])
    valid = surface.valid
    verts = surface.vertices()[valid]
    normals = surface.normals()[valid]
    votes = np.zeros(len(verts))
    seen = np.zeros(len(verts))
    for k, pose in enumerate(poses):  # per-frame loop
        uv = camera.project_world(pose, verts)
        ok = camera.in_image(uv, margin_px=1.0)
        to_cam = pose.centre - verts
        ok &= np.einsum("vi,vi->v", normals, to_cam) > 0
        if not ok.any():
            continue
        m = np.asarray(get(k), bool)
        iu = np.clip(np.rint(uv[ok, 0]).astype(int), 0, m.shape[1] - 1)
        iv = np.clip(np.rint(uv[ok, 1]).astype(int), 0, m.shape[0] - 1)
        votes[ok] += m[iv, iu]
        seen[ok] += 1
    on = np.zeros(valid.shape, bool)
    on[valid] = (seen > 0) & (votes >= options.min_vote * np.maximum(seen, 1))
    return on


def _grid_to_world(surface: Surface, rc: np.ndarray) -> np.ndarray:
    """(K, 2) fractional (row, col) grid coordinates -> (K, 3) world mm by bilinear interpolation of
    the height (nearest valid height where the neighbours are missing)."""
    verts = surface.vertices()
    r = np.clip(rc[:, 0], 0, len(surface.t) - 1)
    c = np.clip(rc[:, 1], 0, len(surface.s) - 1)
    r0 = np.clip(np.floor(r).astype(int), 0, len(surface.t) - 2)
    c0 = np.clip(np.floor(c).astype(int), 0, len(surface.s) - 2)
    fr, fc = (r - r0)[:, None], (c - c0)[:, None]
    p = (verts[r0, c0] * (1 - fr) * (1 - fc) + verts[r0 + 1, c0] * fr * (1 - fc)
         + verts[r0, c0 + 1] * (1 - fr) * fc + verts[r0 + 1, c0 + 1] * fr * fc)
    bad = ~np.all(np.isfinite(p), axis=1)
    if bad.any():
        p[bad] = verts[np.rint(r[bad]).astype(int), np.rint(c[bad]).astype(int)]
    return p


def _star_polygon(contour: np.ndarray, n_vertices: int) -> np.ndarray:
    """Simplify a closed contour (K, 2) to ``n_vertices`` corners by bisecting approxPolyDP's epsilon."""
    perim = cv2.arcLength(contour.astype(np.float32), True)
    lo, hi = 0.0, 0.2 * perim
    best = None
    for _ in range(30):
        eps = 0.5 * (lo + hi)
        poly = cv2.approxPolyDP(contour.astype(np.float32), eps, True).reshape(-1, 2)
        if best is None or abs(len(poly) - n_vertices) < abs(len(best) - n_vertices):
            best = poly
        if len(poly) == n_vertices:
            return poly
        if len(poly) > n_vertices:
            lo = eps
        else:
            hi = eps
    return best


def _polygon_with(contour: np.ndarray, n_vertices: int) -> tuple[np.ndarray, float]:
    """Polygon of ``n_vertices`` corners approximating a closed contour, and its area as a fraction of
    the contour's (1 = the polygon explains the outline)."""
    poly = _star_polygon(contour, n_vertices)
    ratio = cv2.contourArea(poly.astype(np.float32)) / max(cv2.contourArea(contour.astype(np.float32)), 1e-9)
    return poly, float(ratio)


def _shape_and_size(surface: Surface, sel: np.ndarray, area: float, options: FluorescenceOptions):
    """Classify one target region of the grid and measure its size in 3-D (mm).

    star: area / convex-hull area below ``star_solidity``; size = mean *stroke* of the pentagram, tip to
    the tip two along (the 10-corner outline's outer corners), the phantom's and reference's "edge".
    triangle / square: a 3- or 4-corner polygon explains >= 88 / 90 % of the outline's area; size =
    mean edge. disc: otherwise; size = diameter from the area, 2 sqrt(A / pi).
    """
    m8 = sel.astype(np.uint8)
    contours, _ = cv2.findContours(m8, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    contour = max(contours, key=len).reshape(-1, 2)  # (x=col, y=row)
    if len(contour) < 8:
        return "disc", float(2.0 * np.sqrt(area / np.pi)), _grid_to_world(surface, contour[:, ::-1].astype(float))
    hull = cv2.convexHull(contour.astype(np.float32))
    # pixel count ~ polygon area through pixel centres + half its perimeter: compare like with like
    solidity = float(m8.sum()) / max(cv2.contourArea(hull) + 0.5 * cv2.arcLength(hull, True) + 1.0, 1.0)
    if solidity < options.star_solidity and len(contour) >= 4 * options.star_points:
        poly = _star_polygon(contour, 2 * options.star_points).astype(float)
        # approxPolyDP cuts the sharp tips; replace each tip corner by the contour point farthest from
        # the centre within its sector, pushed out by half a cell (the contour runs through cell centres)
        centre2 = contour.mean(axis=0)
        rad = np.linalg.norm(poly - centre2, axis=1)
        tip_idx = np.arange(0 if rad[0::2].mean() > rad[1::2].mean() else 1, len(poly), 2)
        ang_c = np.arctan2(contour[:, 1] - centre2[1], contour[:, 0] - centre2[0])
        r_c = np.linalg.norm(contour - centre2, axis=1)
        half_sector = np.pi / (2 * options.star_points)
        for k in tip_idx:
            a = np.arctan2(poly[k, 1] - centre2[1], poly[k, 0] - centre2[0])
            near = np.abs(np.angle(np.exp(1j * (ang_c - a)))) < half_sector
            if near.any():
                far = np.flatnonzero(near)[np.argmax(r_c[near])]
                direction = (contour[far] - centre2) / max(r_c[far], 1e-9)
                poly[k] = contour[far] + 0.5 * direction
        outline = _grid_to_world(surface, poly[:, ::-1])
        tips = outline[tip_idx]
        strokes = np.linalg.norm(np.roll(tips, -2, axis=0) - tips, axis=1)
        # keep tips first-of-pair so that outline[0::2] are the tips for size_in_plane_mm
        if tip_idx[0] == 1:
            outline = np.roll(outline, -1, axis=0)
        return "star", float(strokes.mean()), outline
    # a 3-corner polygon covering >= 88 % of the outline is a triangle (rounded corners lose a few %);
    # a disc's best inscribed square covers 64 %, its triangle 41 %
    for n, name, min_ratio in ((3, "triangle", 0.88), (4, "square", 0.9)):
        poly, ratio = _polygon_with(contour, n)
        if len(poly) == n and min_ratio <= ratio <= 1.1:
            outline = _grid_to_world(surface, poly[:, ::-1].astype(float))
            edges = np.linalg.norm(np.roll(outline, -1, axis=0) - outline, axis=1)
            # the outline runs through the centres of the boundary cells, half a cell (d) inside the true
            # edge; moving a triangle's sides out by d lengthens them by 2 sqrt(3) d, a square's by 2 d
            d = 0.5 * surface.step_mm
            return name, float(edges.mean() + (2.0 * np.sqrt(3.0) if n == 3 else 2.0) * d), outline
    poly = contour[:: max(1, len(contour) // 64)]
    return "disc", float(2.0 * np.sqrt(area / np.pi)), _grid_to_world(surface, poly[:, ::-1].astype(float))


def measure_targets(surface: Surface, on: np.ndarray, *,
                    options: FluorescenceOptions = FluorescenceOptions()) -> tuple[list[Target], np.ndarray]:
    """Label the fluorescent grid and measure each target in 3-D.

    on : (GH, GW) bool from :func:`carry_to_surface`. Returns the targets (largest first, labels
    1..n in that order) and the label image (GH, GW) int32 (0 = background).
    """
    grid = on & surface.valid
    n, lab = cv2.connectedComponents(grid.astype(np.uint8), connectivity=8)
    areas = surface.cell_areas_mm2()
    verts = surface.vertices()
    found = []
    for k in range(1, n):  # per-target loop
        sel = lab == k
        a = np.where(sel, np.nan_to_num(areas), 0.0)
        area = float(a.sum())
        if area < options.min_area_mm2:
            continue
        centroid = (verts[sel] * a[sel][:, None]).sum(axis=0) / area
        shape, size, outline = _shape_and_size(surface, sel, area, options)
        found.append((area, centroid, shape, size, outline, sel))
    found.sort(key=lambda x: -x[0])
    labels = np.zeros(grid.shape, np.int32)
    targets = []
    for idx, (area, centroid, shape, size, outline, sel) in enumerate(found, start=1):
        labels[sel] = idx
        targets.append(Target(idx, centroid, area, shape, size, outline, surface.step_mm))
    return targets, labels


def targets_on_surface(
    surface: Surface, camera: Camera, poses: list[Pose], masks, *, options: FluorescenceOptions = FluorescenceOptions()
) -> tuple[list[Target], np.ndarray, np.ndarray]:
    """Targets on the surface: vote the masks onto the surface grid, label, then re-measure each
    target on a ``refine_factor`` times finer grid around it (votes recast there).

    masks : sequence of (H, W) bool per frame. Returns targets (labels of the coarse grid), the coarse
    fluorescent grid (GH, GW) bool and its labels (GH, GW) int32.
    """
    from dataclasses import replace

    on = carry_to_surface(surface, camera, poses, masks, options=options)
    coarse, labels = measure_targets(surface, on, options=options)
    if options.refine_factor == 1:
        return coarse, on, labels
    m = int(np.ceil(options.refine_margin_mm / surface.step_mm))
    out = []
    for t in coarse:  # per-target loop
        rr, cc = np.nonzero(labels == t.label)
        rows = slice(max(int(rr.min()) - m, 0), int(rr.max()) + m + 1)
        cols = slice(max(int(cc.min()) - m, 0), int(cc.max()) + m + 1)
        patch = surface.refined(rows, cols, options.refine_factor)
        fine_opts = replace(options, min_area_mm2=options.min_area_mm2)
        found, _ = measure_targets(patch, carry_to_surface(patch, camera, poses, masks, options=fine_opts),
                                   options=fine_opts)
        if not found:
            out.append(t)
            continue
        best = min(found, key=lambda f: np.linalg.norm(f.centroid_mm - t.centroid_mm))
        out.append(replace(best, label=t.label))
    return out, on, labels


def overlay(reflectance: np.ndarray, on: np.ndarray, labels: np.ndarray | None = None, *,
            options: FluorescenceOptions = FluorescenceOptions(), draw_outlines: bool = True) -> np.ndarray:
    """Multimodal image: reflectance (H, W, 3) uint8 with fluorescence (H, W) bool in green, target
    outlines in blue and their labels (reference Fig. 4.4(f), 4.6(d)). Returns (H, W, 3) uint8."""
    rgb = np.asarray(reflectance, np.uint8).copy()
    if rgb.ndim == 2:
        rgb = np.repeat(rgb[..., None], 3, axis=2)
    green = np.array([40, 255, 40], float)
    a = options.overlay_alpha
    rgb[on] = np.clip((1 - a) * rgb[on] + a * green, 0, 255).astype(np.uint8)
    if draw_outlines and labels is not None:
        for k in range(1, int(labels.max()) + 1):
            contours, _ = cv2.findContours((labels == k).astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
            cv2.drawContours(rgb, contours, -1, (30, 60, 255), 1)
            ys, xs = np.nonzero(labels == k)
            cv2.putText(rgb, f"#{k}", (int(xs.max()) + 2, int(ys.min()) + 8), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (30, 60, 255), 1, cv2.LINE_AA)
    return rgb


def match_targets(found: list[Target], truth: list[dict]) -> list[dict]:
    """Pair found targets with ground-truth targets by nearest centroid (Hungarian assignment).

    truth : list of dicts with ``centre_mm`` (3,), ``size_mm``, and optionally ``shape``, ``name``,
    ``area_mm2`` (on the surface) and ``projection_normal`` (the direction along which the target's flat
    design was dropped onto the surface; its size is then compared in that design plane, like for like).
    Returns one dict per true target: its found label (or None), centroid error (mm), size error (mm
    and fraction), area error fraction.
    """
    from scipy.optimize import linear_sum_assignment

    out = []
    if not truth:
        return out
    tc = np.array([t["centre_mm"] for t in truth], float)
    if found:
        fc = np.stack([f.centroid_mm for f in found])
        cost = np.linalg.norm(tc[:, None] - fc[None], axis=2)
        ri, ci = linear_sum_assignment(cost)
        assign = dict(zip(ri.tolist(), ci.tolist()))
    else:
        cost, assign = None, {}
    for k, t in enumerate(truth):
        row = {"name": t.get("name", f"target{k}"), "true_centre_mm": [float(v) for v in tc[k]],
               "true_shape": t.get("shape"), "true_size_mm": float(t["size_mm"])}
        j = assign.get(k)
        if j is not None and cost[k, j] < max(2.0 * float(t["size_mm"]), 3.0):
            f = found[j]
            size = f.size_in_plane_mm(t["projection_normal"]) if t.get("projection_normal") is not None else f.size_mm
            if t.get("area_mm2"):
                row["area_error_fraction"] = round((f.area_mm2 - float(t["area_mm2"])) / float(t["area_mm2"]), 4)
            row.update({
                "found_label": f.label, "found_shape": f.shape, "found_centre_mm": [round(float(v), 4) for v in f.centroid_mm],
                "found_size_on_surface_mm": round(f.size_mm, 4), "found_size_mm": round(size, 4),
                "centroid_error_mm": round(float(cost[k, j]), 4),
                "size_error_mm": round(size - float(t["size_mm"]), 4),
                "size_error_fraction": round((size - float(t["size_mm"])) / float(t["size_mm"]), 4),
            })
        else:
            row.update({"found_label": None})
        out.append(row)
    return out


def write_targets(out_dir: Path, targets: list[Target], vs_truth: list | None = None) -> None:
    """``out_dir/targets.json`` (targets and, when given, their comparison with the truth) and
    ``out_dir/targets.csv`` (one row per target: label, shape, centroid mm, area mm², size mm)."""
    rows = [t.as_dict() for t in targets]
    write_json(out_dir / "targets.json", {"targets": rows, "vs_truth": vs_truth})
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["label", "shape", "x_mm", "y_mm", "z_mm", "area_mm2", "size_mm"])
    for t in targets:
        w.writerow([t.label, t.shape, *(f"{v:.4f}" for v in t.centroid_mm), f"{t.area_mm2:.4f}", f"{t.size_mm:.4f}"])
    (out_dir / "targets.csv").write_text(buf.getvalue())
