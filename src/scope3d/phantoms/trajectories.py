"""Camera paths of the reference's experiments, as lists of true ``cam_from_world`` poses (mm).

* ``grid5x6`` / ``grid7x8``: a raster of cameras looking straight down from 15 mm above the plate top
  (z = 0), 5 mm apart, visited row by row in serpentine order as a robot would (Fig. 4.6(a): 5x6 grid).
* ``axial``: a forward-looking camera on the hole axis, stepping 0.25 mm into the hole (sec. 7.3).
* ``quadrants``: a side-viewing borescope (45° or 90° between its optical axis and the probe axis)
  moving into the hole in 0.1 mm steps, then re-positioned and rotated by 30° about the hole axis, 12
  times (sec. 8.3). The camera centre sits a small, fixed offset away from the rotation axis, as in a
  real set-up where the misalignment is "small and also unknown" (sec. 8.1); the offset is recorded.
* ``spiral``: a camera near the centre of a closed cavity, looking outwards and sweeping a spherical
  spiral from top to bottom (bladder scan, ch. 2).
* ``approach``: a tool-mounted scope approaching a fluorescent target (ch. 5): from the survey's height,
  off to one side, down a straight line to a stop above the target, looking at the target throughout.

A survey's stops can also be flown as a video (:func:`survey_video`): straight moves between them at a
constant speed, a frame every ``1 / fps`` seconds, each frame's time in :attr:`Trajectory.times_s`. With an
acceleration (:class:`SurveyMotion`) the robot instead starts and stops at rest at every corner of the
path, as a controller's linear moves do, so that its velocity is continuous and a log sampled from it is
what a real controller's would be.

Image orientation: down-looking cameras have world +x to the right and world +y up in the picture;
cameras in the hole and the cavity have world +z (towards the opening) up in the picture.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from scope3d.errors import InputError
from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import look_at, rotvec_to_matrix

GRID_SPACING_MM = 5.0
GRID_STANDOFF_MM = 15.0
AXIAL_STEP_MM = 0.25
QUADRANT_STEP_MM = 0.1
QUADRANT_COUNT = 12
QUADRANT_ANGLE_DEG = 30.0
QUADRANT_AXIS_OFFSET_MM = (0.08, -0.05)
#: a survey flown as a video: a scope moved over tissue by a robot at 10 mm/s, which takes the 145 mm of
#: ``grid5x6``'s serpentine in 14.5 s (436 frames at 30 fps; 0.33 mm between frames, 1/45 of the view's
#: 15 mm width at the survey's 15 mm stand-off)
SURVEY_VIDEO_SPEED_MM_S = 10.0


@dataclass(frozen=True)
class Trajectory:
    """poses : true ``cam_from_world`` per frame; params : JSON-ready description (written to scene.json).
    times_s : (n,) each frame's time in seconds for a video-rate trajectory, None for stills."""

    name: str
    poses: list[Pose]
    params: dict = field(default_factory=dict)
    times_s: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.poses)

    def first(self, n: int) -> Trajectory:
        """The first ``n`` frames (all when there are fewer), recorded as ``params["frames_used"]``."""
        return Trajectory(self.name, self.poses[:n], {**self.params, "frames_used": min(n, len(self))},
                          None if self.times_s is None else self.times_s[:n])


def poses_at(key_times: np.ndarray, key_poses: list[Pose], times: np.ndarray) -> list[Pose]:
    """Poses at ``times`` (s) along keys joined by straight moves (centres linear, orientation slerp);
    times outside the keys take the nearest end's pose."""
    times = np.clip(times, key_times[0], key_times[-1])
    centres = np.array([p.centre for p in key_poses])
    centre = np.stack([np.interp(times, key_times, centres[:, k]) for k in range(3)], axis=1)
    rotation = Slerp(np.asarray(key_times, dtype=float),
                     Rotation.from_matrix([p.rotation for p in key_poses]))(times).as_matrix()
    return [Pose.from_centre(r, c) for r, c in zip(rotation, centre)]


