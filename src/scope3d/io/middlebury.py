"""Middlebury multi-view stereo sets (Seitz et al., CVPR 2006): ``*_par.txt`` and its images.

``NAME_par.txt`` holds the number of images on its first line, then one line per image::

    imgname.png k11 k12 k13 k21 k22 k23 k31 k32 k33 r11 r12 r13 r21 r22 r23 r31 r32 r33 t1 t2 t3

with projection ``P = K [R | t]``: ``x_cam = R x_world + t`` (``cam_from_world``), world in metres, image
origin top-left, x right, y down. We take the calibration's pixel coordinates to be scope3d's (origin at
the centre of the top-left pixel); if they meant the pixel corner the principal point is off by 0.5 px,
which no downstream use of this data can resolve. The set's ``README.txt`` gives the object's bounding
box, which is kept in ``dataset.json`` (``bounding_box_mm``) when found.

Published par files print R with anything from ~7 to ~20 digits, so ``R`` is a rotation only up to the
printing's rounding: each R is replaced by the nearest rotation (:func:`scope3d.geometry.rotation.nearest_rotation`,
which refuses matrices farther from every rotation than rounding explains), and ``dataset.json`` records
the largest correction (``source.rotation_orthonormalised_max``, Frobenius norm).

K is taken the same way: a K decomposed from a printed projection matrix keeps a skew (and a third row
off [0 0 1]) of the printing's order, and one camera's per-view K differ by as little. A skew that moves
no pixel by more than :data:`scope3d.sensor.camera.SAME_CALIBRATION_PX` (0.01 px) is zero, and per-view
K that put every pixel within that of the first view's are one camera (whose K is the first view's);
``source.intrinsics_rounding`` records the largest of each. More is refused, naming the line or image.
"""
from __future__ import annotations

import hashlib
import re
from pathlib import Path

import numpy as np

from scope3d import __version__
from scope3d.errors import InputError
from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import nearest_rotation
from scope3d.io.dataset import write_dataset
from scope3d.io.images import read_image
from scope3d.sensor.camera import SAME_CALIBRATION_PX, Camera, calibration_shift_px, without_skew
from scope3d.sensor.pose_tolerance import MeasuredPose, PoseTolerance

MM_PER_M = 1000.0


def read_middlebury_par(par_path: str | Path) -> tuple[list[str], list[np.ndarray], list[Pose], list[float]]:
    """Parse a ``*_par.txt`` file.

    Returns image names, calibration matrices (3, 3) in pixels, poses ``cam_from_world`` with
    translations converted from metres to mm, and for each pose the Frobenius distance between the
    file's R and the rotation used (the rounding of the file). Problems are InputErrors naming the file
    and line.
    """
    path = Path(par_path)
    if not path.is_file():
        raise InputError(f"{path}: Middlebury parameter file is missing")
    try:
        lines = path.read_text(encoding="ascii").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read ({exc})") from None
    rows = [(i, line.split()) for i, line in enumerate(lines, start=1) if line.strip()]
    if not rows:
        raise InputError(f"{path}: file is empty")
    first_line, first = rows[0]
    # more than 18 digits is no image count (and int() refuses strings of over 4300 digits)
    if len(first) != 1 or not first[0].isdigit() or len(first[0]) > 18:
        raise InputError(f"{path} line {first_line}: expected the number of images")
    count = int(first[0])
    if len(rows) - 1 != count:
        raise InputError(f"{path} line {first_line}: says {count} images, the file lists {len(rows) - 1}")
    names, ks, poses, corrections = [], [], [], []
    for number, tokens in rows[1:]:
        where = f"{path} line {number}"
        if len(tokens) != 22:
            raise InputError(f"{where}: expected an image name and 21 numbers (K, R, t), found {len(tokens) - 1}")
        try:
            values = np.array([float(t) for t in tokens[1:]])
        except ValueError:
            raise InputError(f"{where}: K, R and t must be numbers") from None
        if not np.all(np.isfinite(values)):
            raise InputError(f"{where}: NaN or infinite value")
        k, r, t = values[:9].reshape(3, 3), values[9:18].reshape(3, 3), values[18:]
        # the file has no image size: the image the principal point is the centre of stands for it (the
        # import measures again with the real size)
        shift = calibration_shift_px(k, without_skew(k), 2 * abs(k[0, 2]) + 1, 2 * abs(k[1, 2]) + 1) \
            if k[0, 0] > 0 and k[1, 1] > 0 else float("inf")
        if not shift <= SAME_CALIBRATION_PX:
            raise InputError(f"{where}: K must be [[fx 0 cx] [0 fy cy] [0 0 1]] (no skew): its skew and third "
                             f"row move pixels by up to {shift:.3g} px, rounding by at most {SAME_CALIBRATION_PX} px")
        try:
            rotation, correction = nearest_rotation(r)
        except ValueError as exc:
            raise InputError(f"{where}: R is {exc}") from None
        if tokens[0] in names:
            raise InputError(f"{where}: image {tokens[0]} is listed twice")
        try:
            pose = Pose(rotation, t * MM_PER_M)
        except ValueError as exc:  # finite metres, infinite millimetres (t beyond 1.8e305 m)
            raise InputError(f"{where}: t in mm: {exc}") from None
        names.append(tokens[0])
        ks.append(k)
        poses.append(pose)
        corrections.append(correction)
    return names, ks, poses, corrections


