"""The ``beads`` detector on balls rendered analytically (:func:`ctpipe.testing.render_balls`).

Centres are compared with the exact sub-pixel centres the balls were rendered at. Noise levels
are those of a lab scan: 1e4-1e5 photons per unattenuated pixel, balls of peak line integral 1
(a 1 mm steel ball at ~100 kV), a Gaussian detector PSF of 0.7 px.
"""

from __future__ import annotations

import numpy as np
import pytest

from ctpipe.builtin.beads import BeadDetector
from ctpipe.cli import main
from ctpipe.config import build_stage, parse_stage
from ctpipe.errors import ConfigError
from ctpipe.features import render_ball_model
from ctpipe.plugins import get_registry
from ctpipe.testing import check_detector, render_balls


def grid_of_balls(shape, diameter_px, per_side, seed=0):
    """Ball centres on a jittered grid (sub-pixel offsets) and radii within 5 % of the diameter's."""
    rng = np.random.default_rng(seed)
    step = np.array(shape[::-1]) / per_side
    cols, rows = np.meshgrid((np.arange(per_side) + 0.5) * step[0], (np.arange(per_side) + 0.5) * step[1])
    centres = np.column_stack([cols.ravel(), rows.ravel()]) + rng.uniform(-0.5, 0.5, (per_side**2, 2))
    radii = 0.5 * diameter_px * rng.uniform(0.95, 1.05, len(centres))
    return centres, radii


def matched(features, centres):
    """For each true centre, the distance to the nearest keypoint and that keypoint's index."""
    distance = np.linalg.norm(features.xy[:, None, :].astype(np.float64) - centres[None], axis=2)
    return distance.min(axis=0), distance.argmin(axis=0)


def rms(values):
    return float(np.sqrt(np.mean(np.square(values))))


@pytest.mark.parametrize("diameter_px, photons", [(8, 1e4), (8, 1e5), (20, 1e4), (40, 1e4)])
def test_centres_of_line_integral_balls_to_a_few_hundredths_of_a_pixel(diameter_px, photons):
    shape = (256, 256)
    centres, radii = grid_of_balls(shape, diameter_px, 4 if diameter_px < 40 else 3)
    image = render_balls(shape, centres, radii, photons=photons, rng=1)
    # The default range starts at 10 px; 8 px balls need it lowered. Larger ones: sizes found alone.
    features = BeadDetector(**({"min_diameter_px": 6} if diameter_px < 10 else {})).detect(image)
    error, index = matched(features, centres)
    assert len(features) == len(centres)
    assert rms(error) <= 0.05 and error.max() <= 0.1, f"RMS {rms(error):.4f} px, max {error.max():.4f} px"
    np.testing.assert_allclose(features.size[index] / 2, radii, rtol=0.05)
    assert np.all(features.class_id == 0)


def test_the_fit_recovers_its_own_model_exactly():
    """Noise-free balls drawn with the detector's own model: centres to float32's resolution."""
    centres, radii = grid_of_balls((256, 256), 14, 4, seed=1)
    balls = np.column_stack([centres, radii, np.ones(len(centres)), np.full(len(centres), 0.7)])
    features = BeadDetector().detect(render_ball_model(balls, (256, 256)))
    error, index = matched(features, centres)
    assert len(features) == len(centres) and error.max() < 5e-5
    np.testing.assert_allclose(features.response[index], 1.0, atol=1e-3)


def test_noise_free_rendered_balls_give_their_centres_to_a_thousandth_of_a_pixel():
    centres, radii = grid_of_balls((192, 192), 10, 3, seed=2)
    features = BeadDetector().detect(render_balls((192, 192), centres, radii, supersample=9))
    error, _ = matched(features, centres)
    assert error.max() < 1e-3


@pytest.mark.parametrize("peak", [0.3, 3.0])
def test_dark_balls_of_raw_intensities_are_found_as_well_as_bright_ones(peak):
    """uint16 counts of weak (ruby, 0.3) and strong (tungsten, 3: flat-bottomed) absorbers."""
    centres, radii = grid_of_balls((256, 256), 16, 4, seed=3)
    counts = render_balls((256, 256), centres, radii, peak=peak, photons=3e4, intensities=True, rng=2)
    image = counts.astype(np.uint16)
    auto = BeadDetector().detect(image)
    error, _ = matched(auto, centres)
    assert len(auto) == len(centres) and rms(error) <= 0.05
    dark = BeadDetector(polarity="dark").detect(image)
    np.testing.assert_array_equal(auto.xy, dark.xy)
    # The contrast is the ball's peak line integral: intensities are taken -log.
    np.testing.assert_allclose(np.median(auto.response), peak, rtol=0.05)


