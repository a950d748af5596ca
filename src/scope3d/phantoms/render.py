"""Ray-cast renderer with the photometry that matters to feature matching and stereo on scope images.

Light comes from the scope tip (a point light at the camera centre), so a surface point at distance
``d`` (mm) with unit normal ``n`` seen along the unit ray ``r`` receives ``cos i / d^2`` with
``cos i = |n . r|``: near regions are bright, far ones dark and noisy, as in the reference's endoscope
images (sec. 7.3: "the outer scans of original SFE image were dark, which introduced much noise").
The radiance towards the camera is::

    L = albedo * cos i / d^2  +  specular * cos(n, h)^shininess / d^2

(Blinn-Phong; with the light at the eye the half-vector ``h`` is the ray itself). An exposure gain
maps ``L`` to [0, 1]; then optional optical blur, Gaussian sensor noise whose variance grows with the
signal (read + shot noise), quantisation to 8 bits, and black outside the circular field.

Fluorescent targets (sec. 4.2) emit green under the blue excitation: in the fluorescence channel they
appear with ``efficiency * cos i / d^2`` over a dark, noisy background; in reflectance they are nearly
clear (their albedo is reduced by ``target_reflectance_contrast`` only).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from functools import lru_cache

import cv2
import numpy as np

from scope3d.geometry.pose import Pose
from scope3d.phantoms.lenses import vignetting
from scope3d.phantoms.scenes import Scene
from scope3d.sensor.camera import Camera
from scope3d.utils.aot import load_kernels

# compiled at install (scope3d.utils.aot) or, failing that, by numba on first use
_kernels = load_kernels("scope3d.phantoms.render_kernels")


@dataclass(frozen=True)
class RenderOptions:
    """Sensor and appearance settings (intensities are fractions of full scale, 1 = 255).

    read_noise : std of signal-independent Gaussian noise. 0.008 is about 2 grey levels.
    shot_noise : std of signal-dependent noise at full scale; at intensity I the std is shot_noise * sqrt(I).
    blur_sigma_px : Gaussian optical blur (pixels), 0 = sharp.
    exposure_level : auto-exposure puts the ``exposure_percentile`` of the frame's radiance at this level,
        leaving headroom for specular highlights.
    exposure_percentile : percent, see above.
    target_reflectance_contrast : fraction by which targets darken the reflectance image ("nearly clear").
    fluorescence_efficiency : target emission relative to a white Lambertian reflector under the same gain.
    fluorescence_background : autofluorescence of the rest of the scene, same units.
    fluorescence_noise : std of the fluorescence channel's noise (the detector runs at high gain).
    supersample : int or None, anti-aliasing: each pixel's intensity is the mean radiance of
        ``supersample x supersample`` rays spread evenly over the pixel square (offsets
        ``(i + 0.5) / k - 0.5`` px), as a sensor integrates light over its pixel; sharp edges (thread
        crests, highlights) then no longer alias differently in each view. The textures are read at the
        sub-ray footprint, so the box average is their only low-pass. Depth and target id stay those of
        the ray through the pixel centre (exact geometric truth, as with one ray). 1 = one ray per pixel;
        None = the scene's default (:attr:`~scope3d.phantoms.scenes.Scene.render_supersample`: 2 for the
        thread, 1 elsewhere: one ray per pixel).
    vignetting : the lens's relative illumination ``cos(theta)^vignetting`` (theta: the pixel ray's angle
        from the optical axis), applied to the radiance reaching the sensor, reflectance and fluorescence
        alike (:func:`scope3d.phantoms.lenses.vignetting`); 0 or None: none (None lets
        :func:`~scope3d.phantoms.lab.generate` take the lens's own).
    """

    read_noise: float = 0.008
    shot_noise: float = 0.02
    blur_sigma_px: float = 0.0
    exposure_level: float = 0.8
    exposure_percentile: float = 99.0
    target_reflectance_contrast: float = 0.03
    fluorescence_efficiency: float = 0.9
    fluorescence_background: float = 0.02
    fluorescence_noise: float = 0.015
    supersample: int | None = None
    vignetting: float | None = None

    def __post_init__(self) -> None:
        if self.vignetting is not None and not (np.isfinite(self.vignetting) and self.vignetting >= 0):
            raise ValueError(f"vignetting must be None or a non-negative exponent, got {self.vignetting!r}")
        if self.supersample is not None and not (isinstance(self.supersample, (int, np.integer))
                                                 and 1 <= self.supersample <= 8):
            raise ValueError(f"supersample must be None or an integer from 1 to 8, got {self.supersample!r}")
        for name in ("read_noise", "shot_noise", "blur_sigma_px", "target_reflectance_contrast",
                     "fluorescence_efficiency", "fluorescence_background", "fluorescence_noise"):
            if getattr(self, name) < 0:
                raise ValueError(f"render option {name} must be non-negative")
        if not 0 < self.exposure_level <= 1:
            raise ValueError("exposure_level must be in (0, 1]")
        if not 0 < self.exposure_percentile <= 100:
            raise ValueError("exposure_percentile must be in (0, 100]")

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class RenderedFrame:
    """One rendered view.

    image : (H, W, 3) uint8 RGB reflectance; black outside the mask.
    fluorescence : (H, W, 3) uint8 with the emission in the green channel, or None if the scene has no targets.
    depth_mm : (H, W) float32 z-depth in the camera frame, NaN where no surface or outside the mask.
    target_id : (H, W) int16, id of the fluorescent target seen at each pixel, 0 elsewhere.
    exposure : float, the gain used (radiance -> intensity).
    """

    image: np.ndarray
    fluorescence: np.ndarray | None
    depth_mm: np.ndarray
    target_id: np.ndarray
    exposure: float


@dataclass(frozen=True)
class _Radiance:
    valid: np.ndarray  # (H, W) bool, inside the mask
    hit: np.ndarray  # (M,) bool over valid pixels
    reflect: np.ndarray  # (M, 3) float, radiance (0 where no hit)
    fluor: np.ndarray  # (M,) float
    depth: np.ndarray  # (M,) float, NaN where no hit
    target: np.ndarray  # (M,) int16


def _target_ids(scene: Scene, points: np.ndarray) -> np.ndarray:
    """(N,) int16 id of the target each surface point (N, 3) mm lies on, 0 elsewhere.

    ``TrueTarget.contains`` is exact but costs a few array passes over every point; a frame sees ~300k
    points and a target covers a few mm. Only points inside the world box that bounds the target's
    region (outline box x depth range, padded by 1 µm against rounding) can be on it, and ``contains``
    decides point by point, so asking it about those points alone gives the same answer.
    """
    tid = np.zeros(len(points), np.int16)
    xs = np.ascontiguousarray(points[:, 0]) if scene.targets else None
    for tgt in scene.targets:
        lo_uv, hi_uv = tgt.outline_uv_mm.min(axis=0), tgt.outline_uv_mm.max(axis=0)
        corners_local = np.array([[u, v, h] for u in (lo_uv[0], hi_uv[0]) for v in (lo_uv[1], hi_uv[1])
                                  for h in (-tgt.depth_range_mm, 0.0)])
        corners = tgt.origin_mm + corners_local @ tgt.frame
        lo, hi = corners.min(axis=0) - 1e-3, corners.max(axis=0) + 1e-3
        # Narrow axis by axis: after the first axis only a thin slab of the points is left to test.
        cand = np.flatnonzero((xs >= lo[0]) & (xs <= hi[0]))
        for axis in (1, 2):
            coord = points[cand, axis]
            cand = cand[(coord >= lo[axis]) & (coord <= hi[axis])]
        if cand.size:
            tid[cand[tgt.contains(points[cand])]] = tgt.id
    return tid


def _shade(scene: Scene, camera: Camera, pose: Pose, origins: np.ndarray, dirs: np.ndarray, options: RenderOptions,
           footprint_scale: float = 1.0, *, geometry_only: bool = False):
    """Cast rays (N, 3) and shade them: (hits, reflect (N, 3) float32, fluor (N,) float32, target (N,) int16).

    footprint_scale : fraction of a pixel each ray stands for (1 / supersample), for the texture's mip level.
    geometry_only : only the hits and target ids (reflect and fluor stay 0): the supersampled path shades
        the sub-rays instead of the centre ray.
    """
    hits = scene.caster.cast(origins, dirs)
    hit = hits.hit
    m = len(dirs)
    # Where every ray hits (the usual close-up view), select with a slice: views, no gathers or scatters.
    sel = slice(None) if hit.all() else hit
    reflect = np.zeros((m, 3), np.float32)
    fluor = np.zeros(m, np.float32)
    target = np.zeros(m, np.int16)
    if geometry_only and np.any(hit):
        target[sel] = _target_ids(scene, hits.points[sel])
    elif np.any(hit):
        pts, nrm, d = hits.points[sel], hits.normals[sel], dirs[sel]
        dist = hits.distance_mm[sel]
        n_hit = len(dist)
        cos_i, falloff, footprint = np.empty(n_hit), np.empty(n_hit, np.float32), np.empty(n_hit)
        # Pixel size on the surface: distance / focal length, widened on oblique surfaces.
        _kernels.incidence(np.ascontiguousarray(nrm), np.ascontiguousarray(d), np.ascontiguousarray(dist),
                           float(footprint_scale), float(np.sqrt(camera.fx * camera.fy)), cos_i, falloff, footprint)
        albedo = scene.albedo(pts, nrm, footprint)
        tid = _target_ids(scene, pts)
        rows = np.arange(m) if isinstance(sel, slice) else np.flatnonzero(hit)
        # float32 factor: NumPy takes a Python float against the float32 albedo as float32
        _kernels.shade(np.ascontiguousarray(albedo, np.float32), tid, falloff, cos_i, np.ascontiguousarray(dist),
                       np.float32(1.0 - options.target_reflectance_contrast), float(scene.material.specular),
                       float(scene.material.shininess), float(options.fluorescence_efficiency),
                       float(options.fluorescence_background), rows, reflect, fluor, target)
    return hits, reflect, fluor, target


def supersample_factor(scene: Scene, *, options: RenderOptions) -> int:
    """Rays per pixel side actually used: ``options.supersample``, or the scene's default when None."""
    return int(options.supersample if options.supersample is not None else getattr(scene, "render_supersample", 1))


@lru_cache(maxsize=8)
def _camera_rays(camera: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What every frame of a camera shares: the valid mask (H, W) bool (the circular field, and the lens's
    field: :meth:`~scope3d.sensor.camera.Camera.valid_mask`), the pixel centres inside it
    (M, 2) and their unit rays in the camera frame (M, 3), :meth:`~scope3d.sensor.camera.Camera.unproject`'s.
    A frame only rotates the rays (the same product as ``Camera.pixel_rays_world``, so the same bits):
    undistorting them cost ~20 % of a frame. Cached per camera (a frozen, hashable value; read-only arrays)."""
    valid = camera.valid_mask()
    pixels = camera.pixel_grid()[valid]
    rays = camera.unproject(pixels)
    for array in (valid, pixels, rays):
        array.setflags(write=False)
    return valid, pixels, rays


def _rows_times(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a @ b`` for (N, 3) ``a`` and (3, 3) ``b``, each entry summed as ``a0 b0k + a1 b1k + a2 b2k`` in one
    compiled pass: the same sums in the same order as the column-by-column NumPy product it replaced, without
    BLAS, whose threads cost ~5x the arithmetic for N ~ 3e5 on a loaded machine."""
    out = np.empty((len(a), 3))
    _kernels.rotate_rows(np.ascontiguousarray(a, float), np.ascontiguousarray(b, float), out)
    return out


def _radiance(scene: Scene, camera: Camera, pose: Pose, options: RenderOptions) -> _Radiance:
    valid, pixels, rays = _camera_rays(camera)
    dirs = _rows_times(rays, pose.rotation)
    origins = np.broadcast_to(pose.centre, dirs.shape)
    k = supersample_factor(scene, options=options)
    # The centre ray gives the geometric truth (depth, target id) and, with one ray per pixel, the shading.
    hits, reflect, fluor, target = _shade(scene, camera, pose, origins, dirs, options, geometry_only=k > 1)
    if k > 1:
        # k x k rays evenly spread over each pixel square; their mean radiance is the pixel's (box filter).
        # Done in chunks of pixels so the ray arrays stay a few tens of MB at 608 x 608 and k = 3.
        off = (np.arange(k) + 0.5) / k - 0.5
        offsets = np.stack(np.meshgrid(off, off), axis=-1).reshape(-1, 2)  # (k^2, 2) px
        chunk = max(1, 400_000 // (k * k))
        for s0 in range(0, len(pixels), chunk):
            sub = (pixels[s0:s0 + chunk, None, :] + offsets[None]).reshape(-1, 2)
            d = _rows_times(camera.unproject(sub), pose.rotation)
            o = np.broadcast_to(pose.centre, d.shape)
            _, r, f, _ = _shade(scene, camera, pose, o, d, options, footprint_scale=1.0 / k)
            n = len(sub) // (k * k)
            reflect[s0:s0 + n] = r.reshape(n, k * k, 3).mean(axis=1)
            fluor[s0:s0 + n] = f.reshape(n, k * k).mean(axis=1)
    if options.vignetting:
        # the lens passes less light off axis: the radiance reaching each pixel, before exposure and noise
        falloff = vignetting(rays, options.vignetting).astype(np.float32)
        reflect *= falloff[:, None]
        fluor *= falloff
    hit = hits.hit
    depth = np.empty(len(pixels))
    _kernels.depth_along(hits.points, np.ascontiguousarray(hit), np.ascontiguousarray(pose.centre, float),
                         np.ascontiguousarray(pose.optical_axis, float), depth)
    # a writable copy of the cached mask: the compiled sensor model takes writable arrays (a read-only one
    # would make numba compile another specialisation on the JIT path)
    return _Radiance(valid.copy(), hit, reflect, fluor, depth, target)


def auto_exposure(radiance: np.ndarray, *, options: RenderOptions) -> float:
    """Gain putting the ``exposure_percentile`` of the (M, 3) radiance's brightest channel at ``exposure_level``."""
    peak = radiance.max(axis=1) if radiance.ndim == 2 else radiance
    peak = peak[peak > 0]
    if peak.size == 0:
        return 1.0
    return float(options.exposure_level / np.percentile(peak, options.exposure_percentile))


def _to_image(values: np.ndarray, valid: np.ndarray, gain: float, noise: tuple[float, float], blur: float,
              rng: np.random.Generator) -> np.ndarray:
    """(M, C) radiance at the valid pixels -> (H, W, C) uint8 with blur, noise and the mask applied."""
    h, w = valid.shape
    channels = values.shape[1]
    gain32 = np.float32(gain)  # float32 constants, as NumPy takes a Python float against a float32 array
    if blur > 0:
        img = np.zeros((h, w, channels), np.float32)
        img[valid] = values * gain
        values, gain32 = cv2.GaussianBlur(img, (0, 0), blur).reshape(h * w, channels), np.float32(1.0)
    read, shot = noise
    normal = rng.standard_normal((h, w, channels), dtype=np.float32)
    out = np.empty((h, w, channels), np.uint8)
    _kernels.noisy_uint8(np.ascontiguousarray(values, np.float32), blur <= 0, np.ascontiguousarray(valid), normal,
                         gain32, np.float32(shot**2), np.float32(read**2), out)
    return out


def render_frame(
    scene: Scene,
    camera: Camera,
    pose: Pose,
    *,
    seed: int = 0,
    frame_index: int = 0,
    exposure: float | None = None,
    options: RenderOptions = RenderOptions(),
) -> RenderedFrame:
    """Render one view of ``scene`` from the camera at ``pose`` (true ``cam_from_world``, mm).

    seed, frame_index : the sensor noise is drawn from ``default_rng([seed, frame_index])``, so a sequence
        is reproducible frame by frame.
    exposure : gain from radiance to intensity; None picks it from this frame (auto-exposure).
    """
    rad = _radiance(scene, camera, pose, options)
    gain = auto_exposure(rad.reflect[rad.hit], options=options) if exposure is None else float(exposure)
    rng = np.random.default_rng([seed, frame_index])
    image = _to_image(rad.reflect, rad.valid, gain, (options.read_noise, options.shot_noise),
                      options.blur_sigma_px, rng)
    fluorescence = None
    if scene.targets:
        g = _to_image(rad.fluor[:, None], rad.valid, gain, (options.fluorescence_noise, options.shot_noise),
                      options.blur_sigma_px, rng)[..., 0]
        fluorescence = np.zeros_like(image)
        fluorescence[..., 1] = g
    h, w = rad.valid.shape
    depth = np.full((h, w), np.nan, np.float32)
    depth[rad.valid] = rad.depth
    target_id = np.zeros((h, w), np.int16)
    target_id[rad.valid] = rad.target
    return RenderedFrame(image, fluorescence, depth, target_id, gain)


def sequence_exposure(scene: Scene, camera: Camera, poses: list[Pose], *, options: RenderOptions = RenderOptions(),
                      probe_px: int = 96) -> float:
    """One gain for a whole sequence (a fixed, auto-exposed setting): the median over frames of each frame's
    auto-exposure, measured on a ``probe_px``-wide copy of the camera so that it costs little."""
    scale = min(1.0, probe_px / camera.width)
    # the distortion acts on normalised coordinates: only the focal lengths and principal point scale
    params = camera.params.copy()
    params[:4] = [camera.fx * scale, camera.fy * scale, (camera.cx + 0.5) * scale - 0.5, (camera.cy + 0.5) * scale - 0.5]
    probe = Camera.from_params(max(8, int(round(camera.width * scale))), max(8, int(round(camera.height * scale))),
                               camera.model, params,
                               mask_radius_px=None if camera.mask_radius_px is None else camera.mask_radius_px * scale)
    gains = []
    for pose in poses:
        rad = _radiance(scene, probe, pose, options)
        if np.any(rad.hit):
            gains.append(auto_exposure(rad.reflect[rad.hit], options=options))
    return float(np.median(gains)) if gains else 1.0
