"""Projection matching: the derivative it steps along, and angles recovered on a small simulated scan."""

from __future__ import annotations

import numpy as np
import pytest

from ctpipe.builtin.projection_matching import ProjectionMatchingRefiner
from ctpipe.errors import ConfigError, InputError
from ctpipe.evaluate.scoring import view_errors_deg
from ctpipe.geometry import Geometry
from ctpipe.sim.phantoms import load_phantom
from ctpipe.sim.projectors import VoxelProjector
from ctpipe.sim.scan_spec import parse_scan_spec
from ctpipe.sim.simulator import simulate
from ctpipe.solve.reprojection import (HELD_OUT_DECISIVE_Z, HeldOutScore, as_line_integrals, band_pass,
                                       consistency_costs, held_out_decisive, projection_matching,
                                       reconstruction_grid, tangential_derivative)
from ctpipe.testing import check_refiner

SCAN = {
    "geometry": {"source_to_object_mm": 130.0, "source_to_detector_mm": 300.0, "detector_cols": 128,
                 "detector_rows": 128, "pixel_pitch_u_mm": 1.6, "pixel_pitch_v_mm": 1.6},
    "angles": {"n_views": 120, "range_deg": 360.0},
    "jitter": [{"gaussian": {"sigma_deg": 0.4}}, {"jumps": {"count": 2, "size_deg": 1.5}}],
    "noise": {"photons_per_pixel": 100000, "flat_frames": 4, "dark_frames": 2, "dark_counts": 100},
    "projector": {"kind": "analytic", "supersample": 1, "blur_px": 0.5},
    "seed": 1,
}


#: The levels and iterations the tests match the scan with.
MATCH = {"binning": (2, 1), "iterations": (3, 2), "max_voxels": 96}


def rms(angles_deg, truth_deg) -> float:
    return float(np.sqrt(np.mean(view_errors_deg(angles_deg, truth_deg) ** 2)))


@pytest.fixture(scope="module")
def scan():
    return simulate(load_phantom("bead-cylinder"), parse_scan_spec(SCAN), rng=np.random.default_rng(5))


@pytest.fixture(scope="module")
def matched(scan):
    """The scan matched from its nominal angles as several tests here read it (one run of about 8 s, shared)."""
    return projection_matching(scan.projections, scan.geometry, scan.nominal_angles_deg, **MATCH)


def test_the_projected_tangential_derivative_is_the_derivative_of_the_projection():
    geometry = Geometry(130.0, 300.0, 64, 64, 1.6, 1.6)
    grid = reconstruction_grid(geometry, 48)
    rng = np.random.default_rng(0)
    volume = np.zeros(grid.shape, np.float32)
    volume[10:-10, 12:-12, 12:-12] = rng.uniform(0, 1, (grid.n_y - 20, grid.n_z - 24, grid.n_x - 24))
    from scipy.ndimage import gaussian_filter

    volume = gaussian_filter(volume, 2.0).astype(np.float32)
    projector = VoxelProjector(geometry, grid)
    angles = np.array([0.0, 33.0, 101.0])
    eps = 0.05
    finite = (projector.forward(volume, angles + eps) - projector.forward(volume, angles - eps)) / (2 * eps)
    analytic = projector.forward(tangential_derivative(volume, grid), angles)
    # Same sign and scale (a turn of +delta is +delta in ctpipe's convention), up to discretisation.
    ratio = float(np.sum(finite * analytic) / np.sum(analytic * analytic))
    assert ratio == pytest.approx(1.0, abs=0.1)
    assert np.corrcoef(finite.ravel(), analytic.ravel())[0, 1] > 0.95


def test_the_grid_covers_the_field_of_view_and_respects_max_voxels():
    geometry = Geometry(150.0, 390.0, 512, 512, 0.8, 0.8)
    grid = reconstruction_grid(geometry, 192)
    radius = 150.0 * np.sin(np.arctan(256 * 0.8 / 390.0))
    assert grid.n_x == grid.n_z <= 192 and grid.n_y <= 2 * 192
    assert grid.n_x * grid.voxel_size_mm >= 2 * radius
    fine = reconstruction_grid(geometry, 4096)
    assert fine.voxel_size_mm == pytest.approx(0.8 * 150.0 / 390.0)


