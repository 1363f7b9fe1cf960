"""Conjugate rays: where the common ray of two views falls, and a truth-free ranking of angle sets."""

from __future__ import annotations

import numpy as np
import pytest

from ctpipe.errors import InputError
from ctpipe.geometry import Geometry
from ctpipe.model import rotation_matrix
from ctpipe.solve.conjugate import conjugate_pairs, conjugate_ray_costs, conjugate_ray_mismatch, midplane_rows
from ctpipe.solve.reprojection import consistency_costs

from conjugate_scans import simulate_scan


def _candidates(scan):
    truth, nominal = scan.true_angles_deg, scan.nominal_angles_deg
    theta = np.deg2rad(nominal)
    return {"truth": truth, "nominal": nominal, "once-per-turn": truth + 0.3 * np.sin(theta),
            "scale": truth + 0.01 * (nominal - nominal.mean()),
            "jitter": truth + np.random.default_rng(1).normal(0.0, 0.1, len(truth))}


@pytest.fixture(scope="module")
def scan():
    return simulate_scan()


def test_the_common_ray_is_the_line_through_both_sources_in_ctpipes_convention():
    geometry = Geometry(130.0, 300.0, 256, 64, 1.0, 1.0)
    sod = geometry.source_to_object_mm
    centre = np.array([0.0, 0.0, sod])
    for alpha_deg in (170.0, 180.0, 196.0, -172.0):
        # View j's source in view i's frame: X_j = R(alpha)(X_i - c) + c (ctpipe.model) with X_j = 0.
        source_j = rotation_matrix(np.deg2rad(-alpha_deg)) @ (-centre) + centre
        col_i = geometry.u0_px + source_j[0] / source_j[2] * geometry.source_to_detector_mm / geometry.pixel_pitch_u_mm
        source_i = rotation_matrix(np.deg2rad(alpha_deg)) @ (-centre) + centre
        col_j = geometry.u0_px + source_i[0] / source_i[2] * geometry.source_to_detector_mm / geometry.pixel_pitch_u_mm
        rows = np.zeros((2, 256))
        rows[0, int(round(col_i))] = 1.0          # a spike where view 0 must see view 1's source
        rows[1, int(round(col_j))] = 1.0
        angles = np.array([0.0, alpha_deg])
        pairs = conjugate_pairs(angles, geometry)
        assert [list(p) for p in pairs] == [[0], [1]]
        mismatch = conjugate_ray_mismatch(rows, geometry, angles, pairs)
        assert abs(mismatch[0]) < 0.5                 # both sampled near their spikes
        assert np.sign(col_i - geometry.u0_px) == -np.sign(col_j - geometry.u0_px) or abs(alpha_deg) == 180.0


def test_pairs_are_half_a_turn_apart_give_or_take_the_fan():
    geometry = Geometry(130.0, 300.0, 128, 64, 1.6, 1.6)
    angles = np.arange(36) * 10.0
    i, j = conjugate_pairs(angles, geometry)
    half_fan = np.rad2deg(np.arctan(63.5 * 1.6 / 300.0))
    separation = angles[j] - angles[i]
    assert len(i) > 0
    assert np.all(np.abs(separation - 180.0) <= 2 * half_fan)
    assert set(np.round(separation)) == {150.0, 160.0, 170.0, 180.0, 190.0, 200.0, 210.0}


def test_exact_data_agree_best_at_the_true_angles():
    exact = simulate_scan(noise=None)
    rows = midplane_rows(exact.projections, exact.geometry)
    pairs = conjugate_pairs(exact.nominal_angles_deg, exact.geometry)
    truth = exact.true_angles_deg

    def cost(angles):
        return float(np.nanmean(conjugate_ray_mismatch(rows, exact.geometry, angles, pairs) ** 2))

    # A common offset changes nothing; the 0.3 deg jitter of the nominal angles and a 1 % scale
    # error do. What is left at the truth is the midplane falling between two rows and the
    # detector blur, which average neighbouring rays that are not conjugate.
    assert cost(truth + 0.5) == pytest.approx(cost(truth), rel=1e-9)
    assert cost(exact.nominal_angles_deg) > 1.4 * cost(truth)
    assert cost(truth * 1.01) > 5.0 * cost(truth)
    assert cost(truth - 0.01 * truth) > 5.0 * cost(truth)


