"""``camera.json``: the pinhole + k1, k2 camera model of a dataset."""
from __future__ import annotations

import json
import math
from pathlib import Path

from scope3d.errors import InputError
from scope3d.sensor.camera import Camera

CAMERA_KEYS = ("width", "height", "fx", "fy", "cx", "cy", "k1", "k2")


def camera_to_dict(camera: Camera) -> dict:
    return {
        "model": "pinhole_radial_k1k2",
        "width": camera.width, "height": camera.height,
        "fx": camera.fx, "fy": camera.fy, "cx": camera.cx, "cy": camera.cy,
        "k1": camera.k1, "k2": camera.k2, "mask_radius_px": camera.mask_radius_px,
        "fov_deg": camera.fov_deg,
    }


def read_camera_json(path: str | Path) -> Camera:
    """Read ``camera.json`` (pixels; see the module docstring). Problems are InputErrors naming the file."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: camera intrinsics file is missing; scope3d does not guess a camera: calibrate it on "
                         "checkerboard views (`scope3d calibrate`, docs/calibration.md) and put its camera.json here")
    data = _read_json_object(path)
    missing = [k for k in CAMERA_KEYS if k not in data]
    if missing:
        raise InputError(f"{path}: missing key(s) {', '.join(missing)}")
    values = {}
    for k in CAMERA_KEYS:
        # bool is an int subclass in Python; "width": true is a mistake, not 1 pixel.
        if isinstance(data[k], bool) or not isinstance(data[k], (int, float)):
            raise InputError(f"{path}: {k} = {data[k]!r} is not a number")
        try:
            values[k] = float(data[k])
        except OverflowError:  # a JSON integer beyond float64 range
            raise InputError(f"{path}: {k} is too large") from None
    bad = [k for k, v in values.items() if not math.isfinite(v)]
    if bad:
        raise InputError(f"{path}: {', '.join(bad)} is NaN or infinite")
    for k in ("width", "height"):
        if values[k] != int(values[k]):
            raise InputError(f"{path}: {k} = {data[k]} is not a whole number of pixels")
    mask = data.get("mask_radius_px")
    if mask is not None and (isinstance(mask, bool) or not isinstance(mask, (int, float)) or not _finite(mask)):
        raise InputError(f"{path}: mask_radius_px = {mask!r} must be a finite number or null")
    try:
        return Camera(
            int(values["width"]), int(values["height"]), values["fx"], values["fy"], values["cx"], values["cy"],
            values["k1"], values["k2"], None if mask is None else float(mask),
        )
    except ValueError as exc:
        raise InputError(f"{path}: {exc}") from None


def _finite(value: int | float) -> bool:
    try:
        return math.isfinite(value)
    except OverflowError:  # an int beyond float64 range
        return False


def _read_json_object(path: Path) -> dict:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise InputError(f"{path}: not valid JSON ({exc.msg} at line {exc.lineno})") from None
    except (UnicodeDecodeError, OSError) as exc:
        raise InputError(f"{path}: cannot read ({exc})") from None
    except ValueError as exc:  # an integer of more than 4300 digits
        raise InputError(f"{path}: not valid JSON ({exc})") from None
    except RecursionError:
        raise InputError(f"{path}: not valid JSON (arrays or objects nested too deeply)") from None
    if not isinstance(data, dict):
        raise InputError(f"{path}: expected a JSON object {{...}}, found {type(data).__name__}")
    return data
