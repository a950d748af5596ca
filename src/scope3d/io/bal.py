"""Bundle Adjustment in the Large (BAL) problem files: read and write (their bounds files:
:mod:`scope3d.io.bal_bounds`)."""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from scope3d.errors import InputError
from scope3d.geometry.rotation import rotvec_to_matrix


@dataclass
class BALProblem:
    """A BAL problem as stored in the file.

    camera_index, point_index : (K,) int. observations_px : (K, 2), origin at the image centre, y up.
    cameras : (m, 9) ``(rx, ry, rz, tx, ty, tz, f, k1, k2)``. points : (n, 3).
    """

    camera_index: np.ndarray
    point_index: np.ndarray
    observations_px: np.ndarray
    cameras: np.ndarray
    points: np.ndarray

    @property
    def num_observations(self) -> int:
        return int(self.observations_px.shape[0])

    def cost(self) -> float:
        """0.5 sum |r|^2 in the BAL convention, computed directly from the file's numbers."""
        cam = self.cameras[self.camera_index]
        rot = rotvec_to_matrix(cam[:, :3])
        p = np.einsum("kij,kj->ki", rot, self.points[self.point_index]) + cam[:, 3:6]
        xy = -p[:, :2] / p[:, 2:3]
        r2 = np.sum(xy * xy, axis=1)
        pix = cam[:, 6:7] * (1.0 + cam[:, 7:8] * r2[:, None] + cam[:, 8:9] * r2[:, None] ** 2) * xy
        return 0.5 * float(np.sum((pix - self.observations_px) ** 2))


MAX_ROTATION_COMPONENT_RAD = 2.0**52  # a float's spacing is 1 rad here: the angle modulo 2 pi is noise


def read_bal(path: str | os.PathLike) -> BALProblem:
    """Read a BAL text file (uncompressed). Raises InputError, naming the file, on a malformed file.

    Rotations are rotation vectors: any finite one is a rotation however few digits it is printed
    with, so unlike a printed matrix or quaternion there is no rounding to absorb; but a component of
    2^52 rad or more is refused: there a float's spacing reaches 1 rad, so the digits name no definite
    rotation, and beyond 1e154 rad Rodrigues' formula overflows to NaN (found by the long fuzz run).
    """
    text = read_ascii_text(path, "a BAL file")
    try:
        values = np.array(text.split(), dtype=float)
    except ValueError as exc:
        raise InputError(f"{path}: not a BAL file ({exc})") from None
    if values.size < 3:
        raise InputError(f"{path}: not a BAL file (no header)")
    head = values[:3]
    # checked before int(): int(nan) and int(inf) raise, and a header is three whole counts >= 1
    if not np.all(np.isfinite(head)) or np.any(head != np.round(head)) or head.min() < 1:
        raise InputError(f"{path}: bad BAL header {head.tolist()}")
    m, n, k = (int(v) for v in head)
    expected = 3 + 4 * k + 9 * m + 3 * n
    if values.size != expected:
        raise InputError(f"{path}: expected {expected} numbers for {m} cameras, {n} points, {k} observations, "
                         f"found {values.size}")
    obs = values[3:3 + 4 * k].reshape(k, 4)
    cams = values[3 + 4 * k:3 + 4 * k + 9 * m].reshape(m, 9)
    pts = values[3 + 4 * k + 9 * m:].reshape(n, 3)
    for what, block in (("observation", obs), ("camera", cams), ("point", pts)):
        bad = np.flatnonzero(~np.all(np.isfinite(block), axis=1))
        if bad.size:
            raise InputError(f"{path}: {what} {bad[0]} (0-based) has NaN or infinite values")
    bad = np.flatnonzero(np.abs(cams[:, :3]).max(axis=1) >= MAX_ROTATION_COMPONENT_RAD)
    if bad.size:
        raise InputError(f"{path}: camera {bad[0]} (0-based): a rotation vector component of "
                         f"{np.abs(cams[bad[0], :3]).max():.3g} rad names no definite rotation "
                         f"(at 2^52 rad and beyond, a float's spacing is 1 rad or more)")
    bad = np.flatnonzero(np.any(obs[:, :2] != np.round(obs[:, :2]), axis=1))
    if bad.size:
        raise InputError(f"{path}: observation {bad[0]} (0-based): camera and point indices must be integers")
    bad = np.flatnonzero((obs[:, 0] < 0) | (obs[:, 0] >= m) | (obs[:, 1] < 0) | (obs[:, 1] >= n))
    if bad.size:
        raise InputError(f"{path}: observation {bad[0]} (0-based): camera {obs[bad[0], 0]:g} or point "
                         f"{obs[bad[0], 1]:g} is not in the file ({m} cameras, {n} points)")
    return BALProblem(obs[:, 0].astype(np.int64), obs[:, 1].astype(np.int64), obs[:, 2:].copy(), cams, pts)


def read_ascii_text(path: str | os.PathLike, what: str) -> str:
    """The whole file as text; a missing file, or a byte that is not ASCII, is an InputError naming it.

    BAL and bounds files hold numbers and keywords only: a non-ASCII byte means a wrong or damaged file.
    """
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror or exc})") from None
    try:
        return data.decode("ascii")
    except UnicodeDecodeError as exc:
        raise InputError(f"{path}: not {what} (byte {exc.start} is {data[exc.start]:#04x}, not ASCII text)") from None


def write_bal(path: str | os.PathLike, bal: BALProblem) -> None:
    """Write a BAL text file (atomically)."""
    from scope3d.utils.atomic import atomic_file

    with atomic_file(path) as handle:
        handle.write(f"{bal.cameras.shape[0]} {bal.points.shape[0]} {bal.num_observations}\n")
        obs = np.column_stack([bal.camera_index, bal.point_index, bal.observations_px])
        np.savetxt(handle, obs, fmt=["%d", "%d", "%.6e", "%.6e"])
        np.savetxt(handle, bal.cameras.reshape(-1, 1), fmt="%.16e")
        np.savetxt(handle, bal.points.reshape(-1, 1), fmt="%.16e")
