"""The gauge: which similarity frame a reconstruction is expressed in, chosen from the robot's measurements.

Images fix a reconstruction only up to a similarity (rotation, translation, scale). The measured poses
fix it, each through its tolerance:

* :func:`gauge_from_measurements` — least squares on all measured centres and orientations, each weighed by
  its box as a uniform error's sigma (the placement the bounded adjustment's box prior asks for,
  :meth:`scope3d.estimators.bundle.BundleProblem.set_box_prior`);
* :func:`gauge_in_boxes` — the same least squares among the placements that keep every pose in its box;
* :func:`align_gauge` — either applied to adjusted poses (the map it describes is the same).

Units: mm and radians. Poses are ``cam_from_world``.
"""
from __future__ import annotations

import numpy as np

from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import hat, matrix_to_rotvec, rotvec_to_matrix
from scope3d.geometry.similarity import Similarity, fit_similarity
from scope3d.sensor.pose_tolerance import MeasuredPose


def gauge_from_measurements(poses: list[Pose], measured: list[MeasuredPose]) -> Similarity:
    """The similarity that best places an image-fixed reconstruction on the measurements.

    Images fix the cameras up to a similarity (the gauge); every measured centre and orientation says where
    it should be, each within its tolerance (sigma = half-width / sqrt 3, uniform errors). The fit weighs
    both: on a nearly planar trajectory the centres alone barely fix the tilt (on the dome's grid at
    +-1 mm an Umeyama fit of the centres tilted every camera by 2 deg), while the orientations fix it to a
    fraction of their tolerance. Least squares over 7 parameters, from the rotation the orientations agree
    on (or the Umeyama fit of the centres when no orientation is known).

    Returns the :class:`~scope3d.geometry.similarity.Similarity` to apply (the identity when fewer than 3 cameras).
    """
    from scipy.optimize import least_squares

    C = np.stack([p.centre for p in poses])
    R = np.stack([p.rotation for p in poses])
    meas_c = np.stack([m.pose.centre for m in measured])
    meas_R = np.stack([m.pose.rotation for m in measured])
    tol_c = np.stack([m.tolerance.position_mm for m in measured])
    tol_w = np.stack([m.tolerance.orientation_rad for m in measured])
    if len(C) < 3 or np.ptp(C, axis=0).max() <= 0:
        return Similarity(1.0, np.eye(3), np.zeros(3), np.zeros(3))
    start = _start_similarity(C, R, meas_c, meas_R, tol_w)
    w_c = np.where(np.isfinite(tol_c), np.sqrt(3.0) / np.maximum(tol_c, 1e-9), 0.0)
    w_w = np.where(np.isfinite(tol_w), np.sqrt(3.0) / np.maximum(tol_w, 1e-12), 0.0)

    def similarity(x):
        return Similarity(start.scale * np.exp(x[6]), rotvec_to_matrix(x[:3]) @ start.rotation, start.origin,
                          start.target + x[3:6])

    def deviations(x):
        sim = similarity(x)
        dc = sim.apply(C) - meas_c
        dw = matrix_to_rotvec(R @ sim.rotation.T @ np.swapaxes(meas_R, 1, 2))
        return dc, dw

    def least_squares_terms(x):
        dc, dw = deviations(x)
        return np.concatenate([(dc * w_c).ravel(), (dw * w_w).ravel()])

    return similarity(least_squares(least_squares_terms, np.zeros(7), method="lm").x)


def _start_similarity(C, R, meas_c, meas_R, tol_w) -> Similarity:
    """A start for the gauge fit: the rotation that maps the estimated orientations onto the measured ones
    (``R_k S^T = M_k``: the chordal mean of ``M_k^T R_k``), then scale and shift by least squares on the
    centres. The centres' own rotation (Umeyama) is ambiguous for a planar trajectory; the orientations
    are not."""
    known = np.all(np.isfinite(tol_w), axis=1)
    if not known.any():
        return fit_similarity(C, meas_c)
    U, _, Vt = np.linalg.svd(np.einsum("kji,kjl->il", meas_R[known], R[known]))
    rotation = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    a0, b0 = C.mean(axis=0), meas_c.mean(axis=0)
    a = (C - a0) @ rotation.T
    scale = float(np.sum(a * (meas_c - b0)) / max(np.sum(a * a), 1e-300))
    return Similarity(scale if scale > 0 else 1.0, rotation, a0, b0)



