"""Similarity transforms (scale, rotation, translation) and their least-squares fit."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scope3d.geometry.rotation import matrix_to_rotvec, rotvec_to_matrix


@dataclass(frozen=True)
class Similarity:
    """``X' = scale * rotation @ (X - origin) + target`` (mm): a 7-DoF similarity written about a pivot.

    origin : (3,) the pivot in the source frame; target : (3,) where it goes. Written this way, a fraction
    of the transform (:meth:`fraction`) moves the pivot along a straight line and turns and scales about it.
    """

    scale: float
    rotation: np.ndarray
    origin: np.ndarray
    target: np.ndarray

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Transform points (..., 3) mm."""
        return self.scale * (np.asarray(points, float) - self.origin) @ self.rotation.T + self.target

    def apply_to_cam_from_world(self, rotation: np.ndarray, translation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A camera ``x_cam = R X + t`` of the source frame, in the target frame: the same image of the
        transformed scene, camera coordinates scaled by ``scale``. Returns (R', t')."""
        r_new = rotation @ self.rotation.T
        centre = -rotation.T @ translation
        return r_new, -r_new @ self.apply(centre)

    def fraction(self, alpha: float) -> "Similarity":
        """The similarity ``alpha`` of the way from the identity (0) to this one (1): scale ``s^alpha``, rotation
        by ``alpha`` of its angle about its axis, pivot moved by ``alpha`` of the way."""
        return Similarity(float(self.scale**alpha), rotvec_to_matrix(alpha * matrix_to_rotvec(self.rotation)),
                          self.origin, self.origin + alpha * (self.target - self.origin))


def fit_similarity(source: np.ndarray, target: np.ndarray, *, with_scale: bool = True) -> Similarity:
    """Least-squares similarity taking points ``source`` (N, 3) onto ``target`` (N, 3) (Umeyama 1991);
    ``with_scale=False``: the rigid fit (Kabsch), scale held at 1."""
    a0, b0 = source.mean(axis=0), target.mean(axis=0)
    a, b = source - a0, target - b0
    U, S, Vt = np.linalg.svd(b.T @ a)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    scale = float(np.trace(np.diag(S) @ D) / np.sum(a * a)) if with_scale else 1.0
    return Similarity(scale, U @ D @ Vt, a0, b0)
