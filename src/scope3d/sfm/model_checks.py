"""What a map can say about its own trustworthiness when there is no ground truth (a new user's data).

Three figures a user can act on, computed from the model alone:

* **frames used**: a frame with no observation in the final tracks is not in the map. It is listed by
  name, never dropped silently.
* **pose corrections**: how far the bundle adjustment moved each reported pose (camera centre, mm;
  orientation, rad), and how often a correction ends on the edge of the reported tolerance box. The true
  pose lies inside the box by the box's definition, so a correction pinned to its edge means the images
  asked for more than the tolerance allowed: the tolerance may be too tight, or the poses may not be the
  camera's (a missing hand-eye transform) — or, for orientation, the images cannot tell a small tilt from a
  shift (a narrow field of view over a shallow scene) and the solution slides to the edge along that
  ambiguity. The figure is reported, not judged: only the user knows which applies.
* **reprojection error** (already in every report) — how well the model explains the images given the
  intrinsics.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import matrix_to_rotvec
from scope3d.scene.tracks import Tracks
from scope3d.sensor.pose_tolerance import MeasuredPose

# A correction within this fraction of its half-width counts as on the box's edge: the bounded solver
# stops on the bound itself (to round-off), so any small margin separates "on" from "inside".
EDGE_FRACTION = 0.999


@dataclass(frozen=True)
class ModelChecks:
    """Self-checks of a map (see the module docstring).

    unused_frames : names of the frames with no observation in the map.
    position_correction_mm, orientation_correction_rad : (n_used,) per used frame, the length of the move
        of the camera centre and the angle of the rotation applied to the reported pose.
    on_position_edge, on_orientation_edge : (n_used,) bool, some axis of the correction on the edge of a
        finite, non-zero tolerance.
    """

    n_frames: int
    unused_frames: list[str]
    position_correction_mm: np.ndarray
    orientation_correction_rad: np.ndarray
    on_position_edge: np.ndarray
    on_orientation_edge: np.ndarray

    @property
    def n_used(self) -> int:
        return self.n_frames - len(self.unused_frames)

    def as_dict(self) -> dict:
        def stats(values, scale=1.0):
            if len(values) == 0:
                return {"median": None, "max": None}
            return {"median": float(np.median(values)) * scale, "max": float(np.max(values)) * scale}

        return {
            "frames_used": self.n_used, "frames_used_fraction": self.n_used / max(self.n_frames, 1),
            "unused_frames": list(self.unused_frames),
            "pose_correction": {
                "position_mm": stats(self.position_correction_mm),
                "orientation_deg": stats(self.orientation_correction_rad, float(np.rad2deg(1.0))),
                "on_position_tolerance_edge_fraction": float(np.mean(self.on_position_edge)) if self.n_used else None,
                "on_orientation_tolerance_edge_fraction":
                    float(np.mean(self.on_orientation_edge)) if self.n_used else None,
            },
        }


def model_checks_summary(checks: dict) -> str:
    """One line for people from :meth:`ModelChecks.as_dict` (as stored in a map's report.json)."""
    n_used, unused = checks["frames_used"], checks["unused_frames"]
    line = f"{n_used} of {n_used + len(unused)} frames in the map"
    if unused:
        line += f" (not used: {', '.join(unused[:5])}{', ...' if len(unused) > 5 else ''})"
    d = checks["pose_correction"]
    if not n_used:
        return line
    return (f"{line}; reported poses corrected by median {d['position_mm']['median']:.3f} mm / "
            f"{d['orientation_deg']['median']:.3f} deg (max {d['position_mm']['max']:.3f} mm / "
            f"{d['orientation_deg']['max']:.3f} deg); on the edge of their tolerance: "
            f"{100 * d['on_position_tolerance_edge_fraction']:.0f} % of frames in position, "
            f"{100 * d['on_orientation_tolerance_edge_fraction']:.0f} % in orientation")


def check_model(names: list[str], measured: list[MeasuredPose], adjusted: list[Pose], tracks: Tracks) -> ModelChecks:
    """Self-checks of a map whose frames ``names`` were reported at ``measured`` and adjusted to
    ``adjusted`` (``cam_from_world``, same order), with ``tracks`` the final observations (frame indices
    into ``names``)."""
    n = len(names)
    used = np.bincount(np.asarray(tracks.frame, dtype=np.int64), minlength=n)[:n] > 0
    idx = np.flatnonzero(used)
    pos = np.zeros(len(idx))
    ang = np.zeros(len(idx))
    pos_edge = np.zeros(len(idx), bool)
    ang_edge = np.zeros(len(idx), bool)
    for out, k in enumerate(idx):
        m, p = measured[k], adjusted[k]
        dc = p.centre - m.pose.centre
        w = matrix_to_rotvec(p.rotation @ m.pose.rotation.T)  # the tolerance's own parametrisation
        pos[out], ang[out] = np.linalg.norm(dc), np.linalg.norm(w)
        pos_edge[out] = _on_edge(dc, m.tolerance.position_mm)
        ang_edge[out] = _on_edge(w, m.tolerance.orientation_rad)
    return ModelChecks(n, [names[k] for k in np.flatnonzero(~used)], pos, ang, pos_edge, ang_edge)


def _on_edge(correction: np.ndarray, half_width: np.ndarray) -> bool:
    bounded = np.isfinite(half_width) & (half_width > 0)
    return bool(np.any(np.abs(correction[bounded]) >= EDGE_FRACTION * half_width[bounded]))
