"""``map_points.npz``: the map's 3-D points with what localization needs to find them in a new frame.

Written by ``scope3d map`` beside ``points.ply``; read by :mod:`scope3d.sfm.localization`. Arrays:

* ``xyz_mm`` : (N, 3) float64, points in the map's world frame, mm.
* ``descriptors`` : (N, 128) float32, one representative SIFT descriptor per point
  (:func:`scope3d.feature.tracks.track_descriptors`).
* ``n_observations`` : (N,) int32, frames the point was seen in (its track length).
* ``colors`` : (N, 3) uint8, mean RGB.

Optional (maps written before issue 34 lack them; localization then matches the representatives only):

* ``observation_descriptors`` : (M, 128), every observation's own descriptor (uint8 in the file when the
  values are whole numbers in 0-255, as OpenCV's SIFT gives them; float32 in memory).
* ``observation_point`` : (M,) int32, the point each of those observes (an index into ``xyz_mm``).

A new frame between two mapped views often resembles one observation of a point and not the other, and the
representative is only one of them: on the Middlebury temple (even views mapped, 45 deg apart) the odd
views' global matches held 5-14 right ones against the representatives where a search near the true pose
found 71-132 (docs/localization.md, "Real photographs").
"""
from __future__ import annotations

import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from scope3d.errors import InputError
from scope3d.utils.atomic import atomic_path

MAP_POINTS_FILE = "map_points.npz"
ARRAY_NAMES = ("xyz_mm", "descriptors", "n_observations", "colors")
OPTIONAL_ARRAY_NAMES = ("observation_descriptors", "observation_point")
# Deflate cannot shrink data by more than ~1032:1 (RFC 1951: a 258-byte match per 2 bits at best); a
# member claiming more is lying, and believing it would allocate its claim.
DEFLATE_MAX_RATIO = 1032


@dataclass(frozen=True)
class MapPoints:
    """Map points for localization (see the module docstring for shapes and units)."""

    xyz_mm: np.ndarray
    descriptors: np.ndarray
    n_observations: np.ndarray
    colors: np.ndarray
    observation_descriptors: np.ndarray | None = None
    observation_point: np.ndarray | None = None

    def __post_init__(self) -> None:
        n = len(self.xyz_mm)
        if (np.shape(self.xyz_mm) != (n, 3) or np.shape(self.descriptors) != (n, 128)
                or np.shape(self.n_observations) != (n,) or np.shape(self.colors) != (n, 3)):
            raise ValueError("map points need xyz (N, 3), descriptors (N, 128), n_observations (N,), colors (N, 3)")
        if (self.observation_descriptors is None) != (self.observation_point is None):
            raise ValueError("observation_descriptors and observation_point come together")
        if self.observation_point is not None:
            m = len(self.observation_point)
            if np.shape(self.observation_descriptors) != (m, 128) or np.shape(self.observation_point) != (m,):
                raise ValueError("observation descriptors need (M, 128) and their points (M,)")
            if m and not (0 <= int(np.min(self.observation_point)) and int(np.max(self.observation_point)) < n):
                raise ValueError(f"observation_point must index the {n} points")

    def __len__(self) -> int:
        return len(self.xyz_mm)


# zlib level 1 rather than np.savez_compressed's 6: on the dome map's 6,279 points 0.09 s instead of
# 0.46 s of the map's outputs, for a file 16 % larger (1.25 MB instead of 1.08 MB); np.load reads either
ZIP_COMPRESS_LEVEL = 1


def write_map_points(path: str | Path, points: MapPoints) -> None:
    """Write ``map_points.npz`` (an .npz archive any ``np.load`` reads), atomically."""
    arrays = {"xyz_mm": points.xyz_mm.astype(np.float64), "descriptors": points.descriptors.astype(np.float32),
              "n_observations": points.n_observations.astype(np.int32), "colors": points.colors.astype(np.uint8)}
    if points.observation_point is not None:
        d = points.observation_descriptors
        # OpenCV's SIFT values are whole numbers in 0-255: stored as bytes, losslessly (the dome's 19,872
        # observations: the file 4.8 -> 3.2 MB, its writing 0.48 -> 0.30 s at load 15; 1.2 MB without them)
        lossless = d.size == 0 or (np.all(d == np.round(d)) and d.min() >= 0 and d.max() <= 255)
        arrays["observation_descriptors"] = d.astype(np.uint8 if lossless else np.float32)
        arrays["observation_point"] = points.observation_point.astype(np.int32)
    with atomic_path(Path(path)) as tmp:
        with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED, compresslevel=ZIP_COMPRESS_LEVEL) as archive:
            for name, array in arrays.items():
                with archive.open(f"{name}.npy", "w", force_zip64=True) as member:
                    np.lib.format.write_array(member, array, allow_pickle=False)


