"""The compiled passes of axial stereo are the OpenCV + NumPy computations they replace, bit for bit: the
sub-pixel refinement (mvs/refine_kernels.py) and the reliability tests (the same module)."""
import cv2
import numpy as np
import pytest

from scope3d.geometry.pose import Pose
from scope3d.geometry.rotation import look_at
from scope3d.mvs import dense_matching
from scope3d.mvs.axial import make_axial_pair
from scope3d.mvs.confidence import ConfidenceOptions, reliability
from scope3d.mvs.dense_matching import refine_subpixel
from scope3d.sensor.camera import Camera
from scope3d.utils import row_blocks


def _reference_refine(left, right, disparity, window_px, window_rows, iterations, max_shift_px, search_range):
    """The refinement as whole-frame OpenCV and NumPy operations (the code before the compiled passes):
    a two-channel Lanczos-4 cv2.remap of the right image and its gradient, cv2.boxFilter window means."""
    left_f = np.asarray(left, dtype=np.float32)
    right_f = np.asarray(right, dtype=np.float32)
    start = np.asarray(disparity, dtype=np.float32)
    known = np.isfinite(start)
    d = np.where(known, start, 0.0).astype(np.float32)
    h, w = left_f.shape
    grad = cv2.Sobel(right_f, cv2.CV_32F, 1, 0, ksize=1, scale=0.5)
    xs = np.broadcast_to(np.arange(w, dtype=np.float32), (h, w))
    ys = np.broadcast_to(np.arange(h, dtype=np.float32)[:, None], (h, w))
    n = float(window_px * window_rows)

    def mean(a):
        return cv2.boxFilter(a, cv2.CV_32F, (window_px, window_rows), normalize=True, borderType=cv2.BORDER_REFLECT)

    mu_l = mean(left_f)
    var_l = np.maximum(mean(left_f * left_f) - mu_l * mu_l, 1e-6)
    right_and_grad = cv2.merge([right_f, grad])

    def statistics(d):
        map_x = (xs - d).astype(np.float32)
        warped, g = cv2.split(cv2.remap(right_and_grad, map_x, ys, cv2.INTER_LANCZOS4, borderMode=cv2.BORDER_REPLICATE))
        mu_w, mu_g = mean(warped), mean(g)
        var_w = np.maximum(mean(warped * warped) - mu_w * mu_w, 1e-6)
        var_g = np.maximum(mean(g * g) - mu_g * mu_g, 0.0)
        cov_lw = mean(left_f * warped) - mu_l * mu_w
        a = np.sqrt(var_l / var_w)
        jj = a * a * var_g
        ee = np.maximum(var_l - 2 * a * cov_lw + a * a * var_w, 0.0)
        cov_gl = mean(g * left_f) - mu_g * mu_l
        cov_gw = mean(g * warped) - mu_g * mu_w
        return a * (cov_gl - a * cov_gw), jj, ee

    for _ in range(max(iterations, 1)):
        je, jj, _ = statistics(d)
        with np.errstate(divide="ignore", invalid="ignore"):
            delta = np.where(jj > 1e-9, -je / jj, 0.0)
        d = d + np.clip(delta, -0.5, 0.5).astype(np.float32)
    _, jj, ee = statistics(d)
    with np.errstate(divide="ignore", invalid="ignore"):
        sigma = np.sqrt(ee / (n * jj))
    cost = np.sqrt(ee)
    bad = ~known | (np.abs(d - start) > max_shift_px)
    bad |= (d < search_range[0] - 0.5) | (d > search_range[1] - 0.5)
    return [np.where(bad, np.nan, x).astype(np.float32) for x in (d, cost, sigma)]