class SurveyMotion:
    """A robot flying a survey's stops (e.g. ``grid5x6``) in straight moves, the pose at any time.

    accel_mm_s2 None: every move at ``speed_mm_s`` throughout, turning on the spot at each stop (a path
    with corners in its velocity). A number: the stops are joined into straight runs (a stop where the path
    does not turn is passed through), and each run starts and ends at rest, accelerating and braking at
    ``accel_mm_s2`` up to ``speed_mm_s`` (a trapezoidal speed profile, triangular on a run too short to
    reach it): the velocity is continuous, so a log sampled every ``dt`` differs from the straight line
    between its samples by at most ``accel_mm_s2 * dt**2 / 8``. The orientation is slerped between stops by
    arc length. Raises InputError for fewer than two stops, repeated stops or a non-positive rate."""

    def __init__(self, stops: Trajectory, *, speed_mm_s: float = SURVEY_VIDEO_SPEED_MM_S,
                 accel_mm_s2: float | None = None) -> None:
        if not (np.isfinite(speed_mm_s) and speed_mm_s > 0) or (
                accel_mm_s2 is not None and not (np.isfinite(accel_mm_s2) and accel_mm_s2 > 0)):
            raise InputError(f"a survey's motion needs a positive speed and acceleration, got {speed_mm_s} mm/s "
                             f"and {accel_mm_s2} mm/s^2")
        if len(stops) < 2:
            raise InputError("a survey video needs at least two stops")
        centres = np.array([p.centre for p in stops.poses])
        steps = np.diff(centres, axis=0)
        arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(steps, axis=1))])
        if not np.all(np.diff(arc) > 0):
            raise InputError("a survey video needs its stops at distinct places")
        self.stops, self.speed_mm_s, self.accel_mm_s2, self.stop_arcs_mm = stops, float(speed_mm_s), accel_mm_s2, arc
        if accel_mm_s2 is None:
            self._run_arcs = arc  # every stop ends a run, crossed at constant speed
        else:
            unit = steps / np.linalg.norm(steps, axis=1, keepdims=True)
            turns = np.flatnonzero(np.einsum("ij,ij->i", unit[:-1], unit[1:]) < 1.0 - 1e-12) + 1
            self._run_arcs = arc[np.concatenate([[0], turns, [len(arc) - 1]])]
        lengths = np.diff(self._run_arcs)
        if accel_mm_s2 is None:
            self._peak, self._ramp_s = np.full(len(lengths), self.speed_mm_s), np.zeros(len(lengths))
            durations = lengths / self.speed_mm_s
        else:
            self._peak = np.minimum(self.speed_mm_s, np.sqrt(accel_mm_s2 * lengths))
            self._ramp_s = self._peak / accel_mm_s2
            durations = 2.0 * self._ramp_s + (lengths - self._peak * self._ramp_s) / self._peak
        self._run_starts_s = np.concatenate([[0.0], np.cumsum(durations)])
        self.stop_times_s = arc / self.speed_mm_s if accel_mm_s2 is None else self._time_at_arc(arc)

    @property
    def duration_s(self) -> float:
        return float(self._run_starts_s[-1])

    def arc_mm(self, times_s: np.ndarray) -> np.ndarray:
        """Distance travelled along the path at ``times_s`` (clipped to the motion's ends), mm."""
        t = np.clip(np.asarray(times_s, dtype=float), 0.0, self.duration_s)
        k = np.clip(np.searchsorted(self._run_starts_s, t, side="right") - 1, 0, len(self._peak) - 1)
        tau, v, ramp = t - self._run_starts_s[k], self._peak[k], self._ramp_s[k]
        total = self._run_starts_s[k + 1] - self._run_starts_s[k]
        length = self._run_arcs[k + 1] - self._run_arcs[k]
        a = np.divide(v, ramp, out=np.zeros_like(v), where=ramp > 0)
        s = np.where(tau < ramp, 0.5 * a * tau ** 2,
                     np.where(tau <= total - ramp, 0.5 * v * ramp + v * (tau - ramp),
                              length - 0.5 * a * (total - tau) ** 2))
        return self._run_arcs[k] + np.clip(s, 0.0, length)

    def _time_at_arc(self, arcs: np.ndarray) -> np.ndarray:
        """Inverse of :meth:`arc_mm` at ``arcs`` on the path (monotone, so by bisection to 1e-12 s)."""
        lo, hi = np.zeros(len(arcs)), np.full(len(arcs), self.duration_s)
        for _ in range(80):
            mid = 0.5 * (lo + hi)
            below = self.arc_mm(mid) < arcs
            lo, hi = np.where(below, mid, lo), np.where(below, hi, mid)
        return hi

    def poses_at(self, times_s: np.ndarray) -> list[Pose]:
        """True ``cam_from_world`` at ``times_s`` (s from the first stop; the ends' poses outside it)."""
        if self.accel_mm_s2 is None:  # arc and time are proportional: interpolate in time, as always
            return poses_at(self.stop_times_s, self.stops.poses, np.asarray(times_s, dtype=float))
        return poses_at(self.stop_arcs_mm, self.stops.poses, self.arc_mm(times_s))


