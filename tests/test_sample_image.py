"""scope3d.utils.sample_image: cv2.remap at any number of points (its maps must stay under 32767 a side)."""
import cv2
import numpy as np

from scope3d.utils.sample_image import sample_image


def _bilinear(image: np.ndarray, xy: np.ndarray) -> np.ndarray:
    x0, y0 = np.floor(xy[:, 0]).astype(int), np.floor(xy[:, 1]).astype(int)
    fx, fy = (xy[:, 0] - x0)[:, None], (xy[:, 1] - y0)[:, None]
    im = image.reshape(image.shape[0], image.shape[1], -1).astype(float)
    return ((1 - fx) * (1 - fy) * im[y0, x0] + fx * (1 - fy) * im[y0, x0 + 1]
            + (1 - fx) * fy * im[y0 + 1, x0] + fx * fy * im[y0 + 1, x0 + 1])


def test_more_points_than_remap_takes_in_one_column_read_bilinearly():
    rng = np.random.default_rng(0)
    image = rng.random((40, 50, 3)).astype(np.float32)
    xy = rng.uniform([0, 0], [48.999, 38.999], (70_000, 2))  # two SHRT_MAX columns' worth
    got = sample_image(image, xy)
    assert got.shape == (70_000, 3)
    # cv2's bilinear weights are fixed point (1/32 px): float32 images read within that step's effect
    np.testing.assert_allclose(got, _bilinear(image, xy), atol=1.0 / 32)


def test_single_channel_and_points_outside_get_the_border_value():
    image = np.arange(20, dtype=np.float32).reshape(4, 5)
    xy = np.array([[1.0, 2.0], [-3.0, 1.0], [2.0, 9.0]])
    got = sample_image(image, xy, border=cv2.BORDER_CONSTANT, border_value=np.nan)
    assert got.shape == (3,)
    assert got[0] == image[2, 1]
    assert np.isnan(got[1:]).all()
    assert sample_image(image, np.zeros((0, 2))).shape == (0,)
