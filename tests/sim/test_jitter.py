import numpy as np
import pytest

from ctpipe.errors import ConfigError, InputError
from ctpipe.sim.jitter import (GaussianJitter, Jitter, JumpJitter, PeriodicJitter, RandomWalkJitter,
                               nominal_angles_deg, parse_jitter)


def test_full_scans_exclude_the_endpoint_and_short_scans_include_it():
    np.testing.assert_allclose(nominal_angles_deg(4), [0, 90, 180, 270])
    np.testing.assert_allclose(nominal_angles_deg(4, 720.0, 10.0), [10, 190, 370, 550])
    np.testing.assert_allclose(nominal_angles_deg(5, 200.0, -100.0), [-100, -50, 0, 50, 100])
    np.testing.assert_allclose(nominal_angles_deg(1, 180.0, 7.0), [7.0])
    with pytest.raises(InputError, match="n_views: must be an integer >= 1, got 0"):
        nominal_angles_deg(0)


NOMINAL = nominal_angles_deg(20000)


def test_a_closing_view_is_the_first_again_a_turn_on_and_round_trips():
    """A Nikon scan of 16 projections and its closing image: 17 views at 22.5 deg steps, 0 through 360."""
    from ctpipe.sim.scan_spec import parse_scan_spec

    geometry = {"source_to_object_mm": 150.0, "source_to_detector_mm": 870.0, "detector_cols": 64,
                "detector_rows": 64, "pixel_pitch_u_mm": 0.2, "pixel_pitch_v_mm": 0.2}
    spec = parse_scan_spec({"geometry": geometry, "angles": {"n_views": 17, "closing_view": True}})
    np.testing.assert_allclose(spec.nominal_angles_deg(), 22.5 * np.arange(17))
    np.testing.assert_array_equal(parse_scan_spec(spec.to_dict()).nominal_angles_deg(), spec.nominal_angles_deg())
    plain = parse_scan_spec({"geometry": geometry, "angles": {"n_views": 17}})
    assert "closing_view" not in plain.to_dict()["angles"] and plain.nominal_angles_deg()[-1] < 360.0 - 20.0
    with pytest.raises(ConfigError, match="scan.angles.closing_view: must be true or false"):
        parse_scan_spec({"geometry": geometry, "angles": {"n_views": 17, "closing_view": "yes"}})


def test_gaussian_has_its_standard_deviation():
    offsets = GaussianJitter(0.2).sample(NOMINAL, np.random.default_rng(0))
    assert offsets.std() == pytest.approx(0.2, rel=0.03)
    assert abs(offsets.mean()) < 0.01


def test_random_walk_increments_have_the_step_sigma():
    offsets = RandomWalkJitter(0.05).sample(NOMINAL, np.random.default_rng(1))
    assert offsets[0] == 0.0
    assert np.diff(offsets).std() == pytest.approx(0.05, rel=0.03)


def test_periodic_is_exact():
    nominal = nominal_angles_deg(36)
    offsets = PeriodicJitter(0.1, phase_deg=30.0, harmonic=2).sample(nominal, np.random.default_rng(0))
    np.testing.assert_allclose(offsets, 0.1 * np.sin(np.deg2rad(2 * nominal + 30.0)), atol=1e-15)


def test_jumps_by_count_are_persistent_steps_of_the_size():
    nominal = nominal_angles_deg(360)
    offsets = JumpJitter(1.0, count=3).sample(nominal, np.random.default_rng(2))
    steps = np.diff(offsets, prepend=0.0)
    where = np.flatnonzero(steps)
    assert len(where) == 3 and where.min() >= 1
    np.testing.assert_allclose(np.abs(steps[where]), 1.0)
    positive = JumpJitter(0.5, count=4, sign="positive", size_sigma_deg=0.1).sample(nominal, np.random.default_rng(3))
    assert np.all(np.diff(positive) >= 0) and positive[-1] > 0
    with pytest.raises(InputError, match="jumps.count: 5 jumps need at least 6 views, got 4"):
        JumpJitter(1.0, count=5).sample(nominal_angles_deg(4), np.random.default_rng(0))


def test_jumps_by_rate_have_the_expected_count():
    offsets = JumpJitter(0.5, rate_per_view=0.01).sample(NOMINAL, np.random.default_rng(4))
    n = np.count_nonzero(np.diff(offsets))
    assert n == pytest.approx(0.01 * (len(NOMINAL) - 1), abs=4 * np.sqrt(200))


def test_combination_is_the_sum_and_same_seed_gives_same_offsets():
    jitter = parse_jitter([{"gaussian": {"sigma_deg": 0.2}}, {"random_walk": {"sigma_deg": 0.01}},
                           {"periodic": {"amplitude_deg": 0.1}}, {"jumps": {"count": 3, "size_deg": 1.0}}])
    nominal = nominal_angles_deg(100)
    total = jitter.sample(nominal, np.random.default_rng(7))
    rng = np.random.default_rng(7)
    parts = [c.sample(nominal, rng) for c in jitter.components]
    np.testing.assert_array_equal(total, np.sum(parts, axis=0))
    np.testing.assert_array_equal(total, jitter.sample(nominal, np.random.default_rng(7)))
    assert not np.array_equal(total, jitter.sample(nominal, np.random.default_rng(8)))
    assert parse_jitter(jitter.to_dict()) == jitter
    assert not parse_jitter(None) and np.all(parse_jitter([]).sample(nominal, rng) == 0)


@pytest.mark.parametrize("value, message", [
    ([{"gaussian": {"sigma_deg": -1}}], "jitter[0].gaussian.sigma_deg: must be a number >= 0 and <= 360, got -1"),
    ([{"gaussian": {"sigma": 1}}], "jitter[0].gaussian.sigma: unknown key; allowed: sigma_deg"),
    ([{"wobble": {}}], "jitter[0].wobble: unknown jitter kind; allowed: gaussian, random_walk, periodic, jumps"),
    ([{"jumps": {"size_deg": 1}}], "jitter[0].jumps: give exactly one of count"),
    ([{"jumps": {"count": 1, "size_deg": 1, "sign": "up"}}],
     "jitter[0].jumps.sign: must be one of 'random', 'positive', 'negative', got 'up'"),
    ({"gaussian": {"sigma_deg": 1}}, "jitter: must be a list of one-key mappings"),
    ([{"gaussian": {"sigma_deg": 1}, "periodic": {"amplitude_deg": 1}}], "jitter[0]: must be a one-key mapping"),
])
def test_bad_jitter_names_the_path(value, message):
    with pytest.raises(ConfigError) as info:
        parse_jitter(value)
    assert message in str(info.value)


def test_jitter_wraps_components():
    assert Jitter((GaussianJitter(0.1),)).to_dict() == [{"gaussian": {"sigma_deg": 0.1}}]