def test_the_truth_ranks_first_and_smooth_errors_are_seen(scan):
    scores = conjugate_ray_costs(scan.projections, scan.geometry, _candidates(scan), reference="truth")
    for name in ("nominal", "once-per-turn", "scale", "jitter"):
        assert scores[name].cost > scores["truth"].cost
        assert scores[name].z > 2.0, name
    # The reconstruct-and-reproject residual barely separates a once-per-turn error of 0.3 deg.
    assert scores["once-per-turn"].cost / scores["truth"].cost > 1.3
    residual = consistency_costs(scan.projections, scan.geometry,
                                 {k: v for k, v in _candidates(scan).items() if k in ("truth", "once-per-turn")},
                                 binning=2, band_px=(0.7, 4.0), max_voxels=64, filter="ram-lak")
    assert residual["once-per-turn"] / residual["truth"] < 1.05


@pytest.mark.parametrize("case", ["region of interest", "short scan", "metal"])
def test_the_ranking_holds_where_reconstructions_struggle(case):
    scan = {"region of interest": lambda: simulate_scan(**{"geometry.source_to_object_mm": 60.0}),
            "short scan": lambda: simulate_scan(**{"angles.range_deg": 250.0}),
            "metal": lambda: simulate_scan("metal-insert")}[case]()
    scores = conjugate_ray_costs(scan.projections, scan.geometry, _candidates(scan), reference="truth")
    for name in ("nominal", "once-per-turn", "scale"):
        assert scores[name].z > 2.0, (case, name)


def test_an_offset_axis_is_fitted_rather_than_blamed_on_the_angles():
    scan = simulate_scan(misalignment={"cor_offset_px": 1.5})
    candidates = _candidates(scan)
    blind = conjugate_ray_costs(scan.projections, scan.geometry, candidates, reference="truth")
    fitted = conjugate_ray_costs(scan.projections, scan.geometry, candidates, reference="truth", fit_u0_px=3.0)
    assert blind["once-per-turn"].z < 2.0            # the offset hides the angle error...
    assert fitted["once-per-turn"].z > 2.0           # ...until the axis is fitted
    assert fitted["truth"].u0_px == pytest.approx(scan.geometry.u0_px + 1.5, abs=0.1)


def test_a_tilted_detector_is_fitted_rather_than_blamed_on_the_angles():
    """A 0.5 deg in-plane tilt: the fit finds it (first order in the rows' slopes), the truth's
    cost drops, and the angle errors stay visible."""
    scan = simulate_scan(misalignment={"tilt_deg": 0.5})
    candidates = _candidates(scan)
    rows, slopes = midplane_rows(scan.projections, scan.geometry, slopes=True)
    plain = conjugate_ray_costs(None, scan.geometry, candidates, reference="truth", rows=rows, fit_u0_px=3.0)
    fitted = conjugate_ray_costs(None, scan.geometry, candidates, reference="truth", rows=rows, fit_u0_px=3.0,
                                 slopes=slopes, fit_tilt_deg=1.0)
    # ctpipe.sim.drift turns the columns towards the rows by +tilt: the source plane then crosses
    # the detector along row - v0 = -tan(tilt) (col - u0).
    assert fitted["truth"].tilt_deg == pytest.approx(-0.5, abs=0.1)
    assert fitted["truth"].cost < 0.7 * plain["truth"].cost
    for name in ("nominal", "once-per-turn", "scale"):
        assert fitted[name].z > 2.0, name
    # Without a tilt, none is found; and the fit needs the slopes.
    untilted = simulate_scan()
    rows, slopes = midplane_rows(untilted.projections, untilted.geometry, slopes=True)
    level = conjugate_ray_costs(None, untilted.geometry, {"truth": untilted.true_angles_deg}, rows=rows, slopes=slopes,
                                fit_tilt_deg=1.0)
    assert abs(level["truth"].tilt_deg) < 0.1
    with pytest.raises(InputError, match="fitting a tilt needs the rows' slopes"):
        conjugate_ray_costs(None, untilted.geometry, {"truth": untilted.true_angles_deg}, rows=rows, fit_tilt_deg=1.0)