def survey_video(stops: Trajectory, fps: float, *, speed_mm_s: float = SURVEY_VIDEO_SPEED_MM_S,
                 accel_mm_s2: float | None = None) -> Trajectory:
    """A survey's stops (e.g. ``grid5x6``) flown as a video (:class:`SurveyMotion`: straight moves at
    ``speed_mm_s``, starting and ending each straight run at rest when ``accel_mm_s2`` is given), one frame
    every ``1 / fps`` seconds from the first stop (time 0) to the last. Named ``<survey>_video``; its params
    hold the survey's, the frame rate, the speed, the acceleration and the stops' times."""
    if not (np.isfinite(fps) and fps > 0):
        raise InputError(f"a survey video needs a positive frame rate and speed, got {fps} fps and {speed_mm_s} mm/s")
    motion = SurveyMotion(stops, speed_mm_s=speed_mm_s, accel_mm_s2=accel_mm_s2)
    times = np.arange(0.0, motion.duration_s + 1e-9, 1.0 / fps)
    path = ("straight moves between the survey's stops at constant speed, orientation slerped" if accel_mm_s2 is None
            else "straight runs between the path's corners, each from rest to rest at the given acceleration, "
                 "orientation slerped")
    params = {**stops.params, "kind": "survey video", "survey": stops.name, "fps": float(fps),
              "speed_mm_s": float(speed_mm_s), "stop_times_s": [round(float(t), 9) for t in motion.stop_times_s],
              "frames": len(times), "path": path,
              **({} if accel_mm_s2 is None else {"accel_mm_s2": float(accel_mm_s2)})}
    return Trajectory(f"{stops.name}_video", motion.poses_at(times), params, times)


def grid_trajectory(
    rows: int, cols: int, *, spacing_mm: float = GRID_SPACING_MM, standoff_mm: float = GRID_STANDOFF_MM,
    centre_mm=(0.0, 0.0, 0.0),
) -> Trajectory:
    """``rows`` x ``cols`` cameras looking down (-z) from ``standoff_mm`` above ``centre_mm``, serpentine order."""
    if rows < 1 or cols < 1 or spacing_mm <= 0 or standoff_mm <= 0:
        raise ValueError("grid needs rows, cols >= 1 and positive spacing and stand-off")
    centre = np.asarray(centre_mm, dtype=float)
    poses = []
    for r in range(rows):
        order = range(cols) if r % 2 == 0 else range(cols - 1, -1, -1)
        for c in order:
            eye = centre + [(c - (cols - 1) / 2) * spacing_mm, ((rows - 1) / 2 - r) * spacing_mm, standoff_mm]
            rot = look_at(eye, eye - [0.0, 0.0, 1.0], up=(0.0, -1.0, 0.0))
            poses.append(Pose.from_centre(rot, eye))
    params = {"kind": "grid", "rows": rows, "cols": cols, "spacing_mm": spacing_mm, "standoff_mm": standoff_mm,
              "centre_mm": centre.tolist(), "order": "serpentine rows, from +y to -y", "view": "straight down (-z)"}
    return Trajectory(f"grid{cols}x{rows}", poses, params)


