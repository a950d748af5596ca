"""The rigid pose of a marker plate from the 3-D positions of its markers (reference sec. 4.3.2).

:func:`plate_geometry` learns the plate — its markers in its own frame, origin at their centroid — from
the frames where every marker was seen (each aligned onto the first by a rigid fit, then averaged);
:func:`fit_plate_pose` fits it to one frame's visible markers (Kabsch, through
:func:`scope3d.geometry.similarity.fit_similarity` without scale) and gives the covariance of that fit.
The plate's frame is then the first complete frame's placement: a pose relative to it differs from
the tracker's own tool definition by one constant transform.

A pose here is ``plate_from_tracker`` (the ``cam_from_world`` convention of
:class:`~scope3d.geometry.pose.Pose`, the tracker's coordinates as the world).
"""
from __future__ import annotations

import numpy as np

from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import hat
from scope3d.geometry.similarity import fit_similarity

MIN_MARKERS = 3  # a rigid pose needs three markers not on one line


def plate_geometry(markers_mm: np.ndarray) -> np.ndarray:
    """(M, 3) mm markers in the plate frame, from (F, M, 3) tracker positions (NaN = missing).

    Raises ValueError when no frame sees every marker."""
    complete = np.flatnonzero(np.all(np.isfinite(markers_mm), axis=(1, 2)))
    if len(complete) == 0:
        raise ValueError("no frame sees every marker of the plate; its geometry cannot be learned")
    reference = markers_mm[complete[0]] - markers_mm[complete[0]].mean(axis=0)
    aligned = [fit_similarity(markers_mm[k], reference, with_scale=False).apply(markers_mm[k]) for k in complete]
    geometry = np.mean(aligned, axis=0)
    return geometry - geometry.mean(axis=0)


def fit_plate_pose(geometry_mm: np.ndarray, observed_mm: np.ndarray, marker_sigma_mm: float
                   ) -> tuple[Pose, np.ndarray] | None:
    """``plate_from_tracker`` and its (6, 6) ``(w rad, C mm)`` covariance from one frame's markers.

    geometry_mm : (M, 3) plate frame. observed_mm : (M, 3) tracker frame, NaN rows missing.
    marker_sigma_mm : per-axis noise of a marker position. None with fewer than :data:`MIN_MARKERS` or
    markers on a line. Covariance: ``C`` (the plate origin in the tracker) has ``sigma^2 / n`` per axis; the
    rotation ``sigma^2 (sum |p|^2 I - p p^T)^-1`` over the visible markers ``p`` (the first-order
    information of a rigid fit).
    """
    seen = np.all(np.isfinite(observed_mm), axis=1)
    if seen.sum() < MIN_MARKERS:
        return None
    p, m = geometry_mm[seen], observed_mm[seen]
    info_w = np.einsum("kij,kil->jl", hat(p), hat(p))  # sum hat(p)^T hat(p) = sum |p|^2 I - p p^T
    if np.linalg.eigvalsh(info_w)[0] < 1e-6 * np.trace(info_w):
        return None  # markers on one line: the rotation about it is free
    fit = fit_similarity(p, m, with_scale=False)  # tracker = R (p - origin) + target
    tracker_from_plate_t = fit.target - fit.rotation @ fit.origin
    pose = Pose(fit.rotation.T, -fit.rotation.T @ tracker_from_plate_t)
    cov = np.zeros((6, 6))
    # the left rotation of plate_from_tracker is minus the plate-frame rotation of the markers, expressed in
    # the tracker frame: w = -R dtheta, same covariance up to the rotation R
    cov[:3, :3] = fit.rotation @ (marker_sigma_mm**2 * np.linalg.inv(info_w)) @ fit.rotation.T
    cov[3:, 3:] = np.eye(3) * marker_sigma_mm**2 / seen.sum()
    return pose, cov
