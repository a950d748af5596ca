"""How to scan a tapped hole with a side-viewing scope so that the thread gauge can measure it: the axial
step per frame, the frames per quadrant and the frame gap the quadrant maps match over, derived from the
view's axial extent on the wall (issue 13).

A side view at ``alpha`` degrees from the probe axis (-z; 90 looks straight at the wall) with a vertical
half field ``phi`` (image rows run along the hole axis, down into the hole) sees the wall of radius R from
``R cot(alpha + phi)`` above to ``R cot(alpha - phi)`` below the camera: the axial extent E. A wall point
stays in view for E / step frames. Two things need it seen often:

* triangulation within a quadrant: a point becomes a 3-D point only when matched between two frames at
  most ``frame_gap`` steps apart; the more frames see it, the more chances (and the more views, each
  with its descriptor, for matching the neighbour quadrant);
* registration between neighbour quadrants: their common points lie in the strip both views share after
  the stage's 30° turn, a fixed fraction of each frame; the count of 3-D points there scales with the
  points per frame, i.e. with the views per point.

So the step is E / ``views_per_point`` for every size (the thread's scale enters through R), and the
frame gap keeps matched frames' views overlapping by at least half (``gap * step <= E / 2``). The scope
advances until the frames have shown ``thread_pitches`` pitches of thread: the gauge trims a pitch of
run-out at each end, its zone detection needs a one-pitch window, and it must keep at least two pitches
to fit (:func:`scope3d.metrology.thread_gauge.gauge_thread`), plus margin for the ragged ends.

:func:`measured_quadrant_scan` applies the same rules to a scan already taken: its step and side view are
read off the stage's poses, so that ``scope3d thread-scan``, the Python API and the benchmarks all map a
quadrant with the frame gap its own scan calls for, whatever the hole size.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scope3d.geometry.iso_thread import THREAD_SIZES, basic_pitch_diameter
from scope3d.geometry.pose import Pose
from scope3d.sensor.camera import Camera


@dataclass(frozen=True)
class QuadrantScanPlanOptions:
    """views_per_point : frames in which each wall point should appear (default 8: measured on the 90°
        view of 400x320 px, 60° field, rendered holes — see docs/thread_metrology.md — at ~5 views an M6
        hole's neighbour quadrants share too few points to register, at ~7-10 every size registers).
    max_baseline_fraction : matched frames are at most this fraction of the view's extent apart
        (default 0.5: their views overlap by at least half).
    thread_pitches : pitches of thread the scan must show (default 5.5: 2 gauged, one of run-out trimmed
        at each end, the zone detector's one-pitch window, half a pitch for the ragged ends).
    start_below_thread_mm : how far below the thread's first turn the first frame's camera is (mm;
        default 0.5, the phantom's scan: it starts 1.5 mm down a hole whose 1 mm counterbore ends where
        the thread begins)."""

    views_per_point: float = 8.0
    max_baseline_fraction: float = 0.5
    thread_pitches: float = 5.5
    start_below_thread_mm: float = 0.5

    def __post_init__(self) -> None:
        if not (self.views_per_point >= 2 and 0 < self.max_baseline_fraction <= 1 and self.thread_pitches > 0):
            raise ValueError("need views_per_point >= 2, max_baseline_fraction in (0, 1] and thread_pitches > 0")


@dataclass(frozen=True)
class QuadrantScanPlan:
    """step_mm : the scope's advance per frame (mm); frames_per_quadrant : frames of each quadrant;
    frame_gap : the quadrant maps match frames up to this many steps apart
    (``QuadrantMapOptions.max_frame_gap``); view_extent_mm : axial extent of wall one frame shows (mm);
    wall_radius_mm : the radius it was computed at (the pitch radius); side_view_deg : the side view it is
    for (None: not known)."""

    step_mm: float
    frames_per_quadrant: int
    frame_gap: int
    view_extent_mm: float
    wall_radius_mm: float
    side_view_deg: float | None = None

    def to_dict(self) -> dict:
        return {"step_mm": self.step_mm, "frames_per_quadrant": self.frames_per_quadrant, "frame_gap": self.frame_gap,
                "view_extent_mm": self.view_extent_mm, "wall_radius_mm": self.wall_radius_mm,
                "side_view_deg": self.side_view_deg}


def view_extent_mm(camera: Camera, side_view_deg: float, wall_radius_mm: float) -> tuple[float, float]:
    """(above, below): how far above and below the camera (mm, along the hole axis; image rows run down the
    hole) the wall at ``wall_radius_mm`` from the axis is seen by a side view ``side_view_deg`` from the
    probe axis; the camera is taken on the axis."""
    if not 0 < side_view_deg <= 90:
        raise ValueError(f"side view angle must be in (0, 90] degrees, got {side_view_deg}")
    alpha = np.deg2rad(side_view_deg)
    phi_up, phi_down = np.arctan(camera.cy / camera.fy), np.arctan((camera.height - camera.cy) / camera.fy)
    if alpha - phi_down <= np.deg2rad(1.0):
        raise ValueError(f"a {side_view_deg}° side view with a {np.rad2deg(phi_down):.0f}° lower half field looks "
                         "down the hole, not at its wall")
    below = wall_radius_mm / np.tan(alpha - phi_down)
    above = -wall_radius_mm / np.tan(alpha + phi_up)  # > 0 when the upper rays point back up the hole
    return float(above), float(below)


def pitch_radius_mm(designation: str) -> float:
    """The pitch radius (ISO 724 D2 / 2, mm) of a ``designation`` hole: the wall's mean distance from the axis."""
    if designation not in THREAD_SIZES:
        raise ValueError(f"unknown thread {designation!r} (use one of {', '.join(THREAD_SIZES)})")
    major, pitch = THREAD_SIZES[designation]
    return basic_pitch_diameter(major, pitch) / 2


def matched_frame_gap(step_mm: float, extent_mm: float, *,
                      options: QuadrantScanPlanOptions = QuadrantScanPlanOptions()) -> int:
    """The largest frame gap whose matched frames' views still overlap by ``max_baseline_fraction``
    (``gap * step <= fraction * extent``), at least 1."""
    return max(1, int(np.floor(options.max_baseline_fraction * extent_mm / step_mm + 1e-9)))


def plan_quadrant_scan(camera: Camera, designation: str, side_view_deg: float = 90.0,
                       *, step_mm: float | None = None,
                       options: QuadrantScanPlanOptions = QuadrantScanPlanOptions()) -> QuadrantScanPlan:
    """The quadrant scan of a ``designation`` hole (one of ``THREAD_SIZES``) seen by ``camera``
    at ``side_view_deg`` (see the module docstring); ``step_mm`` imposes the step (None: the plan's), the
    frames and the frame gap then follow from it."""
    radius = pitch_radius_mm(designation)
    above, below = view_extent_mm(camera, side_view_deg, radius)
    extent = above + below
    if step_mm is None:
        step = np.floor(extent / options.views_per_point * 100) / 100  # a stage steps in hundredths of a mm
    elif step_mm > 0:
        step = step_mm
    else:
        raise ValueError(f"the step must be a positive length in mm, got {step_mm}")
    gap = matched_frame_gap(step, extent, options=options)
    # every wall point is seen views_per_point times only if the scope crosses a whole view's extent: a
    # 45° view shows the thread in two frames, but each point in only those two
    frames = max(minimum_frames(camera, designation, side_view_deg, float(step), options=options),
                 int(np.ceil(options.views_per_point - 1e-9)))
    return QuadrantScanPlan(float(step), frames, gap, float(extent), float(radius), float(side_view_deg))


def minimum_frames(camera: Camera, designation: str, side_view_deg: float, step_mm: float,
                   *,
                   options: QuadrantScanPlanOptions = QuadrantScanPlanOptions()) -> int:
    """The fewest frames per quadrant, ``step_mm`` apart, whose scan shows ``options.thread_pitches``
    pitches of the thread (at least 2: a point is triangulated from two views)."""
    radius = pitch_radius_mm(designation)
    pitch = THREAD_SIZES[designation][1]
    _, below = view_extent_mm(camera, side_view_deg, radius)
    # thread shown = start offset + advance + the view below the last frame
    advance = max(0.0, options.thread_pitches * pitch - options.start_below_thread_mm - below)
    return max(2, int(np.ceil(advance / step_mm - 1e-9)) + 1)


@dataclass(frozen=True)
class ScanCoverage:
    """What a quadrant scan of ``frames`` frames ``step_mm`` apart shows of a thread: pitches : pitches of
    thread from its first turn to the bottom of the last frame's view (the scope starting
    ``start_below_thread_mm`` below the first turn, as planned); views_per_point : frames that see one wall
    point in the middle of the scan (the view's extent over the step, at most the frame count); and the
    plan's (``plan``) for the same camera, size and side view."""

    designation: str
    side_view_deg: float
    step_mm: float
    frames: int
    pitches: float
    views_per_point: float
    plan: QuadrantScanPlan
    needed_pitches: float
    needed_views: float

    @property
    def short(self) -> bool:
        """Too short to gauge: fewer pitches shown than the gauge needs, or wall points seen fewer than
        twice (nothing to triangulate)."""
        return self.pitches < self.needed_pitches - 1e-9 or self.views_per_point < 2

    @property
    def below_plan(self) -> bool:
        """Fewer pitches shown or fewer views per wall point than the plan's."""
        return self.pitches < self.needed_pitches - 1e-9 or self.views_per_point < self.needed_views - 1e-9

    def message(self) -> str:
        """One line: what the scan shows against what the gauge needs, and the planned scan."""
        p = self.plan
        return (f"a {self.designation} scan at {self.side_view_deg:g}° of {self.frames} frames per quadrant "
                f"{self.step_mm:g} mm apart shows {self.pitches:.1f} pitches of thread (the gauge needs "
                f"{self.needed_pitches:g}) and each wall point in {self.views_per_point:.1f} views (planned "
                f"{self.needed_views:g}); the scan plan: {p.frames_per_quadrant} frames per quadrant "
                f"{p.step_mm:g} mm apart, frame gap {p.frame_gap}")


def scan_coverage(camera: Camera, designation: str, side_view_deg: float, step_mm: float, frames: int,
                  *,
                  options: QuadrantScanPlanOptions = QuadrantScanPlanOptions()) -> ScanCoverage:
    """What a scan of ``frames`` frames per quadrant, ``step_mm`` apart, shows of a ``designation`` hole
    (see :class:`ScanCoverage`)."""
    radius = pitch_radius_mm(designation)
    pitch = THREAD_SIZES[designation][1]
    above, below = view_extent_mm(camera, side_view_deg, radius)
    shown = options.start_below_thread_mm + (frames - 1) * step_mm + below
    views = min(float(frames), (above + below) / step_mm)
    return ScanCoverage(designation, float(side_view_deg), float(step_mm), int(frames), float(shown / pitch),
                        float(views), plan_quadrant_scan(camera, designation, side_view_deg, options=options),
                        options.thread_pitches, options.views_per_point)


def measured_quadrant_scan(camera: Camera, poses: list[Pose], designation: str,
                           *,
                           options: QuadrantScanPlanOptions = QuadrantScanPlanOptions()) -> QuadrantScanPlan:
    """The scan one quadrant's frames were taken with, read off their (stage-reported) ``cam_from_world``
    poses in order of advance, and the frame gap the plan's rule gives it: the step is the median advance
    between consecutive camera centres along the direction of advance (first to last centre), the side
    view the angle between the optical axis and that direction, the view's extent that of the wall at
    the nominal thread's pitch radius. Raises ValueError for fewer than two frames, a scope that does not
    advance, or a camera whose image rows run up the hole (the extent's rule takes them running down)."""
    if len(poses) < 2:
        raise ValueError(f"a quadrant needs at least 2 frames, got {len(poses)}")
    centres = np.array([p.centre for p in poses])
    travel = centres[-1] - centres[0]
    if not np.linalg.norm(travel) > 1e-6:
        raise ValueError("the quadrant's frames do not advance (first and last camera centres coincide)")
    advance = travel / np.linalg.norm(travel)
    step = float(np.median(np.diff(centres @ advance)))
    if not step > 0:
        raise ValueError(f"the quadrant's frames do not advance steadily (median step {step:.4f} mm)")
    # image rows (camera y) in the world, averaged over the frames: they must point down the hole
    rows_down = np.mean([p.rotation[1] for p in poses], axis=0)
    if rows_down @ advance <= 0:
        raise ValueError("the camera's image rows run up the hole, not down it")
    axis = np.mean([p.optical_axis for p in poses], axis=0)
    side_view_deg = float(np.degrees(np.arccos(np.clip(axis @ advance / np.linalg.norm(axis), -1.0, 1.0))))
    side_view_deg = round(side_view_deg, 9)  # a 90° view read off float poses comes out at 90 + 1e-14
    radius = pitch_radius_mm(designation)
    extent = float(sum(view_extent_mm(camera, side_view_deg, radius)))
    return QuadrantScanPlan(step, len(poses), matched_frame_gap(step, extent, options=options), extent, float(radius),
                            side_view_deg)