def test_band_pass_removes_constants_and_keeps_edges():
    image = np.zeros((1, 64, 64), np.float32)
    image[0, :, 32:] = 1.0
    out = band_pass(image + 5.0, 0.7, 4.0)
    assert abs(float(out[0, 32, 5])) < 1e-4 and abs(float(out[0, 32, 60])) < 1e-4
    assert float(np.abs(out[0, 32, 28:36]).max()) > 0.1


def test_intensities_are_recognised_and_turned_into_line_integrals(scan):
    line = scan.projections[:3]
    same, converted = as_line_integrals(line)
    assert not converted and np.array_equal(same, line)
    intensities = 1000.0 * np.exp(-line)
    back, converted = as_line_integrals(intensities)
    assert converted
    inside = line > 0.2
    np.testing.assert_allclose(back[inside], line[inside], atol=0.05)


def test_projection_matching_recovers_the_jitter_from_the_nominal_angles(scan, matched):
    nominal, truth = scan.nominal_angles_deg, scan.true_angles_deg
    before = rms(nominal, truth)
    result = matched
    after = rms(result.angles_deg, truth)
    assert before > 0.4
    assert after < 0.1 * before, (before, after)
    # One entry per evaluation; each level starts with one, and every step kept lowered the cost
    # by more than fitting noise would.
    assert [h["kind"] for h in result.history if h["iteration"] == 0] == ["start", "start"]
    for level in (2, 1):
        kept = [h for h in result.history if h["binning"] == level and h["accepted"]]
        assert all(a["cost"] - b["cost"] > 2 * a["noise_drop"] for a, b in zip(kept, kept[1:]))
    assert result.history[0]["cost"] > result.history[-1]["cost"]
    costs = consistency_costs(scan.projections, scan.geometry, {"nominal": nominal, "matched": result.angles_deg,
                                                                "nan": np.full_like(nominal, np.nan)}, binning=2,
                              max_voxels=96)
    assert costs["matched"] < costs["nominal"] and costs["nan"] == np.inf


def test_the_held_out_test_decides_at_the_coarse_level_only_when_that_is_decisive(scan):
    nominal = scan.nominal_angles_deg
    args = dict(binning=(2, 1), iterations=(1, 1), max_voxels=96)
    clear = projection_matching(scan.projections, scan.geometry, nominal, compare={"nominal": nominal}, **args)
    assert clear.held_out_binning == 2 and clear.held_out["matched"].z < -HELD_OUT_DECISIVE_Z
    # A second angle set no different from the reference (z 0) leaves the coarse level in doubt:
    # the finest level scores them all, and agrees on the matched angles.
    doubt = projection_matching(scan.projections, scan.geometry, nominal,
                                compare={"nominal": nominal, "copy": nominal.copy()}, **args)
    assert doubt.held_out_binning == 1 and doubt.held_out["copy"].z == 0.0
    assert doubt.held_out["matched"].z < -2.0
    np.testing.assert_array_equal(doubt.angles_deg, clear.angles_deg)


def test_the_slow_even_band_is_judged_on_its_own_where_the_held_out_test_is_decisive(scan):
    """The band the conjugate rays cannot see is shown better on its own where it is right, and not
    where it is a warp the rest of the correction carried (issue 33: a sweep scan whose matched
    angles fixed two jumps and added a 4 deg twice-per-turn warp scored z -5.1 as a whole)."""
    from ctpipe.solve.reprojection import _Level, slow_even_band_scores

    truth = scan.true_angles_deg
    twice = np.cos(np.deg2rad(2 * truth))
    nominal = truth + 0.8 * twice
    data, _ = as_line_integrals(scan.projections)
    level = _Level(data, scan.geometry, 2, 96, (0.7, 4.0), "ram-lak")
    right = slow_even_band_scores(level, nominal, truth)
    assert right["band"].z < -2.0 and right["without"].z > right["band"].z
    # Matched angles that fix the fast part of the nominal error but warp twice per turn.
    warped = slow_even_band_scores(level, scan.nominal_angles_deg, truth + 0.8 * twice)
    assert warped["band"].z > 0.0 and warped["without"].z < -2.0
    clear = projection_matching(scan.projections, scan.geometry, nominal, compare={"nominal": nominal},
                                binning=(2, 1), iterations=(1, 1), max_voxels=96)
    assert clear.held_out["matched"].z < -HELD_OUT_DECISIVE_Z
    assert set(clear.held_out_slow_even) == {"band", "without"}