def test_polarity_auto_takes_line_integrals_as_bright():
    centres, radii = grid_of_balls((192, 192), 12, 3, seed=4)
    image = render_balls((192, 192), centres, radii, photons=1e5, rng=3)
    np.testing.assert_array_equal(BeadDetector().detect(image).xy, BeadDetector(polarity="bright").detect(image).xy)
    assert len(BeadDetector(polarity="dark").detect(image)) == 0


@pytest.mark.parametrize("separation", [0.25, 0.6, 0.9])
def test_overlapping_balls_are_flagged_and_keep_their_centres(separation):
    """Pairs whose centres are ``separation`` diameters apart: at 0.25 and 0.6 the pair shows a
    single peak; the line integrals add, the detector blurs intensities (-log)."""
    rng = np.random.default_rng(5)
    first, _ = grid_of_balls((256, 256), 12, 3, seed=5)
    angle = rng.uniform(0, np.pi, len(first))
    centres = np.concatenate([first, first + separation * 12 * np.column_stack([np.cos(angle), np.sin(angle)])])
    image = render_balls((256, 256), centres, 6.0, photons=1e5, rng=4)
    features = BeadDetector().detect(image)
    error, index = matched(features, centres)
    assert len(features) == len(centres)
    assert np.all(features.class_id[index] == 1)
    assert rms(error) <= 0.05 and error.max() <= 0.1, f"RMS {rms(error):.4f} px, max {error.max():.4f} px"


def test_a_chain_of_overlapping_balls_seen_end_on_is_resolved():
    """A ball bar seen along its rod: seven balls in a row, each overlapping the next."""
    step = 0.78 * 24.0 * np.array([0.36, 0.93])
    centres = np.array([70.3, 40.6]) + np.arange(7)[:, None] * step
    radii = np.linspace(12.5, 11.5, 7)  # the far end is farther from the source
    image = render_balls((256, 160), centres, radii, peak=1.25, photons=5e4, rng=6)
    features = BeadDetector().detect(image)
    error, index = matched(features, centres)
    assert len(features) == 7 and np.all(features.class_id == 1)
    assert error.max() <= 0.05, error


def test_balls_cut_by_the_border_are_flagged_truncated():
    centres = np.array([[2.3, 50.2], [60.7, 1.1], [125.4, 70.4], [70.2, 126.6], [64.3, 64.6], [-4.0, 100.0]])
    image = render_balls((128, 128), centres, 8.0, photons=1e5, rng=7)
    features = BeadDetector().detect(image)
    error, index = matched(features, centres[:5])
    assert len(features) == 5, "a ball whose centre is off the detector is no keypoint"
    assert error.max() <= 0.05
    np.testing.assert_array_equal(features.class_id[index], [2, 2, 2, 2, 0])


def test_balls_on_a_rod_keep_their_centres_and_the_rod_gives_none():
    """A plastic rod (line integral 0.5 at its axis) behind the balls, its edges through some."""
    cols = np.arange(256)
    rod = 0.5 * np.sqrt(np.clip(1.0 - ((cols - 128) / 100.0) ** 2, 0.0, None))[None, :].repeat(256, axis=0)
    centres, radii = grid_of_balls((256, 256), 10, 5, seed=8)
    for intensities in (False, True):
        image = render_balls((256, 256), centres, radii, background=rod, photons=1e4, intensities=intensities, rng=8)
        features = BeadDetector().detect(image)
        error, _ = matched(features, centres)
        assert len(features) == len(centres) and rms(error) <= 0.05


@pytest.mark.parametrize("image", [np.zeros((64, 64)), np.full((64, 64), 1000, np.uint16),
                                   np.random.default_rng(0).normal(0.0, 0.01, (256, 256)),
                                   np.random.default_rng(0).poisson(1e4, (256, 256)).astype(np.uint16)],
                         ids=["zeros", "flat", "gaussian-noise", "poisson-noise"])
