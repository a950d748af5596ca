"""A virtual thread gauge (sec. 8.4): from a 3-D point cloud of a threaded hole, the hole axis, the minor,
major and pitch diameters, the pitch and the flank angle, each with a standard uncertainty, a pass/fail
verdict against the ISO 965-1 tolerance class, and local defects (damaged or missing crests).

Method. (1) The hole axis: a cylinder fitted to every point (robust), from the principal axis or a hint.
(2) The threaded zone: the axial stretch where, within one nominal pitch, the radius spans at least half
the basic thread depth (the counterbore, the plain bore and the drill point do not), less one pitch at
each end (the run-outs). (3) The pitch and the phase of the helix: the first harmonic of the radius in
the helical phase ``2 pi z / P - theta`` is largest at the true pitch (a scan, then refined; the fit
below also starts from the nominal pitch and keeps the start of lower robust cost). (4) One
joint robust least-squares fit of axis, pitch, phase and a symmetric ISO profile (crest at the minor
radius, roots at the major radius, straight flanks at the standard 60° or a free angle, a free pitch
radius where the tooth is half a pitch wide) to every point's distance from the profile in its axial
half-plane, with its exact Jacobian (chain rule); a second fit with the flank angle free measures it (and
gives the sizes when it resolves an angle other than 60°). A radius whose part of the profile the cloud
does not show (the root, seen from 45°) is held at its basic size and reported not measured. Uncertainties come from the fit's Jacobian and residuals (1 sigma, independent
point errors assumed).
(5) Defects: on each crest turn, in angular bins, the median distance of the crest points outside the
fitted profile (of the tooth's top half where the crest is seen too sparsely); bins deeper than a
threshold are grouped into defects.

Angles are measured about the fitted axis from the cloud frame's +x projected onto the plane normal to
the axis, counter-clockwise seen from the axis' tip (the axis points the way of the hint, or the cloud's +z).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from scope3d.geometry.iso_thread import ISO_METRIC_FLANK_ANGLE_DEG, THREAD_SIZES, basic_thread_depth, tooth_half_width
from scope3d.metrology.thread_tolerances import ThreadLimits, thread_limits
from scope3d.utils.robust import robust_sigma


@dataclass(frozen=True)
class GaugeOptions:
    """Options of :func:`gauge_thread`.

    designation : str, the nominal thread (one of ``geometry.iso_thread.THREAD_SIZES``): sets the pitch
        search range, the basic depth the zone detection looks for, and the limits
        (:mod:`scope3d.metrology.thread_tolerances`).
    tolerance_class : str, ``6H``.
    noise_mm : float, expected point noise (1 sigma, mm), the scale of the robust loss (default 0.01 mm:
        a few um of a metrology scan up to a sparse reconstruction's ~0.01-0.02 mm).
    max_points : int, points used in the joint fit (a seeded random subset; default 30000: the fit's
        uncertainty falls as 1/sqrt(N) and is far below the limits' widths at this size).
    pitch_search : float, pitches from (1 - x) to (1 + x) times nominal are scanned (default 0.1).
    defect_bin_deg : float, angular bin of the crest defect search (default 5 degrees).
    min_defect_depth_mm : float, a crest bin deeper than this (or 5 robust sigmas of the crest residuals,
        whichever is larger) outside the profile is damaged (default 0.05 mm, ~10 % of the thread depth
        of an M6: a burr or chip a thread inspector would reject).
    min_bin_points : int, a bin with fewer crest points is judged on the points of its tooth's top half
        (crest to half the thread depth: a chip cuts the flanks' inner halves back with the crest), and not
        at all with fewer of those (default 5).
    min_part_points : int, a profile part (crest, either flank, root) with fewer fitted points is not seen,
        and the sizes it alone places are not measured (default 20: a side view looking along the hole sees
        one flank and no root, and the symmetric profile then places the pitch and major diameters by
        assumption only; 20 points place a part to a fifth of the 0.01 mm point noise). A flank with under a
        tenth of the other flank's points is not seen either. An unseen root's or crest's radius is held at
        its basic size (nothing places it) and reported not measured, with no uncertainty.
    engagement_turns : float or None, turns of the length of engagement for the pitch's share of the
        virtual pitch diameter (default None: the turns measured).
    axis_hint : (3,) or None, approximate axis direction (default None: the principal axis of the cloud,
        pointed along the cloud's +z).
    fix_flank_angle : bool, measure the sizes with the flank angle held at the standard's (60° for the ISO
        metric sizes here; default True). A scope that sees one flank better than the other (a 45° side
        view) then still places the other by the profile's symmetry. The flank angle is measured by a
        second fit with it free; when that fit shows it significantly off the standard (beyond 2 sigma),
        the sizes come from the free fit instead (the fixed profile would bias them).
    coverage_factor : float, k of the expanded uncertainty U = k u that guards each limit (ISO 14253-1:
        conformance is proven when the value lies inside the limit by more than U, non-conformance when
        outside by more than U; in between the verdict is ``indeterminate``; default 2, ~95 % for a normal
        error).
    seed : int, the subset's seed.
    """

    designation: str = "M8x1.25"
    tolerance_class: str = "6H"
    noise_mm: float = 0.01
    max_points: int = 30000
    pitch_search: float = 0.1
    defect_bin_deg: float = 5.0
    min_defect_depth_mm: float = 0.05
    min_bin_points: int = 5
    min_part_points: int = 5 * 4
    engagement_turns: float | None = None
    axis_hint: tuple | None = None
    fix_flank_angle: bool = True
    coverage_factor: float = 2.0
    seed: int = 0

    def __post_init__(self) -> None:
        thread_limits(self.designation, self.tolerance_class)
        if not (self.noise_mm > 0 and self.max_points >= 100 and 0 < self.pitch_search < 0.5):
            raise ValueError("need noise_mm > 0, max_points >= 100 and pitch_search in (0, 0.5)")
        if not (0 < self.defect_bin_deg <= 90 and self.min_defect_depth_mm > 0 and self.min_bin_points >= 1
                and self.min_part_points >= 1):
            raise ValueError("need defect_bin_deg in (0, 90], min_defect_depth_mm > 0, min_bin_points >= 1 and "
                             "min_part_points >= 1")
        if not self.coverage_factor > 0:
            raise ValueError("coverage_factor must be positive")
        if self.engagement_turns is not None and self.engagement_turns <= 0:
            raise ValueError("engagement_turns must be positive")
        if self.axis_hint is not None and (len(self.axis_hint) != 3 or not np.linalg.norm(self.axis_hint) > 0):
            raise ValueError("axis_hint must be a non-zero 3-vector")


@dataclass(frozen=True)
class Measured:
    """A measured value and its standard uncertainty (1 sigma), in the unit of the field's name; when a
    systematic term was added (:func:`with_systematic`), ``uncertainty`` is the combined one and
    ``statistical``, ``systematic`` its two parts (combined in quadrature)."""

    value: float
    uncertainty: float
    statistical: float | None = None
    systematic: float | None = None
    # False: the cloud does not show the part of the profile that places this size (the value is the fit's,
    # or a basic size held, with an infinite uncertainty); the verdict leaves its limits undecided
    measured: bool = True

    def to_dict(self) -> dict:
        def number(v):  # JSON has no infinity: a held size's uncertainty is written as null
            return float(v) if np.isfinite(v) else None

        out = {"value": float(self.value), "uncertainty": number(self.uncertainty)}
        if self.systematic is not None:
            out.update(statistical=number(self.statistical), systematic=float(self.systematic))
        if not self.measured:
            out["measured"] = False
        return out


@dataclass(frozen=True)
class ThreadDefect:
    """A damaged crest: centre angle and angular width about the axis (degrees, see the module
    docstring), depth below the fitted crest (mm, outwards), axial position along the axis (mm, from
    ``GaugeResult.axis_point_mm``), and the crest turn it sits on (0 = the first turn in the zone)."""

    angle_deg: float
    width_deg: float
    depth_mm: float
    axial_mm: float
    turn: int

    def to_dict(self) -> dict:
        return {"angle_deg": self.angle_deg, "width_deg": self.width_deg, "depth_mm": self.depth_mm,
                "axial_mm": self.axial_mm, "turn": self.turn}


@dataclass
class GaugeResult:
    """What the gauge measured. Diameters, pitch in mm; flank angle in degrees (the included angle, 60 for
    ISO). axis_point_mm, axis_direction : the fitted axis (cloud frame). verdict : ``pass``, ``fail``, or
    ``indeterminate`` when the measurement is too uncertain to decide (see :func:`gauge_thread`);
    checks : one line per limit with its outcome; residual_rms_mm : profile fit residual (robust core)."""

    minor_diameter_mm: Measured
    major_diameter_mm: Measured
    pitch_diameter_mm: Measured
    pitch_mm: Measured
    flank_angle_deg: Measured
    virtual_pitch_diameter_mm: float
    axis_point_mm: np.ndarray
    axis_direction: np.ndarray
    zone_mm: tuple[float, float]
    defects: list[ThreadDefect]
    limits: ThreadLimits
    verdict: str
    checks: list[dict]
    residual_rms_mm: float
    n_points: int
    profile: dict = field(default_factory=dict)
    virtual_pitch_diameter_uncertainty_mm: float = 0.0
    # profile parts (PROFILE_PARTS) with fewer than GaugeOptions.min_part_points fitted points
    unseen_parts: tuple = ()
    # what :func:`remeasure` needs to fit the same points again: their indices in the input cloud, the
    # axis base frame, the parameters and bounds, which fit gave the sizes
    fit_state: dict = field(default_factory=dict, repr=False)

    def to_dict(self) -> dict:
        return {
            "designation": self.limits.designation, "tolerance_class": self.limits.tolerance_class,
            "minor_diameter_mm": self.minor_diameter_mm.to_dict(),
            "major_diameter_mm": self.major_diameter_mm.to_dict(),
            "pitch_diameter_mm": self.pitch_diameter_mm.to_dict(),
            "pitch_mm": self.pitch_mm.to_dict(), "flank_angle_deg": self.flank_angle_deg.to_dict(),
            "virtual_pitch_diameter_mm": self.virtual_pitch_diameter_mm,
            "axis_point_mm": self.axis_point_mm.tolist(), "axis_direction": self.axis_direction.tolist(),
            "zone_mm": list(self.zone_mm), "verdict": self.verdict, "checks": self.checks,
            "defects": [d.to_dict() for d in self.defects], "residual_rms_mm": self.residual_rms_mm,
            "n_points": self.n_points, "limits_source": self.limits.source,
            "unseen_parts": list(self.unseen_parts),
        }

    def summary(self) -> str:
        """A readable table of the measurement against the limits."""
        lim = self.limits
        rows = [
            ("minor diameter D1", self.minor_diameter_mm, f"{lim.d1_min_mm:.3f} .. {lim.d1_max_mm:.3f}"),
            ("pitch diameter D2", self.pitch_diameter_mm, f"{lim.d2_min_mm:.3f} .. {lim.d2_max_mm:.3f}"),
            ("major diameter D", self.major_diameter_mm, f">= {lim.d_min_mm:.3f}"),
            ("pitch P", self.pitch_mm, ""),
        ]
        lines = [f"thread gauge {lim.designation}-{lim.tolerance_class}: {self.verdict.upper()}",
                 f"  {'':20s} {'value':>9s} {'± 1σ':>8s}  limits (mm)"]
        held = self.profile.get("held_at_basic", ())
        for name, m, text in rows:
            parts = "" if m.systematic is None else f"  (fit {m.statistical:.4f}, systematic {m.systematic:.4f})"
            if not m.measured:  # its value is the fit's by the profile's symmetry, or a basic size held
                parts = "  (held at the basic size, not measured)" if name.rsplit(" ", 1)[0] in held else "  (not measured)"
            lines.append(f"  {name:20s} {m.value:9.4f} {m.uncertainty:8.4f}  {text}{parts}")
        f = self.flank_angle_deg
        held = " (sizes fitted with 60°: the free fit above does not resolve another)" if self.profile.get(
            "flank_angle_held") else ""
        lines.append(f"  {'flank angle (deg)':20s} {f.value:9.3f} {f.uncertainty:8.3f}  60 nominal{held}")
        lines.append(f"  virtual pitch diameter {self.virtual_pitch_diameter_mm:.4f} mm")
        if self.unseen_parts:
            lines.append(f"  not in the cloud: {' and '.join(self.unseen_parts)} (the sizes they place are not measured)")
        for d in self.defects:
            lines.append(f"  defect: crest turn {d.turn} at {d.angle_deg:.1f}° (width {d.width_deg:.0f}°), "
                         f"depth {d.depth_mm:.3f} mm")
        for c in self.checks:
            if not c["ok"] and not c["check"].endswith("(not measured)"):
                lines.append(f"  out of limits: {c['check']}")
        return "\n".join(lines)


# --- axis frame -----------------------------------------------------------------------------------


def _frame(direction: np.ndarray) -> np.ndarray:
    """(3, 3) rows ex, ey, d: the axis' frame, ex = the cloud's +x made normal to d (+y when d is near x)."""
    d = direction / np.linalg.norm(direction)
    ref = np.array([1.0, 0.0, 0.0]) if abs(d[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    ex = ref - (ref @ d) * d
    ex /= np.linalg.norm(ex)
    return np.stack([ex, np.cross(d, ex), d])


def _axis_from_params(base_point, base_frame, a, b, cx, cy):
    """The axis (point, direction) a small tilt (a, b) and shift (cx, cy) away from a base frame."""
    d = base_frame[2] + a * base_frame[0] + b * base_frame[1]
    d = d / np.linalg.norm(d)
    return base_point + cx * base_frame[0] + cy * base_frame[1], d


def _cylindrical(points, point, direction):
    """points (N, 3) -> (theta (N,) rad, r (N,) mm, z (N,) mm along the axis from ``point``)."""
    local = (points - point) @ _frame(direction).T
    return np.arctan2(local[:, 1], local[:, 0]), np.hypot(local[:, 0], local[:, 1]), local[:, 2]


def fit_cylinder_axis(points: np.ndarray, *, direction_hint: np.ndarray | None = None,
                      scale_mm: float = 0.05) -> tuple[np.ndarray, np.ndarray, float]:
    """Robust axis of a roughly cylindrical cloud: minimise the spread of the distances to the axis.

    points : (N, 3) mm. direction_hint : (3,) or None (the principal axis, pointed along +z).
    Returns (point_mm (3,), direction (3,) unit, mean radius mm)."""
    points = np.asarray(points, float)
    centre = np.median(points, axis=0)
    if direction_hint is None:
        _, _, vt = np.linalg.svd(points - points.mean(0), full_matrices=False)
        d0 = vt[0]
        d0 = d0 if d0[2] >= 0 else -d0
    else:
        d0 = np.asarray(direction_hint, float) / np.linalg.norm(direction_hint)
    base = _frame(d0)

    def residual(x):
        p, d = _axis_from_params(centre, base, *x[:4])
        _, r, _ = _cylindrical(points, p, d)
        return r - x[4]

    r0 = float(np.median(_cylindrical(points, centre, d0)[1]))
    sol = least_squares(residual, [0.0, 0.0, 0.0, 0.0, r0], loss="soft_l1", f_scale=scale_mm, x_scale="jac")
    p, d = _axis_from_params(centre, base, *sol.x[:4])
    return p, d, float(sol.x[4])


# --- profile --------------------------------------------------------------------------------------


def _profile_distance(w, r, r1, r2, rp, half_angle, pitch):
    """Signed distance (mm, + where material is missing: the groove side) of points at (w, r) from the
    symmetric profile: w (N,) axial offset from the crest centre in [-P/2, P/2), r (N,) radius.
    The tooth (material inwards of the surface) is half a pitch wide at rp, its flanks at ``half_angle``
    from the radial direction: crest flat at r1, root flat at r2."""
    hc = tooth_half_width(r1, pitch, rp, half_angle)  # at the crest
    hr = tooth_half_width(r2, pitch, rp, half_angle)  # at the root
    aw = np.abs(w)
    # polyline (0, r1) -> (hc, r1) -> (hr, r2) -> (P/2, r2) in (|w|, r)
    xs = np.array([0.0, hc, hr, 0.5 * pitch])
    ys = np.array([r1, r1, r2, r2])
    best = np.full(len(w), np.inf)
    for k in range(3):
        x0, y0, x1, y1 = xs[k], ys[k], xs[k + 1], ys[k + 1]
        dx, dy = x1 - x0, y1 - y0
        length2 = dx * dx + dy * dy
        t = np.clip(((aw - x0) * dx + (r - y0) * dy) / max(length2, 1e-18), 0.0, 1.0)
        best = np.minimum(best, np.hypot(aw - x0 - t * dx, r - y0 - t * dy))
    surface_r = np.interp(aw, xs, ys)
    return np.where(r >= surface_r, best, -best)


def _profile_distance_and_gradient(w, r, r1, r2, rp, half_angle, pitch):
    """:func:`_profile_distance` and its partial derivatives: returns (dist (N,), d dist / d w (N,),
    d dist / d r (N,), d dist / d (r1, r2, rp, half_angle, pitch) (N, 5)), the last through the profile's
    corners. The distance to the nearest segment moves with a corner as the segment's closest point does
    (the envelope theorem: the closest point's own shift along the segment changes nothing to first
    order), i.e. by -(1 - t) or -t times the unit vector from that point, t its clipped position."""
    tan_h = np.tan(half_angle)
    sec2 = 1.0 + tan_h * tan_h
    hc = tooth_half_width(r1, pitch, rp, half_angle)
    hr = tooth_half_width(r2, pitch, rp, half_angle)
    aw = np.abs(w)
    xs = np.array([0.0, hc, hr, 0.5 * pitch])
    ys = np.array([r1, r1, r2, r2])
    # d(corner x) / d(r1, r2, rp, half, pitch), d(corner y) / d(...): rows the four corners
    dxs = np.array([[0.0, 0.0, 0.0, 0.0, 0.0],
                    [tan_h, 0.0, -tan_h, (r1 - rp) * sec2, 0.25],
                    [0.0, tan_h, -tan_h, (r2 - rp) * sec2, 0.25],
                    [0.0, 0.0, 0.0, 0.0, 0.5]])
    dys = np.array([[1.0, 0, 0, 0, 0], [1.0, 0, 0, 0, 0], [0, 1.0, 0, 0, 0], [0, 1.0, 0, 0, 0]])
    best = np.full(len(w), np.inf)
    g_aw, g_r = np.zeros(len(w)), np.zeros(len(w))
    g_p = np.zeros((len(w), 5))
    for k in range(3):
        x0, y0, x1, y1 = xs[k], ys[k], xs[k + 1], ys[k + 1]
        dx, dy = x1 - x0, y1 - y0
        t = np.clip(((aw - x0) * dx + (r - y0) * dy) / max(dx * dx + dy * dy, 1e-18), 0.0, 1.0)
        ex, ey = aw - x0 - t * dx, r - y0 - t * dy
        dist = np.hypot(ex, ey)
        closer = dist < best
        if not closer.any():
            continue
        best = np.where(closer, dist, best)
        inv = np.where(dist > 0, 1.0 / np.maximum(dist, 1e-300), 0.0)
        ux, uy = ex * inv, ey * inv
        g_aw = np.where(closer, ux, g_aw)
        g_r = np.where(closer, uy, g_r)
        corner = -((1 - t)[:, None] * (ux[:, None] * dxs[k] + uy[:, None] * dys[k])
                   + t[:, None] * (ux[:, None] * dxs[k + 1] + uy[:, None] * dys[k + 1]))
        g_p = np.where(closer[:, None], corner, g_p)
    sign = np.where(r >= np.interp(aw, xs, ys), 1.0, -1.0)
    return sign * best, sign * g_aw * np.sign(w), sign * g_r, sign[:, None] * g_p


def _profile_residuals(points, p0, base, x, jacobian: bool = False):
    """Every point's signed distance (mm) from the profile of parameters ``x`` (10,) (see gauge_thread:
    axis tilt a, b and shift cx, cy from the base frame ``base`` at ``p0``, pitch, phase, r1, r2, rp,
    half-angle); with ``jacobian``, also its (N, 10) derivative by the chain rule through the axis frame,
    the cylindrical coordinates, the helical offset w and the profile's corners (one pass, where finite
    differences need one per parameter)."""
    a, b, cx, cy, pitch, phase, r1, r2, rp, half = x
    e0x, e0y, e0z = base
    n = e0z + a * e0x + b * e0y
    norm_n = np.linalg.norm(n)
    d = n / norm_n
    p = p0 + cx * e0x + cy * e0y
    frame = _frame(d)
    v = points - p
    lx, ly, lz = v @ frame[0], v @ frame[1], v @ frame[2]
    t, rad = np.arctan2(ly, lx), np.hypot(lx, ly)
    u = lz - pitch * t / (2 * np.pi) - phase + pitch / 2
    wrapped = np.mod(u, pitch)
    w = wrapped - pitch / 2
    if not jacobian:
        return _profile_distance(w, rad, r1, r2, rp, half, pitch)
    dist, g_w, g_r, g_prof = _profile_distance_and_gradient(w, rad, r1, r2, rp, half, pitch)
    turns = np.round((u - wrapped) / pitch)  # w = lz - P t / 2pi - phase - turns P
    jac = np.empty((len(points), 10))
    # the axis: d = n / |n| tilted by (a, b); the frame's ex = (ref - (ref.d) d) normalised, ey = d x ex
    ref = np.array([1.0, 0.0, 0.0]) if abs(d[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    m = ref - (ref @ d) * d
    norm_m = np.linalg.norm(m)
    ex = frame[0]
    for col, e0 in ((0, e0x), (1, e0y)):
        dd = (e0 - d * (d @ e0)) / norm_n
        dm = -(ref @ dd) * d - (ref @ d) * dd
        dex = (dm - ex * (ex @ dm)) / norm_m
        dey = np.cross(dd, ex) + np.cross(d, dex)
        dlx, dly, dlz = v @ dex, v @ dey, v @ dd
        dt = (lx * dly - ly * dlx) / rad**2
        drad = (lx * dlx + ly * dly) / rad
        jac[:, col] = g_w * (dlz - pitch / (2 * np.pi) * dt) + g_r * drad
    for col, e0 in ((2, e0x), (3, e0y)):  # the axis point moves by e0: every point by -e0
        dlx, dly, dlz = -(e0 @ frame[0]), -(e0 @ frame[1]), -(e0 @ frame[2])
        dt = (lx * dly - ly * dlx) / rad**2
        drad = (lx * dlx + ly * dly) / rad
        jac[:, col] = g_w * (dlz - pitch / (2 * np.pi) * dt) + g_r * drad
    jac[:, 4] = g_w * (-t / (2 * np.pi) - turns) + g_prof[:, 4]
    jac[:, 5] = -g_w
    jac[:, 6:10] = g_prof[:, :4]
    return dist, jac


def _thread_zone(z, r, pitch, depth, r_minor, r_major):
    """Axial limits of the threaded stretch: windows one pitch long in which the radius spans at least
    half the basic thread depth and 95 % of the radii lie within 30 % of a thread depth of the nominal
    minor and major radii (a drill point's cone or a counterbore's shoulder span radii too, but outside
    that band), the longest run of them, less one pitch at each end (the run-outs)."""
    band = (r_minor - 0.3 * depth, r_major + 0.3 * depth)
    lo, hi = float(z.min()), float(z.max())
    step = pitch / 4
    edges = np.arange(lo, hi + step, step)
    ok = np.zeros(len(edges), bool)
    order = np.argsort(z)
    zs, rs = z[order], r[order]
    for k, e in enumerate(edges):
        a, b = np.searchsorted(zs, [e - pitch / 2, e + pitch / 2])
        if b - a >= 20:
            q = np.percentile(rs[a:b], [5, 95])
            in_band = np.mean((rs[a:b] >= band[0]) & (rs[a:b] <= band[1]))
            ok[k] = q[1] - q[0] >= 0.5 * depth and in_band >= 0.95
    if not ok.any():
        raise ValueError("no threaded stretch found in the cloud (the radius never varies by a thread depth)")
    # longest run of True
    runs, start = [], None
    for k, v in enumerate(np.append(ok, False)):
        if v and start is None:
            start = k
        elif not v and start is not None:
            runs.append((start, k - 1))
            start = None
    a, b = max(runs, key=lambda ab: ab[1] - ab[0])
    z0, z1 = edges[a] + pitch, edges[b] - pitch
    if z1 - z0 < 2 * pitch:
        raise ValueError(f"threaded stretch too short to gauge: {edges[b] - edges[a]:.2f} mm")
    return z0, z1


def _ends_on_thread(z, r, side, pitch, depth):
    """Whether the cloud's last half pitch at its ``side`` end (+1: the far end along the axis, -1: the near
    one) spans half a thread depth of radius (thread) rather than lying on one radius (a counterbore's or
    a plain bore's wall)."""
    end = side * np.max(side * z)
    last = r[side * (end - z) <= pitch / 2]
    if len(last) < 20:
        return True  # too few points to tell a wall from thread: the stretch's own rule decides
    q = np.percentile(last, [5, 95])
    return bool(q[1] - q[0] >= 0.5 * depth)


def _pitch_scan(theta, z, r, nominal, search):
    """Pitch maximising the first harmonic of the radius in the helical phase; and the root's phase (mm)."""
    dr = r - r.mean()
    # The harmonic's peak is ~P^2 / L wide (L the zone's length): a grid of a fifth of that, then a finer
    # one round the best; the joint fit refines further.
    length = max(float(np.ptp(z)), nominal)
    step = nominal**2 / length / 5
    best = nominal
    for half_width in (search * nominal, 2 * step):
        pitches = np.arange(best - half_width, best + half_width + step / 2, step)
        amp = np.array([np.abs(np.mean(dr * np.exp(1j * (2 * np.pi * z / p - theta)))) for p in pitches])
        best = float(pitches[int(np.argmax(amp))])
        step /= 10
    return float(best), _root_phase(theta, z, r, best)


def _root_phase(theta, z, r, pitch):
    """The axial phase (mm) of the radius' first harmonic in the helical phase ``2 pi z / P - theta``."""
    phasor = np.mean((r - r.mean()) * np.exp(1j * (2 * np.pi * z / pitch - theta)))
    return float(np.angle(phasor) / (2 * np.pi) * pitch)


def gauge_thread(points: np.ndarray, *, options: GaugeOptions = GaugeOptions()) -> GaugeResult:
    """Measure an internal thread from a cloud of its surface (see the module docstring).

    points : (N, 3) float64 mm, the hole's inner surface (thread; a counterbore, plain bore or drill point
        may be in it too), in any frame; outliers should be removed first (a robust loss copes with a few).
    Raises ValueError when no thread is found. Returns a :class:`GaugeResult`."""
    points = np.asarray(points, float)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) < 200:
        raise ValueError(f"need (N, 3) points with N >= 200, got shape {points.shape}")
    index = np.flatnonzero(np.all(np.isfinite(points), axis=1))  # into the input, for remeasure
    points = points[index]
    limits = thread_limits(options.designation, options.tolerance_class)
    major_nom, pitch_nom = THREAD_SIZES[options.designation]
    depth_nom = basic_thread_depth(pitch_nom)  # ISO 68-1 basic thread depth (5/8 H)
    rng = np.random.default_rng(options.seed)

    # (1) axis from the whole cloud
    hint = None if options.axis_hint is None else np.asarray(options.axis_hint, float)
    sample = points if len(points) <= options.max_points else points[rng.choice(len(points), options.max_points, replace=False)]
    p0, d0, _ = fit_cylinder_axis(sample, direction_hint=hint, scale_mm=depth_nom / 4)
    if hint is not None and d0 @ hint < 0:
        d0 = -d0
    # (2) zone
    theta, r, z = _cylindrical(points, p0, d0)
    z0, z1 = _thread_zone(z, r, pitch_nom, depth_nom, major_nom / 2 - depth_nom, major_nom / 2)
    # The defect search runs on through the pitch of run-out trimmed for the sizes' fit at an end where the
    # cloud itself ends within a pitch of the threaded stretch, still on thread (the scan's last view: the
    # crests there are whole thread), not where the wall leaves the thread (a counterbore or a plain bore
    # lies beyond: the turn there is cut short, not damaged). A counterbore 1 mm deep can sit inside the
    # stretch's last window when the pitch nears 2 mm (M12x1.75), so the cloud's last half pitch must itself
    # span half a thread depth of radius, as thread does and a plain wall does not.
    near_end = (z.min() > z0 - 2 * pitch_nom and _ends_on_thread(z, r, -1, pitch_nom, depth_nom),
                z.max() < z1 + 2 * pitch_nom and _ends_on_thread(z, r, 1, pitch_nom, depth_nom))
    search_z = (z0 - pitch_nom if near_end[0] else z0, z1 + pitch_nom if near_end[1] else z1)
    zone_index = np.flatnonzero((z >= z0) & (z <= z1))
    if len(zone_index) > options.max_points:
        zone_index = np.sort(rng.choice(zone_index, options.max_points, replace=False))
    zone_points = points[zone_index]
    # the axis again, from the thread alone (the counterbore and the bore are not coaxial in general)
    p0, d0, _ = fit_cylinder_axis(zone_points, direction_hint=d0, scale_mm=depth_nom / 4)
    base = _frame(d0)
    th, rr, zz = _cylindrical(zone_points, p0, d0)
    # (3) pitch and phase
    pitch0, root_phase = _pitch_scan(th, zz, rr, pitch_nom, options.pitch_search)
    crest_phase = root_phase + pitch0 / 2
    r1_0, r2_0 = np.percentile(rr, [3, 97])
    standard_half = np.deg2rad(ISO_METRIC_FLANK_ANGLE_DEG / 2)
    x0 = np.array([0.0, 0.0, 0.0, 0.0, pitch0, crest_phase, r1_0, r2_0, r1_0 + 0.4 * (r2_0 - r1_0), standard_half])
    # (4) joint fit
    # Bounds keep a noisy cloud's fit a thread: axis tilt within ~0.1 rad and shift within a thread depth,
    # the pitch within the searched range, radii within a thread depth of their start, the pitch radius
    # between them, the half-angle from 15° to 45°.
    lower = np.array([-0.1, -0.1, -depth_nom, -depth_nom, pitch_nom * (1 - options.pitch_search), -np.inf,
                      r1_0 - depth_nom, r2_0 - depth_nom, r1_0, np.deg2rad(15.0)])
    upper = np.array([0.1, 0.1, depth_nom, depth_nom, pitch_nom * (1 + options.pitch_search), np.inf,
                      r1_0 + depth_nom, r2_0 + depth_nom, r2_0, np.deg2rad(45.0)])
    x0 = np.clip(x0, lower + 1e-9, upper - 1e-9)
    # Over a short zone (~3 pitches) the harmonic's peak is wider than the pitch search and a slightly
    # uneven sampling along the axis can put its maximum a few percent off (an M6 scan: 1.017 mm for a
    # 1.000 mm pitch), from where the joint fit can run into a wrong minimum; so the fit also starts from
    # the nominal pitch, and the start whose robust cost ends lower wins.
    starts = [x0]
    if abs(pitch0 - pitch_nom) > 1e-6:
        x1 = x0.copy()
        x1[4], x1[5] = pitch_nom, _root_phase(th, zz, rr, pitch_nom) + pitch_nom / 2
        starts.append(np.clip(x1, lower + 1e-9, upper - 1e-9))
    def size_fits(starts, held=()):
        """(the fit that gives the sizes, the fit with the flank angle free) from the start of lower cost,
        the parameters ``held`` held at the start's values."""
        if not options.fix_flank_angle:
            free = min((_fit_profile(zone_points, p0, base, x, lower, upper, True, options.noise_mm, held)
                        for x in starts), key=lambda f: f.cost)
            return free, free
        fixed = min((_fit_profile(zone_points, p0, base, x, lower, upper, False, options.noise_mm, held)
                     for x in starts), key=lambda f: f.cost)
        free = _fit_profile(zone_points, p0, base, fixed.x, lower, upper, True, options.noise_mm, held)
        # The standard angle stands unless the free fit resolves a different one (a bound is no resolution).
        rejected = not free.flank_at_bound and abs(free.x[9] - standard_half) > 2 * free.std[9]
        return (free if rejected else fixed), free

    fit, free = size_fits(starts)
    unseen = _unseen_parts(zone_points, p0, base, fit, options.min_part_points)
    # A radius whose part of the profile the cloud does not show (a 45° view: the root's) is placed by no
    # point: free, the fit ran it to a bound through an ill-conditioned valley (M8 at 45°: D 1.0 mm off,
    # sigma 1e8 mm), and every warm-started re-fit of the systematic terms chased it again. It is held at
    # its basic size (ISO 724) instead, reported as held, not measured, with no uncertainty (the sizes it
    # alone places are left undecided by the verdict, as before). The crest's too (320x256 frames at 45°:
    # free, it ran 1.4 mm off and the defect search, which measures from it, missed the chip). Held at the
    # basic minor radius, a hole's D1 offset shows on its crest points as missing material (mid-class M10:
    # 0.075 mm, no false chip seen; a hole near D1's upper limit is untested there).
    held = tuple(i for i, part in ((6, "crest"), (7, "root")) if part in unseen)
    if held:
        x_held = fit.x.copy()
        basic = {6: major_nom / 2 - depth_nom, 7: major_nom / 2}
        for i in held:
            x_held[i] = basic[i]
        fit, free = size_fits([np.clip(x_held, lower + 1e-9, upper - 1e-9)], held)
    x, res, core = fit.x, fit.residuals, fit.core
    std = fit.std.copy()
    std[list(held)] = np.inf  # a held radius was not measured: no uncertainty can be claimed for it
    pitch, r1, r2, rp, half = x[4], x[6], x[7], x[8], x[9]
    axis_point, axis_dir = _axis_from_params(p0, base, *x[:4])
    # a size the cloud does not place is not measured, and a radius of it at its bound says nothing about
    # the parts seen (a chip on a seen crest still fails the hole)
    unmeasured = unmeasured_sizes(unseen)
    unplaced = {i for i, size in ((6, "minor diameter"), (7, "major diameter"), (8, "pitch diameter"))
                if size in unmeasured}
    at_bound = any(6 <= i <= 9 and i not in unplaced for i in fit.stopped)

    # virtual pitch diameter (ISO 965-1 sec. 3 / ISO 1502): the go side sees D2 reduced by the
    # pitch-diameter equivalents of the pitch error over the engagement, fP = 1.732 |dP| n (60° thread),
    # and of the flank angle error, f_alpha = 0.073 P K (|d_alpha1| + |d_alpha2|) um with P in mm, the
    # half-angle errors in minutes and K = 3 (the larger factor, conservative). With the flank angle held
    # at the standard's (the free fit did not resolve another), its equivalent is zero.
    turns = options.engagement_turns or (z1 - z0) / pitch
    f_p = 1.732 * abs(pitch - pitch_nom) * turns
    d_alpha_min = abs(np.rad2deg(half) - 30.0) * 60.0
    f_alpha = 0.073 * pitch_nom * 3 * 2 * d_alpha_min * 1e-3
    d2 = 2 * rp
    d2_virtual = d2 - f_p - f_alpha

    # (5) crest defects, over the zone and where the cloud ends within a pitch of it (search_z above)
    # (search_z is in step (2)'s axial coordinate, z: the fitted axis' point is the zone's median, not the
    # whole cloud's, so its axial origin lies elsewhere; selecting by the fitted one shifted the searched
    # stretch by that difference, into an M12's counterbore)
    keep = (z >= search_z[0]) & (z <= search_z[1])
    t_all, r_all, z_all = _cylindrical(points[keep], axis_point, axis_dir)
    s = z_all - pitch * t_all / (2 * np.pi) - x[5]
    w = np.mod(s + pitch / 2, pitch) - pitch / 2
    dist = _profile_distance(w, r_all, r1, r2, rp, half, pitch)
    hc = tooth_half_width(r1, pitch, rp, half)
    on_crest = np.abs(w) <= max(hc, 0.05 * pitch)
    # the tooth's top half: from its crest to half the thread depth, the flanks' inner halves included (a
    # chip cuts them back with the crest; a 45° view sees the crest at a grazing angle, hence sparsely, and
    # the flank facing it square on)
    top = np.abs(w) <= max(tooth_half_width((r1 + r2) / 2, pitch, rp, half), hc, 0.05 * pitch)
    defects = _crest_defects(t_all[top], z_all[top], np.round((s[top] - w[top]) / pitch).astype(int), dist[top],
                             on_crest[top], options)

    # the pitch's share of the virtual D2 moves with the pitch: u(D2v)^2 = u(D2)^2 + (1.732 n u(P))^2
    u_d2v = float(np.hypot(2 * std[8], 1.732 * turns * std[4]))
    verdict, checks = judge(limits, options, 2 * r1, 2 * std[6], d2, 2 * std[8], float(d2_virtual), u_d2v, 2 * r2,
                             2 * std[7], defects, at_bound, unseen)
    seen = {name: name not in unmeasured for name in ("minor diameter", "major diameter", "pitch diameter")}
    return GaugeResult(
        minor_diameter_mm=Measured(2 * r1, 2 * std[6], measured=seen["minor diameter"]),
        major_diameter_mm=Measured(2 * r2, 2 * std[7], measured=seen["major diameter"]),
        pitch_diameter_mm=Measured(d2, 2 * std[8], measured=seen["pitch diameter"]), pitch_mm=Measured(pitch, std[4]),
        flank_angle_deg=Measured(float(np.rad2deg(2 * free.x[9])), float(np.rad2deg(2 * free.std[9]))),
        virtual_pitch_diameter_mm=float(d2_virtual), axis_point_mm=axis_point, axis_direction=axis_dir,
        zone_mm=(float(z0), float(z1)), defects=defects, limits=limits, verdict=verdict, checks=checks,
        residual_rms_mm=float(np.sqrt(np.mean(res[core] ** 2))), n_points=len(zone_points),
        profile={"crest_half_width_mm": float(hc), "phase_mm": float(x[5]),
                 "flank_angle_in_size_fit_deg": float(np.rad2deg(2 * half)),
                 "flank_angle_held": fit is not free,
                 "held_at_basic": [PROFILE_PARTS_SIZE[i] for i in held]},
        virtual_pitch_diameter_uncertainty_mm=u_d2v, unseen_parts=unseen,
        fit_state={"index": index[zone_index], "p0": p0, "base": base, "x": x.copy(), "lower": lower,
                   "upper": upper, "free_flank": fit is free, "turns": float(turns), "f_alpha": float(f_alpha),
                   "pitch_nominal": float(pitch_nom), "at_bound": at_bound, "held": held},
    )