def test_held_out_decisive_asks_every_angle_set_to_be_past_the_margin_either_way():
    def scores(*zs):
        return {"nominal": HeldOutScore(1.0), **{f"s{k}": HeldOutScore(1.0, z, 1.0) for k, z in enumerate(zs)}}

    assert held_out_decisive(scores(-6.0), "nominal") and held_out_decisive(scores(7.5, -30.0), "nominal")
    assert not held_out_decisive(scores(-5.9), "nominal") and not held_out_decisive(scores(-20.0, 1.0), "nominal")


def test_the_standard_errors_cover_the_errors_and_grow_with_the_noise(scan, matched):
    """Most matched views within two standard errors, not all; fewer photons, larger error bars.

    The calibration (SE_CALIBRATION) was set on the 1e5-photon scan; the 300-photon one is not.
    """
    from ctpipe.evaluate.scoring import se_coverage

    results = {}
    for photons in (100000, 300):
        if photons == 100000:
            noisy, result = scan, matched
        else:
            spec = parse_scan_spec({**SCAN, "noise": {**SCAN["noise"], "photons_per_pixel": photons}})
            noisy = simulate(load_phantom("bead-cylinder"), spec, rng=np.random.default_rng(5))
            result = projection_matching(noisy.projections, noisy.geometry, noisy.nominal_angles_deg, **MATCH)
        coverage = se_coverage(view_errors_deg(result.angles_deg, noisy.true_angles_deg), result.angle_se_deg)
        assert coverage["views"] == 120 and 0.85 <= coverage["fraction"] <= 0.99, coverage
        results[photons] = coverage["median_se_deg"]
    assert results[300] > 1.3 * results[100000], results


def test_a_drifting_detector_is_fitted_with_the_angles_instead_of_bending_them():
    """Per-view shifts (a walk and two jumps of the whole projection) are found, and the angles
    they would otherwise be taken for come out closer to the truth than without fitting them."""
    from ctpipe.solve.reprojection import _shift_gauge

    spec = parse_scan_spec({**SCAN, "misalignment": {"drift": {"walk_px": 0.1, "jumps": 2, "jump_px": 1.0}}})
    drifting = simulate(load_phantom("bead-cylinder"), spec, rng=np.random.default_rng(5))
    nominal, truth = drifting.nominal_angles_deg, drifting.true_angles_deg
    plain = projection_matching(drifting.projections, drifting.geometry, nominal, **MATCH)
    fitted = projection_matching(drifting.projections, drifting.geometry, nominal, shifts=True, **MATCH)
    assert plain.shifts_px is None and fitted.shifts_px.shape == (120, 2)
    assert rms(fitted.angles_deg, truth) < 0.7 * rms(plain.angles_deg, truth), (rms(fitted.angles_deg, truth),
                                                                                 rms(plain.angles_deg, truth))
    # The drift found is the drift simulated, less what the object's own place on the table explains.
    true_drift = _shift_gauge(drifting.true_detector_offsets_px, np.deg2rad(nominal))
    for axis in (0, 1):
        assert np.corrcoef(fitted.shifts_px[:, axis], true_drift[:, axis])[0, 1] > 0.9, axis
    assert np.sqrt(np.mean((fitted.shifts_px - true_drift) ** 2)) < 0.3 * np.sqrt(np.mean(true_drift ** 2))


def test_fitting_shifts_costs_nothing_on_a_scan_without_drift(scan, matched):
    nominal, truth = scan.nominal_angles_deg, scan.true_angles_deg
    plain = matched
    fitted = projection_matching(scan.projections, scan.geometry, nominal, shifts=True, **MATCH)
    assert rms(fitted.angles_deg, truth) < 1.1 * rms(plain.angles_deg, truth)
    assert np.sqrt(np.mean(fitted.shifts_px ** 2)) < 0.15