def read_map_points(path: str | Path) -> MapPoints:
    """Read ``map_points.npz`` (a file, or a map folder holding one); every problem is one InputError."""
    path = Path(path)
    if path.is_dir():
        path = path / MAP_POINTS_FILE
    if not path.is_file():
        raise InputError(f"{path}: no map points (run `scope3d map` first; it writes {MAP_POINTS_FILE})")
    try:
        arrays = _read_arrays(path)
    # RuntimeError: zipfile's refusal of a member flagged as encrypted (found by the long atheris run)
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, NotImplementedError, zlib.error, RuntimeError) as exc:
        raise InputError(f"{path}: not a readable .npz file ({exc})") from None
    if any(a.dtype.kind not in "biuf" for a in arrays.values()):
        raise InputError(f"{path}: arrays must hold numbers, found "
                         f"{', '.join(f'{k} {a.dtype}' for k, a in arrays.items())}")
    if not all(np.all(np.isfinite(arrays[k])) for k in ("xyz_mm", "descriptors", "observation_descriptors")
               if k in arrays):
        raise InputError(f"{path}: points or descriptors hold NaN or infinite values")
    observations = {}
    if "observation_point" in arrays:
        # one without the other is refused by MapPoints (an empty stand-in has the wrong shape)
        observations = {"observation_descriptors": arrays.get("observation_descriptors", np.zeros((0, 128))),
                        "observation_point": arrays["observation_point"].astype(np.int64)}
        observations["observation_descriptors"] = observations["observation_descriptors"].astype(np.float32)
    try:
        return MapPoints(arrays["xyz_mm"].astype(np.float64), arrays["descriptors"].astype(np.float32),
                         arrays["n_observations"].astype(np.int32), arrays["colors"].astype(np.uint8), **observations)
    except ValueError as exc:
        raise InputError(f"{path}: {exc}") from None


def _read_arrays(path: Path) -> dict[str, np.ndarray]:
    """The four arrays of the archive (and the optional ones it holds), each checked against the archive before it is allocated: the shape
    in a ``.npy`` header must match the member's size, and that size what its compressed bytes can hold."""
    arrays = {}
    with zipfile.ZipFile(path) as archive:
        members = {info.filename: info for info in archive.infolist()}
        for name in ARRAY_NAMES + OPTIONAL_ARRAY_NAMES:
            info = members.get(f"{name}.npy")
            if info is None and name in OPTIONAL_ARRAY_NAMES:
                continue
            if info is None:
                raise InputError(f"{path}: missing array {name}")
            packed = info.compress_size if info.compress_type != zipfile.ZIP_STORED else info.file_size
            if info.file_size > DEFLATE_MAX_RATIO * packed + 1024:
                raise InputError(f"{path}: {name}.npy claims {info.file_size} bytes from {info.compress_size} "
                                 "compressed: more than deflate can hold")
            with archive.open(info) as member:
                version = np.lib.format.read_magic(member)
                read_header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                               else np.lib.format.read_array_header_2_0)
                shape, fortran, dtype = read_header(member)
                header_bytes = member.tell()
                count = int(np.prod(shape, dtype=object))
                if dtype.hasobject or count * dtype.itemsize != info.file_size - header_bytes:
                    raise InputError(f"{path}: {name}.npy's header says {shape} {dtype}, its data holds "
                                     f"{info.file_size - header_bytes} bytes")
                data = member.read(info.file_size - header_bytes)
            arrays[name] = np.frombuffer(data, dtype=dtype).reshape(shape, order="F" if fortran else "C")
    return arrays
