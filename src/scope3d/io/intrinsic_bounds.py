"""``intrinsic_bounds.json``: a box on the intrinsics ``(fx, fy, cx, cy, k1, k2)`` for bundle adjustment.

Written by ``scope3d calibrate`` (value +- k sigma of the calibration) and read by ``scope3d map`` and
``scope3d bundle-adjust`` (``--intrinsic-bounds``), which let the intrinsics move inside the box (BCBA,
reference eq. 6.2 and sec. 6.3, where the field of view was known only as 50-56 deg)::

    {"model": "pinhole_radial_k1k2", "k_sigma": 3.0,
     "fx": {"value": 228.6, "std": 0.09, "lower": 228.3, "upper": 228.9}, ... "k2": {...}}

Only ``lower`` and ``upper`` are required per parameter; a parameter left out is held fixed by the reader's
caller. Units: pixels for fx, fy, cx, cy; unitless for the distortion coefficients. ``scope3d calibrate
--model`` writes the bounds of any camera model (``model`` names it, one entry per parameter of
:mod:`scope3d.sensor.camera_models`). ``scope3d map`` reads the bounds of every parameter of its camera's model
(``names``: fx, fy, cx, cy, k1, k2, then the model's later ones, e.g. OPENCV's p1, p2, the fisheye's k3, k4);
``scope3d bundle-adjust`` those of ``(fx, fy, cx, cy, k1, k2)``.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from scope3d.errors import InputError
from scope3d.io.json_object import read_json_object
from scope3d.sensor.camera import INTRINSIC_NAMES
from scope3d.sensor.camera_models import DEFAULT_MODEL
from scope3d.utils.jsonio import write_json


def write_intrinsic_bounds(path: str | Path, values: np.ndarray, std: np.ndarray, k_sigma: float, *,
                           source: str = "", model: str = DEFAULT_MODEL,
                           names: tuple[str, ...] = INTRINSIC_NAMES) -> None:
    """values, std : (P,) the model's parameters (default ``(fx, fy, cx, cy, k1, k2)``) and their standard
    deviations; names : the parameters' names in that order."""
    values, std = np.asarray(values, float), np.asarray(std, float)
    if not len(names) == len(values) == len(std):
        raise ValueError(f"{len(names)} names, {len(values)} values and {len(std)} sigmas")
    data: dict = {"model": model, "k_sigma": float(k_sigma), "source": source}
    for name, v, s in zip(names, values, std):
        data[name] = {"value": float(v), "std": float(s), "lower": float(v - k_sigma * s),
                      "upper": float(v + k_sigma * s)}
    write_json(path, data)


def read_intrinsic_bounds(path: str | Path, model: str = DEFAULT_MODEL, *,
                          names: tuple[str, ...] = INTRINSIC_NAMES) -> tuple[np.ndarray, np.ndarray]:
    """(lower, upper) (P,) in the order of ``names`` (default ``INTRINSIC_NAMES``, the six); a missing parameter
    gives NaN in both (held fixed).

    model : the camera model the bounds are for (the dataset camera's); a file of another model is refused.
    Problems are InputErrors naming the file and the parameter."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: intrinsic bounds file is missing")
    data = read_json_object(path)
    found_model = data.get("model", DEFAULT_MODEL)
    if found_model != model:
        raise InputError(f"{path}: bounds of a {found_model!r} camera, for a {model} camera")
    lower = np.full(len(names), np.nan)
    upper = np.full(len(names), np.nan)
    found = 0
    for i, name in enumerate(names):
        if name not in data:
            continue
        entry = data[name]
        if not isinstance(entry, dict) or "lower" not in entry or "upper" not in entry:
            raise InputError(f"{path}: {name} must be an object with lower and upper")
        for key in ("lower", "upper"):
            v = entry[key]
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise InputError(f"{path}: {name}.{key} = {v!r} is not a finite number")
        if entry["lower"] > entry["upper"]:
            raise InputError(f"{path}: {name}: lower {entry['lower']:g} > upper {entry['upper']:g}")
        lower[i], upper[i] = float(entry["lower"]), float(entry["upper"])
        found += 1
    if found == 0:
        raise InputError(f"{path}: no bounds on any of {', '.join(names)}")
    return lower, upper


def read_intrinsic_sigmas(path: str | Path, model: str, param_names: tuple[str, ...]) -> np.ndarray:
    """(P,) each of ``param_names``' standard deviation: its ``std``, else ``(upper - lower) / (2 k_sigma)``;
    NaN for a parameter the file leaves out. model : the camera's, as :func:`read_intrinsic_bounds`.
    Problems are InputErrors naming the file and the parameter."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: intrinsic bounds file is missing")
    data = read_json_object(path)
    if data.get("model", DEFAULT_MODEL) != model:
        raise InputError(f"{path}: bounds of a {data.get('model', DEFAULT_MODEL)!r} camera, for a {model} camera")
    k_sigma = data.get("k_sigma", float("nan"))
    sigmas = np.full(len(param_names), np.nan)
    for i, name in enumerate(param_names):
        entry = data.get(name)
        if entry is None:
            continue
        if not isinstance(entry, dict):
            raise InputError(f"{path}: {name} must be an object with std or lower and upper")
        sigma = entry.get("std")
        if sigma is None and isinstance(k_sigma, (int, float)) and k_sigma > 0 and "lower" in entry and "upper" in entry:
            sigma = (entry["upper"] - entry["lower"]) / (2.0 * k_sigma)
        if sigma is None:
            continue
        if isinstance(sigma, bool) or not isinstance(sigma, (int, float)) or not math.isfinite(sigma) or sigma < 0:
            raise InputError(f"{path}: {name}: standard deviation {sigma!r} is not a finite number >= 0")
        sigmas[i] = float(sigma)
    return sigmas
