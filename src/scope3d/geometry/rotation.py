"""Rotation maths shared by every layer.

Conventions
-----------
* A rotation vector ``w`` (3,) in radians encodes ``R = exp([w]x)`` (Rodrigues).
* Quaternions are scalar-last ``(x, y, z, w)``, as in :mod:`scipy.spatial.transform`.
* Every function is vectorised over a leading batch axis where the docstring says ``(N, ...)``.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

#: below this angle (rad) the rotation's series replace sin(t) / t and (1 - cos(t)) / t^2 (their round-off
#: there exceeds the series' truncation); the compiled pose kernels take the same value
SMALL_ANGLE_RAD = 1e-8


# Rotations and quaternions read from text files carry the file's rounding. An entry |r| <= 1 printed to
# d significant digits is off by at most eps = 0.5e-d, so a printed rotation matrix lies within
# sqrt(9) eps = 1.5e-d (Frobenius) of the true rotation, hence at most that far from the nearest one, and
# a printed quaternion's norm is within sqrt(4) eps = 1e-d of 1. 1e-3 accepts every matrix printed with 4
# or more digits (and typical 3-digit ones) and every quaternion with 3 or more, with room for the
# rounding of whatever computed them. A matrix farther than that from every rotation is not a rounded
# rotation but something else: scaled, sheared, a mistyped entry, columns of another matrix.
ROTATION_ROUNDING_TOLERANCE = 1e-3


def hat(v: np.ndarray) -> np.ndarray:
    """Skew-symmetric matrices ``[v]x`` such that ``hat(v) @ x == cross(v, x)``.

    v : (..., 3) float  ->  (..., 3, 3) float
    """
    v = np.asarray(v, dtype=float)
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1] = -v[..., 2]
    out[..., 0, 2] = v[..., 1]
    out[..., 1, 0] = v[..., 2]
    out[..., 1, 2] = -v[..., 0]
    out[..., 2, 0] = -v[..., 1]
    out[..., 2, 1] = v[..., 0]
    return out


def rotvec_to_matrix(rotvec: np.ndarray) -> np.ndarray:
    """Rodrigues' formula. rotvec : (..., 3) rad  ->  (..., 3, 3)."""
    rotvec = np.asarray(rotvec, dtype=float)
    theta = np.linalg.norm(rotvec, axis=-1)[..., None, None]
    k = hat(rotvec)
    small = theta < SMALL_ANGLE_RAD
    theta_safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(theta_safe) / theta_safe)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(theta_safe)) / theta_safe**2)
    eye = np.broadcast_to(np.eye(3), k.shape)
    return eye + a * k + b * (k @ k)


def matrix_to_rotvec(matrix: np.ndarray) -> np.ndarray:
    """Inverse of :func:`rotvec_to_matrix`. matrix : (..., 3, 3) -> (..., 3) rad, angle in [0, pi]."""
    matrix = np.asarray(matrix, dtype=float)
    flat = matrix.reshape(-1, 3, 3)
    out = Rotation.from_matrix(flat).as_rotvec()
    return out.reshape(matrix.shape[:-2] + (3,))


def quaternion_to_matrix(quat_xyzw: np.ndarray) -> np.ndarray:
    """(..., 4) scalar-last unit quaternion -> (..., 3, 3)."""
    quat_xyzw = np.asarray(quat_xyzw, dtype=float)
    out = Rotation.from_quat(quat_xyzw.reshape(-1, 4)).as_matrix()
    return out.reshape(quat_xyzw.shape[:-1] + (3, 3))


def matrix_to_quaternion(matrix: np.ndarray) -> np.ndarray:
    """(..., 3, 3) -> (..., 4) scalar-last unit quaternion with w >= 0."""
    matrix = np.asarray(matrix, dtype=float)
    q = Rotation.from_matrix(matrix.reshape(-1, 3, 3)).as_quat()
    q = np.where(q[:, 3:4] < 0, -q, q)
    return q.reshape(matrix.shape[:-2] + (4,))