def gauge_in_boxes(poses: list[Pose], measured: list[MeasuredPose], *, rounds: int = 3) -> Similarity:
    """:func:`gauge_from_measurements`'s least squares restricted to the similarities that keep every pose in
    its box: the box prior's minimum (:meth:`scope3d.estimators.bundle.BundleProblem.set_box_prior`) over the
    moves that leave the images unchanged, with the boxes as the hard constraints they are. One camera the
    images hold at a wall must not veto the whole move (on a 2 mm box one camera's rotation at its wall left
    a 0.8 % scale where a fraction of the free fit was all that kept it inside), and must not be pushed out.

    Linear in a small rotation, shift and log-scale about the current placement (a quadratic programme in 7
    unknowns, SLSQP from the identity, which is feasible), re-linearised ``rounds`` times. Scalars with an
    infinite tolerance take no part; an exact scalar pins the gauge (the identity is returned).
    """
    from scipy.optimize import minimize

    total = Similarity(1.0, np.eye(3), np.zeros(3), np.zeros(3))
    if any(np.any(m.tolerance.position_mm == 0) or np.any(m.tolerance.orientation_rad == 0) for m in measured):
        return total  # an exact scalar pins the gauge: no similarity may move it
    current = list(poses)
    for _ in range(rounds):
        c0 = np.stack([p.centre for p in current]).mean(axis=0)
        J_rows, d0, tol = [], [], []
        for m, p in zip(measured, current):
            # centre: c + omega x (c - c0) + tau + lambda (c - c0); orientation: R exp(-omega) = exp(-R omega) R
            Jc = np.zeros((3, 7))
            Jc[:, :3] = -hat(p.centre - c0)
            Jc[:, 3:6] = np.eye(3)
            Jc[:, 6] = p.centre - c0
            Jw = np.zeros((3, 7))
            Jw[:, :3] = -p.rotation
            J_rows += [Jc, Jw]
            d0 += [p.centre - m.pose.centre, matrix_to_rotvec(p.rotation @ m.pose.rotation.T)]
            tol += [m.tolerance.position_mm, m.tolerance.orientation_rad]
        J, d0, tol = np.concatenate(J_rows), np.concatenate(d0), np.concatenate(tol)
        keep = np.isfinite(tol)
        if not keep.any():
            return total
        J, d0, tol = J[keep], d0[keep], tol[keep]
        w2 = 3.0 / tol**2  # sigma = half-width / sqrt(3)
        # a scalar already outside its box (by rounding) may not go further out, nothing more
        room = np.maximum(tol, np.abs(d0))
        qp = minimize(lambda x: float(np.sum(w2 * (d0 + J @ x) ** 2)), np.zeros(7),
                      jac=lambda x: 2.0 * J.T @ (w2 * (d0 + J @ x)), method="SLSQP",
                      constraints=[{"type": "ineq", "fun": lambda x: room - (d0 + J @ x), "jac": lambda x: -J},
                                   {"type": "ineq", "fun": lambda x: room + (d0 + J @ x), "jac": lambda x: J}])
        if not qp.success:
            break
        x = qp.x
        step = Similarity(float(np.exp(x[6])), rotvec_to_matrix(x[:3]), c0, c0 + x[3:6])
        total = _compose(step, total)
        current = moved_by(current, step)
    return total


def _compose(outer: Similarity, inner: Similarity) -> Similarity:
    """``outer(inner(X))`` as one Similarity about inner's origin."""
    return Similarity(outer.scale * inner.scale, outer.rotation @ inner.rotation, inner.origin, outer.apply(inner.target))


def align_gauge(poses: list[Pose], measured: list[MeasuredPose], *, bounded: bool = False) -> list[Pose]:
    """Express adjusted poses in the similarity frame that best fits the measured poses.

    Images fix a reconstruction only up to a similarity (rotation, translation, scale: the gauge).
    Free BA pins it to one camera's measurement. Moving to the similarity that best fits every measured
    centre and orientation (:func:`gauge_from_measurements`) changes no reprojection error — it is the same
    map — but uses every measurement, so their random errors average out (a common bias cannot: it is
    unobservable).

    bounded : the poses (in their boxes) must stay in their boxes. The bounded adjustment's box prior asks
        for the same placement (its cost over the similarities that leave the images unchanged is exactly
        this least squares), but the adjustment converges slowly along those directions: the images'
        curvature dwarfs the prior's in its damping, and it stops on its relative cost change first. This
        finishes that minimisation among the moves that keep every pose in its box (:func:`gauge_in_boxes`);
        should the linearisation still leave one outside, only as much of it is applied
        (:meth:`scope3d.geometry.similarity.Similarity.fraction`) as keeps every pose inside.
    """
    similarity = gauge_in_boxes(poses, measured) if bounded else gauge_from_measurements(poses, measured)
    if bounded and not all_in_boxes(moved_by(poses, similarity), measured):
        lo, hi = 0.0, 1.0  # the identity keeps them inside; bisect for the largest step that does
        for _ in range(30):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if all_in_boxes(moved_by(poses, similarity.fraction(mid)), measured) else (lo, mid)
        similarity = similarity.fraction(lo)
    return moved_by(poses, similarity)


def moved_by(poses: list[Pose], similarity: Similarity) -> list[Pose]:
    """The poses of the same cameras after the world moved by ``similarity``."""
    return [Pose(*similarity.apply_to_cam_from_world(p.rotation, p.translation)) for p in poses]


def all_in_boxes(poses: list[Pose], measured: list[MeasuredPose]) -> bool:
    """True when every pose lies in its measured tolerance box."""
    return all(m.contains(p) for p, m in zip(poses, measured))
