"""The gate: the estimate, one band of its correction, or the nominal angles, as the projections show."""

from __future__ import annotations

import numpy as np
import pytest

from ctpipe.errors import InputError
from ctpipe.solve.conjugate import conjugate_pairs, midplane_rows
from ctpipe.solve.bands import split_bands
from ctpipe.solve.gate import gate_angles, needed_z

from conjugate_scans import simulate_scan

def _seen(s) -> np.ndarray:
    first, second = conjugate_pairs(s.nominal_angles_deg, s.geometry, margin_px=4.0)
    seen = np.zeros(len(s.nominal_angles_deg), bool)
    seen[first] = seen[second] = True
    return seen


def _rms(angles, truth) -> float:
    error = angles - truth
    return float(np.sqrt(np.mean((error - error.mean()) ** 2)))


@pytest.fixture(scope="module", params=["full turn", "short scan"])
def scan(request):
    s = simulate_scan(**({"angles.range_deg": 250.0} if request.param == "short scan" else {}))
    return s, midplane_rows(s.projections, s.geometry)


def test_the_bands_add_up_and_split_where_they_should():
    theta = np.linspace(0.0, 360.0, 200, endpoint=False)
    odd = 0.3 * np.sin(np.deg2rad(theta)) - 0.05 * np.cos(np.deg2rad(3 * theta))
    even = 0.1 * np.cos(np.deg2rad(2 * theta)) + 0.2
    fast = np.where(np.arange(200) % 2 == 0, 0.05, -0.05)   # the alternation has no low harmonic
    parts = split_bands(odd + even + fast, theta, harmonics=3)
    assert list(parts) == ["fast", "slow-odd", "slow-even"]
    np.testing.assert_allclose(sum(parts.values()), odd + even + fast, atol=1e-12)
    for name, truth in (("fast", fast), ("slow-odd", odd), ("slow-even", even)):
        np.testing.assert_allclose(parts[name], truth, atol=1e-9, err_msg=name)


def test_a_round_that_tries_several_bands_on_an_estimated_error_asks_for_more():
    assert needed_z(2.0, 1, 0) == pytest.approx(2.0)              # one band, exact standard error
    assert needed_z(2.0, 3, 0) == pytest.approx(2.43, abs=0.01)   # Bonferroni over three
    assert needed_z(2.0, 3, 15) > needed_z(2.0, 3, 63) > needed_z(2.0, 3, 0)
    # Null bands (pure noise) pass at the single-test rate (at z 2 alone: 9 %), with 16 blocks.
    rng = np.random.default_rng(0)
    blocks = rng.normal(size=(20000, 3, 16))
    z = blocks.mean(axis=2) / (blocks.std(axis=2, ddof=1) / 4.0)
    passed = (z.min(axis=1) < -needed_z(2.0, 3, 15)).mean()
    assert 0.015 < passed < 0.03


def test_a_good_estimate_is_kept(scan):
    s, rows = scan
    truth, nominal = s.true_angles_deg, s.nominal_angles_deg
    estimate = truth + np.random.default_rng(3).normal(0.0, 0.03, len(truth)) + 7.0   # any common offset
    decision = gate_angles(rows, s.geometry, nominal, estimate)
    assert decision.decided and decision.improvement > 0.1 and decision.scores["returned"].z < -2
    assert "fast" in decision.bands              # the jitter is what the estimate corrects
    if decision.chosen == "estimate":
        np.testing.assert_allclose(decision.angles_deg, estimate, atol=1e-9)
    # Where conjugate rays reach (all views of a full turn, both ends of a short scan), corrected.
    seen = _seen(s)
    assert seen.sum() == decision.views_seen
    assert _rms(decision.angles_deg[seen], truth[seen]) < 0.3 * _rms(nominal[seen], truth[seen])


def test_an_estimate_worse_than_nominal_gives_the_nominal_angles(scan):
    s, rows = scan
    truth, nominal = s.true_angles_deg, s.nominal_angles_deg
    estimate = nominal + np.random.default_rng(4).normal(0.0, 0.5, len(truth))
    decision = gate_angles(rows, s.geometry, nominal, estimate)
    assert decision.chosen == "nominal" and "no band of the correction is shown better" in decision.reason
    assert _rms(decision.angles_deg, truth) == pytest.approx(_rms(nominal, truth))


