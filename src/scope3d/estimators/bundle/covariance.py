"""How well the images fix each camera relative to the others, after an adjustment.

A frame seen in one pair with a hundred matches on a small patch can reproject to a tenth of a pixel and
still be half a millimetre off: the two-view geometry trades rotation against translation along directions
the residuals barely see. Its reprojection error says nothing of that; the curvature of the cost does. The
covariance of the poses is the inverse of the reduced camera system (the Hessian with the points
eliminated, Schur complement), scaled by the keypoints' noise.

Images fix a reconstruction only up to a similarity, so that matrix is singular along the 7 gauge
directions (a common rotation, translation and scale of every camera and point), and what a matcher needs
is how far a camera may be off *relative to the one it is matched with*: :func:`pairwise_pose_covariances`
gives the covariance of each pair's pose difference, with the robot's measurements as priors (they hold
the gauge and any camera the images leave loose) or, without them, in the complement of the gauge (the
minimum-norm inverse, "inner constraints").
"""
from __future__ import annotations

import numpy as np

from scope3d.estimators.bundle.problem import BundleParameters, BundleProblem
from scope3d.estimators.bundle.solver import evaluate
from scope3d.geometry.rotation import hat


def pairwise_pose_covariances(problem: BundleProblem, parameters: BundleParameters, pairs: list[tuple[int, int]], *,
                              loss_scale_px: float = 1.0, noise_px: float | None = None,
                              prior_sigmas: np.ndarray | None = None) -> np.ndarray:
    """Covariance (len(pairs), 6, 6) of each pair's pose difference ``(w_j - w_i, C_j - C_i)`` (rad, mm):
    how far camera j may be off relative to camera i, which is what predicting i's features in j needs.

    Two cameras tied to each other by many points but, as a group, loosely to the rest have large
    covariances relative to the whole map and a small one relative to
    each other: ``S_ii + S_jj - S_ij - S_ji`` (S: the joint covariance of every camera's pose scalars
    ``(w (rad), centre (mm))``). The Hessian uses the observations' Huber weights at ``loss_scale_px`` (as
    the adjustment did); the noise is ``noise_px`` or, by default, estimated from the residuals (median
    norm / 1.1774, the median of a 2-D Gaussian's norm). Intrinsics and fixed pose scalars are held (zero
    sigma). Infinity where either camera has no observation. Needs positions parametrised as centres
    (``from_measured_poses``).

    prior_sigmas : optional (m, 6) finite standard deviations of the measured poses (rad, mm; a box of
        half-width a is a uniform error of sigma a / sqrt(3)). With them the covariance is the posterior of
        images and measurements: the gauge and a camera the images barely hold are held by the
        measurements, instead of being removed by the minimum-norm gauge, which spreads one loose camera's
        freedom over every other (on the tracker dome one frame's 4 m sigma became every pair's). Without
        them the gauge is removed by the minimum-norm inverse.
    """
    if prior_sigmas is not None and not np.all(np.isfinite(prior_sigmas) & (np.asarray(prior_sigmas) > 0)):
        raise ValueError("prior_sigmas must be finite and positive")
    full, seen = _pose_covariance(problem, parameters, loss_scale_px, noise_px, prior_sigmas)
    out = np.empty((len(pairs), 6, 6))
    for k, (i, j) in enumerate(pairs):
        if not (seen[i] and seen[j]):
            out[k] = np.diag(np.full(6, np.inf))
            continue
        a, b = slice(6 * i, 6 * i + 6), slice(6 * j, 6 * j + 6)
        out[k] = full[a, a] + full[b, b] - full[a, b] - full[b, a]
    return out


