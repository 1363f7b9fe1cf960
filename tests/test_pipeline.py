import numpy as np
import pytest

from ctpipe.errors import EstimationError, InputError
from ctpipe.pipeline import Pipeline
from ctpipe.solve import view_pairs
from ctpipe.solve.bands import split_bands


def test_pipeline_recovers_view_angles_of_a_rendered_bead_scan(bead_scan):
    projections, geometry, truth = bead_scan
    result = Pipeline.from_config({"matcher": {"name": "brute-force", "ratio": 0.8, "mutual": True}}).run(
        projections, geometry)
    assert result.pair_status == ("ok",) * 4
    np.testing.assert_allclose(result.angles_deg, truth, atol=0.15)
    np.testing.assert_allclose(result.pair_angles_deg, np.diff(truth), atol=0.15)
    assert np.all(result.n_inliers >= 10)


def test_multi_baseline_pairs_are_chained_by_least_squares(bead_scan):
    projections, geometry, truth = bead_scan
    result = Pipeline.from_config({"pairs": {"baselines": [1, 2]}}).run(projections, geometry)
    assert len(result.pairs) == 4 + 3
    np.testing.assert_allclose(result.angles_deg, truth, atol=0.15)


def test_reversed_scan_gives_negative_angles(bead_scan):
    projections, geometry, truth = bead_scan
    result = Pipeline.from_config(None).run(projections[::-1].copy(), geometry)
    np.testing.assert_allclose(result.angles_deg, truth[::-1] - truth[-1], atol=0.15)


def test_pipeline_is_reproducible(bead_scan):
    projections, geometry, _ = bead_scan
    pipeline = Pipeline.from_config({"seed": 3})
    a, b = pipeline.run(projections, geometry), pipeline.run(projections, geometry)
    assert np.array_equal(a.angles_deg, b.angles_deg)


def test_bad_inputs_are_named(bead_scan):
    projections, geometry, _ = bead_scan
    pipeline = Pipeline.from_config(None)
    with pytest.raises(InputError, match="3-D array"):
        pipeline.run(projections[0], geometry)
    with pytest.raises(InputError, match="at least 2 views"):
        pipeline.run(projections[:1], geometry)
    with pytest.raises(InputError, match=r"\(rows, cols\) = \(256, 100\) but the geometry says \(256, 256\)"):
        pipeline.run(projections[:, :, :100], geometry)
    bad = projections.copy()
    bad[1, 5, 5] = np.nan
    with pytest.raises(InputError, match="1 NaN or infinite pixels"):
        pipeline.run(bad, geometry)
    with pytest.raises(InputError, match="pairs must index views 0..4"):
        pipeline.run(projections, geometry, pairs=np.array([[0, 9]]))


def test_blank_projections_say_no_pair_could_be_estimated(bead_scan):
    _, geometry, _ = bead_scan
    with pytest.raises(EstimationError, match="no view pair could be estimated.*view 0: 0"):
        Pipeline.from_config(None).run(np.zeros((3, 256, 256), np.float32), geometry)


def test_consecutive_pairs():
    assert view_pairs(4, (1, 2)).tolist() == [[0, 1], [1, 2], [2, 3], [0, 2], [1, 3]]


def test_the_readme_python_example_runs(tmp_path, monkeypatch):
    """The README's 'From Python' block, on a small simulated scan folder in place of results/scan."""
    import re
    from pathlib import Path

    import ctpipe
    from ctpipe.sim import parse_scan_spec, write_simulated_scan

    root = Path(__file__).resolve().parents[1]
    block = re.search(r"From Python:\n\n```python\n(.*?)```", (root / "README.md").read_text(), re.S)[1]
    spec = parse_scan_spec({
        "geometry": {"source_to_object_mm": 130.0, "source_to_detector_mm": 300.0, "detector_cols": 128,
                     "detector_rows": 128, "pixel_pitch_u_mm": 1.6, "pixel_pitch_v_mm": 1.6},
        "angles": {"n_views": 36, "range_deg": 360.0}, "jitter": [{"gaussian": {"sigma_deg": 0.3}}], "seed": 2})
    phantom = ctpipe.load_phantom("bead-cylinder")
    scan = ctpipe.simulate(phantom, spec, rng=np.random.default_rng(2))
    write_simulated_scan(tmp_path / "scan", scan, phantom=phantom, spec=spec, seed=2)
    monkeypatch.chdir(root)
    namespace = {}
    exec(block.replace('"results/scan"', repr(str(tmp_path / "scan"))), namespace)
    assert namespace["result"].angles_deg.shape == (36,)
    assert namespace["volume"].shape == (128, 128, 128)
    assert namespace["graph"].angles_deg.shape == (36,)