def axial_trajectory(
    n_frames: int, *, step_mm: float = AXIAL_STEP_MM, start_z_mm: float = 1.0, axis_offset_mm: float = 0.0,
    axis_tilt_deg: float = 0.0,
) -> Trajectory:
    """Forward-looking camera stepping ``step_mm`` along the hole axis (-z) from ``start_z_mm``.

    axis_offset_mm : float, mm, the camera centre's lateral offset from the hole axis, along world +x
        (a scope mounted off-centre on the stage; the motion stays parallel to the axis).
    axis_tilt_deg : float, degrees, the optical axis tilted away from the motion by a rotation about the
        camera's own x axis (image rows), the misalignment the reference's aligned model (eqs. 7.3-7.4)
        ignores. 0 and 0 give the reference's aligned set-up (sec. 7.3). Limited to 15° (beyond it the
        epipole leaves the centre of the view and axial stereo no longer applies).
    """
    if n_frames < 1 or step_mm <= 0:
        raise ValueError("axial trajectory needs n_frames >= 1 and a positive step")
    if not (np.isfinite(axis_offset_mm) and np.isfinite(axis_tilt_deg) and abs(axis_tilt_deg) <= 15.0):
        raise ValueError(f"axis offset must be finite and axis tilt within ±15 degrees, got "
                         f"{axis_offset_mm} mm and {axis_tilt_deg} degrees")
    rot = look_at(np.zeros(3), [0.0, 0.0, -1.0], up=(0.0, -1.0, 0.0))
    # Pre-multiplying rotates about the camera's own x axis: the tilt is a property of the mount.
    rot = rotvec_to_matrix(np.array([np.deg2rad(axis_tilt_deg), 0.0, 0.0])) @ rot
    poses = [Pose.from_centre(rot, [axis_offset_mm, 0.0, start_z_mm - i * step_mm]) for i in range(n_frames)]
    params = {"kind": "axial", "step_mm": step_mm, "start_z_mm": start_z_mm, "frames": n_frames,
              "axis_offset_mm": float(axis_offset_mm), "axis_tilt_deg": float(axis_tilt_deg),
              "view": "forward along -z, on the hole axis" if axis_offset_mm == 0 and axis_tilt_deg == 0 else
              "forward along -z, moving parallel to the hole axis, offset along +x by axis_offset_mm, optical axis "
              "tilted by axis_tilt_deg about the camera x axis"}
    return Trajectory("axial", poses, params)


def quadrant_trajectory(
    frames_per_quadrant: int, *, step_mm: float = QUADRANT_STEP_MM, quadrants: int = QUADRANT_COUNT,
    angle_step_deg: float = QUADRANT_ANGLE_DEG, side_view_deg: float = 45.0, start_z_mm: float = -1.5,
    axis_offset_mm=QUADRANT_AXIS_OFFSET_MM, axis_tilt_deg: float = 0.0,
) -> Trajectory:
    """Side-view scans: per quadrant ``frames_per_quadrant`` frames moving inwards by ``step_mm``; quadrant q
    is quadrant 0 rotated by ``q * angle_step_deg`` about the hole axis (world z through the origin).

    side_view_deg : angle between the optical axis and the probe axis (-z); 45 or 90 in the reference.
    axis_offset_mm : (2,) camera centre's (x, y) offset from the rotation axis in quadrant 0.
    axis_tilt_deg : the camera tilted on its mount by a rotation about its own x axis (image rows),
        degrees within ±10; the probe still advances along the rotation axis.
    """
    if not abs(axis_tilt_deg) <= 10.0:
        raise ValueError(f"quadrant camera tilt must be within ±10 degrees, got {axis_tilt_deg}")
    if frames_per_quadrant < 1 or quadrants < 1 or step_mm <= 0:
        raise ValueError("quadrant trajectory needs frames_per_quadrant, quadrants >= 1 and a positive step")
    if not 0.0 < side_view_deg <= 90.0:
        raise ValueError(f"side view angle must be in (0, 90] degrees, got {side_view_deg}")
    a = np.deg2rad(side_view_deg)
    view = np.array([np.sin(a), 0.0, -np.cos(a)])
    # Image "down" is towards the hole bottom, so the opening is at the top of the picture.
    rot0 = look_at(np.zeros(3), view, up=(0.0, 0.0, -1.0))
    rot0 = rotvec_to_matrix(np.array([np.deg2rad(axis_tilt_deg), 0.0, 0.0])) @ rot0
    ox, oy = (float(v) for v in axis_offset_mm)
    poses = []
    for q in range(quadrants):
        spin = rotvec_to_matrix(np.array([0.0, 0.0, np.deg2rad(q * angle_step_deg)]))
        for i in range(frames_per_quadrant):
            centre0 = np.array([ox, oy, start_z_mm - i * step_mm])
            poses.append(Pose.from_centre(rot0 @ spin.T, spin @ centre0))
    params = {"kind": "quadrants", "quadrants": quadrants, "frames_per_quadrant": frames_per_quadrant,
              "step_mm": step_mm, "angle_step_deg": angle_step_deg, "side_view_deg": side_view_deg,
              "start_z_mm": start_z_mm, "rotation_axis": "world z through the origin",
              "axis_offset_mm": [ox, oy], "axis_tilt_deg": float(axis_tilt_deg),
              "note": "frame q*frames_per_quadrant + i: quadrant q rotated by q*angle_step about z, step i inwards; "
                      "axis_offset_mm is the camera centre's (x, y) in quadrant 0"}
    return Trajectory("quadrants", poses, params)


