"""``hand_eye.json``, as ``scope3d calibrate-hand-eye`` writes it: the camera's pose on the robot's flange.

The key read is ``flange_from_cam``: ``{"rotation": 3x3, "translation_mm": [x, y, z]}``, the transform taking
a point from the camera's frame to the flange's (so the camera centre in flange coordinates is its
translation). A camera's pose in the robot base is then ``base_from_cam = base_from_flange @ flange_from_cam``.
Other keys (residuals, tolerance, ``cam_from_flange``) are the calibration's report and are not read.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from scope3d.errors import InputError
from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import nearest_rotation
from scope3d.io.json_object import read_json_object


def read_hand_eye_json(path: str | Path) -> Pose:
    """``flange_from_cam`` from a ``hand_eye.json``; InputError naming the file for anything malformed
    (a missing key, a non-numeric or non-finite entry, a matrix that is not a rounded rotation)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: hand-eye file is missing (`scope3d calibrate-hand-eye` writes hand_eye.json)")
    data = read_json_object(path)
    block = data.get("flange_from_cam")
    if not isinstance(block, dict):
        raise InputError(f"{path}: no 'flange_from_cam' object (the camera's pose on the flange)")
    rotation = _array(path, block, "rotation", (3, 3))
    translation = _array(path, block, "translation_mm", (3,))
    try:
        rotation, _ = nearest_rotation(rotation)
    except ValueError as exc:
        raise InputError(f"{path}: flange_from_cam.rotation is {exc}") from None
    return Pose(rotation, translation)


def _array(path: Path, block: dict, key: str, shape: tuple[int, ...]) -> np.ndarray:
    if key not in block:
        raise InputError(f"{path}: flange_from_cam has no '{key}'")
    value = block[key]
    try:
        # bool is an int subclass; true is a mistake, not 1
        if _has_bool(value):
            raise ValueError
        out = np.array(value, dtype=float)
    except (ValueError, TypeError, OverflowError):
        raise InputError(f"{path}: flange_from_cam.{key} is not an array of numbers") from None
    if out.shape != shape:
        raise InputError(f"{path}: flange_from_cam.{key} has shape {list(out.shape)}, expected {list(shape)}")
    if not np.all(np.isfinite(out)):
        raise InputError(f"{path}: flange_from_cam.{key} has NaN or infinite entries")
    return out


def _has_bool(value) -> bool:
    if isinstance(value, bool):
        return True
    return isinstance(value, list) and any(_has_bool(v) for v in value)