def test_a_wrong_slow_band_is_dropped_and_the_fast_one_kept(scan):
    s, rows = scan
    truth, nominal = s.true_angles_deg, s.nominal_angles_deg
    theta = np.deg2rad(nominal)
    # Right about the jitter, wrong by a 0.5 deg once-per-turn error: no better than nominal as a whole.
    estimate = truth + 0.5 * np.sin(theta) + np.random.default_rng(3).normal(0.0, 0.03, len(truth))
    assert _rms(estimate, truth) > 0.9 * _rms(nominal, truth)
    decision = gate_angles(rows, s.geometry, nominal, estimate)
    assert decision.bands == ("fast",) and decision.chosen == "fast"
    assert _rms(decision.angles_deg, truth) < 0.5 * _rms(nominal, truth)


def test_a_wrong_even_band_does_not_ride_in_on_a_right_odd_one(scan):
    s, rows = scan
    truth, nominal = s.true_angles_deg, s.nominal_angles_deg
    theta = np.deg2rad(nominal)
    # The nominal angles carry a once-per-turn error the estimate corrects, and the estimate adds
    # a twice-per-turn error of its own, which conjugate rays see only weakly.
    nominal_odd = nominal + 0.4 * np.sin(theta)
    estimate = truth + 0.5 * np.sin(2 * theta)
    decision = gate_angles(rows, s.geometry, nominal_odd, estimate)
    assert "slow-even" not in decision.bands
    assert _rms(decision.angles_deg, truth) < _rms(nominal_odd, truth)


def test_views_no_conjugate_ray_reaches_keep_their_nominal_angle():
    s = simulate_scan(**{"angles.range_deg": 250.0})
    rows = midplane_rows(s.projections, s.geometry)
    truth, nominal = s.true_angles_deg, s.nominal_angles_deg
    middle = (nominal > 120.0) & (nominal < 140.0)
    # Right where pairs see it, 5 deg off in the middle of the short scan, where none does.
    estimate = truth + np.where(middle, 5.0, 0.0)
    decision = gate_angles(rows, s.geometry, nominal, estimate)
    assert decision.decided and decision.views_seen < len(nominal)
    offset = decision.angles_deg[middle] - nominal[middle]      # the estimate's frame: one common offset
    assert np.ptp(offset) < 1e-9
    assert "keep their nominal angle" in decision.reason


def test_without_conjugate_rays_the_gate_cannot_tell_and_returns_the_nominal_angles(scan):
    s, rows = scan
    nominal, estimate = s.nominal_angles_deg[:30], s.true_angles_deg[:30] + 7.0
    decision = gate_angles(rows[:30], s.geometry, nominal, estimate)
    assert not decision.decided and decision.chosen == "nominal" and "half a turn" in decision.reason
    assert "cannot tell" in decision.reason and "nominal angles are returned" in decision.reason
    # The nominal angles in the estimate's frame; the refiner's kept, in the nominal frame, for refiner_deg.
    offset = decision.angles_deg - nominal
    assert np.ptp(offset) < 1e-9 and abs(offset[0] - np.median(estimate - nominal)) < 1e-9
    np.testing.assert_allclose(decision.estimate_deg - nominal, estimate - nominal - offset[0], atol=1e-9)
    assert decision.improvement is None


def test_views_without_an_estimate_keep_their_nominal_angle_and_the_rest_is_gated(scan):
    s, rows = scan
    estimate = s.true_angles_deg.copy()
    estimate[5:9] = np.nan
    decision = gate_angles(rows, s.geometry, s.nominal_angles_deg, estimate)
    assert decision.decided and "4 views the refiner gave no angle keep their nominal one" in decision.reason
    assert np.all(np.isfinite(decision.angles_deg))
    everything = gate_angles(rows, s.geometry, s.nominal_angles_deg, np.full_like(estimate, np.nan))
    assert not everything.decided and everything.chosen == "nominal" and "no view" in everything.reason


def test_bad_arguments_are_one_clear_error(scan):
    s, rows = scan
    with pytest.raises(InputError, match="must be finite angles of one shape"):
        gate_angles(rows, s.geometry, s.nominal_angles_deg, s.nominal_angles_deg[:5])
    with pytest.raises(InputError, match="z must be > 0"):
        gate_angles(rows, s.geometry, s.nominal_angles_deg, s.nominal_angles_deg, z=0.0)