def marginal_sigmas(information: np.ndarray, *, rcond: float = 1e-12) -> np.ndarray:
    """(n,) standard deviations of each parameter from a symmetric positive semi-definite ``information``
    matrix (n, n): the square roots of the diagonal of its inverse, inf for a parameter that leans on a
    direction the information does not fix.

    ``np.linalg.inv`` of a nearly singular information (a camera the images barely tie down, in mm and rad
    at once) returns round-off, including negative variances whose square root is NaN. Scaled to a unit
    diagonal first (so millimetres and radians do not set the conditioning), the eigenvalues below
    ``rcond`` times the largest are the unfixed directions; a parameter with weight on one of them has an
    unbounded variance, the others the inverse restricted to the fixed directions."""
    d = np.sqrt(np.clip(np.diag(information), 0.0, None))
    observed = d > 0
    out = np.full(len(d), np.inf)
    if not observed.any():
        return out
    scaled = information[np.ix_(observed, observed)] / np.outer(d[observed], d[observed])
    lam, vectors = np.linalg.eigh(scaled)
    fixed = lam > rcond * lam[-1]
    variance = (vectors[:, fixed] ** 2) @ (1.0 / lam[fixed])
    # round-off puts ~1e-16 of weight on every direction; a parameter truly on an unfixed one carries O(1)
    loose = (vectors[:, ~fixed] ** 2).sum(axis=1) > 1e-6
    variance[loose] = np.inf
    out[observed] = np.sqrt(variance) / d[observed]
    return out


