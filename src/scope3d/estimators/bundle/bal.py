"""Bundle Adjustment in the Large (BAL) problems: reading, conversion to a BundleProblem, bounds files.

BAL convention (Agarwal et al., ECCV 2010): ``P = R X + t``, ``p = -P[:2] / P.z`` (the camera looks down
-z, y up), ``pixel = f (1 + k1 |p|^2 + k2 |p|^4) p`` with the origin at the image centre, cost
``0.5 sum |r|^2``. Each camera has 9 numbers ``(rx, ry, rz, tx, ty, tz, f, k1, k2)``.

scope3d's camera looks down +z with y down, so the conversion turns each camera frame by 180° about x:
``R' = F R``, ``t' = F t`` with ``F = diag(1, -1, -1)``, and flips the observed y. The projection and
the cost are then identical. Each camera gets its own intrinsic group ``(f, f, 0, 0, k1, k2)`` with
square pixels and a fixed principal point, poses are parameterised by ``(w, t)`` with
``R = exp([w]x) R_initial`` (``position_parameter="translation"``), as Ceres's BAL examples do.

Bounds file
-----------
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
"""
from __future__ import annotations

import os

import numpy as np

from scope3d.errors import InputError
from scope3d.estimators.bundle.problem import BundleProblem
from scope3d.geometry.rotation import matrix_to_rotvec, rotvec_to_matrix
from scope3d.io.bal import BALProblem, _parse_floats, _parse_indices, read_ascii_text

_FLIP = np.array([1.0, -1.0, -1.0])


_CAMERA_COMPONENTS = ("rx", "ry", "rz", "tx", "ty", "tz", "f", "k1", "k2")


_CAMERA_GROUPS = {
    "rotation": ("rx", "ry", "rz"),
    "translation": ("tx", "ty", "tz"),
    "intrinsics": ("f", "k1", "k2"),
    "all": _CAMERA_COMPONENTS,
}


_POINT_COMPONENTS = ("x", "y", "z")


def bal_to_problem(bal: BALProblem) -> BundleProblem:
    """BundleProblem with the same cost as ``bal`` (see the module docstring for the conventions)."""
    rot = _FLIP[None, :, None] * rotvec_to_matrix(bal.cameras[:, :3])
    trans = _FLIP * bal.cameras[:, 3:6]
    m = bal.cameras.shape[0]
    intr = np.zeros((m, 6))
    intr[:, 0] = intr[:, 1] = bal.cameras[:, 6]
    intr[:, 4:6] = bal.cameras[:, 7:9]
    obs = bal.observations_px * np.array([1.0, -1.0])
    problem = BundleProblem(obs, bal.camera_index, bal.point_index, rot, trans, bal.points, intr,
                            position_parameter="translation", square_pixels=True)
    problem.fix("intrinsics", components=["cx", "cy"])
    return problem


def bound_bal_intrinsics(problem: BundleProblem, lower: np.ndarray, upper: np.ndarray) -> list[str]:
    """Box every camera's ``f, k1, k2`` of a problem made by :func:`bal_to_problem` with a calibration's
    bounds (``(fx, fy, cx, cy, k1, k2)`` lower and upper, (6,), NaN = no bound, e.g. from
    ``intrinsic_bounds.json``). BAL has square pixels, so f takes fx's box; its principal point is the
    origin of the observations, so cx, cy do not apply. Returns the names bounded."""
    lower = np.asarray(lower, dtype=float)
    upper = np.asarray(upper, dtype=float)
    bounded = []
    for name, k in (("fx", 0), ("k1", 4), ("k2", 5)):
        if np.isfinite(lower[k]) and np.isfinite(upper[k]):
            problem.set_bounds("intrinsics", None, [name], lower[k], upper[k])
            bounded.append("f" if name == "fx" else name)
    return bounded


def result_to_bal(bal: BALProblem, result) -> BALProblem:
    """The solved problem back in BAL form (same observations)."""
    rot = _FLIP[None, :, None] * result.rotations
    trans = _FLIP * result.translations
    intr = result.intrinsics
    cams = np.column_stack([matrix_to_rotvec(rot), trans, intr[:, 0], intr[:, 4], intr[:, 5]])
    return BALProblem(bal.camera_index.copy(), bal.point_index.copy(), bal.observations_px.copy(), cams,
                      result.points_world.copy())


def apply_bounds_file(problem: BundleProblem, path: str | os.PathLike) -> int:
    """Apply the rules of a bounds file (format in the module docstring) to a problem made by
    :func:`bal_to_problem`. Returns the number of rules applied; raises InputError naming file and line."""
    lines = read_ascii_text(path, "a bounds file").splitlines()
    applied = 0
    for number, raw in enumerate(lines, start=1):
        tokens = raw.split("#", 1)[0].split()
        if not tokens:
            continue
        where = f"{path} line {number}"
        try:
            _apply_rule(problem, tokens, where)
        except InputError as exc:
            if str(exc).startswith(where):
                raise
            # the problem's own checks (an empty shell, a zero axis) do not know the file: name it
            raise InputError(f"{where}: {exc}") from None
        applied += 1
    return applied