def nearest_rotation(matrix: np.ndarray) -> tuple[np.ndarray, float]:
    """The rotation nearest to a (3, 3) matrix that should be one but was rounded, and how far it was.

    Returns ``(R, distance)``: ``R`` orthonormal with det +1 (the orthogonal polar factor, from the SVD),
    ``distance = ||matrix - R||_F``. Raises ValueError, saying why, when ``matrix`` has NaN or infinite
    entries, is a reflection (det < 0), or is farther than :data:`ROTATION_ROUNDING_TOLERANCE` from every
    rotation. Messages
    start with "not a rotation matrix", to follow e.g. "R is".
    """
    m = np.asarray(matrix, dtype=float).reshape(3, 3)
    if not np.all(np.isfinite(m)):
        raise ValueError("not a rotation matrix: it has NaN or infinite entries")
    det = float(np.linalg.det(m))
    if det < 0:
        raise ValueError(f"not a rotation matrix: it is a reflection (determinant {det:.4g})")
    u, sigma, vt = np.linalg.svd(m)
    # det(m) >= 0, so det(u @ vt) = +1 unless m is singular; the last singular value then takes the sign.
    d = np.array([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    distance = float(np.linalg.norm(sigma - d))
    if distance > ROTATION_ROUNDING_TOLERANCE:
        raise ValueError(f"not a rotation matrix: it is {distance:.3g} from the nearest rotation "
                         f"(Frobenius norm; rounding explains at most {ROTATION_ROUNDING_TOLERANCE:g})")
    return (u * d) @ vt, distance


def normalised_quaternion(quat: np.ndarray) -> tuple[np.ndarray, float]:
    """A (4,) quaternion that should be unit but was rounded, scaled to unit length, and ``| |q| - 1 |``.

    The component order is kept. Raises ValueError, saying why, when ``quat`` has NaN or infinite
    components or its norm is farther than :data:`ROTATION_ROUNDING_TOLERANCE` from 1 (a zero
    quaternion, a typo). Messages start with "not", to follow e.g. "quaternion is".
    """
    q = np.asarray(quat, dtype=float).reshape(4)
    if not np.all(np.isfinite(q)):
        raise ValueError("not finite (NaN or infinite components)")
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > ROTATION_ROUNDING_TOLERANCE:
        raise ValueError(f"not unit length (norm {norm:.4g}; rounding explains 1 +- "
                         f"{ROTATION_ROUNDING_TOLERANCE:g})")
    return q / norm, abs(norm - 1.0)


def so3_left_jacobian(rotvec: np.ndarray) -> np.ndarray:
    """Left Jacobian of SO(3), ``J_l(w)``, such that ``exp(w + d) ~= exp(J_l(w) d) exp(w)``.

    It gives the exact derivative of a rotated vector with respect to the rotation vector:
    ``d(exp(w) y)/dw = -[exp(w) y]x J_l(w)``. rotvec : (..., 3) -> (..., 3, 3).
    """
    rotvec = np.asarray(rotvec, dtype=float)
    theta = np.linalg.norm(rotvec, axis=-1)[..., None, None]
    k = hat(rotvec)
    small = theta < 1e-5
    theta_safe = np.where(small, 1.0, theta)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(theta_safe)) / theta_safe**2)
    c = np.where(small, 1.0 / 6.0 - theta**2 / 120.0, (theta_safe - np.sin(theta_safe)) / theta_safe**3)
    eye = np.broadcast_to(np.eye(3), k.shape)
    return eye + b * k + c * (k @ k)


def rotation_angle(matrix: np.ndarray) -> np.ndarray:
    """Angle (rad, in [0, pi]) of rotation matrices, (..., 3, 3) -> (...), accurate over the whole range.

    ``arccos((trace - 1) / 2)`` cannot resolve angles below ~sqrt(2 eps) = 2.1e-8 rad (the cosine of such
    an angle rounds to 1), so two equal rotations came out 2e-8 rad apart or not depending on the last bit
    of a matrix product. Here the sine comes from the skew-symmetric part, ``sin(angle) = |vee(R - R^T)| / 2``,
    and the cosine from the trace: ``atan2`` of the two is accurate to a few eps (absolute) everywhere,
    near 0 and near pi alike, since each part carries only rounding of order eps in the entries.
    """
    m = np.asarray(matrix, dtype=float)
    skew = np.stack([m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], axis=-1)
    sin = 0.5 * np.linalg.norm(skew, axis=-1)
    cos = 0.5 * (np.trace(m, axis1=-2, axis2=-1) - 1.0)
    return np.arctan2(sin, cos)


def rotation_angle_between(r_a: np.ndarray, r_b: np.ndarray) -> np.ndarray:
    """Geodesic angle (rad, in [0, pi]) between rotation matrices, (..., 3, 3) each -> (...);
    accurate near 0 and pi (:func:`rotation_angle`)."""
    return rotation_angle(np.swapaxes(np.asarray(r_a, dtype=float), -1, -2) @ np.asarray(r_b, dtype=float))


def look_at(centre: np.ndarray, target: np.ndarray, up: np.ndarray = (0.0, -1.0, 0.0)) -> np.ndarray:
    """Rotation ``cam_from_world`` of a camera at ``centre`` whose optical axis (+z) points at ``target``.

    The camera's +y axis (image down) is chosen as close as possible to ``up`` (world), so that
    the default ``(0, -1, 0)`` gives images with world +y pointing up in the picture.
    centre, target : (3,) mm  ->  (3, 3).
    """
    z = np.asarray(target, float) - np.asarray(centre, float)
    norm = np.linalg.norm(z)
    if norm == 0:
        raise ValueError("look_at: camera centre and target coincide")
    z /= norm
    up = np.asarray(up, float)
    y = up - np.dot(up, z) * z
    if np.linalg.norm(y) < 1e-9:  # up parallel to the optical axis: pick any perpendicular
        y = np.cross(z, [1.0, 0.0, 0.0])
        if np.linalg.norm(y) < 1e-9:
            y = np.cross(z, [0.0, 1.0, 0.0])
    y /= np.linalg.norm(y)
    x = np.cross(y, z)
    return np.stack([x, y, z])


def slerp_rotations(r_a: np.ndarray, r_b: np.ndarray, fraction: float) -> np.ndarray:
    """Spherical interpolation between two rotation matrices; fraction 0 -> r_a, 1 -> r_b."""
    key = Rotation.from_matrix(np.stack([r_a, r_b]))
    return Slerp([0.0, 1.0], key)([float(fraction)]).as_matrix()[0]