def test_few_views_say_little_and_the_standard_error_says_so():
    scan = simulate_scan(**{"angles.n_views": 16})
    scores = conjugate_ray_costs(scan.projections, scan.geometry, _candidates(scan), reference="truth")
    assert scores["truth"].n_pairs < 40
    assert abs(scores["jitter"].z) < 2.0


def test_bad_input_is_one_clear_error(scan):
    geometry = scan.geometry
    with pytest.raises(InputError, match="no two views are half a turn apart"):
        conjugate_ray_costs(scan.projections[:20], geometry, {"a": scan.nominal_angles_deg[:20]})
    with pytest.raises(InputError, match=r"candidates\['b'\]: must be 180 finite angles"):
        conjugate_ray_costs(scan.projections, geometry, {"a": scan.nominal_angles_deg, "b": np.zeros(3)})
    with pytest.raises(InputError, match="reference: 'c' is not a candidate"):
        conjugate_ray_costs(scan.projections, geometry, {"a": scan.nominal_angles_deg}, reference="c")
    off = Geometry(130.0, 300.0, 128, 128, 1.6, 1.6, v0_px=140.0)
    with pytest.raises(InputError, match="v0_px: the midplane row must be on the detector"):
        midplane_rows(scan.projections, off)


def test_blocking_sees_the_correlation_of_neighbouring_views():
    """A smooth (correlated) series has a much larger SE of its sum than std * sqrt(n) says; white noise not."""
    from ctpipe.solve.conjugate import _blocked_se

    rng = np.random.default_rng(0)
    white = rng.normal(size=512)
    plain = float(np.std(white, ddof=1) * np.sqrt(512))
    se, blocks = _blocked_se(white)
    assert plain <= se < 1.5 * plain
    # AR(1) with rho 0.9: the sum's variance is about (1 + rho) / (1 - rho) = 19 times n var.
    smooth = np.empty(512)
    smooth[0] = rng.normal()
    for k in range(1, 512):
        smooth[k] = 0.9 * smooth[k - 1] + np.sqrt(1 - 0.81) * rng.normal()
    naive = float(np.std(smooth, ddof=1) * np.sqrt(512))
    se, blocks = _blocked_se(smooth)
    assert se > 2.5 * naive
    # ...taken over blocks longer than the correlation (about 10 views): fewer of them, fewer
    # degrees of freedom for a test on it.
    assert 16 <= blocks <= 64


def test_the_row_sampler_is_the_2d_spline_at_whole_views():
    """The 1-D sampler equals ``map_coordinates`` on 2-D coefficients at integer views, edges included."""
    from scipy.ndimage import map_coordinates, spline_filter

    from ctpipe.solve.conjugate import _sample_rows, _spline

    rng = np.random.default_rng(3)
    rows = rng.random((40, 64))
    views = rng.integers(0, 40, 500)
    cols = np.concatenate([rng.uniform(-2.0, 65.0, 495), [0.0, 63.0, 0.4, 62.6, np.nan]])
    expected = map_coordinates(spline_filter(rows, order=3, mode="nearest"), [views.astype(float),
                                                                              np.clip(cols, 0.0, 63.0)],
                               order=3, mode="nearest", prefilter=False)
    got = _sample_rows(_spline(rows), views, cols, 63.0)
    assert np.isnan(got[-1])
    np.testing.assert_allclose(got[:-1], expected[:-1], rtol=0, atol=1e-12)