def _apply_rule(problem: BundleProblem, tokens: list[str], where: str) -> None:
    """Apply one rule of a bounds file (its tokens, comment removed); ``where`` names the file and line."""
    kind = tokens[0]
    if kind in ("camera", "point"):
        if len(tokens) < 4:
            raise InputError(f"{where}: expected '{kind} INDICES COMPONENTS SPEC'")
        count = problem.num_cameras if kind == "camera" else problem.num_points
        idx = _parse_indices(tokens[1], count, where)
        names = []
        for name in tokens[2].split(","):
            if kind == "camera" and name in _CAMERA_GROUPS:
                names.extend(_CAMERA_GROUPS[name])
            elif kind == "point" and name == "all":
                names.extend(_POINT_COMPONENTS)
            elif name in (_CAMERA_COMPONENTS if kind == "camera" else _POINT_COMPONENTS):
                names.append(name)
            else:
                raise InputError(f"{where}: unknown {kind} component {name!r}")
        spec = tokens[3:]
        for name in names:
            _apply_component(problem, kind, idx, name, spec, where)
    elif kind == "depth":
        if len(tokens) != 10:
            raise InputError(f"{where}: expected 'depth INDICES OX OY OZ AX AY AZ MIN MAX'")
        idx = _parse_indices(tokens[1], problem.num_points, where)
        v = _parse_floats(tokens[2:], 8, where)
        problem.bound_point_depth(v[0:3], v[3:6], v[6], v[7], idx)
    elif kind == "shell":
        if len(tokens) != 7:
            raise InputError(f"{where}: expected 'shell INDICES CX CY CZ RMIN RMAX'")
        idx = _parse_indices(tokens[1], problem.num_points, where)
        v = _parse_floats(tokens[2:], 5, where)
        problem.bound_points_to_shell(v[0:3], v[3], v[4], idx)
    else:
        raise InputError(f"{where}: unknown rule {kind!r} (expected camera, point, depth or shell)")


def _apply_component(problem: BundleProblem, kind: str, idx: np.ndarray, name: str, spec: list[str], where: str):
    if kind == "camera":
        target, comp, flip = {
            "rx": ("pose", "wx", 1), "ry": ("pose", "wy", -1), "rz": ("pose", "wz", -1),
            "tx": ("pose", "px", 1), "ty": ("pose", "py", -1), "tz": ("pose", "pz", -1),
            "f": ("intrinsics", "fx", 1), "k1": ("intrinsics", "k1", 1), "k2": ("intrinsics", "k2", 1),
        }[name]
        items = idx if target == "pose" else problem.intrinsics_index[idx]
        table = ("wx", "wy", "wz", "px", "py", "pz") if target == "pose" else ("fx", "fy", "cx", "cy", "k1", "k2")
        initial = (problem.initial.pose if target == "pose" else problem.initial.intrinsics)[items, table.index(comp)]
    else:
        if np.any(problem.point_kind[idx] != 0) or np.any(problem.point_frame[idx] != np.eye(3)) \
                or np.any(problem.point_origin[idx] != 0):
            raise InputError(f"{where}: point coordinate bounds must come before depth/shell rules on the same points")
        target, comp, flip = "point", ("y0", "y1", "y2")[_POINT_COMPONENTS.index(name)], 1
        items = idx
        initial = problem.initial.points[items, _POINT_COMPONENTS.index(name)]
    if spec == ["fixed"]:
        problem.fix(target, items, [comp])
        return
    if len(spec) == 2 and spec[0] in ("+-", "±"):
        half = _parse_floats(spec[1:], 1, where)[0]
        if half < 0:
            raise InputError(f"{where}: half-width must be non-negative, got {half:g}")
        lo, hi = initial - half, initial + half
    else:
        lo_bal, hi_bal = _parse_floats(spec, 2, where)
        if lo_bal > hi_bal:
            raise InputError(f"{where}: lower bound {lo_bal:g} > upper bound {hi_bal:g}")
        # y and z of the camera frame are flipped between BAL and scope3d (see module docstring)
        lo, hi = (lo_bal, hi_bal) if flip > 0 else (-hi_bal, -lo_bal)
        lo = np.full(items.shape, lo)
        hi = np.full(items.shape, hi)
    problem.set_bounds(target, items, [comp], np.asarray(lo)[:, None], np.asarray(hi)[:, None])