def test_images_without_balls_give_no_keypoints(image):
    features = BeadDetector().detect(image)
    assert len(features) == 0 and features.descriptors.shape == (0, 2)


def test_keypoints_carry_diameter_contrast_and_no_orientation():
    centres, radii = grid_of_balls((128, 128), 12, 2, seed=9)
    peaks = np.array([0.4, 0.8, 1.2, 1.6])
    features = BeadDetector().detect(render_balls((128, 128), centres, radii, peak=peaks))
    _, index = matched(features, centres)
    assert features.norm == "L2" and features.descriptors.dtype == np.float32
    np.testing.assert_allclose(features.size, 2.0 * features.descriptors[:, 0])
    np.testing.assert_array_equal(features.response, features.descriptors[:, 1])
    np.testing.assert_allclose(features.response[index], peaks, rtol=0.01)
    assert np.all(np.isnan(features.angle_deg)) and np.all(np.diff(features.response) <= 0)
    strongest = BeadDetector(max_beads=2).detect(render_balls((128, 128), centres, radii, peak=peaks))
    np.testing.assert_allclose(np.sort(strongest.response), peaks[2:], rtol=0.01)


def test_balls_outside_the_diameter_range_are_left_out():
    centres = np.array([[40.2, 40.7], [100.6, 100.1]])
    image = render_balls((160, 160), centres, [4.0, 12.0], photons=1e5, rng=10)
    features = BeadDetector(min_diameter_px=16, max_diameter_px=30).detect(image)
    error, _ = matched(features, centres[1:])
    assert len(features) == 1 and error[0] <= 0.05


def test_the_centroid_is_the_faster_rougher_alternative():
    centres, radii = grid_of_balls((256, 256), 16, 4, seed=11)
    image = render_balls((256, 256), centres, radii, photons=1e5, rng=11)
    error, _ = matched(BeadDetector(centre_method="centroid").detect(image), centres)
    assert rms(error) <= 0.1


def test_conformance():
    check_detector(BeadDetector())


def test_registered_as_beads(capsys):
    info = get_registry().get("detector", "beads")
    assert info.cls is BeadDetector and info.plugin == "ctpipe.builtin.beads"
    assert main(["plugins"]) == 0
    assert "beads" in capsys.readouterr().out


@pytest.mark.parametrize("params, message", [
    ({"min_diameter_px": 20.0, "max_diameter_px": 12.0},
     "BeadDetector.min_diameter_px: must be <= max_diameter_px (12), got 20"),
    ({"min_diameter_px": 1.0}, "BeadDetector.min_diameter_px: must be a number >= 2 and <= 4096 or null, got 1.0"),
    ({"polarity": "white"}, "BeadDetector.polarity: must be one of 'auto', 'bright', 'dark', got 'white'"),
    ({"min_contrast_sigma": 0}, "BeadDetector.min_contrast_sigma: must be a number > 0 and <= 1000000, got 0"),
    ({"max_beads": 0}, "BeadDetector.max_beads: must be an integer >= 1 and <= 1000000, got 0"),
    ({"centre_method": "moments"}, "BeadDetector.centre_method: must be one of 'auto', 'fit', 'centroid', 'rim', got 'moments'"),
])
def test_parameters_are_validated_with_one_line_messages(params, message):
    with pytest.raises(ConfigError) as error:
        BeadDetector(**params)
    assert str(error.value) == message


def test_yaml_parameters_name_their_path():
    registry = get_registry()
    with pytest.raises(ConfigError, match=r"^detector\.max_diameter_px: must be a number >= 2 and <= 4096 or null, got -3$"):
        parse_stage({"name": "beads", "max_diameter_px": -3}, "detector", registry, "detector")
    spec = parse_stage({"name": "beads", "min_diameter_px": 10, "max_diameter_px": 30}, "detector", registry,
                       "detector")
    assert build_stage(spec, registry) == BeadDetector(min_diameter_px=10.0, max_diameter_px=30.0)