def test_with_the_refiners_held_out_evidence_a_good_estimate_is_returned_whole(scan):
    s, rows = scan
    truth, nominal = s.true_angles_deg, s.nominal_angles_deg
    estimate = truth + np.random.default_rng(3).normal(0.0, 0.03, len(truth)) + 7.0
    decision = gate_angles(rows, s.geometry, nominal, estimate, held_out_z=-7.0)
    assert decision.held_out_z == -7.0 and "held-out views" in decision.reason
    assert decision.bands == ("fast", "slow-odd", "slow-even")
    # Whole where conjugate rays reach; the middle of a short scan, which none does, stays nominal.
    seen = _seen(s)
    returned = decision.angles_deg - estimate
    assert np.ptp(returned[seen]) < 1e-9
    if not seen.all():
        assert np.ptp((decision.angles_deg - nominal)[~seen]) < 1e-9
        assert "keep their nominal angle" in decision.reason
    assert _rms(decision.angles_deg[seen], truth[seen]) == pytest.approx(_rms(estimate[seen], truth[seen]))


def test_short_of_held_out_evidence_beyond_doubt_the_slow_even_band_is_left_out(scan):
    """Held-out views and conjugate rays together show the estimate better, the held-out views short of doubt: the
    conjugate rays' evidence is of the estimate less its slow-even band, and held-out views hardly see a slow warp
    (it is in their reference too), so that band stays nominal. A sweep scan whose matched angles fixed two jumps
    and added a 4 deg twice-per-turn warp was returned whole so: 2.13 -> 2.77 deg RMS (1.41 without the band)."""
    s, rows = scan
    truth, nominal = s.true_angles_deg, s.nominal_angles_deg
    estimate = truth + np.random.default_rng(3).normal(0.0, 0.03, len(truth)) + 7.0
    decision = gate_angles(rows, s.geometry, nominal, estimate, held_out_z=-3.0)
    assert decision.bands == ("fast", "slow-odd") and "the slow-even band is left out" in decision.reason
    seen = _seen(s)
    correction = estimate - nominal
    correction -= np.median(correction)
    left = split_bands(np.where(seen, correction, 0.0), nominal, decision.harmonics, seen)["slow-even"]
    # What is returned is the estimate less that band, in the estimate's frame.
    returned = decision.angles_deg - (estimate - left)
    assert np.ptp(returned[seen]) < 1e-6


def test_held_out_evidence_the_conjugate_rays_contradict_is_not_taken(scan):
    """A band the conjugate rays show worse discredits the refiner's evidence: the bands are then
    selected as without it (here the fast one alone, as in the test without evidence)."""
    s, rows = scan
    truth, nominal = s.true_angles_deg, s.nominal_angles_deg
    theta = np.deg2rad(nominal)
    estimate = truth + 0.5 * np.sin(theta) + np.random.default_rng(3).normal(0.0, 0.03, len(truth))
    decision = gate_angles(rows, s.geometry, nominal, estimate, held_out_z=-3.0)
    assert decision.bands == ("fast",) and "not together with the conjugate rays" in decision.reason
    assert _rms(decision.angles_deg, truth) < 0.5 * _rms(nominal, truth)


def test_with_held_out_evidence_an_estimate_the_conjugate_rays_show_worse_gives_the_nominal_angles(scan):
    s, rows = scan
    truth, nominal = s.true_angles_deg, s.nominal_angles_deg
    estimate = nominal + np.random.default_rng(4).normal(0.0, 0.5, len(truth))
    decision = gate_angles(rows, s.geometry, nominal, estimate, held_out_z=-3.0)
    assert decision.chosen == "nominal"
    assert _rms(decision.angles_deg, truth) == pytest.approx(_rms(nominal, truth))


def test_held_out_evidence_short_of_the_threshold_changes_nothing(scan):
    s, rows = scan
    truth, nominal = s.true_angles_deg, s.nominal_angles_deg
    estimate = nominal + np.random.default_rng(4).normal(0.0, 0.5, len(truth))
    plain = gate_angles(rows, s.geometry, nominal, estimate)
    weak = gate_angles(rows, s.geometry, nominal, estimate, held_out_z=-1.5)
    assert weak.chosen == plain.chosen == "nominal" and weak.reason == plain.reason


@pytest.mark.parametrize("conjugate_z, seen_z, returned", [(-1.7, -1.7, False), (-2.5, -2.5, True),
                                                         (-2.5, -0.1, False)])