def spiral_trajectory(
    n_frames: int, *, turns: float = 3.0, radius_mm: float = 8.0, polar_range_deg=(25.0, 155.0),
    centre_mm=(0.0, 0.0, 0.0),
) -> Trajectory:
    """Camera on a sphere of ``radius_mm`` about ``centre_mm``, looking outwards along the radius, its
    direction sweeping ``turns`` turns of a spiral from polar angle ``polar_range_deg[0]`` (near +z) down
    to ``polar_range_deg[1]``."""
    if n_frames < 1:
        raise ValueError("spiral trajectory needs n_frames >= 1")
    centre = np.asarray(centre_mm, dtype=float)
    t = (np.arange(n_frames) + 0.5) / n_frames
    polar = np.deg2rad(polar_range_deg[0] + (polar_range_deg[1] - polar_range_deg[0]) * t)
    azimuth = 2 * np.pi * turns * t
    dirs = np.stack([np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth), np.cos(polar)], 1)
    poses = []
    for d in dirs:
        eye = centre + radius_mm * d
        poses.append(Pose.from_centre(look_at(eye, eye + d, up=(0.0, 0.0, -1.0)), eye))
    params = {"kind": "spiral", "frames": n_frames, "turns": turns, "radius_mm": radius_mm,
              "polar_range_deg": list(polar_range_deg), "centre_mm": centre.tolist(), "view": "outwards, radial"}
    return Trajectory("spiral", poses, params)


APPROACH_START_HEIGHT_MM = GRID_STANDOFF_MM
APPROACH_START_OFFSET_MM = 6.0
APPROACH_STOP_DISTANCE_MM = 9.0


def approach_trajectory(
    n_frames: int, target_mm, *, azimuth_deg: float = 0.0, start_height_mm: float = APPROACH_START_HEIGHT_MM,
    start_offset_mm: float = APPROACH_START_OFFSET_MM, stop_distance_mm: float = APPROACH_STOP_DISTANCE_MM,
) -> Trajectory:
    """A scope approaching ``target_mm`` (3,) mm: from ``start_offset_mm`` to the side of it (towards
    ``azimuth_deg`` about world z) at ``start_height_mm`` above the plate top (z = 0, the survey's height),
    in a straight line to ``stop_distance_mm`` above the target, looking at it all the way. The steps shrink
    towards the stop (smooth start and stop: ``s = (1 - cos(pi t)) / 2``), as a controller brakes."""
    if n_frames < 2:
        raise ValueError("an approach needs at least 2 frames")
    if not (start_offset_mm >= 0 and stop_distance_mm > 0 and start_height_mm > 0):
        raise ValueError("approach needs a non-negative start offset and positive heights")
    target = np.asarray(target_mm, dtype=float).reshape(3)
    a = np.deg2rad(azimuth_deg)
    start = np.array([target[0] + start_offset_mm * np.cos(a), target[1] + start_offset_mm * np.sin(a), start_height_mm])
    stop = target + [0.0, 0.0, stop_distance_mm]
    if start[2] <= stop[2]:
        raise ValueError(f"the stop ({stop[2]:.1f} mm) must lie below the start height ({start[2]:.1f} mm)")
    s = (1.0 - np.cos(np.pi * np.linspace(0.0, 1.0, n_frames))) / 2.0
    poses = []
    for f in s:
        eye = (1.0 - f) * start + f * stop
        poses.append(Pose.from_centre(look_at(eye, target, up=(0.0, -1.0, 0.0)), eye))
    params = {"kind": "approach", "frames": n_frames, "target_mm": target.tolist(), "azimuth_deg": azimuth_deg,
              "start_mm": start.tolist(), "stop_mm": stop.tolist(),
              "spacing": "(1 - cos(pi t)) / 2 along the straight line", "view": "looking at the target"}
    return Trajectory("approach", poses, params)


# name -> (description, default number of frames)
TRAJECTORIES = {
    "grid5x6": ("5 x 6 raster looking down from 15 mm, 5 mm spacing (30 frames)", 30),
    "grid7x8": ("7 x 8 raster looking down from 15 mm, 5 mm spacing (56 frames)", 56),
    "axial": ("forward view on the hole axis from z = +1 mm, 0.25 mm steps inwards (30 frames)", 30),
    "quadrants": ("45° side view, 0.1 mm steps from z = -1.5 mm, 12 quadrants 30° apart, camera 0.094 mm off "
                  "the rotation axis (8 frames per quadrant, 96 frames; `scope3d phantom thread` takes the scan "
                  "plan's step and frames instead)", 96),
    "spiral": ("camera 8 mm from the cavity centre looking outwards, 3-turn spherical spiral (36 frames)", 36),
    "approach": ("from 15 mm above the plate, 6 mm to the side of target N (--target), straight down to 9 mm "
                 "above it, looking at it; a tool hides part of the view (30 frames)", 30),
}