def judge(limits: ThreadLimits, options: GaugeOptions, d1: float, u_d1: float, d2: float, u_d2: float,
           d2_virtual: float, u_d2v: float, d: float, u_d: float, defects: list, at_bound: bool,
           unseen: tuple = ()) -> tuple[str, list[dict]]:
    """The verdict and its checks from the sizes and their standard uncertainties (mm).

    Each limit is guarded by the expanded uncertainty U = k u (ISO 14253-1, k = ``coverage_factor``): a
    value inside the limit by more than U proves conformance there, outside by more than U proves
    non-conformance; within U of the limit it proves neither. ``fail``: a limit proven broken, or a
    damaged crest. ``pass``: every limit proven kept, and the gauge capable — U at most a quarter of the
    tolerance (the usual 4:1 gauge-maker's rule; TD1 stands in for the major diameter, which has no
    width) and no profile parameter stopped at its bound (the cloud did not show that part of the
    profile). Anything else is ``indeterminate``; a profile at its bound proves nothing either way, nor
    does a size whose part of the profile the cloud did not show (``unseen``, names from PROFILE_PARTS:
    its limits are left undecided)."""
    k = options.coverage_factor
    unmeasured = set(unmeasured_sizes(unseen))
    checks = []
    for name, value, u, limit, upper in (
            ("minor diameter", d1, u_d1, limits.d1_min_mm, False), ("minor diameter", d1, u_d1, limits.d1_max_mm, True),
            ("virtual pitch diameter", d2_virtual, u_d2v, limits.d2_min_mm, False),
            ("pitch diameter", d2, u_d2, limits.d2_max_mm, True), ("major diameter", d, u_d, limits.d_min_mm, False)):
        margin = (limit - value) if upper else (value - limit)  # > 0 inside the limit
        gauge = " (go)" if name == "virtual pitch diameter" else " (no-go)" if name == "pitch diameter" else ""
        seen = name.removeprefix("virtual ") not in unmeasured
        checks.append({"check": f"{name} {value:.4f} {'<=' if upper else '>='} {limit:.3f}{gauge}"
                       + ("" if seen else " (not measured)"), "quantity": name,
                       "ok": bool(margin >= 0), "margin_mm": float(margin),
                       "expanded_uncertainty_mm": float(k * u) if np.isfinite(u) else None,
                       "decided": bool(seen and abs(margin) > k * u)})
    checks.append({"check": f"{len(defects)} damaged crest(s)", "ok": not defects, "decided": True})
    td1 = limits.d1_max_mm - limits.d1_min_mm
    td2 = limits.d2_max_mm - limits.d2_min_mm
    incapable = [name for name, u, tol in (("minor diameter", u_d1, td1), ("pitch diameter", u_d2, td2),
                                           ("major diameter", u_d, td1)) if not k * u <= tol / 4 and name not in unmeasured]
    undecided = [c["check"] for c in checks if not c["decided"] and not c["check"].endswith("(not measured)")]
    notes = ([f"{' and '.join(unseen)} not seen: {', '.join(sorted(unmeasured))} not measured"] if unmeasured else []) + \
        ([f"uncertainty over a quarter of the tolerance: {', '.join(incapable)}"] if incapable else []) + \
        (["profile fit at a bound"] if at_bound else []) + \
        ([f"within the expanded uncertainty of a limit: {', '.join(undecided)}"] if undecided else [])
    checks.append({"check": "measurement decides every limit" + (f" (not: {'; '.join(notes)})" if notes else ""),
                   "ok": not notes, "decided": True})
    proven_out = [c for c in checks[:-1] if not c["ok"] and c["decided"]]
    if at_bound:
        verdict = "indeterminate"
    elif proven_out:
        verdict = "fail"
    else:
        verdict = "indeterminate" if notes else "pass"
    return verdict, checks


