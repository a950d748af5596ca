"""The gauge: which similarity frame a reconstruction is expressed in, chosen from the robot's measurements.

Images fix a reconstruction only up to a similarity (rotation, translation, scale). The measured poses
fix it, each through its tolerance:

* :func:`gauge_from_measurements` — least squares on all measured centres and orientations;
* :func:`gauge_centred_in_boxes` — the least-squares placement among those that keep every camera
  well inside its tolerance box (bound-constrained adjustment's poses must stay in their boxes);
* :func:`align_gauge` — either of them applied to adjusted poses (the map it describes is the same).

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



def gauge_centred_in_boxes(poses: list[Pose], measured: list[MeasuredPose], *, rounds: int = 3) -> Similarity:
    """The similarity that best fits the measurements while keeping every camera well inside its box.

    A measurement's tolerance box says the truth is inside; with uniform errors that is all it says, and
    the intersection of all boxes can pin the gauge better than a least-squares fit of the centres (the
    midrange of n uniform errors has a spread ~1/n, their mean ~1/sqrt n: on the dome at +-3 mm the
    centres' least-squares scale was 7 % off). But the deepest point alone (the Chebyshev centre) is
    set by the few tightest walls and is not unique; on the tracker's anisotropic boxes it left the
    cameras 0.17 mm off where least squares gives 0.04 mm. So two steps, linear in a small rotation,
    shift and log-scale about the current placement, re-linearised ``rounds`` times:

    1. the largest common slack ``delta*`` (each scalar's distance to its wall as a fraction of its
       half-width) any placement reaches (a linear programme, HiGHS);
    2. the least-squares fit of every measured centre and orientation (sigma = half-width / sqrt 3)
       among the placements that keep every scalar at least ``delta* / 2`` inside (a small quadratic
       programme, SLSQP).

    Scalars with an infinite tolerance take part in neither; an exact scalar pins the gauge (the
    identity is returned), as does an empty feasible set.
    """
    from scipy.optimize import linprog, minimize

    total = Similarity(1.0, np.eye(3), np.zeros(3), np.zeros(3))
    if any(np.any(m.tolerance.position_mm == 0) or np.any(m.tolerance.orientation_rad == 0) for m in measured):
        return total  # an exact scalar pins the gauge: no similarity may move it
    current = list(poses)
    for _ in range(rounds):
        C = np.stack([p.centre for p in current])
        c0 = C.mean(axis=0)
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
        # 1. |d0 + J x| <= tol (1 - delta), maximise delta
        A = np.r_[np.c_[J, tol], np.c_[-J, tol]]
        b = np.r_[tol - d0, tol + d0]
        lp = linprog(np.r_[np.zeros(7), -1.0], A_ub=A, b_ub=b, bounds=[(None, None)] * 7 + [(None, 1.0)],
                     method="highs")
        if lp.status != 0 or lp.x[7] < 0:
            return total
        margin = 0.5 * lp.x[7]
        # 2. least squares inside the boxes shrunk by that margin, from the deepest point
        w = np.sqrt(3.0) / tol
        qp = minimize(lambda x: float(np.sum((w * (d0 + J @ x)) ** 2)), lp.x[:7],
                      jac=lambda x: 2.0 * J.T @ (w**2 * (d0 + J @ x)), method="SLSQP",
                      constraints=[{"type": "ineq", "fun": lambda x: tol * (1 - margin) - (d0 + J @ x),
                                    "jac": lambda x: -J},
                                   {"type": "ineq", "fun": lambda x: tol * (1 - margin) + (d0 + J @ x),
                                    "jac": lambda x: J}])
        x = qp.x if qp.success else lp.x[:7]
        step = Similarity(float(np.exp(x[6])), rotvec_to_matrix(x[:3]), c0, c0 + x[3:6])
        total = _compose(step, total)
        current = [Pose(*step.apply_to_cam_from_world(p.rotation, p.translation)) for p in current]
    return total


def _compose(outer: Similarity, inner: Similarity) -> Similarity:
    """``outer(inner(X))`` as one Similarity about inner's origin."""
    target = outer.apply(inner.target)
    return Similarity(outer.scale * inner.scale, outer.rotation @ inner.rotation, inner.origin, target)


def align_gauge(poses: list[Pose], measured: list[MeasuredPose], *, bounded: bool = False) -> list[Pose]:
    """Express adjusted poses in the similarity frame that best fits the measured poses.

    Images fix a reconstruction only up to a similarity (rotation, translation, scale: the gauge).
    Free BA pins it to one camera's measurement; bounded BA keeps it inside the tolerance boxes, but
    where the boxes are wide compared with the trajectory, LM drifts along the scale (on the
    cable-driven-robot test the map shrank by 9 %, as the reference's Fig. 6.4 shows BA doing).
    Moving to the similarity that best fits every measured centre and orientation
    (:func:`gauge_from_measurements`) changes no reprojection error — it is the same
    map — but uses every measurement, so their random errors average out (a common bias cannot: it is
    unobservable).

    bounded : the poses (in their boxes) must stay in their boxes. Then the placement is the
        least-squares one among those that keep every camera well inside its box
        (:func:`gauge_centred_in_boxes`): with uniform errors the boxes' intersection
        says more than a least-squares fit alone (on the dome at +-3 mm the centres' least-squares scale
        was 7 % off); and only as much of it is applied (:meth:`scope3d.geometry.similarity.Similarity.fraction`)
        as keeps every pose inside.
    """
    if not bounded:
        return moved_by(poses, gauge_from_measurements(poses, measured))
    similarity = gauge_centred_in_boxes(poses, measured)
    if not all_in_boxes(moved_by(poses, similarity), measured):
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