def test_projection_matching_says_what_is_wrong_with_its_arguments(scan):
    with pytest.raises(InputError, match="angles_deg: must be 120 finite angles"):
        projection_matching(scan.projections, scan.geometry, scan.nominal_angles_deg[:5])
    with pytest.raises(InputError, match="binning: each factor must be an integer from 1 to 16"):
        projection_matching(scan.projections, scan.geometry, scan.nominal_angles_deg, binning=(32,), iterations=(1,))
    with pytest.raises(InputError, match="band_px"):
        projection_matching(scan.projections, scan.geometry, scan.nominal_angles_deg, band_px=(4.0, 1.0))


def test_the_refiner_passes_the_conformance_check_and_returns_its_start_without_projections():
    solution = check_refiner(ProjectionMatchingRefiner())
    assert solution.info["matching"].startswith("skipped: no projections")


def test_levels_bin_any_detector_to_about_the_same_sizes():
    from ctpipe.solve.reprojection import matching_levels

    assert matching_levels((512, 512), (3, 2)) == [(4, 3), (2, 2)]
    assert matching_levels((2048, 1536), (3, 2)) == [(12, 3), (6, 2)]
    assert matching_levels((128, 128), (3, 2)) == [(2, 3), (1, 2)]   # a small detector keeps its coarse level
    assert matching_levels((192, 256), (3, 2)) == [(2, 3), (1, 2)]
    assert matching_levels((512, 512), (3, 2), level_px=(256, 256)) == [(2, 5)]   # the same factor twice: merged
    assert matching_levels((512, 512), (3, 2), binning=(2, 1)) == [(2, 3), (1, 2)]
    assert matching_levels((40, 40), (3, 2), binning=(4, 2)) == [(2, 2)]   # 10 px a side is too few


def test_the_refiner_rejects_levels_that_do_not_line_up():
    with pytest.raises(ConfigError, match="one count per level"):
        ProjectionMatchingRefiner(binning=(4, 2), iterations=(3,))
    with pytest.raises(ConfigError, match="one count per level"):
        ProjectionMatchingRefiner(level_px=(128,))
    with pytest.raises(ConfigError, match="band_low_px: must be below band_high_px"):
        ProjectionMatchingRefiner(band_low_px=5.0, band_high_px=4.0)


def test_the_pipeline_with_projection_matching_beats_the_nominal_angles_by_far(scan):
    from ctpipe.pipeline import Pipeline

    config = {
        "estimator": {"name": "ransac-1pt", "hypotheses": "all", "scoring": "msac", "sampson_threshold": 3.0e-3},
        "refiner": {"name": "projection-matching", "level_px": [64, 128], "iterations": [3, 2], "max_voxels": 96},
        "pairs": {"baselines": [1, 2]},
        "gate": "off",
    }
    result = Pipeline.from_config(config).run(scan.projections, scan.geometry, nominal_angles_deg=scan.nominal_angles_deg)
    truth = scan.true_angles_deg
    # Over 24 noise draws of this scan the matched angles' RMS was 0.06-0.21 of the nominal's
    # (median 0.09): a tenth is typical, a quarter is what every draw kept.
    assert rms(result.angles_deg, truth) < 0.25 * rms(scan.nominal_angles_deg, truth)
    assert result.refiner_info["chosen"] == "matched"
    # Judged on views held out of the reference, against the nominal angles.
    held_out = result.refiner_info["held_out"]
    assert set(held_out) == set(result.refiner_info["consistency_cost"]) == {"matched", "nominal"}
    assert held_out["matched"]["z"] < -2.0 and held_out["nominal"]["z"] == 0.0
    # With that evidence the gate returns the whole estimate, the twice-per-turn part the conjugate
    # rays alone do not show beyond noise at 120 views included.
    gated = Pipeline.from_config({**config, "gate": "auto"}).run(scan.projections, scan.geometry,
                                                                 nominal_angles_deg=scan.nominal_angles_deg)
    assert gated.gate.chosen == "estimate" and gated.gate.held_out_z == held_out["matched"]["z"]
    assert rms(gated.angles_deg, truth) < 0.25 * rms(scan.nominal_angles_deg, truth)