def test_a_returned_angle_s_standard_error_adds_the_correction_the_gate_left_out():
    from ctpipe.pipeline import _angle_se_deg
    from ctpipe.solve.gate import GateDecision

    nominal = np.arange(16) * 22.5
    theta = np.deg2rad(nominal)
    fast = 0.1 * np.array([1, -2, 0, 3, -1, 0.5, 0, -1.5, 2, -0.5, 1, -1, 0.5, 0, -2, 1.0])
    slow = 0.3 * np.sin(theta)
    correction = fast + slow
    refiner_se = np.full(16, 0.02)
    # The nominal angles returned (in the estimate's frame: 2 deg off); the estimate had the correction.
    kept = GateDecision("nominal", nominal + 2.0, True, "no band shown better", estimate_deg=nominal + correction,
                        harmonics=3)
    bands = split_bands(correction - np.median(correction), nominal, 3)
    expected = np.sqrt(0.02**2 + np.mean(bands["fast"] ** 2) + (bands["slow-odd"] + bands["slow-even"]) ** 2)
    np.testing.assert_allclose(_angle_se_deg(refiner_se, kept, nominal), expected, rtol=1e-12)
    # The slow part is there view by view, the fast part as one RMS for every view.
    assert np.ptp(_angle_se_deg(refiner_se, kept, nominal)) > 0.2
    returned = GateDecision("estimate", nominal + correction, True, "all bands", estimate_deg=nominal + correction)
    np.testing.assert_array_equal(_angle_se_deg(refiner_se, returned, nominal), refiner_se)
    assert _angle_se_deg(None, kept, nominal) is None


def test_detection_binning_follows_the_detector_and_the_detector_size():
    sift = Pipeline.from_config({"detector": {"name": "sift"}})
    assert sift.detect_max_px == 1024
    shapes = [(512, 512), (1024, 1024), (2048, 2048), (2000, 3000)]
    assert [sift.detect_binning(shape) for shape in shapes] == [1, 1, 2, 3]
    # A ball finder fits sub-pixel discs on the full views; null keeps every detector at full size.
    assert Pipeline.from_config({"detector": {"name": "beads"}}).detect_binning((4096, 4096)) == 1
    full = Pipeline.from_config({"detector": {"name": "sift"}, "preprocess": {"detect_max_px": None}})
    assert full.detect_binning((4096, 4096)) == 1
    with pytest.raises(InputError, match="detect_max_px: must be an integer from 64 to 65536"):
        Pipeline(sift.detector, sift.matcher, sift.estimator, sift.refiner, detect_max_px=10)


def test_keypoints_found_on_binned_views_are_in_the_full_views_pixels():
    from ctpipe.pipeline import _detect_view

    rng = np.random.default_rng(5)
    from scipy.ndimage import gaussian_filter
    small = gaussian_filter(rng.random((160, 200)), 2.0).astype(np.float32)
    detector = Pipeline.from_config({"detector": {"name": "sift"}}).detector
    # Each pixel repeated 2 x 2: binning by 2 gives the small image back exactly.
    large = np.kron(small, np.ones((2, 2), np.float32))[None]
    direct = detector.detect(small)
    binned = _detect_view(detector, large, None, 0, 2)
    assert len(direct) > 20 and len(binned) == len(direct)
    np.testing.assert_allclose(binned.xy, (direct.xy + 0.5) * 2 - 0.5, atol=1e-4)
    np.testing.assert_allclose(binned.size, direct.size * 2, rtol=1e-6)
    np.testing.assert_array_equal(binned.descriptors, direct.descriptors)


def test_a_binned_detection_still_recovers_the_angles_and_says_so(bead_scan):
    projections, geometry, truth = bead_scan
    config = {"matcher": {"name": "brute-force", "ratio": 0.8, "mutual": True}, "preprocess": {"detect_max_px": 128}}
    result = Pipeline.from_config(config).run(projections, geometry)
    assert result.detect_binning == 2 and result.report()["detect_binning"] == 2
    assert "(keypoints found on views binned 2 x 2)" in result.summary()
    # The keypoints are in the full views' pixels: the angles hold, a little less sharply.
    assert result.pair_status == ("ok",) * 4
    np.testing.assert_allclose(result.angles_deg, truth, atol=0.3)


def test_descriptors_are_dropped_after_matching_only_where_the_refiner_does_not_read_them(bead_scan):
    projections, geometry, _ = bead_scan
    graph = Pipeline.from_config({"refiner": {"name": "least-squares"}})
    observations = graph.observe(projections, geometry)
    assert all(len(f) > 0 and f.descriptors.shape == (len(f), 0) for f in observations.features)
    assert all(f.xy.shape == (len(f), 2) for f in observations.features)
    result = graph.refine(observations)
    assert result.pair_status == ("ok",) * 4 and np.all(result.n_keypoints > 0)

    bundle = Pipeline.from_config({"refiner": {"name": "bundle-adjustment"}})
    kept = bundle.observe(projections, geometry)
    assert all(f.has_descriptors and f.descriptors.shape[1] == 128 for f in kept.features)
    with pytest.raises(InputError, match="BundleAdjustmentRefiner reads the features' descriptors"):
        bundle.refine(observations)
    with pytest.raises(InputError, match="cannot match features without descriptors"):
        graph.matcher.match(observations.features[0], observations.features[1])


def test_projection_matching_reads_descriptors_only_through_a_refiner_start():
    from ctpipe.builtin.bundle import BundleAdjustmentRefiner
    from ctpipe.builtin.projection_matching import ProjectionMatchingRefiner
    assert not ProjectionMatchingRefiner().reads_descriptors
    assert ProjectionMatchingRefiner(start=BundleAdjustmentRefiner()).reads_descriptors