def remeasure(result: GaugeResult, points: np.ndarray, noise_mm: float = 0.01) -> dict:
    """Fit the profile of ``result`` again to the same points moved (``points``: the cloud ``result`` was
    measured on, (N, 3) mm, each point displaced, e.g. by another draw of the registration), warm-started
    at ``result``'s solution with the same flank-angle choice: returns the sizes ``minor_diameter``,
    ``pitch_diameter``, ``major_diameter``, ``virtual_pitch_diameter``, ``pitch`` (mm)."""
    st = result.fit_state
    fit = _fit_profile(np.asarray(points, float)[st["index"]], st["p0"], st["base"], st["x"], st["lower"], st["upper"],
                       st["free_flank"], noise_mm, st.get("held", ()))
    x = fit.x
    d2 = 2 * x[8]
    return {"minor_diameter": 2 * x[6], "pitch_diameter": d2, "major_diameter": 2 * x[7], "pitch": x[4],
            "virtual_pitch_diameter": d2 - 1.732 * abs(x[4] - st["pitch_nominal"]) * st["turns"] - st["f_alpha"]}


PROFILE_PARTS = ("crest", "flank towards +z", "flank towards -z", "root")
# the size each fitted radius gives (x[6], x[7]): what a radius held at its basic value leaves unmeasured
PROFILE_PARTS_SIZE = {6: "minor diameter", 7: "major diameter"}


