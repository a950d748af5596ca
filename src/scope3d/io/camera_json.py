"""``camera.json``: a camera's model, image size and parameters (pixels; unitless distortion).

::

    {"model": "OPENCV_FISHEYE", "width": 256, "height": 256,
     "fx": 120.1, "fy": 120.3, "cx": 127.6, "cy": 128.2, "k1": 0.02, "k2": -0.01, "k3": 0.003, "k4": -0.001,
     "mask_radius_px": null, "fov_deg": 158.2}

``model`` is a name of :data:`scope3d.sensor.camera_models.MODELS` (COLMAP's ``PINHOLE``, ``OPENCV``,
``FULL_OPENCV``, ``OPENCV_FISHEYE``, or scope3d's ``pinhole_radial_k1k2``); each of the model's parameters
is a key of its own name. A file without ``model`` is a ``pinhole_radial_k1k2`` camera (every camera.json
written before other models existed). ``fov_deg`` is informative and not read.
"""
from __future__ import annotations

import math
from pathlib import Path

from scope3d.errors import InputError
from scope3d.io.json_object import read_json_object
from scope3d.sensor.camera import Camera
from scope3d.sensor.camera_models import DEFAULT_MODEL, MODELS

# every parameter name of any model: one that is not the file's model's is a mistake, not extra data
_ALL_PARAMS = {n for m in MODELS.values() for n in m.param_names}


def camera_to_dict(camera: Camera) -> dict:
    data = {"model": camera.model, "width": camera.width, "height": camera.height}
    # the first six as the Camera holds them (an int stays an int, as camera.json was always written)
    values = [camera.fx, camera.fy, camera.cx, camera.cy, camera.k1, camera.k2, *camera.extra]
    data.update(zip(camera.param_names, values))
    data.update({"mask_radius_px": camera.mask_radius_px, "fov_deg": camera.fov_deg})
    return data


def read_camera_json(path: str | Path) -> Camera:
    """Read ``camera.json`` (pixels; see the module docstring). Problems are InputErrors naming the file."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: camera intrinsics file is missing; scope3d does not guess a camera: calibrate it on "
                         "checkerboard views (`scope3d calibrate`, docs/calibration.md) and put its camera.json here")
    data = read_json_object(path)
    model = data.get("model", DEFAULT_MODEL)
    if not isinstance(model, str) or model not in MODELS:
        raise InputError(f"{path}: unknown camera model {model!r} (known: {', '.join(MODELS)})")
    names = MODELS[model].param_names
    foreign = sorted(k for k in _ALL_PARAMS.intersection(data) if k not in names)
    if foreign:
        raise InputError(f"{path}: {', '.join(foreign)} is not a parameter of the {model} model "
                         f"({len(names)} parameters: {', '.join(names)})")
    keys = ("width", "height", *names)
    missing = [k for k in keys if k not in data]
    if missing:
        raise InputError(f"{path}: missing key(s) {', '.join(missing)} of the {model} model")
    values = {}
    for k in keys:
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
        return Camera.from_params(int(values["width"]), int(values["height"]), model, [values[n] for n in names],
                                  mask_radius_px=None if mask is None else float(mask))
    except ValueError as exc:
        raise InputError(f"{path}: {exc}") from None


def _finite(value: int | float) -> bool:
    try:
        return math.isfinite(value)
    except OverflowError:  # an int beyond float64 range
        return False