def import_middlebury(
    par_path: str | Path,
    out_dir: str | Path,
    *,
    tolerance: PoseTolerance | None = None,
    finish=None,
) -> Path:
    """Import a Middlebury multi-view set (images beside ``par_path``) as a scope3d dataset, in mm.
    finish : see :func:`scope3d.io.dataset.write_dataset`.

    tolerance : reported with every pose; default exact (0), since the gantry calibration is the
    reference. All images must share one K (within :data:`scope3d.sensor.camera.SAME_CALIBRATION_PX` at
    every pixel: the module docstring) and one size. ``dataset.json`` records the provenance (file, its
    SHA-256, the scope3d version, the largest correction that made a printed R a rotation, the skew zeroed
    and the per-view K spread accepted as rounding) and, when ``README.txt`` gives it, the object's
    bounding box in mm. Written atomically: on any error ``out_dir`` is left as it was.
    """
    par_path = Path(par_path)
    names, ks, poses, corrections = read_middlebury_par(par_path)
    sources = [par_path.parent / n for n in names]
    size = None
    for source in sources:
        img = read_image(source)
        if size is None:
            size = img.shape[:2]
        elif img.shape[:2] != size:
            raise InputError(f"{source}: image is {img.shape[1]}x{img.shape[0]}, {names[0]} is {size[1]}x{size[0]}")
    k0 = without_skew(ks[0])
    zeroed = [calibration_shift_px(k, without_skew(k), size[1], size[0]) for k in ks]
    spread = [calibration_shift_px(without_skew(k), k0, size[1], size[0]) for k in ks]
    for name, skew_px, shift_px in zip(names, zeroed, spread):
        if not skew_px <= SAME_CALIBRATION_PX:  # the reader's check, with the image's real size
            raise InputError(f"{par_path}: image {name}: K's skew and third row move pixels by up to {skew_px:.3g} px, "
                             f"rounding by at most {SAME_CALIBRATION_PX} px")
        if not shift_px <= SAME_CALIBRATION_PX:
            raise InputError(f"{par_path}: image {name} has a different K from {names[0]} (pixels up to "
                             f"{shift_px:.3g} px apart, rounding {SAME_CALIBRATION_PX} px at most); "
                             "a scope3d dataset has one camera")
    camera = Camera(size[1], size[0], k0[0, 0], k0[1, 1], k0[0, 2], k0[1, 2])
    tolerance = PoseTolerance.exact() if tolerance is None else tolerance
    metadata = {
        "source": {
            "format": "middlebury-par",
            "path": str(par_path.resolve()),
            "sha256": hashlib.sha256(par_path.read_bytes()).hexdigest(),
            "world_unit": "m",
            "scale_to_mm": MM_PER_M,
            "rotation_orthonormalised_max": max(corrections),
            "intrinsics_rounding": {"tolerance_px": SAME_CALIBRATION_PX,
                                    "skew_max_px": float(max(abs(k[0, 1]) for k in ks)),
                                    "skew_and_third_row_shift_max_px": max(zeroed),
                                    "per_view_k_shift_max_px": max(spread)},
            "imported_by": f"scope3d {__version__}",
            "reference": "Seitz, Curless, Diebel, Scharstein, Szeliski: A comparison and evaluation of "
                         "multi-view stereo reconstruction algorithms, CVPR 2006",
        }
    }
    box = read_middlebury_bounding_box(par_path.parent / "README.txt")
    if box is not None:
        metadata["bounding_box_mm"] = (box * MM_PER_M).tolist()
    measured = [MeasuredPose(p, tolerance) for p in poses]
    return write_dataset(out_dir, camera, sources, measured, names=names, metadata=metadata, finish=finish)


_TRIPLE = re.compile(r"\(\s*([-+0-9.eE]+)\s+([-+0-9.eE]+)\s+([-+0-9.eE]+)\s*\)")


def read_middlebury_bounding_box(readme_path: str | Path) -> np.ndarray | None:
    """(2, 3) min and max corners (metres) of the object from a Middlebury README, or None."""
    path = Path(readme_path)
    if not path.is_file():
        return None
    text = path.read_text(encoding="latin-1")
    at = text.lower().find("bounding box")
    if at < 0:
        return None
    triples = _TRIPLE.findall(text[at:])[:2]
    if len(triples) < 2:
        return None
    try:
        box = np.array(triples, dtype=float)
    except ValueError:  # the pattern also matches signs and dots that are no number ('--5', '.')
        return None
    if not np.all(np.isfinite(box)) or np.any(box[0] > box[1]):
        return None
    return box


__all__ = ["import_middlebury", "read_middlebury_bounding_box", "read_middlebury_par"]