def _textured_pair(shape, shift_px, seed):
    """A smooth random texture and its copy shifted by ``shift_px`` columns, with flat and dark patches (the
    floors of the variances) and 8-bit noise; a start disparity off by up to 0.7 column, NaN in places."""
    rng = np.random.default_rng(seed)
    base = cv2.GaussianBlur(rng.uniform(0, 255, (shape[0], shape[1] + 40)).astype(np.float32), (0, 0), 1.5)
    left = base[:, 20 : 20 + shape[1]]
    right = cv2.remap(base, (np.arange(shape[1], dtype=np.float32) + 20 + shift_px)[None, :].repeat(shape[0], 0),
                      np.arange(shape[0], dtype=np.float32)[:, None].repeat(shape[1], 1), cv2.INTER_CUBIC)
    left, right = (np.clip(x + rng.normal(0, 1.0, shape), 0, 255).astype(np.uint8) for x in (left, right))
    left[5:12, 10:30] = 0  # no texture and no light: var_l and var_w take their floor, mean(J^2) is 0
    right[5:12, 10:30] = 0
    start = (shift_px + rng.uniform(-0.7, 0.7, shape)).astype(np.float32)
    start[rng.uniform(size=shape) < 0.1] = np.nan
    return left, right, start


@pytest.mark.parametrize("shape, window, iterations, block_rows", [
    ((60, 90), (5, 21), 1, 128),  # the axial pipeline's window, one block
    ((70, 50), (7, 7), 3, 16),  # the default window, several iterations, blocks cut mid-frame
    ((9, 40), (5, 21), 1, 4),  # windows taller than the image: reflected more than once
])
def test_compiled_refinement_is_the_opencv_numpy_computation(monkeypatch, shape, window, iterations, block_rows):
    monkeypatch.setattr(row_blocks, "BLOCK_ROWS", block_rows)
    left, right, start = _textured_pair(shape, 6.3, seed=shape[0])
    kw = dict(window_px=window[0], window_rows=window[1], iterations=iterations, max_shift_px=1.0, search_range=(0, 32))
    got = refine_subpixel(left, right, start, **kw)
    want = _reference_refine(left, right, start, window[0], window[1], iterations, 1.0, (0, 32))
    assert np.isfinite(got.disparity).mean() > 0.5  # the comparison covers refined values, not only NaN
    for name, g, w in zip(("disparity", "cost", "sigma"), (got.disparity, got.cost, got.sigma), want):
        assert np.array_equal(g, w, equal_nan=True), name


def test_lanczos_weights_are_opencvs_interpolation():
    """The warp's table resamples like cv2.remap at any position of a 1/32 pixel phase."""
    weights = dense_matching._lanczos_weights()
    np.testing.assert_allclose(weights.sum(axis=1), 1.0, atol=1e-6)  # a partition of unity (float32 sums)
    assert weights[0, 3] == 1.0 and np.count_nonzero(weights[0]) == 1  # phase 0 copies the pixel
    np.testing.assert_array_equal(weights[16], weights[16, ::-1])  # half a pixel: symmetric


def _reference_reliability(front, rear, disparity, cost, disparity_sigma, pair, valid, options):
    """The reliability tests as whole-frame OpenCV and NumPy operations (the code before the compiled pass)."""
    k = (options.window_px, options.window_px)
    img = front.astype(np.float32)
    mean_f = cv2.boxFilter(img, cv2.CV_32F, k, borderType=cv2.BORDER_REFLECT)
    var = cv2.boxFilter(img * img, cv2.CV_32F, k, borderType=cv2.BORDER_REFLECT) - mean_f * mean_f
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=1, scale=0.5)
    grad_f = np.sqrt(np.maximum(cv2.boxFilter(gx * gx, cv2.CV_32F, k, borderType=cv2.BORDER_REFLECT), 0))
    std_f = np.sqrt(np.maximum(var, 0))
    mean_r = cv2.boxFilter(rear.astype(np.float32), cv2.CV_32F, k, borderType=cv2.BORDER_REFLECT)
    d = disparity
    sigma_d = np.fmax(disparity_sigma, options.disparity_sigma_floor_px)
    sigma_d = np.where(np.isfinite(sigma_d), sigma_d, options.disparity_sigma_floor_px)
    s = pair.grid.log_rho_step
    d64 = d.astype(float)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        dz = pair.baseline_mm * s * np.exp(d64 * s) / np.expm1(d64 * s) ** 2
        rho = pair.grid.radii()[None, :]
        range_sigma = np.where(d64 > 0, dz * np.sqrt(1.0 + rho * rho) * sigma_d, np.nan).astype(np.float32)
        norm_cost = cost / std_f
    reasons = {
        "outside_view": ~valid,
        "no_match": ~np.isfinite(d),
        "near_epipole": ~(d >= options.min_disparity_px),
        "ill_conditioned": ~(range_sigma <= options.max_range_sigma_mm),
        "dark": ~((mean_f >= options.min_intensity) & (mean_r >= options.min_intensity)),
        "low_texture": ~(grad_f >= options.min_gradient),
        "poor_match": np.isfinite(norm_cost) & (norm_cost > options.max_normalised_cost),
    }
    mask = ~np.any(list(reasons.values()), axis=0)
    mask = cv2.erode(mask.astype(np.uint8), np.ones((3, 3), np.uint8), borderType=cv2.BORDER_CONSTANT,
                     borderValue=0).astype(bool)
    with np.errstate(invalid="ignore", over="ignore"):
        confidence = np.where(mask, 1.0 / (1.0 + (range_sigma / options.max_range_sigma_mm) ** 2), 0.0)
    return mask, confidence.astype(np.float32), range_sigma, reasons