def test_strong_held_out_evidence_does_not_carry_conjugate_rays_that_see_too_little(conjugate_z, seen_z, returned):
    """Each line of evidence must show the estimate better on its own: a held-out z of -2.9 with a
    conjugate z of -1.7 sums to -3.3, past one band's threshold, and is not enough (a sweep scan
    whose matched angles had walked, a few views 2 deg off, came out 2 dB worse that way). The
    conjugate rays' z is that of the estimate less its slow-even band: a whole at -2.5 whose other
    bands score -0.1 is not enough either (a sweep scan 2.8 deg off, nearly all slow-even)."""
    from ctpipe.solve.conjugate import ConjugateRayScore
    from ctpipe.solve.gate import _backward

    def delta(name, reference):
        if reference != "nominal":   # removing a band makes things worse (z > 0 against the estimate)
            return 0.0 if name == reference else 1.0
        return {"returned": conjugate_z, "visible": seen_z}.get(name, 0.0)

    def scored(candidates, reference):
        return {name: ConjugateRayScore(cost=1.0, u0_px=0.0, n_pairs=100, versus=reference,
                                        delta=delta(name, reference), delta_se=1.0, dof=30) for name in candidates}

    theta = np.linspace(0.0, 360.0, 90, endpoint=False)
    correction = np.random.default_rng(0).normal(0.0, 0.1, 90)
    parts = split_bands(correction, theta, harmonics=3)
    stands = _backward(scored, theta, correction, list(parts), parts, 2.0, -2.9)
    assert (stands is not None) == returned


def _mock_scored(whole_z: float, seen_z: float, band_worse: str | None = None):
    """A conjugate-ray scorer that gives the estimate (whole and without its slow-even band) these z
    against the nominal angles, and shows removing ``band_worse`` better than keeping it."""
    from ctpipe.solve.conjugate import ConjugateRayScore

    def delta(name, reference):
        if reference != "nominal":
            return 0.0 if name == reference else (-5.0 if name == band_worse else 1.0)
        return {"returned": whole_z, "visible": seen_z}.get(name, 0.0)

    def scored(candidates, reference):
        return {name: ConjugateRayScore(cost=1.0, u0_px=0.0, n_pairs=100, versus=reference,
                                        delta=delta(name, reference), delta_se=1.0, dof=30) for name in candidates}
    return scored


@pytest.mark.parametrize("held_out_z, band_z, without_z, whole_z, seen_z, band_worse, kept", [
    # A twice-per-turn correction the conjugate rays hardly see, its band shown better on its own.
    (-9.4, -6.6, None, -2.4, -0.1, None, "all"),
    (-6.0, -2.1, None, 0.0, 0.0, None, "all"),                 # decisive from -6 on
    (-5.9, -6.6, None, -2.4, -0.1, None, None),                # short of it: the conjugate rays must agree
    (-9.4, None, None, -2.4, -0.1, None, None),                # the band never judged on its own
    # The band not shown better on its own: the rest, where the held-out views vouch for it.
    (-9.4, -1.3, -7.0, -1.5, -1.5, None, "without slow-even"),
    (-9.4, -1.3, -5.0, -1.5, -1.5, None, None),
    (-9.4, -1.3, -7.0, -1.5, +0.5, None, None),                # ... where the conjugate rays lean against it
    (-9.4, -1.3, -7.0, +0.5, -1.5, None, "without slow-even"), # ... not where only the whole leans against it
    (-9.4, -6.6, -7.0, +1.1, -0.5, None, "without slow-even"), # a whole leaning against it keeps the nominal band
    # The conjugate rays lean the other way, too weakly to decide (a bead cloud of 63 views whose
    # angles came out a little better and its reconstruction 0.4 dB worse).
    (-9.4, -6.6, None, +1.1, +0.9, None, None),
    (-9.4, -6.6, None, 3.0, 3.0, None, None),                  # the conjugate rays show the nominal angles better
    (-9.4, -6.6, None, -2.4, -0.1, "slow-odd", None),          # or a band of the estimate worse
])
def test_decisive_held_out_evidence_stands_alone_band_by_band_unless_the_conjugate_rays_contradict_it(
        held_out_z, band_z, without_z, whole_z, seen_z, band_worse, kept):
    """Held-out views that show the estimate better beyond doubt (``HELD_OUT_DECISIVE_Z``) decide the
    band the conjugate rays cannot see where they show that band better on its own: on a sweep scan
    whose error was nearly all twice per turn the held-out z was -9.4 (the band alone -6.6) and the
    conjugate rays' -0.1 without the band. A whole decisive on its other bands (two jumps fixed, a
    4 deg twice-per-turn warp added: -5.1 as a whole, the band alone -1.3) keeps the nominal band."""
    from ctpipe.solve.gate import _backward

    theta = np.linspace(0.0, 360.0, 90, endpoint=False)
    correction = 0.5 * np.cos(np.deg2rad(2 * theta)) + np.random.default_rng(0).normal(0.0, 0.05, 90)
    parts = split_bands(correction, theta, harmonics=3)
    stands = _backward(_mock_scored(whole_z, seen_z, band_worse), theta, correction, list(parts), parts, 2.0,
                       held_out_z, band_z, without_z)
    if kept is None:
        assert stands is None
        return
    assert stands is not None and "beyond doubt" in stands[0]
    assert list(stands[4]) == (list(parts) if kept == "all" else ["fast", "slow-odd"])