def test_removing_the_static_background_takes_the_container_out_of_the_pair_angles(scan):
    from ctpipe.evaluate.scoring import pair_errors_deg
    from ctpipe.pipeline import Pipeline

    def bias_percent(static_background):
        pipeline = Pipeline.from_config({
            "estimator": {"name": "ransac-1pt", "hypotheses": "all", "scoring": "msac", "sampson_threshold": 3.0e-3},
            "refiner": {"name": "least-squares"}, "preprocess": {"static_background": static_background}})
        result = pipeline.run(scan.projections, scan.geometry, nominal_angles_deg=scan.nominal_angles_deg)
        errors = pair_errors_deg(result.pairs, result.pair_angles_deg, scan.true_angles_deg)
        return 100.0 * float(np.nanmean(errors)) / 3.0, result.static_background_removed

    off, removed_off = bias_percent("off")
    on, removed_on = bias_percent("auto")          # a full turn: auto removes it
    assert (removed_off, removed_on) == (False, True)
    # The container's static profile holds the features' localisation back: pairs come out short.
    assert off < -3.0 and abs(on) < 0.6 * abs(off), (off, on)


def test_auto_keeps_the_background_without_nominal_angles_or_on_a_narrow_range(bead_scan):
    from ctpipe.pipeline import Pipeline

    projections, geometry, truth = bead_scan
    pipeline = Pipeline.from_config({"refiner": {"name": "least-squares"}})
    assert not pipeline.run(projections, geometry).static_background_removed
    assert not pipeline.run(projections, geometry, nominal_angles_deg=truth).static_background_removed
    with pytest.raises(InputError, match="static_background: must be one of"):
        Pipeline(pipeline.detector, pipeline.matcher, pipeline.estimator, pipeline.refiner, static_background="yes")


@pytest.mark.parametrize("tilt_deg", [0.3, -0.3])
def test_the_axis_and_the_detector_tilt_are_fitted_with_the_angles(tilt_deg):
    """An axis 1.5 px off and a tilted detector are found (the tilt in the camera convention of
    ctpipe.solve.camera: a simulated tilt t comes back as -t), and the angles come out closer to the
    truth than when matched without them."""
    spec = parse_scan_spec({**SCAN, "misalignment": {"cor_offset_px": 1.5, "tilt_deg": tilt_deg}})
    misaligned = simulate(load_phantom("bead-cylinder"), spec, rng=np.random.default_rng(5))
    nominal, truth = misaligned.nominal_angles_deg, misaligned.true_angles_deg
    kwargs = {**MATCH, "shifts": True}
    fitted = projection_matching(misaligned.projections, misaligned.geometry, nominal, detector=True, **kwargs)
    plain = projection_matching(misaligned.projections, misaligned.geometry, nominal, **kwargs)
    assert fitted.axis_offset_px == pytest.approx(1.5, abs=0.1)
    assert fitted.tilt_deg == pytest.approx(-tilt_deg, abs=0.03)
    assert plain.axis_offset_px is None and plain.tilt_deg is None
    assert rms(fitted.angles_deg, truth) < 0.9 * rms(plain.angles_deg, truth) < 0.1 * rms(nominal, truth)


def test_candidates_are_costed_on_the_detector_aligned_to_them():
    """An axis 1.5 px off and a 0.3 deg tilt make every candidate's residual (here 0.18 for the
    true angles and the nominal ones alike, 3 % apart), hiding which explains the views better;
    costed on the detector aligned to each, they score as on the aligned scanner (0.060 and
    0.067, 12 % apart)."""
    def costs(misalignment, detector):
        spec = parse_scan_spec({**SCAN, "misalignment": misalignment})
        s = simulate(load_phantom("bead-cylinder"), spec, rng=np.random.default_rng(5))
        candidates = {"truth": s.true_angles_deg, "nominal": s.nominal_angles_deg}
        return consistency_costs(s.projections, s.geometry, candidates, binning=2, max_voxels=96, detector=detector)

    aligned = costs(None, False)
    recorded = costs({"cor_offset_px": 1.5, "tilt_deg": 0.3}, False)
    fitted = costs({"cor_offset_px": 1.5, "tilt_deg": 0.3}, True)
    assert recorded["truth"] > 2.0 * aligned["truth"]
    assert recorded["nominal"] / recorded["truth"] < 1.05
    for name in aligned:
        assert fitted[name] == pytest.approx(aligned[name], rel=0.02)
    assert fitted["nominal"] / fitted["truth"] > 1.08
    # On an aligned scanner there is nothing to align: the costs are the plain ones.
    assert costs(None, True) == pytest.approx(aligned, rel=1e-3)


