import numpy as np
import pytest

from ctpipe.errors import ConfigError, InputError
from ctpipe.io.flatfield import log_transform
from ctpipe.sim.acquisition import NoiseModel, acquire, beer_lambert, parse_noise


def test_log_of_noise_free_intensities_recovers_the_line_integrals():
    p = np.random.default_rng(0).uniform(0.05, 6.0, (3, 16, 20))
    i0, dark = 1e5, 100.0
    intensities = beer_lambert(p, i0, dark)
    assert intensities.dtype == np.float32
    flats = beer_lambert(np.zeros((2, 16, 20)), i0, dark)
    darks = np.full((4, 16, 20), dark, np.float32)
    recovered = log_transform(intensities, flats, darks)
    assert recovered.dtype == np.float32
    np.testing.assert_allclose(recovered, p, rtol=1e-5)
    np.testing.assert_allclose(log_transform(beer_lambert(p, i0), photons_per_pixel=i0), p, rtol=1e-5)


@pytest.mark.parametrize("p", [0.5, 2.0])
def test_poisson_noise_is_unbiased_with_variance_one_over_the_counts(p):
    i0 = 2e4
    noise = NoiseModel(photons_per_pixel=i0, flat_frames=200, dark_frames=50, dark_counts=20.0)
    line_integrals = np.full((4, 100, 100), p)
    intensities, flats, darks = acquire(line_integrals, noise, np.random.default_rng(1))
    assert intensities.dtype == flats.dtype == darks.dtype == np.float32
    assert flats.shape == (200, 100, 100) and darks.shape == (50, 100, 100)
    estimate = log_transform(intensities, flats, darks)
    counts = i0 * np.exp(-p)
    assert estimate.mean() == pytest.approx(p, abs=5 * np.sqrt(1 / counts / estimate.size) + 1 / counts)
    # Var(-log I) ~ 1/I0e^-p, plus the projection's and the averaged frames' dark noise.
    expected = 1 / counts + 20.0 / counts**2 + 1 / (200 * i0)
    assert estimate.var() == pytest.approx(expected, rel=0.05)
    assert intensities.mean() == pytest.approx(counts + 20.0, rel=1e-3)


def test_acquisition_is_seeded():
    noise = NoiseModel(photons_per_pixel=1000.0, flat_frames=2, dark_frames=0)
    p = np.ones((2, 8, 8))
    a = acquire(p, noise, np.random.default_rng(3))
    b = acquire(p, noise, np.random.default_rng(3))
    c = acquire(p, noise, np.random.default_rng(4))
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    assert a[2] is None
    assert not np.array_equal(a[0], c[0])


def test_starved_and_dead_pixels_are_clipped_not_infinite():
    intensities = np.array([[[0.0, 5.0, 50.0]]], np.float32)
    flats = np.array([[100.0, 100.0, 10.0]])
    darks = np.array([[10.0, 10.0, 10.0]])
    p = log_transform(intensities, flats, darks)
    assert np.all(np.isfinite(p))
    assert p[0, 0, 0] == pytest.approx(-np.log(1e-6))
    assert p[0, 0, 1] == pytest.approx(-np.log(1e-6))
    assert p[0, 0, 2] == 0.0


def test_bad_inputs():
    with pytest.raises(InputError, match="flats: each frame must have the projections' shape"):
        log_transform(np.ones((1, 4, 4)), np.ones((2, 3, 3)))
    with pytest.raises(InputError, match="give flats or photons_per_pixel"):
        log_transform(np.ones((1, 4, 4)))
    assert parse_noise(None) is None and parse_noise({"photons_per_pixel": None}) is None
    assert parse_noise({"photons_per_pixel": 100, "dark_counts": 5}) == NoiseModel(100.0, 8, 4, 5.0)
    with pytest.raises(ConfigError, match=r"noise.photons_per_pixel: must be a number > 0 and <= 1e12 or null, got -1"):
        parse_noise({"photons_per_pixel": -1})
    with pytest.raises(ConfigError, match=r"noise.flat_frames: must be an integer >= 1 and <= 10000, got 0"):
        parse_noise({"photons_per_pixel": 10, "flat_frames": 0})
    with pytest.raises(ConfigError, match=r"noise.photons: unknown key"):
        parse_noise({"photons": 10})