def _pose_covariance(problem: BundleProblem, parameters: BundleParameters, loss_scale_px: float,
                     noise_px: float | None, prior_sigmas: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """The joint pose covariance (6m, 6m) (gauge removed, or held by the priors) and which cameras are
    observed (m,) bool."""
    S, seen, sigma = reduced_camera_system(problem, parameters, loss_scale_px, noise_px)
    m = problem.num_cameras
    free = ~problem.pose_fixed.ravel() & np.repeat(seen, 6)
    Sf = S[np.ix_(free, free)] / sigma**2
    if prior_sigmas is not None:
        # the measurements as Gaussian priors: they hold the gauge and any camera the images leave loose
        prior = np.asarray(prior_sigmas, float).reshape(-1)[free]
        cov = np.linalg.inv(Sf + np.diag(1.0 / prior**2))
    else:
        gauge = _gauge_basis(problem, parameters)[free]
        q, _ = np.linalg.qr(gauge)
        lam = max(float(np.trace(Sf)) / max(len(Sf), 1), 1e-12)
        projector = np.eye(len(Sf)) - q @ q.T
        cov = projector @ np.linalg.inv(Sf + lam * q @ q.T) @ projector
    full = np.zeros((6 * m, 6 * m))
    full[np.ix_(free, free)] = cov
    return full, seen


def reduced_camera_system(problem: BundleProblem, parameters: BundleParameters, loss_scale_px: float = 1.0,
                          noise_px: float | None = None) -> tuple[np.ndarray, np.ndarray, float]:
    """The images' information on every camera's pose scalars, the points eliminated (Schur complement).

    Returns ``S`` (6m, 6m) in px^2 per squared parameter unit (``J^T J`` with the observations' Huber
    weights at ``loss_scale_px``; divide by ``sigma^2`` for the information), which cameras are observed
    (m,) bool, and ``sigma`` (px): ``noise_px`` or the residuals' median norm / 1.1774 (the median of a 2-D
    Gaussian's norm). Fixed scalars are included (rows for every scalar); the 7 gauge directions are in
    its null space. Needs positions parametrised as centres (``from_measured_poses``).
    """
    if problem.position_parameter != "centre":
        raise ValueError("relative_pose_sigmas needs poses parametrised by their centres")
    m = problem.num_cameras
    r, jc, jp = evaluate(problem, parameters)
    norm = np.linalg.norm(r, axis=1)
    sigma = noise_px if noise_px is not None else max(float(np.median(norm)) / 1.1774, 1e-3)
    w = np.where(norm <= loss_scale_px, 1.0, loss_scale_px / np.maximum(norm, 1e-300))
    cam, pt = problem.camera_index, problem.point_index
    jpose = jc[:, :, :6] * np.sqrt(w)[:, None, None]
    jpt = jp * np.sqrt(w)[:, None, None]
    # blocks of J^T J: U (cameras), V (points), W (one per observation)
    U = np.zeros((m, 6, 6))
    np.add.at(U, cam, np.einsum("kai,kaj->kij", jpose, jpose))
    V = np.zeros((problem.num_points, 3, 3))
    np.add.at(V, pt, np.einsum("kai,kaj->kij", jpt, jpt))
    V += 1e-12 * np.eye(3)  # a point seen along one ray only
    W = np.einsum("kai,kaj->kij", jpose, jpt)
    S = np.zeros((6 * m, 6 * m))
    for c in range(m):
        S[6 * c:6 * c + 6, 6 * c:6 * c + 6] = U[c]
    # S -= W V^-1 W^T with W (6m, 3n) block-sparse (one 6 x 3 block per observation) and V block-diagonal:
    # one sparse product, not a loop over each point's pairs of observations (a python loop per pair of track
    # positions cost 70 ms on a 30-frame dome's few hundred points)
    from scipy.sparse import csr_matrix

    rows = (6 * cam[:, None, None] + np.arange(6)[None, :, None]).repeat(3, axis=2)
    cols = (3 * pt[:, None, None] + np.arange(3)[None, None, :]).repeat(6, axis=1)
    w_mat = csr_matrix((W.ravel(), (rows.ravel(), cols.ravel())), shape=(6 * m, 3 * problem.num_points))
    wv_mat = csr_matrix(((W @ np.linalg.inv(V)[pt]).ravel(), (rows.ravel(), cols.ravel())),
                        shape=(6 * m, 3 * problem.num_points))
    S -= (wv_mat @ w_mat.T).toarray()
    seen = np.bincount(cam, minlength=m) > 0
    return S, seen, sigma



def reduced_gradient(problem: BundleProblem, parameters: BundleParameters, loss_scale_px: float = 1.0) -> np.ndarray:
    """(6m,) the gradient of the Huber-weighted half sum of squared residuals (px^2) over every camera's
    pose scalars with the points eliminated (``g_c - W V^-1 g_p``, the right-hand side of the reduced
    camera system): with :func:`reduced_camera_system` it is the quadratic model of the images' cost in the
    poses alone, at poses that are not the images' own optimum. Fixed scalars included."""
    m = problem.num_cameras
    r, jc, jp = evaluate(problem, parameters)
    norm = np.linalg.norm(r, axis=1)
    w = np.sqrt(np.where(norm <= loss_scale_px, 1.0, loss_scale_px / np.maximum(norm, 1e-300)))
    cam, pt = problem.camera_index, problem.point_index
    jpose, jpt, rw = jc[:, :, :6] * w[:, None, None], jp * w[:, None, None], r * w[:, None]
    grad = np.zeros((m, 6))
    np.add.at(grad, cam, np.einsum("kai,ka->ki", jpose, rw))
    V = np.zeros((problem.num_points, 3, 3))
    np.add.at(V, pt, np.einsum("kai,kaj->kij", jpt, jpt))
    V += 1e-12 * np.eye(3)
    g_point = np.zeros((problem.num_points, 3))
    np.add.at(g_point, pt, np.einsum("kai,ka->ki", jpt, rw))
    W = np.einsum("kai,kaj->kij", jpose, jpt)
    step = np.linalg.solve(V, g_point[..., None])[..., 0]  # V^-1 g_p per point
    np.subtract.at(grad, cam, np.einsum("kij,kj->ki", W, step[pt]))
    return grad.ravel()

def _gauge_basis(problem: BundleProblem, parameters: BundleParameters) -> np.ndarray:
    """(6m, 7) directions in pose space of a common rotation, translation and scale of the whole scene."""
    rot, _, _ = problem.camera_state(parameters.pose)
    centres = parameters.pose[:, 3:]
    m = len(rot)
    G = np.zeros((m, 6, 7))
    # world rotation by omega: R_k exp(-omega) = exp(-R_k omega) R_k, and C_k + omega x C_k
    G[:, :3, :3] = -rot
    G[:, 3:, :3] = -hat(centres - centres.mean(axis=0))
    G[:, 3:, 3:6] = np.eye(3)
    G[:, 3:, 6] = centres - centres.mean(axis=0)
    return G.reshape(6 * m, 7)
