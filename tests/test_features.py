"""SIFT features: circular field, CLAHE for dim frames, options and presets."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from scope3d.feature.detection import FEATURE_PRESETS, FeatureOptions, Features, detect, detection_mask
from scope3d.sensor.camera import Camera


def _textured(size=320, seed=0, gain=1.0):
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.random((size, size)).astype(np.float32), (0, 0), 2.0)
    img = (img - img.min()) / (img.max() - img.min())
    return np.clip(255 * gain * img, 0, 255).astype(np.uint8)


def test_keypoints_stay_inside_the_circular_field_shrunk_by_the_margin():
    cam = Camera.from_fov(320, 320, 60.0, mask_radius_px=150.0)
    f = detect(_textured(), cam, options=FeatureOptions(mask_margin_px=8.0))
    assert len(f) > 100
    r = np.linalg.norm(f.keypoints - [(cam.width - 1) / 2, (cam.height - 1) / 2], axis=1)
    assert r.max() <= 150.0 - 8.0 + 1.0  # + 1 px: keypoints are refined to sub-pixel positions
    assert f.descriptors.shape == (len(f), 128) and f.descriptors.dtype == np.float32
    assert f.colors.shape == (len(f), 3) and f.scales.shape == (len(f),)


def test_without_mask_the_rim_of_the_field_produces_features():
    # the disc's rim is a strong edge: unmasked detection finds corners on it, masked does not
    cam = Camera.from_fov(320, 320, 60.0, mask_radius_px=150.0)
    img = _textured(gain=0.6)
    img[~cam.mask()] = 0
    unmasked = detect(img, None, options=FeatureOptions())
    r = np.linalg.norm(unmasked.keypoints - [159.5, 159.5], axis=1)
    assert np.any(np.abs(r - 150.0) < 4.0)


def test_clahe_preset_finds_more_features_on_a_dim_frame():
    dim = _textured(gain=0.08)
    plain = detect(dim, None, options=FEATURE_PRESETS["default"])
    boosted = detect(dim, None, options=FEATURE_PRESETS["dim_endoscope"])
    assert len(boosted) > 2 * max(len(plain), 1)


def test_max_features_keeps_the_strongest():
    f = detect(_textured(), None, options=FeatureOptions(max_features=50))
    assert len(f) == 50


def test_colour_image_and_grey_give_the_same_keypoints():
    grey = _textured()
    rgb = np.repeat(grey[..., None], 3, axis=2)
    a, b = detect(grey), detect(rgb)
    assert len(a) == len(b)
    np.testing.assert_allclose(a.keypoints, b.keypoints)


def test_blank_image_gives_empty_features():
    f = detect(np.zeros((64, 64), np.uint8))
    assert len(f) == 0 and f.descriptors.shape == (0, 128)
    assert len(Features.empty()) == 0


def test_bad_inputs():
    cam = Camera.from_fov(320, 320, 60.0)
    with pytest.raises(ValueError, match="camera is 320x320"):
        detect(np.zeros((100, 100), np.uint8), cam)
    with pytest.raises(ValueError, match="must be"):
        detect(np.zeros((10, 10, 4), np.uint8))
    with pytest.raises(ValueError, match="empty"):
        detect(np.zeros((0, 0), np.uint8))
    for bad in (dict(max_features=-1), dict(contrast_threshold=0), dict(n_octave_layers=0),
                dict(clahe_clip_limit=-1), dict(mask_margin_px=-2)):
        with pytest.raises(ValueError):
            FeatureOptions(**bad)


def test_detection_mask_without_circle_is_a_framed_rectangle():
    cam = Camera.from_fov(40, 30, 60.0)
    m = detection_mask(cam, 3)
    assert m[3:-3, 3:-3].all() and not m[:3].any() and not m[:, :3].any()