@pytest.mark.parametrize("block_rows", [128, 7])
def test_compiled_reliability_is_the_opencv_numpy_computation(monkeypatch, block_rows):
    """Every test on a small grid whose cells take each outcome: dark and flat windows, NaN and tiny
    disparities, unknown and infinite sigmas, cells outside the view; the range sigma to the bit."""
    monkeypatch.setattr(row_blocks, "BLOCK_ROWS", block_rows)
    camera = Camera.from_fov(120, 120, 70.0, mask_radius_px=58.0)
    down = look_at(np.zeros(3), [0.0, 0.0, -1.0])
    pair = make_axial_pair(camera, Pose.from_centre(down, [0, 0, 0.0]), Pose.from_centre(down, [0, 0, -0.25]))
    rng = np.random.default_rng(3)
    shape = pair.grid.shape
    front = cv2.GaussianBlur(rng.uniform(0, 255, shape).astype(np.float32), (0, 0), 1.2).astype(np.uint8)
    rear = cv2.GaussianBlur(rng.uniform(0, 255, shape).astype(np.float32), (0, 0), 1.2).astype(np.uint8)
    front[:, :6] = 10  # dark and flat: the normalised cost divides by a zero deviation
    disparity = rng.uniform(1.0, 30.0, shape).astype(np.float32)
    disparity[rng.uniform(size=shape) < 0.01] = -0.5
    disparity[rng.uniform(size=shape) < 0.01] = np.nan
    cost = rng.uniform(0, 8, shape).astype(np.float32)
    sigma = rng.uniform(0.0, 0.1, shape).astype(np.float32)
    sigma[rng.uniform(size=shape) < 0.01] = np.nan
    sigma[rng.uniform(size=shape) < 0.01] = np.inf
    valid = rng.uniform(size=shape) > 0.01
    options = ConfidenceOptions(max_normalised_cost=0.8, disparity_sigma_floor_px=0.02, max_range_sigma_mm=0.3)
    got = reliability(front, rear, disparity, cost, sigma, pair, valid, options=options)
    mask, confidence, range_sigma, reasons = _reference_reliability(front, rear, disparity, cost, sigma, pair, valid,
                                                                    options)
    assert 0.02 < mask.mean() < 0.9  # kept and rejected cells both compared
    assert np.array_equal(got.mask, mask)
    assert np.array_equal(got.confidence, confidence)
    assert np.array_equal(got.range_sigma_mm, range_sigma, equal_nan=True)
    assert list(got.reasons) == list(reasons)
    for name, rejected in reasons.items():
        assert 0 < rejected.sum() < rejected.size, name  # each test both passes and fails somewhere
        assert np.array_equal(got.reasons[name], rejected), name