def unmeasured_sizes(unseen) -> list[str]:
    """The sizes a cloud without the profile parts ``unseen`` (names from PROFILE_PARTS) does not measure:
    the crest places D1, the root D; D2 is where the tooth is half a pitch wide, so it needs both flanks,
    or one flank and the tooth's centre, which the crest and root flats together give (the symmetric
    profile: the crest's centre half a pitch from the root's)."""
    unseen = set(unseen)
    out = (["minor diameter"] if "crest" in unseen else []) + (["major diameter"] if "root" in unseen else [])
    if unseen & {"flank towards +z", "flank towards -z"} and unseen & {"crest", "root"}:
        out.append("pitch diameter")
    return out


def _unseen_parts(zone_points, p0, base, fit: "_ProfileFit", min_part_points: int) -> tuple:
    """The names (PROFILE_PARTS) of the profile parts the fit's core points do not show: a part with fewer
    than ``min_part_points`` of them, or a flank with under a tenth of the other flank's. A part not seen
    places its sizes by the profile's symmetry alone, which measures nothing (a 45° view: one flank, no
    root)."""
    x = fit.x
    pitch, r1, r2, rp, half = x[4], x[6], x[7], x[8], x[9]
    axis_point, axis_dir = _axis_from_params(p0, base, *x[:4])
    tz, _, zz = _cylindrical(zone_points[fit.core], axis_point, axis_dir)
    wz = np.mod(zz - pitch * tz / (2 * np.pi) - x[5] + pitch / 2, pitch) - pitch / 2
    counts = np.bincount(_part_of(wz, tooth_half_width(r1, pitch, rp, half), tooth_half_width(r2, pitch, rp, half)),
                         minlength=len(PROFILE_PARTS))
    # A flank seen as a surface gathers about as many points as the other (90° scans: 0.7-0.9 of it); one
    # seen only in scraps past the crests, with under a tenth of the other's (45°: 0.01-0.02), is not seen.
    weak = 1 + int(np.argmin(counts[1:3]))
    scraps = counts[weak] < 0.1 * counts[3 - weak]
    return tuple(name for k, (name, n) in enumerate(zip(PROFILE_PARTS, counts))
                 if n < min_part_points or (k == weak and scraps))


