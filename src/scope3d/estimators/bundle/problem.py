"""What a bundle adjustment estimates: observations, parameters, and which are fixed, free or bounded.

Parameters (every scalar is fixed, free, or bounded by a box ``[lower, upper]``, reference eq. 6.2)
-----------------------------------------------------------------------------------------------------
* **Pose** of camera ``c``, 6 scalars ``(w_x, w_y, w_z, p_x, p_y, p_z)``:

  - ``w`` (rad) is a rotation applied on the left of the camera's *reference* orientation,
    ``R = exp([w]x) @ R_ref`` (cam_from_world). ``R_ref`` is the measured (or initial) orientation, so
    ``w = 0`` initially and an orientation tolerance of ``±a`` rad is the box ``|w_i| <= a``; this is the
    convention of :class:`scope3d.sensor.pose_tolerance.PoseTolerance`.
  - ``p`` (mm) is either the camera centre ``C`` in the world (``position_parameter="centre"``, the
    default: a robot's position tolerance is a box on ``C`` per world axis) or the translation ``t`` of
    cam_from_world (``position_parameter="translation"``: ``P = R X + t``, as Ceres and the BAL files
    use; used for generic problems where no bound is put on positions).
* **Intrinsics** ``(fx, fy, cx, cy, k1, k2)`` of each intrinsic group (pixels, pixels, pixels, pixels,
  unitless, unitless); one group shared by all cameras, or one per camera, or any mapping
  ``intrinsics_index``. With ``square_pixels=True`` fy is tied to fx (the BAL and COLMAP RADIAL model)
  and fy is held fixed and ignored. The lens ``model`` (:mod:`scope3d.sensor.camera_models`, default
  scope3d's radial ``pinhole_radial_k1k2``) decides what k1, k2 mean: radial for the pinhole family, the
  fisheye's first two for ``OPENCV_FISHEYE``; a ``PINHOLE`` camera's k1, k2 are fixed at 0.
* **The model's later parameters** (``extra``, :func:`lens_block`: OPENCV's p1, p2, FULL_OPENCV's p1, p2,
  k3..k6, the fisheye's k3, k4) enter the projection. They start *held* at their (calibrated) values, and
  are intrinsics like the six above otherwise: named in :meth:`BundleProblem.fix`, :meth:`~BundleProblem.free`
  and :meth:`~BundleProblem.set_bounds` (kind ``"intrinsics"``, :attr:`BundleProblem.intrinsic_names`),
  boxed alike. Once one is free, the camera side gets a third 6-block per intrinsic group for them (the
  kernels' layout, :mod:`.kernels`; a fisheye's two padded with four held zeros); while all are held the
  problem is solved exactly as before they could move.
* **Points**, 3 scalars each, in one of two parameterisations chosen per point:

  - linear (default): ``X = o + Q y`` with an origin ``o`` and an orthonormal frame ``Q``. With
    ``o = 0, Q = I`` (the default) ``y`` is the world coordinates. With ``Q[:, 2]`` an axis, ``y_2`` is
    the depth along that axis, so a depth bound is a box bound (:meth:`BundleProblem.bound_point_depth`).
  - spherical: ``X = o + Q (r u(theta, phi))``, ``u = (sin theta cos phi, sin theta sin phi, cos theta)``:
    ``y = (r, theta, phi)``, so a spherical shell ``r_min <= |X - o| <= r_max`` is a box bound on ``r``
    (:meth:`BundleProblem.bound_points_to_shell`).

A pose scalar may also carry a Gaussian prior at its box's centre (:meth:`BundleProblem.set_box_prior`): the
measurement's weak hold inside its box, for the directions the images leave free.

Bounds on a point are stated in its parameterisation; changing the parameterisation resets the point's
bounds. Initial values outside their box are clamped onto it by the solver, with a warning.

Observations are stored sorted by point (the Schur complement eliminates points one by one);
``observation_order[i]`` is the input row of stored observation ``i``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Iterable, Sequence

import numpy as np

from scope3d.errors import InputError
from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import matrix_to_rotvec, rotvec_to_matrix, so3_left_jacobian
from scope3d.sensor.camera import INTRINSIC_NAMES, Camera
from scope3d.sensor.camera_models import DEFAULT_MODEL, lens_model
from scope3d.sensor.pose_tolerance import MeasuredPose

POSE_NAMES = ("wx", "wy", "wz", "px", "py", "pz")
POINT_LINEAR = 0
POINT_SPHERICAL = 1
POSITION_PARAMETERS = ("centre", "translation")


@dataclass
class BundleParameters:
    """Values of all parameters.

    pose : (m, 6) float, ``(w rad, position mm)`` per camera, see the module docstring.
    intrinsics : (g, 6) float, ``(fx, fy, cx, cy, k1, k2)`` per intrinsic group.
    points : (n, 3) float, each point in its own parameterisation.
    extra : (g, E) float, the lens model's later parameters per group in :func:`lens_block`'s layout
        (E = 0 for the default model).
    """

    pose: np.ndarray
    intrinsics: np.ndarray
    points: np.ndarray
    extra: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))

    def copy(self) -> "BundleParameters":
        return BundleParameters(self.pose.copy(), self.intrinsics.copy(), self.points.copy(), self.extra.copy())

    def camera_vector(self, with_extra: bool = False) -> np.ndarray:
        """The camera side of the parameter vector: poses then intrinsics (6 (m + g),), and with ``with_extra``
        the later lens parameters, padded to a 6-block per group with zeros (6 (m + 2 g),)."""
        parts = [self.pose.ravel(), self.intrinsics.ravel()]
        if with_extra:
            block = np.zeros((self.intrinsics.shape[0], EXTRA_BLOCK))
            block[:, :self.extra.shape[1]] = self.extra
            parts.append(block.ravel())
        return np.concatenate(parts)


# the parameters after k2 that each family's kernel takes (scope3d.estimators.bundle.lens_kernels)
_PINHOLE_EXTRA = ("p1", "p2", "k3", "k4", "k5", "k6")
_FISHEYE_EXTRA = ("k3", "k4")
EXTRA_BLOCK = 6  # their block on the camera side when refined: the kernels' 6-blocks


def extra_layout(model: str) -> tuple[str, ...]:
    """The names of ``model``'s parameters after k2 in the kernels' layout (:func:`lens_block`), including the
    pinhole family's terms the model lacks (held at 0); () for the default model. ValueError for an unknown
    model."""
    lens = lens_model(model)
    if model == DEFAULT_MODEL:
        return ()
    return _FISHEYE_EXTRA if lens.is_fisheye else _PINHOLE_EXTRA


def lens_block(camera: Camera) -> tuple[np.ndarray, str, np.ndarray]:
    """The bundle adjuster's view of a camera: its intrinsic block ``(fx, fy, cx, cy, k1, k2)`` (6,), its model's
    name and the model's fixed parameters after k2 (E,) in the kernels' layout (the pinhole family's
    ``(p1, p2, k3, k4, k5, k6)`` with zeros for terms the model lacks, the fisheye's ``(k3, k4)``; empty for
    the default model)."""
    values = dict(zip(camera.param_names, camera.params))
    block = np.array([values[n] if n in values else 0.0 for n in INTRINSIC_NAMES])
    if camera.model == DEFAULT_MODEL:
        return block, camera.model, np.zeros(0)
    return block, camera.model, np.array([values.get(n, 0.0) for n in extra_layout(camera.model)])


def camera_from_block(camera: Camera, block: np.ndarray, extra: np.ndarray | None = None) -> Camera:
    """``camera`` with its intrinsic block replaced by an adjusted one, and its later parameters by ``extra``
    (:func:`lens_block`'s layout) when given (else as they were)."""
    params = camera.params.copy()
    n = min(6, len(params))
    params[:n] = np.asarray(block, dtype=float)[:n]
    if extra is not None:
        names = camera.param_names
        for name, value in zip(extra_layout(camera.model), np.asarray(extra, dtype=float)):
            if name in names:
                params[names.index(name)] = value
    return camera.with_params(params)


def _extra_block(model: str, extra, groups: int) -> np.ndarray:
    """(g, E) the later parameters of ``groups`` intrinsic groups (E = 0 for the default model)."""
    size = len(extra_layout(model))  # ValueError naming the known models
    if extra is None:
        return np.zeros((groups, size))
    out = np.atleast_2d(np.asarray(extra, dtype=float)).reshape(-1, size) if size else np.zeros((groups, 0))
    if out.shape[0] == 1:
        out = np.repeat(out, groups, axis=0)
    if out.shape != (groups, size) or not np.all(np.isfinite(out)):
        raise InputError(f"{model}: extra parameters must be {size} finite values per intrinsic group")
    return np.ascontiguousarray(out)


def _as_index_list(items, count: int, what: str) -> np.ndarray:
    if items is None:
        return np.arange(count)
    idx = np.atleast_1d(np.asarray(items, dtype=np.int64))
    if idx.size and (idx.min() < -count or idx.max() >= count):
        raise InputError(f"{what} index out of range [0, {count}): {idx[(idx < -count) | (idx >= count)][0]}")
    return idx % count if count else idx


def _components(names: Sequence[str] | str | None, table: Sequence[str], what: str) -> np.ndarray:
    if names is None:
        return np.arange(len(table))
    if isinstance(names, str):
        names = [names]
    out = []
    for name in names:
        if name not in table:
            raise InputError(f"unknown {what} component {name!r}; expected one of {', '.join(table)}")
        out.append(table.index(name))
    return np.array(out, dtype=np.int64)


class BundleProblem:
    """A bundle adjustment problem: observations, initial parameters and per-scalar bounds (eq. 6.2).

    Parameters
    ----------
    observations_px : (K, 2) float, observed pixels (u right, v down, origin at the top-left pixel's
        centre, or any origin consistent with cx, cy).
    camera_index : (K,) int, camera of each observation, in [0, m).
    point_index : (K,) int, point of each observation, in [0, n).
    rotations : (m, 3, 3) float, initial (or measured) cam_from_world rotations; they become the
        reference orientations ``R_ref``.
    translations : (m, 3) float, mm, initial cam_from_world translations.
    points_world : (n, 3) float, mm, initial points.
    intrinsics : (6,) or (g, 6) float, ``(fx, fy, cx, cy, k1, k2)``.
    intrinsics_index : (m,) int or None. None means one shared group when ``intrinsics`` has one row,
        one group per camera when it has m rows.
    position_parameter : "centre" (camera centre C, mm, world axes) or "translation" (t of cam_from_world).
    square_pixels : bool, tie fy to fx.
    model : the lens model's name; extra : (E,) or (g, E) its later parameters in :func:`lens_block`'s
        layout (None: zeros), for a model other than the default.

    Every parameter starts free but the model's later parameters (``extra``), which start held. Use :meth:`fix`, :meth:`set_bounds` and the convenience methods to
    constrain them, or :meth:`from_measured_poses` to build the reference's BCBA problem.
    """

    def __init__(
        self,
        observations_px: np.ndarray,
        camera_index: np.ndarray,
        point_index: np.ndarray,
        rotations: np.ndarray,
        translations: np.ndarray,
        points_world: np.ndarray,
        intrinsics: np.ndarray,
        *,
        intrinsics_index: np.ndarray | None = None,
        position_parameter: str = "centre",
        square_pixels: bool = False,
        model: str = DEFAULT_MODEL,
        extra: np.ndarray | None = None,
    ) -> None:
        obs = np.asarray(observations_px, dtype=float)
        cam = np.asarray(camera_index)
        pt = np.asarray(point_index)
        rot = np.asarray(rotations, dtype=float)
        trans = np.asarray(translations, dtype=float)
        pts = np.asarray(points_world, dtype=float)
        intr = np.atleast_2d(np.asarray(intrinsics, dtype=float))
        if position_parameter not in POSITION_PARAMETERS:
            raise InputError(f"position_parameter must be one of {POSITION_PARAMETERS}, got {position_parameter!r}")
        if obs.ndim != 2 or obs.shape[1] != 2:
            raise InputError(f"observations must have shape (K, 2), got {obs.shape}")
        if obs.shape[0] == 0:
            raise InputError("the problem is empty: there are no observations")
        if cam.shape != (obs.shape[0],) or pt.shape != (obs.shape[0],):
            raise InputError(
                f"camera_index and point_index must have shape ({obs.shape[0]},), got {cam.shape} and {pt.shape}"
            )
        if not (np.issubdtype(cam.dtype, np.integer) and np.issubdtype(pt.dtype, np.integer)):
            raise InputError("camera_index and point_index must be integers")
        if rot.ndim != 3 or rot.shape[1:] != (3, 3) or rot.shape[0] == 0:
            raise InputError(f"rotations must have shape (m, 3, 3) with m >= 1, got {rot.shape}")
        m = rot.shape[0]
        if trans.shape != (m, 3):
            raise InputError(f"translations must have shape ({m}, 3), got {trans.shape}")
        if pts.ndim != 2 or pts.shape[1] != 3 or pts.shape[0] == 0:
            raise InputError(f"points must have shape (n, 3) with n >= 1, got {pts.shape}")
        n = pts.shape[0]
        if intr.shape[1] != 6:
            raise InputError(f"intrinsics must have shape (6,) or (g, 6), got {np.shape(intrinsics)}")
        g = intr.shape[0]
        if intrinsics_index is None:
            if g == 1:
                intr_idx = np.zeros(m, dtype=np.int64)
            elif g == m:
                intr_idx = np.arange(m)
            else:
                raise InputError(f"{g} intrinsic groups for {m} cameras: give intrinsics_index")
        else:
            intr_idx = np.asarray(intrinsics_index, dtype=np.int64)
            if intr_idx.shape != (m,) or intr_idx.min() < 0 or intr_idx.max() >= g:
                raise InputError(f"intrinsics_index must have shape ({m},) with values in [0, {g})")
        for name, arr in (("observations", obs), ("rotations", rot), ("translations", trans),
                          ("points", pts), ("intrinsics", intr)):
            bad = ~np.isfinite(arr)
            if bad.any():
                row = int(np.argwhere(bad)[0][0])
                raise InputError(f"{name} row {row} has NaN or infinite values")
        for name, idx, count in (("camera", cam, m), ("point", pt, n)):
            bad = (idx < 0) | (idx >= count)
            if bad.any():
                row = int(np.flatnonzero(bad)[0])
                raise InputError(f"observation row {row}: {name} index {int(idx[row])} out of range [0, {count})")
        ortho = np.abs(rot @ np.swapaxes(rot, 1, 2) - np.eye(3)).max(axis=(1, 2))
        if np.any(ortho > 1e-6) or np.any(np.linalg.det(rot) < 0):
            c = int(np.flatnonzero((ortho > 1e-6) | (np.linalg.det(rot) < 0))[0])
            raise InputError(f"rotation of camera {c} is not a proper rotation matrix")

        order = np.lexsort((cam, pt))
        self.observation_order = order
        self.observations_px = np.ascontiguousarray(obs[order])
        self.camera_index = np.ascontiguousarray(cam[order], dtype=np.int64)
        self.point_index = np.ascontiguousarray(pt[order], dtype=np.int64)
        self.point_ptr = np.concatenate([[0], np.cumsum(np.bincount(self.point_index, minlength=n))]).astype(np.int64)
        self.intrinsics_index = intr_idx
        self.model = model
        self.extra = _extra_block(model, extra, g)
        self.position_parameter = position_parameter
        self.square_pixels = bool(square_pixels)
        self.reference_rotations = rot.copy()
        self.num_cameras, self.num_points, self.num_groups = m, n, g

        position = -np.einsum("mji,mj->mi", rot, trans) if position_parameter == "centre" else trans.copy()
        self.initial = BundleParameters(
            np.concatenate([np.zeros((m, 3)), position], axis=1), intr.copy(), pts.copy(), self.extra.copy()
        )
        self.pose_lower = np.full((m, 6), -np.inf)
        self.pose_upper = np.full((m, 6), np.inf)
        self.pose_fixed = np.zeros((m, 6), dtype=bool)
        # a Gaussian prior 0.5 * weight * (pose - mean)^2 per pose scalar, in the residuals' px^2
        # (:meth:`set_box_prior`); weight 0: none
        self.pose_prior_mean = np.zeros((m, 6))
        self.pose_prior_weight = np.zeros((m, 6))
        # the intrinsics' bounds and holds, (g, 6 + E): the six of the block, then the model's later parameters
        # (held at the start); ``intrinsics_*`` (g, 6) and ``extra_*`` (g, E) are views of them
        layout = extra_layout(model)
        model_names = set(lens_model(model).param_names)
        self.intrinsic_names = INTRINSIC_NAMES + layout
        # scalars the model lacks (PINHOLE's k1, k2; OPENCV's k3..k6): held at 0 for good
        self.intrinsic_absent = np.array([n not in model_names for n in self.intrinsic_names])
        if model == DEFAULT_MODEL:
            self.intrinsic_absent[:] = False
        self.intrinsic_lower = np.full((g, 6 + len(layout)), -np.inf)
        self.intrinsic_upper = np.full((g, 6 + len(layout)), np.inf)
        self.intrinsic_fixed = np.zeros((g, 6 + len(layout)), dtype=bool)
        self.intrinsic_fixed[:, 6:] = True
        self.intrinsic_fixed[:, self.intrinsic_absent] = True
        if self.square_pixels:
            self.intrinsic_fixed[:, 1] = True
        self.intrinsics_lower, self.extra_lower = self.intrinsic_lower[:, :6], self.intrinsic_lower[:, 6:]
        self.intrinsics_upper, self.extra_upper = self.intrinsic_upper[:, :6], self.intrinsic_upper[:, 6:]
        self.intrinsics_fixed, self.extra_fixed = self.intrinsic_fixed[:, :6], self.intrinsic_fixed[:, 6:]
        self.point_lower = np.full((n, 3), -np.inf)
        self.point_upper = np.full((n, 3), np.inf)
        self.point_fixed = np.zeros((n, 3), dtype=bool)
        self.point_kind = np.zeros(n, dtype=np.int8)
        self.point_origin = np.zeros((n, 3))
        self.point_frame = np.broadcast_to(np.eye(3), (n, 3, 3)).copy()

    # --- construction from robot measurements --------------------------------------------------
    @classmethod
    def from_measured_poses(
        cls,
        measured_poses: Sequence[MeasuredPose],
        camera: Camera | np.ndarray,
        points_world: np.ndarray,
        observations_px: np.ndarray,
        camera_index: np.ndarray,
        point_index: np.ndarray,
        *,
        refine_intrinsics: bool | Sequence[str] = True,
        intrinsics_lower: np.ndarray | None = None,
        intrinsics_upper: np.ndarray | None = None,
    ) -> "BundleProblem":
        """The reference's BCBA problem (sec. 6.2.2): poses bounded by measured ± tolerance.

        Camera centres are bounded per world axis by ``tolerance.position_mm`` and orientations by
        ``|w_i| <= tolerance.orientation_rad[i]``; a zero tolerance fixes the scalar, an infinite one
        leaves it free. One intrinsic group is shared by all frames (a single scope).

        measured_poses : m MeasuredPose. camera : Camera of any model (:func:`lens_block`) or (6,) radial
        intrinsics.
        points_world : (n, 3) mm initial points. observations_px : (K, 2). camera_index, point_index : (K,).
        refine_intrinsics : True (all six; the model's later parameters stay held), False, or names from
            :attr:`intrinsic_names` to refine (the six and the later parameters, e.g. ``"p1"``).
        intrinsics_lower, intrinsics_upper : (6,) optional box on the intrinsics (e.g. from an FOV range).
        """
        if len(measured_poses) == 0:
            raise InputError("the problem is empty: there are no cameras")
        rotations = np.stack([mp.pose.rotation for mp in measured_poses])
        translations = np.stack([mp.pose.translation for mp in measured_poses])
        model, extra = DEFAULT_MODEL, None
        if isinstance(camera, Camera):
            intr, model, extra = lens_block(camera)
        else:
            intr = np.asarray(camera, dtype=float)
        problem = cls(observations_px, camera_index, point_index, rotations, translations, points_world, intr,
                      position_parameter="centre", model=model, extra=extra)
        for c, mp in enumerate(measured_poses):
            half = np.concatenate([mp.tolerance.orientation_rad, mp.tolerance.position_mm])
            value = problem.initial.pose[c]
            exact = half == 0
            problem.pose_fixed[c] = exact
            problem.pose_lower[c] = np.where(exact, -np.inf, value - half)
            problem.pose_upper[c] = np.where(exact, np.inf, value + half)
        if refine_intrinsics is False:
            problem.fix("intrinsics")
        elif refine_intrinsics is not True:
            keep = set(refine_intrinsics)
            problem.fix("intrinsics", components=[n for n in INTRINSIC_NAMES if n not in keep])
            later = [n for n in problem.intrinsic_names[6:] if n in keep]
            if later:
                problem.free("intrinsics", components=later)
        if intrinsics_lower is not None or intrinsics_upper is not None:
            lo = np.full(6, -np.inf) if intrinsics_lower is None else np.asarray(intrinsics_lower, float)
            hi = np.full(6, np.inf) if intrinsics_upper is None else np.asarray(intrinsics_upper, float)
            problem.set_bounds("intrinsics", None, None, lo, hi)
        return problem

    def start_from(self, poses: Sequence[Pose]) -> None:
        """Start the adjustment from ``poses`` (m ``cam_from_world``) instead of the poses the problem was
        built with, keeping every bound and fixed scalar where it is. Each start is clipped into its box,
        and fixed scalars keep their value: a start is a guess, the bounds are the measurement."""
        if len(poses) != self.num_cameras:
            raise InputError(f"{len(poses)} start poses for {self.num_cameras} cameras")
        w = matrix_to_rotvec(np.stack([p.rotation for p in poses]) @ np.swapaxes(self.reference_rotations, 1, 2))
        if self.position_parameter == "centre":
            position = np.stack([p.centre for p in poses])
        else:
            position = np.stack([p.translation for p in poses])
        start = np.clip(np.concatenate([w, position], axis=1), self.pose_lower, self.pose_upper)
        self.initial.pose[:] = np.where(self.pose_fixed, self.initial.pose, start)

    def set_box_prior(self, noise_px: float) -> None:
        """Hold every bounded pose scalar weakly at its box's centre, as its measurement says, besides the box.

        Why: images fix the cameras only up to the gauge (a similarity of all cameras and points together)
        and leave some directions weak (slow bendings of the camera chain; each camera's small rotation
        traded for a shift across the view). Inside its box a bound-constrained adjustment's cost is flat
        along them, so it stops wherever its path, its iteration limit and the arithmetic's last bits leave
        it: on a 30-frame dome with true poses in a 0.5 mm / 0.25 deg box it ended 0.6 mm from the truth in
        one run and 0.05 mm in another (benchmarks/bench_map_box_width.py).

        What the measurement says: a robot's error is zero-mean inside its box of half-width ``a``; read as
        uniform there, its variance is ``a^2 / 3``. Among estimators linear in the measurements, least
        squares weighted by the inverse variances is the best unbiased one for any zero-mean errors of
        those variances (Gauss-Markov), so each scalar ``x`` (in this problem's parameters, where the box is
        ``[mu - a, mu + a]``) gets the term ``0.5 ((x - mu) / sigma)^2`` with ``sigma = a / sqrt(3)``. The
        image residuals are in pixels with noise ``noise_px``; their cost ``0.5 sum r^2`` is the likelihood's
        times ``noise_px^2``, so the prior enters at that scale: ``weight = (noise_px / sigma)^2`` px^2 per
        unit^2. Where the images are decisive the prior changes nothing measurable (their information is
        larger by orders of magnitude); in the weak directions it puts the adjustment where the
        measurements, averaged, say, and makes the minimum unique. The box stays a hard constraint (the
        uniform density's support). Scalars fixed or unbounded get no prior.

        noise_px : the observations' noise, px (> 0).
        """
        if not noise_px > 0:
            raise InputError(f"noise_px must be > 0, got {noise_px}")
        half = 0.5 * (self.pose_upper - self.pose_lower)
        held = np.isfinite(half) & (half > 0) & ~self.pose_fixed
        self.pose_prior_mean = np.where(held, self.pose_lower, 0.0) + np.where(held, half, 0.0)
        self.pose_prior_weight = np.where(held, 3.0 * noise_px**2 / np.where(held, half, 1.0) ** 2, 0.0)

    def pose_prior_cost(self, pose_params: np.ndarray) -> float:
        """The prior's cost ``0.5 sum weight (pose - mean)^2`` at ``pose_params`` (m, 6)."""
        return 0.5 * float(np.sum(self.pose_prior_weight * (pose_params - self.pose_prior_mean) ** 2))

    # --- fixing and bounding -------------------------------------------------------------------
    def _block(self, kind: str):
        if kind == "pose":
            return self.pose_lower, self.pose_upper, self.pose_fixed, POSE_NAMES, self.num_cameras
        if kind == "intrinsics":
            return self.intrinsic_lower, self.intrinsic_upper, self.intrinsic_fixed, self.intrinsic_names, self.num_groups
        if kind == "point":
            return self.point_lower, self.point_upper, self.point_fixed, ("y0", "y1", "y2"), self.num_points
        raise InputError(f"unknown parameter kind {kind!r}; expected pose, intrinsics or point")

    def fix(self, kind: str, items: Iterable[int] | None = None, components: Sequence[str] | None = None) -> None:
        """Hold parameters at their initial values.

        kind : "pose", "intrinsics" or "point". items : indices (cameras, groups, points), None for all.
        components : names (pose: wx wy wz px py pz; intrinsics: :attr:`intrinsic_names`, fx fy cx cy k1 k2
        then the model's later parameters; point: y0 y1 y2), None for all.
        """
        _, _, fixed, names, count = self._block(kind)
        rows = _as_index_list(items, count, kind)
        cols = _components(components, names, kind)
        fixed[np.ix_(rows, cols)] = True

    def free(self, kind: str, items: Iterable[int] | None = None, components: Sequence[str] | None = None) -> None:
        """Undo :meth:`fix` and drop bounds: the parameters become unconstrained. The intrinsics a model
        lacks (:attr:`intrinsic_absent`) and fy with square pixels stay held."""
        lower, upper, fixed, names, count = self._block(kind)
        rows = _as_index_list(items, count, kind)
        cols = _components(components, names, kind)
        if kind == "intrinsics":
            cols = cols[~self.intrinsic_absent[cols]]
            if self.square_pixels:
                cols = cols[cols != 1]
        fixed[np.ix_(rows, cols)] = False
        lower[np.ix_(rows, cols)] = -np.inf
        upper[np.ix_(rows, cols)] = np.inf

    def set_bounds(self, kind: str, items, components, lower, upper) -> None:
        """Box ``lower <= value <= upper`` (eq. 6.2) on the selected scalars, broadcast to (items, components).

        Use -inf / inf for a one-sided bound. Raises InputError if lower > upper or a bound is NaN.
        """
        lo_arr, up_arr, _, names, count = self._block(kind)
        rows = _as_index_list(items, count, kind)
        cols = _components(components, names, kind)
        shape = (rows.size, cols.size)
        lo = np.broadcast_to(np.asarray(lower, dtype=float), shape)
        up = np.broadcast_to(np.asarray(upper, dtype=float), shape)
        if np.isnan(lo).any() or np.isnan(up).any():
            raise InputError(f"{kind} bounds contain NaN")
        if np.any(lo > up):
            r, c = np.argwhere(lo > up)[0]
            raise InputError(
                f"{kind} {rows[r]} {names[cols[c]]}: lower bound {lo[r, c]:g} > upper bound {up[r, c]:g}"
            )
        lo_arr[np.ix_(rows, cols)] = lo
        up_arr[np.ix_(rows, cols)] = up

    def bound_poses(
        self,
        cameras: Iterable[int] | None = None,
        *,
        position_mm: float | np.ndarray | None = None,
        orientation_rad: float | np.ndarray | None = None,
    ) -> None:
        """Bound poses to their initial values ± half-widths (per axis, broadcast to (3,)).

        position_mm : half-width on the position parameter (camera centre or translation), mm.
        orientation_rad : half-width on each component of ``w``, rad.
        """
        rows = _as_index_list(cameras, self.num_cameras, "camera")
        for offset, half in ((3, position_mm), (0, orientation_rad)):
            if half is None:
                continue
            h = np.broadcast_to(np.asarray(half, dtype=float), (3,))
            if np.any(~(h >= 0)):
                raise InputError(f"pose half-widths must be non-negative, got {h}")
            value = self.initial.pose[rows, offset:offset + 3]
            self.set_bounds("pose", rows, list(POSE_NAMES[offset:offset + 3]), value - h, value + h)

    def bound_point_depth(
        self,
        origin_mm: np.ndarray,
        axis: np.ndarray,
        min_mm: float,
        max_mm: float,
        points: Iterable[int] | None = None,
    ) -> None:
        """Bound the depth ``axis . (X - origin)`` of points to ``[min_mm, max_mm]``.

        The points are re-parameterised as ``X = origin + Q y`` with ``Q[:, 2] = axis`` (unit), so the
        depth is the box bound ``min_mm <= y_2 <= max_mm`` and ``y_0, y_1`` are free. For the depth
        along a camera's optical axis use ``origin = pose.centre`` and ``axis = pose.rotation[2]``.
        origin_mm : (3,) or (n_sel, 3); axis : (3,) or (n_sel, 3), need not be unit.
        """
        rows = _as_index_list(points, self.num_points, "point")
        if not min_mm <= max_mm:
            raise InputError(f"depth bound: min {min_mm:g} mm > max {max_mm:g} mm")
        origin = np.broadcast_to(np.asarray(origin_mm, dtype=float), (rows.size, 3))
        ax = np.broadcast_to(np.asarray(axis, dtype=float), (rows.size, 3))
        norm = np.linalg.norm(ax, axis=1)
        if not np.all(norm > 0) or not np.all(np.isfinite(origin)):
            raise InputError("depth bound: the axis must be a non-zero finite vector and the origin finite")
        z = ax / norm[:, None]
        frame = _frames_with_z(z)
        world = self.points_world(self.initial.points)[rows]
        self.point_kind[rows] = POINT_LINEAR
        self.point_origin[rows] = origin
        self.point_frame[rows] = frame
        self.initial.points[rows] = np.einsum("nji,nj->ni", frame, world - origin)
        self.point_lower[rows] = [-np.inf, -np.inf, min_mm]
        self.point_upper[rows] = [np.inf, np.inf, max_mm]

    def bound_points_to_shell(
        self,
        centre_mm: np.ndarray,
        r_min_mm: float,
        r_max_mm: float,
        points: Iterable[int] | None = None,
        *,
        pole_axis: np.ndarray | None = None,
    ) -> None:
        """Keep points in the spherical shell ``r_min_mm <= |X - centre| <= r_max_mm``.

        The points are re-parameterised in spherical coordinates ``(r, theta, phi)`` about the centre,
        so the shell is the box bound on ``r`` and the angles are free. The coordinates are singular at
        the poles (theta = 0, pi); by default the pole axis is chosen perpendicular to the mean
        direction of the points from the centre, which keeps a cap of up to ±80° clear of them.
        """
        rows = _as_index_list(points, self.num_points, "point")
        if not 0 <= r_min_mm <= r_max_mm:
            raise InputError(f"shell bound: need 0 <= r_min <= r_max, got r_min={r_min_mm:g}, r_max={r_max_mm:g} mm")
        centre = np.asarray(centre_mm, dtype=float).reshape(3)
        world = self.points_world(self.initial.points)[rows]
        rel = world - centre
        if pole_axis is None:
            mean_dir = rel.mean(axis=0)
            if np.linalg.norm(mean_dir) < 1e-12:
                mean_dir = np.array([1.0, 0.0, 0.0])
            mean_dir /= np.linalg.norm(mean_dir)
            helper = np.eye(3)[np.argmin(np.abs(mean_dir))]
            pole = np.cross(mean_dir, helper)
        else:
            pole = np.asarray(pole_axis, dtype=float).reshape(3)
        if not np.linalg.norm(pole) > 0:
            raise InputError("shell bound: the pole axis must be non-zero")
        frame = _frames_with_z(pole[None] / np.linalg.norm(pole))[0]
        local = rel @ frame
        r = np.linalg.norm(local, axis=1)
        theta = np.arccos(np.clip(local[:, 2] / np.where(r > 0, r, 1.0), -1.0, 1.0))
        phi = np.arctan2(local[:, 1], local[:, 0])
        self.point_kind[rows] = POINT_SPHERICAL
        self.point_origin[rows] = centre
        self.point_frame[rows] = frame
        self.initial.points[rows] = np.stack([r, theta, phi], axis=1)
        self.point_lower[rows] = [r_min_mm, -np.inf, -np.inf]
        self.point_upper[rows] = [r_max_mm, np.inf, np.inf]

    # --- parameter decoding --------------------------------------------------------------------
    def camera_state(self, pose_params: np.ndarray):
        """Rotations (m, 3, 3), translations (m, 3) mm and SO(3) left Jacobians (m, 3, 3) of the poses."""
        w = pose_params[:, :3]
        rot = rotvec_to_matrix(w) @ self.reference_rotations
        if self.position_parameter == "centre":
            trans = -np.einsum("mij,mj->mi", rot, pose_params[:, 3:])
        else:
            trans = pose_params[:, 3:].copy()
        return np.ascontiguousarray(rot), np.ascontiguousarray(trans), np.ascontiguousarray(so3_left_jacobian(w))

    def points_world(self, point_params: np.ndarray, with_jacobian: bool = False):
        """World points (n, 3) mm from point parameters (n, 3); optionally also d X / d y (n, 3, 3)."""
        y = np.asarray(point_params, dtype=float)
        sph = self.point_kind == POINT_SPHERICAL
        if not sph.any():
            # linear points only: X = o + Q y and d X / d y = Q, without n products by the identity
            world = self.point_origin + np.einsum("nij,nj->ni", self.point_frame, y)
            return (world, np.array(self.point_frame, order="C")) if with_jacobian else world
        local = y.copy()
        jac_local = np.broadcast_to(np.eye(3), y.shape + (3,)).copy() if with_jacobian else None
        r, th, ph = y[sph, 0], y[sph, 1], y[sph, 2]
        st, ct, sp, cp = np.sin(th), np.cos(th), np.sin(ph), np.cos(ph)
        u = np.stack([st * cp, st * sp, ct], axis=1)
        local[sph] = r[:, None] * u
        if with_jacobian:
            du_dth = np.stack([ct * cp, ct * sp, -st], axis=1)
            du_dph = np.stack([-st * sp, st * cp, np.zeros_like(st)], axis=1)
            jac_local[sph] = np.stack([u, r[:, None] * du_dth, r[:, None] * du_dph], axis=2)
        world = self.point_origin + np.einsum("nij,nj->ni", self.point_frame, local)
        if not with_jacobian:
            return world
        return world, np.ascontiguousarray(self.point_frame @ jac_local)

    def poses(self, pose_params: np.ndarray) -> list[Pose]:
        rot, trans, _ = self.camera_state(pose_params)
        return [Pose(r, t) for r, t in zip(rot, trans)]

    # --- flat views used by the solver ---------------------------------------------------------
    @property
    def refines_extra(self) -> bool:
        """Whether one of the model's later parameters is free: then the camera side has their blocks."""
        return bool(self.extra.shape[1]) and not self.extra_fixed.all()

    @property
    def num_camera_blocks(self) -> int:
        """6-blocks on the camera side: m poses, g intrinsic groups, and g blocks of later lens parameters
        when :attr:`refines_extra`."""
        return self.num_cameras + self.num_groups * (2 if self.refines_extra else 1)

    def camera_bounds(self):
        """lower, upper (6 B,) and fixed (6 B,) bool on the camera side, B = :attr:`num_camera_blocks` (the
        later lens parameters' padding held)."""
        lower = [self.pose_lower.ravel(), self.intrinsics_lower.ravel()]
        upper = [self.pose_upper.ravel(), self.intrinsics_upper.ravel()]
        fixed = [self.pose_fixed.ravel(), self.intrinsics_fixed.ravel()]
        if self.refines_extra:
            pad = EXTRA_BLOCK - self.extra.shape[1]
            g = self.num_groups
            lower.append(np.hstack([self.extra_lower, np.full((g, pad), -np.inf)]).ravel())
            upper.append(np.hstack([self.extra_upper, np.full((g, pad), np.inf)]).ravel())
            fixed.append(np.hstack([self.extra_fixed, np.ones((g, pad), dtype=bool)]).ravel())
        return np.concatenate(lower), np.concatenate(upper), np.concatenate(fixed)

    def cam_blocks(self) -> np.ndarray:
        """(K, H) int64: per stored observation its pose block and its intrinsic block, and (H = 3) its later
        lens parameters' block when :attr:`refines_extra`."""
        group = self.num_cameras + self.intrinsics_index[self.camera_index]
        blocks = [self.camera_index, group]
        if self.refines_extra:
            blocks.append(group + self.num_groups)
        return np.ascontiguousarray(np.stack(blocks, axis=1))

    @property
    def num_observations(self) -> int:
        return int(self.observations_px.shape[0])

    @property
    def num_parameters(self) -> int:
        later = int((~self.intrinsic_absent[6:]).sum())
        return (6 + later) * self.num_groups + 6 * self.num_cameras + 3 * self.num_points

    def num_free_parameters(self) -> int:
        _, _, fixed_c = self.camera_bounds()
        return int((~fixed_c).sum() + (~self.point_fixed).sum())

    def validate(self) -> None:
        """Check bounds and that every non-fixed point is seen by at least two cameras (InputError)."""
        for kind in ("pose", "intrinsics", "point"):
            lower, upper, _, names, _ = self._block(kind)
            if np.isnan(lower).any() or np.isnan(upper).any():
                raise InputError(f"{kind} bounds contain NaN")
            bad = lower > upper
            if bad.any():
                r, c = np.argwhere(bad)[0]
                raise InputError(f"{kind} {r} {names[c]}: lower bound {lower[r, c]:g} > upper bound {upper[r, c]:g}")
        counts = np.diff(self.point_ptr)
        distinct = np.ones(self.num_observations, dtype=bool)
        same = (self.point_index[1:] == self.point_index[:-1]) & (self.camera_index[1:] == self.camera_index[:-1])
        distinct[1:] = ~same
        n_cams = np.bincount(self.point_index[distinct], minlength=self.num_points)
        weak = (n_cams < 2) & ~self.point_fixed.all(axis=1)
        if weak.any():
            j = int(np.flatnonzero(weak)[0])
            seen = np.unique(self.camera_index[self.point_ptr[j]:self.point_ptr[j + 1]]).tolist()
            raise InputError(
                f"point {j} is observed by {len(seen)} camera(s) {seen} (of {int(weak.sum())} such points); "
                "a point needs at least two cameras unless it is fixed"
                + ("" if counts[j] else ": it has no observations")
            )

    def summary(self) -> str:
        _, _, fixed_c = self.camera_bounds()
        lower_c, upper_c, _ = self.camera_bounds()
        bounded_c = int((np.isfinite(lower_c) | np.isfinite(upper_c))[~fixed_c].sum())
        bounded_p = int((np.isfinite(self.point_lower) | np.isfinite(self.point_upper))[~self.point_fixed].sum())
        return (
            f"BundleProblem: {self.num_cameras} cameras, {self.num_points} points, {self.num_observations} "
            f"observations, {self.num_groups} intrinsic group(s); {self.num_free_parameters()} of "
            f"{self.num_parameters} parameters free ({bounded_c + bounded_p} bounded); positions as "
            f"{self.position_parameter}"
        )


def _frames_with_z(z: np.ndarray) -> np.ndarray:
    """(n, 3) unit vectors -> (n, 3, 3) right-handed orthonormal frames whose third column is z."""
    helper = np.eye(3)[np.argmin(np.abs(z), axis=1)]
    x = np.cross(helper, z)
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=2)
