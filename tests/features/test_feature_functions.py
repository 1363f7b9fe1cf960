"""The plain functions of :mod:`ctpipe.features`, called without a stage."""

from __future__ import annotations

import numpy as np
import pytest

from ctpipe.builtin.beads import BeadDetector
from ctpipe.builtin.surf import surf
from ctpipe.errors import InputError
from ctpipe.features import compute_surf, despike, find_balls, noise_sigma, render_ball_model
from ctpipe.testing import render_balls


def test_find_balls_gives_the_rows_the_beads_stage_packs():
    centres = np.array([[30.3, 40.6], [80.1, 70.7], [40.5, 95.2]])
    image = render_balls((128, 128), centres, np.full(3, 6.0), photons=3e4, rng=0)
    rows = find_balls(image)
    features = BeadDetector().detect(image)
    assert rows.shape == (3, 5)
    np.testing.assert_array_equal(rows[:, :2].astype(np.float32), features.xy)
    np.testing.assert_array_equal((2.0 * rows[:, 2]).astype(features.size.dtype), features.size)
    np.testing.assert_array_equal(rows[:, 4].astype(np.int32), features.class_id)
    assert np.abs(rows[:, :2][np.argsort(rows[:, 0])] - centres[np.argsort(centres[:, 0])]).max() < 0.1


def test_find_balls_on_a_flat_image_finds_none_and_refuses_unknown_options():
    assert find_balls(np.ones((32, 32))).shape == (0, 5)
    with pytest.raises(ValueError, match="polarity"):
        find_balls(np.ones((32, 32)), polarity="grey")
    with pytest.raises(InputError):
        find_balls(np.zeros((4, 4, 3)))


def test_render_ball_model_draws_the_balls_volume():
    image = render_ball_model(np.array([[32.0, 32.0, 8.0, 1.0, 0.7]]), (64, 64))
    # A chord profile of height A and radius r holds 2 pi A r^2 / 3; blur and pixels keep it.
    assert image.sum() == pytest.approx(2.0 * np.pi * 64.0 / 3.0, rel=1e-3)
    assert image[32, 32] == image.max()


def test_noise_sigma_measures_gaussian_noise_and_floors_integer_images():
    rng = np.random.default_rng(0)
    noise = rng.normal(0.0, 0.2, (256, 256))
    assert noise_sigma(noise, integer=False, span=float(np.ptp(noise))) == pytest.approx(0.2, rel=0.05)
    assert noise_sigma(np.zeros((8, 8)), integer=True, span=0.0) == pytest.approx(1.0 / np.sqrt(12.0))


def test_despike_replaces_a_hot_pixel_and_keeps_a_smooth_image():
    rows, cols = np.mgrid[0:32, 0:32]
    smooth = np.exp(-((rows - 16.0) ** 2 + (cols - 16.0) ** 2) / 50.0)
    np.testing.assert_allclose(despike(smooth, 0.01), smooth, atol=1e-6)
    hot = smooth.copy()
    hot[5, 7] = 10.0
    # Beyond its neighbours along x and along y: the mean of all four.
    neighbours = smooth[5, 6] + smooth[5, 8] + smooth[4, 7] + smooth[6, 7]
    assert despike(hot, 0.01)[5, 7] == pytest.approx(0.25 * neighbours, abs=1e-6)


def test_compute_surf_gives_the_keypoints_the_surf_stage_packs():
    rng = np.random.default_rng(1)
    rows, cols = np.mgrid[0:128, 0:128]
    image = sum(np.exp(-((cols - x) ** 2 + (rows - y) ** 2) / (2 * s * s))
                for x, y, s in rng.uniform((10, 10, 2), (118, 118, 5), (20, 3)))
    keypoints, angles, descriptors = compute_surf(image)
    features = surf(image)
    assert len(keypoints) == len(features) > 5
    order = np.lexsort((keypoints[:, 0], keypoints[:, 1], -keypoints[:, 3]))
    np.testing.assert_array_equal(keypoints[order, :2], features.xy)
    np.testing.assert_array_equal(descriptors[order], features.descriptors)
    np.testing.assert_array_equal(angles[order], features.angle_deg)
