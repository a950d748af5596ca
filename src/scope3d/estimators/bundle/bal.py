"""Bundle Adjustment in the Large (BAL) problems as BundleProblems: conversion both ways, bounds applied.

BAL convention (Agarwal et al., ECCV 2010): ``P = R X + t``, ``p = -P[:2] / P.z`` (the camera looks down
-z, y up), ``pixel = f (1 + k1 |p|^2 + k2 |p|^4) p`` with the origin at the image centre, cost
``0.5 sum |r|^2``. Each camera has 9 numbers ``(rx, ry, rz, tx, ty, tz, f, k1, k2)``.

scope3d's camera looks down +z with y down, so the conversion turns each camera frame by 180° about x:
``R' = F R``, ``t' = F t`` with ``F = diag(1, -1, -1)``, and flips the observed y. The projection and
the cost are then identical. Each camera gets its own intrinsic group ``(f, f, 0, 0, k1, k2)`` with
square pixels and a fixed principal point, poses are parameterised by ``(w, t)`` with
``R = exp([w]x) R_initial`` (``position_parameter="translation"``), as Ceres's BAL examples do.

Bounds files (their text format and reader: :mod:`scope3d.io.bal_bounds`) are applied to such a problem by
:func:`apply_bounds` (:func:`apply_bounds_file` reads and applies one).
"""
from __future__ import annotations

import os

import numpy as np

from scope3d.errors import InputError
from scope3d.estimators.bundle.problem import BundleProblem
from scope3d.geometry.rotation import matrix_to_rotvec, rotvec_to_matrix
from scope3d.io.bal import BALProblem
from scope3d.io.bal_bounds import POINT_COMPONENTS, BoundsRule, read_bounds_file

_FLIP = np.array([1.0, -1.0, -1.0])


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
    """Read a bounds file (:func:`scope3d.io.bal_bounds.read_bounds_file`) and apply its rules to a problem made
    by :func:`bal_to_problem`. Returns the number of rules applied; raises InputError naming file and line."""
    rules = read_bounds_file(path, problem.num_cameras, problem.num_points)
    apply_bounds(problem, rules)
    return len(rules)


def apply_bounds(problem: BundleProblem, rules: list[BoundsRule]) -> None:
    """Apply a bounds file's rules, in order, to a problem made by :func:`bal_to_problem` (BAL's camera frame
    turned into scope3d's); raises InputError naming the rule's file and line."""
    for rule in rules:
        try:
            _apply_rule(problem, rule)
        except InputError as exc:
            if str(exc).startswith(rule.where):
                raise
            # the problem's own checks (an empty shell, a zero axis) do not know the file: name it
            raise InputError(f"{rule.where}: {exc}") from None


def _apply_rule(problem: BundleProblem, rule: BoundsRule) -> None:
    if rule.kind == "depth":
        v = rule.values
        problem.bound_point_depth(list(v[0:3]), list(v[3:6]), v[6], v[7], rule.indices)
    elif rule.kind == "shell":
        v = rule.values
        problem.bound_points_to_shell(list(v[0:3]), v[3], v[4], rule.indices)
    else:
        for name in rule.components:
            _apply_component(problem, rule, name)


def _apply_component(problem: BundleProblem, rule: BoundsRule, name: str) -> None:
    idx = rule.indices
    if rule.kind == "camera":
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
            raise InputError(f"{rule.where}: point coordinate bounds must come before depth/shell rules on the same "
                             "points")
        target, comp, flip = "point", ("y0", "y1", "y2")[POINT_COMPONENTS.index(name)], 1
        items = idx
        initial = problem.initial.points[items, POINT_COMPONENTS.index(name)]
    if rule.fixed:
        problem.fix(target, items, [comp])
        return
    if rule.half_width is not None:
        lo, hi = initial - rule.half_width, initial + rule.half_width
    else:
        # y and z of the camera frame are flipped between BAL and scope3d (see module docstring)
        lo, hi = (rule.lower, rule.upper) if flip > 0 else (-rule.upper, -rule.lower)
        lo = np.full(items.shape, lo)
        hi = np.full(items.shape, hi)
    problem.set_bounds(target, items, [comp], np.asarray(lo)[:, None], np.asarray(hi)[:, None])
