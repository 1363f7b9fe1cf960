"""Detector artefacts against closed forms and measured properties (ctpipe.sim.detector)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter
from scipy.special import ndtri

from ctpipe.errors import ConfigError
from ctpipe.geometry import Geometry
from ctpipe.io.flatfield import log_transform
from ctpipe.recon import VolumeGrid, fdk
from ctpipe.sim.acquisition import NoiseModel, acquire
from ctpipe.sim.detector import (FULL_SCALE_PER_FLAT, DetectorModel, DetectorPattern, _blur, detected_line_integrals,
                                 draw_pattern, parse_detector, record)
from ctpipe.sim.phantoms import parse_phantom
from ctpipe.sim.scan_spec import parse_scan_spec
from ctpipe.sim.simulator import project_phantom, simulate

SHAPE = (24, 40)


def _flat_stack(values, shape=SHAPE) -> np.ndarray:
    return np.stack([np.full(shape, v, np.float32) for v in values])


def test_an_ideal_detector_gives_the_line_integrals_back():
    p = np.random.default_rng(0).uniform(0.0, 5.0, (3, *SHAPE)).astype(np.float32)
    np.testing.assert_allclose(detected_line_integrals(p, DetectorModel(), np.random.default_rng(0)), p, atol=1e-6)


@pytest.mark.parametrize("s, p", [(0.05, 1.0), (0.2, 3.0), (1.0, 0.5)])
def test_scatter_lowers_a_slab_by_log_one_plus_spr(s, p):
    # A slab over the whole detector: scatter-to-primary ratio s * p, so -log reads p - log(1 + s p).
    model = DetectorModel(scatter_fraction=s, scatter_sigma_px=30.0)
    out = detected_line_integrals(_flat_stack([p, p]), model, np.random.default_rng(0))
    np.testing.assert_allclose(out, p - np.log1p(s * p), rtol=1e-6)
    # No object, no scatter: the flats have none, and an empty view reads exactly 0.
    assert np.array_equal(detected_line_integrals(_flat_stack([0.0]), model, np.random.default_rng(0)),
                          np.zeros((1, *SHAPE), np.float32))


def test_scatter_makes_a_cylinder_cup_most_at_its_centre():
    # Chord of a 30-px-radius disc (mu = 0.05/px): p is largest at the centre, so is the deficit.
    x = np.arange(96) - 47.5
    chord = np.where(np.abs(x) < 30, 2 * np.sqrt(np.maximum(30 ** 2 - x ** 2, 0)) * 0.05, 0.0)
    p = np.broadcast_to(chord, (1, 16, 96)).astype(np.float32)
    out = detected_line_integrals(p, DetectorModel(scatter_fraction=0.1, scatter_sigma_px=20.0),
                                  np.random.default_rng(0))[0, 8]
    deficit = chord - out
    assert np.all(deficit[np.abs(x) < 30] > 0)
    assert deficit[47] == pytest.approx(deficit.max(), rel=0.02) and deficit[47] > 3 * deficit[np.argmin(np.abs(x - 25))]


def test_the_coarse_blur_of_wide_kernels_matches_the_exact_gaussian():
    frame = gaussian_filter(np.random.default_rng(1).uniform(0, 1, (200, 260)), 6)
    for sigma in (8.0, 13.0, 40.0):
        exact = gaussian_filter(frame, sigma, mode="reflect")
        assert np.max(np.abs(_blur(frame, sigma) - exact)) < 0.01 * np.ptp(exact) + 1e-12


@pytest.mark.parametrize("sigma", [1.0, 2.5])
def test_the_psf_blurs_an_edge_to_the_gaussian_10_90_width(sigma):
    # The blur acts on the intensity: the transmission across an edge is a Gaussian CDF.
    p = np.zeros((1, 8, 120), np.float32)
    p[..., 60:] = 2.0
    out = detected_line_integrals(p, DetectorModel(psf_sigma_px=sigma), np.random.default_rng(0))
    t = np.exp(-out[0, 4].astype(np.float64))
    lo, hi = np.exp(-2.0), 1.0
    level = (t - lo) / (hi - lo)                         # 1 -> 0 across the edge
    cols = np.arange(120.0)
    x90 = np.interp(-0.9, -level, cols)
    x10 = np.interp(-0.1, -level, cols)
    width = x10 - x90
    assert width == pytest.approx(2 * ndtri(0.9) * sigma, rel=0.05)
    assert np.allclose(out[0, :, :40], 0.0, atol=1e-6) and np.allclose(out[0, :, 80:], 2.0, atol=1e-6)


def test_dead_and_hot_pixels_are_where_drawn_in_every_frame():
    model = DetectorModel(dead_pixels=7, hot_pixels=5, dead_columns=2)
    pattern = draw_pattern(model, SHAPE, np.random.default_rng(3))
    full_columns = np.flatnonzero(pattern.dead.all(axis=0))
    assert len(full_columns) == 2
    others = pattern.dead.copy()
    others[:, full_columns] = False
    assert others.sum() <= 7 and pattern.hot.sum() <= 5 and not np.any(pattern.dead & pattern.hot)
    bare = draw_pattern(DetectorModel(dead_pixels=7, hot_pixels=5), SHAPE, np.random.default_rng(3))
    assert bare.dead.sum() == 7 and bare.hot.sum() == 5 and not np.any(bare.dead & bare.hot)

    noise = NoiseModel(photons_per_pixel=1e4, flat_frames=3, dark_frames=2, dark_counts=50.0)
    p = np.random.default_rng(0).uniform(0.1, 2.0, (5, *SHAPE))
    intensities, flats, darks = record(p, noise, model, np.random.default_rng(3))
    full = FULL_SCALE_PER_FLAT * (1e4 + 50.0)
    for frames in (intensities, flats, darks):
        assert np.all(frames[:, pattern.dead] == 0)
        assert np.all(frames[:, pattern.hot] == np.float32(full))
    live = ~(pattern.dead | pattern.hot)
    assert np.all(intensities[:, live] > 0) and np.all(intensities[:, live] < full)
    # The flat correction gives stuck pixels no information: p = 0 there.
    projections = log_transform(intensities, flats, darks)
    assert np.all(projections[:, ~live] == 0)


def test_gain_errors_common_to_flats_cancel_and_a_drift_survives_exactly():
    p = _flat_stack([0.0, 1.0, 2.0])
    common = detected_line_integrals(p, DetectorModel(gain_sigma=0.1), np.random.default_rng(0))
    np.testing.assert_allclose(common, p, atol=1e-6)
    model = DetectorModel(gain_sigma=0.1, gain_drift_sigma=0.02)
    pattern = draw_pattern(model, SHAPE, np.random.default_rng(5))
    out = detected_line_integrals(p, model, np.random.default_rng(5))
    error = p - np.log(pattern.projection_gain / pattern.flat_gain)
    np.testing.assert_allclose(out, np.broadcast_to(error, p.shape), atol=1e-6)
    assert 0.015 < np.std(np.log(pattern.projection_gain / pattern.flat_gain)) < 0.025


@pytest.mark.parametrize("col", [49, 40, 10])
def test_a_pixel_whose_gain_drifted_makes_a_ring_at_its_radius(col):
    geometry = Geometry(source_to_object_mm=100.0, source_to_detector_mm=200.0, detector_cols=64, detector_rows=9,
                        pixel_pitch_u_mm=0.5, pixel_pitch_v_mm=0.5)
    row = 4                                               # the central row: the slice iy = centre
    gain = np.ones((9, 64))
    gain[row, col] = 1.05
    pattern = DetectorPattern(np.zeros((9, 64), bool), np.zeros((9, 64), bool), None, gain)
    angles = np.arange(120) * 3.0
    p = np.zeros((120, 9, 64), np.float32)                # an air scan: only the artefact is left
    out = detected_line_integrals(p, DetectorModel(gain_drift_sigma=0.05), None, pattern=pattern)
    assert np.allclose(out[:, row, col], -np.log(1.05), atol=1e-6) and np.count_nonzero(out) == 120
    grid = VolumeGrid(64, 1, 64, 0.25)
    volume = fdk(out, geometry, angles, grid, filter="ram-lak")[0]     # (iz, ix)
    xs = (np.arange(64) - 31.5) * 0.25
    radius = np.hypot(xs[None, :], xs[:, None])
    expected = abs(col - geometry.u0_px) * 0.5 * 100.0 / 200.0   # 4.375, 2.125, 5.375 mm
    bins = np.round(radius / 0.25).astype(int)
    profile = np.bincount(bins.ravel(), volume.ravel()) / np.maximum(np.bincount(bins.ravel()), 1)
    ring = np.argmin(profile[: int(31.5 * 1.0)]) * 0.25   # the error is negative: a dark ring
    assert ring == pytest.approx(expected, abs=0.15)   # radii are binned by 0.25 mm
    assert profile.min() < -5 * np.std(volume[radius > expected + 2])


def test_lag_leaves_a_residue_that_shrinks_by_the_lag_fraction_per_frame():
    lag = 0.2
    p = _flat_stack([0.0] * 3 + [1.5] * 6)
    out = detected_line_integrals(p, DetectorModel(lag_fraction=lag), np.random.default_rng(0))
    assert np.all(out[:3] == 0)
    residue = np.exp(-out[3:, 0, 0].astype(np.float64)) - np.exp(-1.5)
    np.testing.assert_allclose(residue[1:] / residue[:-1], lag, rtol=1e-4)
    assert residue[0] == pytest.approx(lag * (1 - np.exp(-1.5)), rel=1e-5)


def test_noisy_recording_has_the_closed_form_mean():
    noise = NoiseModel(photons_per_pixel=5e4, flat_frames=20, dark_frames=4, dark_counts=20.0)
    model = DetectorModel(scatter_fraction=0.1, scatter_sigma_px=20.0, psf_sigma_px=0.7, gain_sigma=0.05)
    intensities, flats, darks = record(_flat_stack([2.0] * 4, (32, 32)), noise, model, np.random.default_rng(2))
    estimate = log_transform(intensities, flats, darks)
    assert estimate.mean() == pytest.approx(2.0 - np.log1p(0.2), abs=2e-3)


SPEC = {"geometry": {"source_to_object_mm": 100.0, "source_to_detector_mm": 200.0, "detector_cols": 32,
                     "detector_rows": 16, "pixel_pitch_u_mm": 0.5, "pixel_pitch_v_mm": 0.5},
        "angles": {"n_views": 6}, "jitter": [{"gaussian": {"sigma_deg": 0.3}}],
        "noise": {"photons_per_pixel": 1e4, "flat_frames": 2, "dark_frames": 1, "dark_counts": 10.0}, "seed": 1}
PHANTOM = {"name": "ball", "objects": [{"sphere": {"centre_mm": [0, 0, 0], "radius_mm": 3.0, "density_per_mm": 0.1}}]}


def test_no_detector_section_simulates_bit_for_bit_as_before():
    phantom = parse_phantom(PHANTOM)
    for noise in (SPEC["noise"], None):
        spec = parse_scan_spec({**SPEC, "noise": noise})
        assert spec.detector is None and parse_scan_spec({**SPEC, "noise": noise, "detector": None}) == spec
        scan = simulate(phantom, spec, rng=np.random.default_rng(7))
        # The chain before detector artefacts existed, drawn from the same generator.
        rng = np.random.default_rng(7)
        nominal = spec.nominal_angles_deg()
        truth = nominal + spec.jitter.sample(nominal, rng)
        p = project_phantom(phantom, spec.geometry, truth)
        if noise is None:
            assert np.array_equal(scan.projections, p)
        else:
            intensities, flats, darks = acquire(p, spec.noise, rng)
            assert np.array_equal(scan.intensities, intensities) and np.array_equal(scan.flats, flats)
            assert np.array_equal(scan.projections, log_transform(intensities, flats, darks))
        assert "detector" not in spec.to_dict()


def test_a_detector_section_is_simulated_and_round_trips():
    phantom = parse_phantom(PHANTOM)
    section = {"scatter_fraction": 0.05, "scatter_sigma_px": 10, "psf_sigma_px": 0.8, "dead_pixels": 3,
               "hot_pixels": 2, "dead_columns": 1, "gain_sigma": 0.02, "gain_drift_sigma": 0.01, "lag_fraction": 0.02,
               "flux_sigma": 0.01}
    for noise in (SPEC["noise"], None):
        spec = parse_scan_spec({**SPEC, "noise": noise, "detector": section})
        assert parse_scan_spec(spec.to_dict()) == spec and spec.to_dict()["detector"]["dead_pixels"] == 3
        a = simulate(phantom, spec, rng=np.random.default_rng(7))
        b = simulate(phantom, spec, rng=np.random.default_rng(7))
        plain = simulate(phantom, parse_scan_spec({**SPEC, "noise": noise}), rng=np.random.default_rng(7))
        assert np.array_equal(a.projections, b.projections) and a.projections.dtype == np.float32
        assert np.array_equal(a.true_angles_deg, plain.true_angles_deg)   # the jitter is drawn first
        assert not np.array_equal(a.projections, plain.projections)
        assert np.all(np.isfinite(a.projections))


@pytest.mark.parametrize("section, message", [
    ({"scatter_fraction": -0.1}, r"^scan\.detector\.scatter_fraction: must be a number >= 0 and <= 10, got -0\.1$"),
    ({"scatter_sigma_px": 0}, r"^scan\.detector\.scatter_sigma_px: must be a number > 0"),
    ({"psf_sigma_px": "wide"}, r"^scan\.detector\.psf_sigma_px: must be a number >= 0"),
    ({"dead_pixels": 1.5}, r"^scan\.detector\.dead_pixels: must be an integer >= 0, got 1\.5$"),
    ({"hot_pixels": -1}, r"^scan\.detector\.hot_pixels: must be an integer >= 0"),
    ({"dead_columns": 33}, r"^scan\.detector\.dead_columns: must be at most the detector's 32 columns, got 33$"),
    ({"gain_sigma": 0.9}, r"^scan\.detector\.gain_sigma: must be a number >= 0 and <= 0\.5, got 0\.9$"),
    ({"gain_drift_sigma": -1}, r"^scan\.detector\.gain_drift_sigma: must be a number >= 0"),
    ({"lag_fraction": 1.0}, r"^scan\.detector\.lag_fraction: must be a number >= 0 and < 1, got 1\.0$"),
    ({"flux_sigma": 0.3}, r"^scan\.detector\.flux_sigma: must be a number >= 0 and <= 0\.2, got 0\.3$"),
    ({"lag": 0.1}, r"^scan\.detector\.lag: unknown key; allowed: scatter_fraction, "),
    ({"dead_pixels": 40, "dead_columns": 3}, r"^scan\.detector: dead_pixels \+ hot_pixels \+ dead_columns x 16 rows = "
                                             r"88 pixels, more than 10 % of the 16 x 32 detector"),
    ([1, 2], r"^scan\.detector: must be a mapping with keys scatter_fraction, "),
])
def test_bad_detector_values_are_one_line_naming_the_key(section, message):
    with pytest.raises(ConfigError, match=message) as info:
        parse_scan_spec({**SPEC, "detector": section})
    assert "\n" not in str(info.value)
    assert parse_detector(None) is None


def test_dust_since_the_flats_stays_as_fixed_dark_specks_in_every_view():
    p = _flat_stack([0.0, 1.0, 2.0], shape=(64, 96))
    model = DetectorModel(dust_specks=5)
    pattern = draw_pattern(model, (64, 96), np.random.default_rng(3))
    out = detected_line_integrals(p, model, np.random.default_rng(3))
    residue = -np.log(pattern.dust)
    assert residue.max() > 0.04 and np.mean(residue > 1e-2) < 0.3           # specks, not a veil
    np.testing.assert_allclose(out, p + residue[None], atol=1e-6)          # the same in every view, on top


def test_a_saturated_detector_reads_its_background_flat_and_cuts_faint_edges():
    p = _flat_stack([0.0, 0.02, 0.5])
    out = detected_line_integrals(p, DetectorModel(saturation_fraction=0.9), np.random.default_rng(0))
    # The flats clip at 0.9 I0: a line integral below -log(0.9) = 0.105 reads 0, one above it that much less.
    np.testing.assert_allclose(out[0], 0.0, atol=1e-6)
    np.testing.assert_allclose(out[1], 0.0, atol=1e-6)
    np.testing.assert_allclose(out[2], 0.5 + np.log(0.9), atol=1e-6)


def test_a_wandering_tube_shifts_each_views_line_integrals_by_its_output_unless_the_clip_hides_it():
    p = _flat_stack([0.0] * 200 + [0.5] * 200)
    model = DetectorModel(flux_sigma=0.01)
    out = detected_line_integrals(p, model, np.random.default_rng(4)).astype(np.float64)
    # Each view's beam is I0 (1 + f_v), the flats' I0: the whole view reads -log(1 + f_v) off.
    f = np.exp(-(out[:, 0, 0] - p[:, 0, 0])) - 1.0
    assert np.all(np.ptp(out - out[:, :1, :1], axis=(1, 2)) < 1e-6)
    assert np.std(f) == pytest.approx(0.01, rel=0.15) and abs(np.mean(f)) < 0.003
    # Drawn after the pattern and only where set: the same generator gives the same pattern either way.
    dust = DetectorModel(dust_specks=3)
    assert np.array_equal(detected_line_integrals(p[:2], DetectorModel(dust_specks=3, flux_sigma=0.0),
                                                  np.random.default_rng(4)),
                          detected_line_integrals(p[:2], dust, np.random.default_rng(4)))
    # A clip at 90 % hides the change in the background but not under the object: the cut moves view by view.
    clipped = detected_line_integrals(p, DetectorModel(flux_sigma=0.01, saturation_fraction=0.9),
                                      np.random.default_rng(4)).astype(np.float64)
    np.testing.assert_allclose(clipped[:200], 0.0, atol=1e-6)
    np.testing.assert_allclose(clipped[200:, 0, 0], 0.5 + np.log(0.9) - np.log1p(f[200:]), atol=1e-5)


def test_a_wandering_tube_is_recorded_in_the_projections_and_not_in_the_flats():
    noise = NoiseModel(photons_per_pixel=1e6, flat_frames=8, dark_frames=0, dark_counts=0.0)
    intensities, flats, _ = record(_flat_stack([0.0] * 50, (8, 8)), noise, DetectorModel(flux_sigma=0.02),
                                   np.random.default_rng(6))
    assert abs(flats.mean() / 1e6 - 1.0) < 1e-3
    assert np.std(intensities.mean(axis=(1, 2)) / 1e6) == pytest.approx(0.02, rel=0.25)