@pytest.mark.parametrize("diameter_px, per_side", [(10, 4), (30, 3), (80, 2)])
def test_the_ball_size_is_found_without_a_diameter_range(diameter_px, per_side):
    """Defaults only: 10 px to a third of the image, the balls' own size picked from the data."""
    centres, radii = grid_of_balls((256, 256), diameter_px, per_side, seed=12)
    image = render_balls((256, 256), centres, radii, photons=3e4, rng=12)
    features = BeadDetector().detect(image)
    error, index = matched(features, centres)
    assert len(features) == len(centres)
    assert rms(error) <= 0.05 and error.max() <= 0.1, f"RMS {rms(error):.4f} px, max {error.max():.4f} px"
    np.testing.assert_allclose(features.size[index] / 2, radii, rtol=0.05)


def with_defects(image, rng, dead, hot, dust):
    """Dead and hot pixels, a dead column segment, a dead pair of pixels and dust specks of 2-6 px
    (``dust(values)``: what a speck makes of the pixels it covers)."""
    image = image.copy()
    rows, cols = image.shape
    y, x = rng.integers(2, rows - 2, 30), rng.integers(2, cols - 2, 30)
    image[y[:15], x[:15]] = dead
    image[y[15:], x[15:]] = hot
    image[20:200, 141] = dead
    image[230, 30:32] = dead
    yy, xx = np.mgrid[0:rows, 0:cols]
    for cy, cx, r in rng.uniform([10, 10, 1.0], [rows - 10, cols - 10, 3.0], (6, 3)):
        speck = (yy - cy) ** 2 + (xx - cx) ** 2 <= r * r
        image[speck] = dust(image[speck])
    return image


@pytest.mark.parametrize("intensities", [False, True], ids=["line-integrals", "raw-counts"])
def test_dead_and_hot_pixels_lines_and_dust_give_no_balls(intensities):
    """Defects of a real detector on a 256^2 image of 30 px balls: none becomes a ball, one crosses a
    ball (the dead column), and the balls keep their centres."""
    centres, radii = grid_of_balls((256, 256), 30, 3, seed=13)
    rng = np.random.default_rng(13)
    if intensities:
        counts = render_balls((256, 256), centres, radii, photons=3e4, intensities=True, rng=14)
        image = with_defects(counts, rng, dead=0.0, hot=65535.0, dust=lambda v: 0.6 * v).astype(np.uint16)
    else:
        image = with_defects(render_balls((256, 256), centres, radii, photons=3e4, rng=14), rng, dead=13.8,
                             hot=-0.3, dust=lambda v: v + 0.5)
    features = BeadDetector().detect(image)
    error, _ = matched(features, centres)
    assert len(features) == len(centres)
    assert rms(error) <= 0.05 and error.max() <= 0.1, f"RMS {rms(error):.4f} px, max {error.max():.4f} px"


def test_defects_alone_give_no_keypoints():
    image = with_defects(np.random.default_rng(15).normal(0.0, 0.005, (256, 256)), np.random.default_rng(16),
                         dead=13.8, hot=-0.3, dust=lambda v: v + 0.5)
    assert len(BeadDetector().detect(image)) == 0


def test_a_large_ball_is_found_on_a_coarse_level_and_fitted_at_full_resolution():
    """A ball 80 px across in a 512^2 image with smaller specks of dust around it (12 px blobs a
    tenth as strong, far from the ball's size): only the ball, its centre to a few hundredths."""
    centres = np.array([[250.3, 261.7]])
    dust = np.array([[60.2, 70.4], [430.6, 90.1], [100.5, 440.3]])
    image = render_balls((512, 512), np.concatenate([centres, dust]), [40.0, 6.0, 6.0, 6.0],
                         peak=[2.0, 0.2, 0.2, 0.2], photons=3e4, rng=17)
    features = BeadDetector().detect(image)
    error, _ = matched(features, centres)
    assert len(features) == 1 and error[0] <= 0.05


def test_balls_placed_by_their_rims_are_found_at_half_the_fit_radius_but_none_below_the_finders_smallest():
    from ctpipe.builtin.beads import _rim_binning

    assert _rim_binning(4, 76.0, 52.0, 16.0) == 9        # the mixed phantom: 76 px balls found at about 8 px
    assert _rim_binning(4, 76.0, 20.0, 16.0) == 4        # a 20 px ball would fall under 5 px: no coarser than before
    assert _rim_binning(4, 76.0, 30.0, 16.0) == 6        # the smallest ball kept at 5 px