def ring_poses(n: int, *, tilt_deg: float, distance_mm: float, target=(0.0, 0.0, 0.0)) -> list[Pose]:
    """``n`` cameras evenly spaced on a cone ``tilt_deg`` off the world z axis, ``distance_mm`` from
    ``target`` (mm), all looking at it, image up towards +z (90 deg: a horizontal ring around an object,
    like Middlebury's)."""
    t = np.asarray(target, float)
    a = np.deg2rad(tilt_deg)
    poses = []
    for k in range(n):
        phi = 2.0 * np.pi * k / n
        eye = t + distance_mm * np.array([np.sin(a) * np.cos(phi), np.sin(a) * np.sin(phi), np.cos(a)])
        poses.append(Pose.from_centre(look_at(eye, t, up=(0.0, 0.0, 1.0)), eye))
    return poses


def build_trajectory(name: str, *, n_frames: int | None = None, side_view_deg: float = 45.0,
                     axis_offset_mm: float = 0.0, axis_tilt_deg: float = 0.0, target_mm=None,
                     azimuth_deg: float = 0.0, quadrant_mount: tuple | None = None,
                     quadrant_step_mm: float | None = None) -> Trajectory:
    """Build a named trajectory. ``n_frames`` limits the grids (first frames in scan order), sets the
    length of ``axial`` and ``spiral``, and for ``quadrants`` gives the total (``n_frames // 12`` per
    quadrant, at least one). ``axis_offset_mm`` and ``axis_tilt_deg`` misalign ``axial`` (see
    :func:`axial_trajectory`); other trajectories reject them. ``approach`` needs ``target_mm`` (3,) and
    starts towards ``azimuth_deg`` (see :func:`approach_trajectory`). ``quadrant_mount`` (offset_x_mm,
    offset_y_mm, tilt_deg) misaligns the ``quadrants`` camera from the rotation axis (None: the default
    offset :data:`QUADRANT_AXIS_OFFSET_MM`, no tilt). ``quadrant_step_mm`` is the ``quadrants`` advance per
    frame (None: :data:`QUADRANT_STEP_MM`; a 90° view sees ~3 mm of wall and must advance further to see
    enough thread turns to gauge)."""
    if name not in TRAJECTORIES:
        raise InputError(f"unknown trajectory {name!r} (use one of {', '.join(TRAJECTORIES)})")
    if n_frames is not None and n_frames < 1:
        raise InputError(f"number of frames must be at least 1, got {n_frames}")
    n = n_frames or TRAJECTORIES[name][1]
    if quadrant_step_mm is not None and name != "quadrants":
        raise InputError(f"a quadrant step applies to the quadrants trajectory only, not {name!r}")
    if quadrant_step_mm is not None and not quadrant_step_mm > 0:
        raise InputError(f"the quadrant step must be a positive length in mm, got {quadrant_step_mm}")
    if name != "axial" and (axis_offset_mm != 0 or axis_tilt_deg != 0):
        raise InputError(f"axis offset and tilt apply to the axial trajectory only, not {name!r}")
    if name.startswith("grid"):
        cols, rows = (int(v) for v in name[4:].split("x"))
        traj = grid_trajectory(rows, cols)
        if n_frames is not None:
            traj = traj.first(n_frames)
        return traj
    if name == "axial":
        return axial_trajectory(n, axis_offset_mm=axis_offset_mm, axis_tilt_deg=axis_tilt_deg)
    if quadrant_mount is not None and name != "quadrants":
        raise InputError(f"a quadrant mount applies to the quadrants trajectory only, not {name!r}")
    if name == "quadrants":
        ox, oy, tilt = quadrant_mount if quadrant_mount is not None else (*QUADRANT_AXIS_OFFSET_MM, 0.0)
        return quadrant_trajectory(max(1, n // QUADRANT_COUNT), side_view_deg=side_view_deg,
                                   axis_offset_mm=(ox, oy), axis_tilt_deg=tilt,
                                   step_mm=quadrant_step_mm or QUADRANT_STEP_MM)
    if name == "approach":
        if target_mm is None:
            raise InputError("the approach trajectory needs a target (--target N)")
        return approach_trajectory(n, target_mm, azimuth_deg=azimuth_deg)
    return spiral_trajectory(n)