def test_a_step_is_kept_only_where_the_cost_falls_beyond_fitting_noise():
    """On views of pure noise every Gauss-Newton step only fits the noise: none is kept, the start
    angles come back as they were, and the result says why."""
    geometry = Geometry(130.0, 300.0, 64, 64, 1.6, 1.6)
    noise = np.random.default_rng(3).normal(1.0, 0.1, (48, 64, 64)).astype(np.float32)
    start = np.linspace(0.0, 360.0, 48, endpoint=False)
    result = projection_matching(noise, geometry, start, binning=(2, 1), iterations=(2, 2), max_voxels=48,
                                 shifts=True, detector=True)
    np.testing.assert_array_equal(result.angles_deg, start)
    assert not any(h["accepted"] for h in result.history if h["kind"] != "start")
    assert "no step lowered the cost" in result.stopped


def test_the_static_part_is_the_mean_of_a_full_turn_and_the_median_of_a_short_scan():
    from ctpipe.solve.reprojection import static_part, static_part_applies

    views = np.random.default_rng(0).uniform(0, 1, (40, 4, 5)).astype(np.float32)
    full, short = np.linspace(0, 360, 40, endpoint=False), np.linspace(0, 250, 40)
    np.testing.assert_allclose(static_part(views, full), views.mean(axis=0), rtol=1e-6)
    np.testing.assert_allclose(static_part(views, short), np.median(views, axis=0), rtol=1e-6)
    assert static_part_applies(full) and static_part_applies(short)
    assert not static_part_applies(np.linspace(0, 120, 40)) and not static_part_applies(full[::4])


def test_aligning_a_view_undoes_the_simulated_shift_and_tilt():
    """The aligned detector of matching is the nominal one the simulator resamples from:
    ctpipe.sim.drift's shift (du, dv) and tilt t are undone by the shift (du, dv) and the tilt -t."""
    from scipy.ndimage import gaussian_filter

    from ctpipe.sim.drift import resample_to_detector
    from ctpipe.solve.reprojection import _align

    geometry = Geometry(130.0, 300.0, 96, 80, 0.8, 1.0, u0_px=50.0, v0_px=37.0)
    image = gaussian_filter(np.random.default_rng(1).uniform(0, 1, (80, 96)), 3.0).astype(np.float32)
    moved = resample_to_detector(image[None], geometry, [[1.3, -0.6]], tilt_deg=0.8)[0]
    back = _align(moved, geometry, (1.3, -0.6), np.deg2rad(-0.8))
    inner = (slice(12, -12), slice(12, -12))
    assert np.abs(back[inner] - image[inner]).max() < 0.02 * np.ptp(image)


def test_the_views_own_and_common_unknowns_are_solved_as_one_least_squares_problem():
    from ctpipe.solve.reprojection import _solve_blocks

    rng = np.random.default_rng(2)
    n_views, per_view, common = 6, 3, 2
    columns = rng.normal(size=(n_views, 50, per_view + common))
    data = rng.normal(size=(n_views, 50))
    gram = np.einsum("vpa,vpb->vab", columns, columns)
    rhs = np.einsum("vpa,vp->va", columns, data)
    solution, informative = _solve_blocks(gram, rhs, per_view)
    # The same problem written out whole: every view's own unknowns, then the common ones.
    dense = np.zeros((n_views * 50, n_views * per_view + common))
    for v in range(n_views):
        dense[v * 50:(v + 1) * 50, v * per_view:(v + 1) * per_view] = columns[v, :, :per_view]
        dense[v * 50:(v + 1) * 50, n_views * per_view:] = columns[v, :, per_view:]
    exact = np.linalg.lstsq(dense, data.ravel(), rcond=None)[0]
    assert informative.all()
    np.testing.assert_allclose(solution[:, :per_view].ravel(), exact[:n_views * per_view], atol=1e-7)
    np.testing.assert_allclose(solution[0, per_view:], exact[n_views * per_view:], atol=1e-7)