def _part_of(w, hc, hr):
    """Index into PROFILE_PARTS of points at axial offset ``w`` from the crest centre, the crest ``hc`` and
    the root ``hr`` half a tooth wide (a root wider than the pitch allows leaves no root)."""
    aw = np.abs(w)
    return np.where(aw <= hc, 0, np.where(aw >= hr, 3, np.where(w > 0, 1, 2)))


def profile_parts(result: GaugeResult, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Which part of the fitted profile each fitted point lies on, and the profile's outward normal there.

    points : (N, 3) mm, the cloud ``result`` was measured on. Returns (part (M,) int, index into
    :data:`PROFILE_PARTS`; normal (M, 3) unit, pointing into the material) for the M fitted points
    (``result.fit_state['index']``): crest and root flats normal along the radius, each flank normal to its
    straight line in the point's axial half-plane."""
    st = result.fit_state
    x = st["x"]
    pitch, phase, r1, r2, rp, half = x[4], x[5], x[6], x[7], x[8], x[9]
    axis_point, axis_dir = _axis_from_params(st["p0"], st["base"], *x[:4])
    frame = _frame(axis_dir)
    local = (np.asarray(points, float)[st["index"]] - axis_point) @ frame.T
    t = np.arctan2(local[:, 1], local[:, 0])
    w = np.mod(local[:, 2] - pitch * t / (2 * np.pi) - phase + pitch / 2, pitch) - pitch / 2
    hc, hr = tooth_half_width(r1, pitch, rp, half), tooth_half_width(r2, pitch, rp, half)
    part = _part_of(w, hc, hr)
    # flank line from (hc, r1) to (hr, r2) in (|w|, r): into the material is towards the tooth and outwards
    length = np.hypot(hr - hc, r2 - r1)
    n_w, n_r = -(r2 - r1) / length, (hr - hc) / length
    axial = np.where(part == 1, n_w, np.where(part == 2, -n_w, 0.0))
    radial_part = np.where((part == 1) | (part == 2), n_r, 1.0)
    radial = np.cos(t)[:, None] * frame[0] + np.sin(t)[:, None] * frame[1]
    return part, radial_part[:, None] * radial + axial[:, None] * frame[2]


@dataclass
class _ProfileFit:
    """One robust fit of axis, pitch, phase and profile: x (10,) the parameters (see gauge_thread), std (10,)
    their 1-sigma uncertainties (0 for a held one), residuals (N,) mm, core (N,) the points within the
    noise that the uncertainties come from; profile_at_bound: a fitted radius or the half-angle stopped at
    its bound; flank_at_bound: the half-angle did (only when it was free); cost: the robust loss at the
    solution (compares starts on the same points)."""

    x: np.ndarray
    std: np.ndarray
    residuals: np.ndarray
    core: np.ndarray
    profile_at_bound: bool
    flank_at_bound: bool
    cost: float = 0.0
    stopped: tuple = ()  # indices of the free parameters that stopped at a bound


def _fit_profile(points, p0, base, x0, lower, upper, free_flank: bool, noise_mm: float,
                 held: tuple = ()) -> _ProfileFit:
    """Fit the profile to ``points`` from ``x0`` within the bounds, the half-angle x[9] held at x0's
    unless ``free_flank``, and the parameters ``held`` (indices) at x0's."""
    free = np.ones(len(x0), bool)
    free[9] = free_flank
    free[list(held)] = False

    def full(xf):
        x = x0.copy()
        x[free] = xf
        return x

    def residual(xf):
        return _profile_residuals(points, p0, base, full(xf))

    def jacobian(xf):
        return _profile_residuals(points, p0, base, full(xf), jacobian=True)[1][:, free]

    scale = np.array([1e-3, 1e-3, 1e-2, 1e-2, 1e-3, 1e-2, 1e-2, 1e-2, 1e-2, 1e-2])
    sol = least_squares(residual, x0[free], jac=jacobian, loss="soft_l1", f_scale=noise_mm, x_scale=scale[free],
                        bounds=(lower[free], upper[free]))
    x = full(sol.x)
    res = sol.fun
    core = np.abs(res) < 3 * noise_mm + 3 * robust_sigma(res, about=0.0)
    dof = max(int(core.sum()) - int(free.sum()), 1)
    sigma2 = float(np.sum(res[core] ** 2) / dof)
    jac = sol.jac[core]
    try:
        cov = np.linalg.inv(jac.T @ jac) * sigma2
    except np.linalg.LinAlgError:
        cov = np.full((int(free.sum()),) * 2, np.nan)
    std = np.zeros(len(x0))
    std[free] = np.sqrt(np.maximum(np.diag(cov), 0.0))
    stopped = (np.isclose(x, lower, atol=1e-6) | np.isclose(x, upper, atol=1e-6)) & free
    return _ProfileFit(x, std, res, core, bool(stopped[6:10].any()), bool(stopped[9]), float(sol.cost),
                       tuple(int(i) for i in np.flatnonzero(stopped)))


def _crest_defects(theta, z, turn, dist, crest, options: GaugeOptions) -> list[ThreadDefect]:
    """Group angular bins of each crest turn whose median outward distance is too deep.

    theta, z, turn, dist : (N,) the angle (rad), axial position (mm), crest turn and outward distance from
    the profile (mm) of the points on the teeth's top halves; crest : (N,) bool, the points on the crest
    flat. A bin is judged on its crest points, or, with fewer than ``options.min_bin_points`` of them, on
    its points of the tooth's top half: a chip cuts the crest and the flanks' inner halves back together,
    and a view that sees the crest only sparsely (45°: 1-10 crest points per 10° of a turn) still sees the
    flank beside it. A crest bin is too deep beyond max(``options.min_defect_depth_mm``, 5 robust sigmas of
    the crest points); a top-half bin beyond max(``options.min_defect_depth_mm``, 5 standard errors of its
    median, 1.25 sigma / sqrt(n) of the top halves' robust sigma): seen from 45°, the few crest points
    scatter by 0.3 mm, whose 5 sigmas would hide any chip, and the flank beside them by 0.02 mm, while a
    chip's cut face, seen as sparsely as the crest, is diluted in its bin's median by the flank's points
    at its edge (M12: 0.06 mm of a 0.3 mm chip)."""
    if len(dist) == 0:
        return []
    crest_limit = max(options.min_defect_depth_mm, 5 * robust_sigma(dist[crest])) if crest.any() else np.inf
    top_sigma = robust_sigma(dist)
    n_bins = int(round(360.0 / options.defect_bin_deg))
    bins = np.floor(np.mod(theta, 2 * np.pi) / (2 * np.pi) * n_bins).astype(int) % n_bins
    first = int(turn.min())
    defects = []
    for k in np.unique(turn):
        sel = turn == k
        depth = np.full(n_bins, np.nan)
        limit = np.full(n_bins, np.inf)
        zmean = np.full(n_bins, np.nan)
        for b in np.unique(bins[sel]):
            m = sel & (bins == b)
            on_crest = (m & crest).sum() >= options.min_bin_points
            if on_crest:
                m = m & crest
            if m.sum() >= options.min_bin_points:
                depth[b] = np.median(dist[m])
                limit[b] = crest_limit if on_crest else max(options.min_defect_depth_mm,
                                                            5 * 1.25 * top_sigma / np.sqrt(m.sum()))
                zmean[b] = np.mean(z[m])
        bad = np.nan_to_num(depth, nan=-np.inf) > limit
        if not bad.any():
            continue
        # contiguous runs, wrapping round the circle
        if bad.all():
            runs = [np.arange(n_bins)]
        else:
            start = int(np.flatnonzero(~bad)[0])
            order = (np.arange(n_bins) + start) % n_bins
            runs, cur = [], []
            for b in order:
                if bad[b]:
                    cur.append(b)
                elif cur:
                    runs.append(np.array(cur))
                    cur = []
            if cur:
                runs.append(np.array(cur))
        for run in runs:
            centres = (run + 0.5) * 2 * np.pi / n_bins
            mean_angle = float(np.rad2deg(np.angle(np.mean(np.exp(1j * centres))))) % 360.0
            defects.append(ThreadDefect(angle_deg=round(mean_angle, 2), width_deg=len(run) * options.defect_bin_deg,
                                        depth_mm=float(np.max(depth[run])), axial_mm=float(np.nanmean(zmean[run])),
                                        turn=int(k - first)))
    return defects