def test_decisive_held_out_evidence_returns_a_correct_twice_per_turn_correction_whole():
    """On a simulated full turn whose nominal angles are off twice per turn (the band conjugate rays
    see only through the fan), a correct estimate comes back whole where the held-out views vouch
    for the whole and for the band beyond doubt; without the band's own evidence, or short of
    decisive, the gate keeps the nominal angles."""
    s = simulate_scan()
    rows = midplane_rows(s.projections, s.geometry)
    truth = s.true_angles_deg
    nominal = truth + 0.5 * np.cos(np.deg2rad(2 * truth))
    estimate = truth + np.random.default_rng(3).normal(0.0, 0.02, len(truth))
    decision = gate_angles(rows, s.geometry, nominal, estimate, held_out_z=-9.0, held_out_slow_even_z=-7.0,
                           held_out_without_slow_even_z=-2.0)
    assert decision.chosen == "estimate" and "beyond doubt" in decision.reason
    assert _rms(decision.angles_deg, truth) < 0.05
    assert gate_angles(rows, s.geometry, nominal, estimate, held_out_z=-9.0).chosen == "nominal"
    assert gate_angles(rows, s.geometry, nominal, estimate, held_out_z=-3.0, held_out_slow_even_z=-7.0).chosen == \
        "nominal"


def test_on_a_full_turn_what_does_not_turn_is_taken_out_before_the_conjugate_rays_judge():
    """A static edge over a third of the detector makes the true angles' conjugate rays disagree
    more than the nominal ones' (z about +4.7 on this scan); without the views' mean they score
    as on the clean scan (:func:`~ctpipe.solve.conjugate.turning_part`)."""
    from ctpipe.solve.conjugate import conjugate_ray_costs, turning_part

    s = simulate_scan()
    rows = midplane_rows(s.projections, s.geometry)
    cols = rows.shape[1]
    static = np.where(np.arange(cols) > 0.7 * cols, 0.5 * rows.max(), 0.0)
    sets = {"nominal": s.nominal_angles_deg, "truth": s.true_angles_deg}

    def truth_z(r):
        return conjugate_ray_costs(None, s.geometry, sets, reference="nominal", fit_u0_px=3.0, rows=r)["truth"].z

    assert truth_z(rows) < -3.0 < 3.0 < truth_z(rows + static)
    assert truth_z(turning_part(rows + static, s.nominal_angles_deg)[0]) == pytest.approx(
        truth_z(turning_part(rows, s.nominal_angles_deg)[0]), abs=1e-9)
    decision = gate_angles(rows + static, s.geometry, s.nominal_angles_deg,
                           s.true_angles_deg + np.random.default_rng(3).normal(0.0, 0.03, len(rows)))
    assert decision.chosen != "nominal"


def test_the_turning_part_of_a_short_scan_is_its_rows_as_they_are():
    from ctpipe.solve.conjugate import turning_part

    rows = np.random.default_rng(0).normal(size=(40, 16))
    slopes = np.random.default_rng(1).normal(size=(40, 16))
    short = np.linspace(0.0, 250.0, 40)
    same, same_slopes = turning_part(rows, short, slopes)
    assert np.array_equal(same, rows) and np.array_equal(same_slopes, slopes) and same is not rows
    full, full_slopes = turning_part(rows, np.linspace(0.0, 360.0, 40, endpoint=False), slopes)
    assert np.allclose(full.mean(axis=0), 0.0) and np.allclose(full_slopes.mean(axis=0), 0.0)
    assert np.allclose(full - rows, full[0] - rows[0])