@pytest.mark.parametrize("shape", [(3, 40, 52), (2, 5, 9)])
@pytest.mark.parametrize("band", [(0.7, 4.0), (0.0, 2.0)])
def test_band_pass_is_scipys_difference_of_gaussians(shape, band):
    """The fused kernel is SciPy's Gaussian filter pair (4-sigma kernels, mirrored edges), even
    where a kernel is wider than the image."""
    from scipy.ndimage import gaussian_filter

    images = np.random.default_rng(3).random(shape).astype(np.float32)
    low, high = band
    fine = gaussian_filter(images, (0, low, low)) if low > 0 else images
    expected = fine - gaussian_filter(images, (0, high, high))
    np.testing.assert_allclose(band_pass(images, low, high), expected, atol=2e-6)
    np.testing.assert_allclose(band_pass(images[0], low, high), expected[0], atol=2e-6)


def test_the_parallel_gradients_and_normal_equations_are_numpys():
    from ctpipe.solve.reprojection import _image_gradients, _normal_equations

    rng = np.random.default_rng(4)
    images = rng.normal(size=(3, 17, 23)).astype(np.float32)
    for spacing in (1.0, 0.37):
        along_u, along_v = _image_gradients(images, spacing)
        np.testing.assert_array_equal(along_u, np.gradient(images, spacing, axis=2))
        np.testing.assert_array_equal(along_v, np.gradient(images, spacing, axis=1))
    columns = rng.normal(size=(3, 4, 17, 23)).astype(np.float32)
    gram, rhs = np.zeros((3, 4, 4)), np.zeros((3, 4))
    _normal_equations(columns, images, gram, rhs)
    np.testing.assert_allclose(gram, np.einsum("vaij,vbij->vab", columns, columns, dtype=np.float64), rtol=1e-12)
    np.testing.assert_allclose(rhs, np.einsum("vaij,vij->va", columns, images, dtype=np.float64), rtol=1e-12)


def test_a_spent_array_takes_the_aligned_views_and_keeps_the_recorded_ones_in_16_bits(scan):
    """The finest level aligns into the array handed over, with the views as recorded kept as codes
    (issue 35: a second float32 copy of 2,000 views of 256^2 was half a gigabyte), and matches as
    the float32 copy did."""
    from ctpipe.solve.reprojection import _Level, _Views

    data, _ = as_line_integrals(scan.projections)
    kept = data.copy()
    views = _Views(data, spend=True)
    level = _Level(views, scan.geometry, 1, 96, (0.7, 4.0), "ram-lak")
    assert views.codes is None and level.data is data        # not aligned: the views themselves, exact
    shifts = np.column_stack([np.linspace(-0.7, 0.7, len(data)), np.zeros(len(data))])
    level.align(shifts, 0.002)
    assert np.shares_memory(level.data, data) and views.codes.dtype == np.int16
    decoded = views.recorded(0, len(data))
    step = (kept.max(axis=(1, 2)) - kept.min(axis=(1, 2))) / 65534.0
    assert np.all(np.abs(decoded - kept) <= 0.51 * step[:, None, None] + 1e-6)
    unspent = _Level(kept, scan.geometry, 1, 96, (0.7, 4.0), "ram-lak")
    unspent.align(shifts, 0.002)
    assert not np.shares_memory(unspent.data, kept)          # an array not ours gets a copy beside it
    np.testing.assert_allclose(level.data, unspent.data, atol=float(step.max()))
    truth = scan.true_angles_deg
    assert level.cost(truth) == pytest.approx(unspent.cost(truth), rel=1e-4)
    level.align(None, 0.0)                                     # back to the views as recorded, decoded
    assert level.data is data and np.all(np.abs(data - kept) <= 0.51 * step[:, None, None] + 1e-6)
    spent = projection_matching(kept.copy(), scan.geometry, scan.nominal_angles_deg, binning=(2, 1),
                                iterations=(2, 2), max_voxels=96, detector=True, overwrite=True)
    held = projection_matching(kept, scan.geometry, scan.nominal_angles_deg, binning=(2, 1),
                               iterations=(2, 2), max_voxels=96, detector=True)
    assert np.max(np.abs(spent.angles_deg - held.angles_deg)) < 1e-4
