"""Bounds files for BAL problems: the text format, read into rules (:func:`read_bounds_file`); bundle adjustment
applies them (:func:`scope3d.estimators.bundle.bal.apply_bounds`).

A text file, one rule per line, ``#`` starts a comment. Indices are 0-based: ``*`` (all), ``7``,
``0-9`` (inclusive) or a comma list ``1,4,10-12``. Rules:

``camera INDICES COMPONENTS SPEC`` with COMPONENTS a comma list of ``rx ry rz`` (rotation relative to the
initial orientation, BAL frame, rad: ``R = exp([w]x) R_initial``), ``tx ty tz`` (translation, BAL frame
and units), ``f k1 k2``, or the groups ``rotation``, ``translation``, ``intrinsics``, ``all``;
``point INDICES COMPONENTS SPEC`` with COMPONENTS from ``x y z`` or ``all``. SPEC is one of
``fixed`` (hold at the initial value), ``LOWER UPPER`` (absolute, ``-inf``/``inf`` allowed) or
``+- HALF`` (initial value ± HALF).

``depth INDICES OX OY OZ AX AY AZ MIN MAX``: depth ``(X - O) . A/|A|`` of the points in [MIN, MAX].
``shell INDICES CX CY CZ RMIN RMAX``: points inside the spherical shell ``RMIN <= |X - C| <= RMAX``.

Example::

    camera 0 all fixed            # gauge: first camera fixed
    camera * k1,k2 -1e-6 1e-6
    camera 1-5 translation +- 0.05
    shell * 0 0 0 1 50

Units: the BAL problem's (its frame, lengths and radians).
"""
from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from scope3d.errors import InputError
from scope3d.io.bal import read_ascii_text

CAMERA_COMPONENTS = ("rx", "ry", "rz", "tx", "ty", "tz", "f", "k1", "k2")
CAMERA_GROUPS = {
    "rotation": ("rx", "ry", "rz"),
    "translation": ("tx", "ty", "tz"),
    "intrinsics": ("f", "k1", "k2"),
    "all": CAMERA_COMPONENTS,
}
POINT_COMPONENTS = ("x", "y", "z")


@dataclass(frozen=True)
class BoundsRule:
    """One rule of a bounds file.

    kind : ``"camera"``, ``"point"``, ``"depth"`` or ``"shell"``. indices : (k,) int64, the cameras or points
    it applies to. where : the file and line, for messages.
    camera and point rules: components, the names (groups expanded, in the file's order); fixed : hold them;
    else half_width (``+- HALF``, about the initial value) or lower and upper (absolute, BAL frame).
    depth rules: values ``(OX, OY, OZ, AX, AY, AZ, MIN, MAX)``; shell rules: ``(CX, CY, CZ, RMIN, RMAX)``.
    """

    kind: str
    indices: np.ndarray
    where: str
    components: tuple[str, ...] = ()
    fixed: bool = False
    half_width: float | None = None
    lower: float | None = None
    upper: float | None = None
    values: tuple[float, ...] = ()


def read_bounds_file(path: str | os.PathLike, n_cameras: int, n_points: int) -> list[BoundsRule]:
    """The rules of a bounds file (format in the module docstring) for a problem of ``n_cameras`` cameras and
    ``n_points`` points; raises InputError naming the file and line."""
    rules = []
    for number, raw in enumerate(read_ascii_text(path, "a bounds file").splitlines(), start=1):
        tokens = raw.split("#", 1)[0].split()
        if tokens:
            rules.append(_rule(tokens, n_cameras, n_points, f"{path} line {number}"))
    return rules


def _rule(tokens: list[str], n_cameras: int, n_points: int, where: str) -> BoundsRule:
    """One rule from its tokens (comment removed); ``where`` names the file and line."""
    kind = tokens[0]
    if kind in ("camera", "point"):
        if len(tokens) < 4:
            raise InputError(f"{where}: expected '{kind} INDICES COMPONENTS SPEC'")
        idx = _parse_indices(tokens[1], n_cameras if kind == "camera" else n_points, where)
        names = []
        for name in tokens[2].split(","):
            if kind == "camera" and name in CAMERA_GROUPS:
                names.extend(CAMERA_GROUPS[name])
            elif kind == "point" and name == "all":
                names.extend(POINT_COMPONENTS)
            elif name in (CAMERA_COMPONENTS if kind == "camera" else POINT_COMPONENTS):
                names.append(name)
            else:
                raise InputError(f"{where}: unknown {kind} component {name!r}")
        spec = tokens[3:]
        if spec == ["fixed"]:
            return BoundsRule(kind, idx, where, tuple(names), fixed=True)
        if len(spec) == 2 and spec[0] in ("+-", "±"):
            half = _parse_floats(spec[1:], 1, where)[0]
            if half < 0:
                raise InputError(f"{where}: half-width must be non-negative, got {half:g}")
            return BoundsRule(kind, idx, where, tuple(names), half_width=half)
        lower, upper = _parse_floats(spec, 2, where)
        if lower > upper:
            raise InputError(f"{where}: lower bound {lower:g} > upper bound {upper:g}")
        return BoundsRule(kind, idx, where, tuple(names), lower=lower, upper=upper)
    if kind == "depth":
        if len(tokens) != 10:
            raise InputError(f"{where}: expected 'depth INDICES OX OY OZ AX AY AZ MIN MAX'")
        return BoundsRule(kind, _parse_indices(tokens[1], n_points, where), where,
                          values=tuple(_parse_floats(tokens[2:], 8, where)))
    if kind == "shell":
        if len(tokens) != 7:
            raise InputError(f"{where}: expected 'shell INDICES CX CY CZ RMIN RMAX'")
        return BoundsRule(kind, _parse_indices(tokens[1], n_points, where), where,
                          values=tuple(_parse_floats(tokens[2:], 5, where)))
    raise InputError(f"{where}: unknown rule {kind!r} (expected camera, point, depth or shell)")


def _parse_indices(token: str, count: int, where: str) -> np.ndarray:
    if token == "*":
        return np.arange(count)
    ranges = []
    for part in token.split(","):
        try:
            a, b = (int(v) for v in part.split("-", 1)) if "-" in part else (int(part),) * 2
        except ValueError:
            raise InputError(f"{where}: bad index list {token!r} (use *, 7, 0-9 or 1,4,10-12)") from None
        # checked before expanding: '0-999999999999' must not allocate a trillion indices
        if a < 0 or b >= count or a > b:
            raise InputError(f"{where}: index out of range [0, {count}) in {token!r}")
        ranges.append(np.arange(a, b + 1, dtype=np.int64))
    return np.concatenate(ranges)


def _parse_floats(tokens: list[str], count: int, where: str) -> list[float]:
    if len(tokens) != count:
        raise InputError(f"{where}: expected {count} numbers, got {len(tokens)}")
    try:
        values = [float(t) for t in tokens]
    except ValueError:
        raise InputError(f"{where}: expected numbers, got {' '.join(tokens)!r}") from None
    if any(np.isnan(values)):
        raise InputError(f"{where}: NaN is not a bound")
    return values
