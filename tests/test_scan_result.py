"""What a Python user of Pipeline.run gets without the CLI: refined geometry, turn check, refiner's choice, report."""

import dataclasses
import json

import numpy as np
import pytest

from ctpipe.data import ScanSolution
from ctpipe.errors import InputError
from ctpipe.evaluate.scoring import score_against_truth
from ctpipe.geometry import Geometry
from ctpipe.io import open_scan
from ctpipe.io.outputs import to_jsonable
from ctpipe.pipeline import ClosingView, Pipeline, RefinedGeometry, RefinerChoice, TurnCheck

#: Fast on the small scan folder: the robust view graph, no projection matching.
FAST = {
    "detector": {"name": "sift"},
    "matcher": {"name": "brute-force", "ratio": 0.8, "mutual": True},
    "estimator": {"name": "ransac-1pt", "hypotheses": "all", "scoring": "msac", "sampson_threshold": 3.0e-3},
    "refiner": {"name": "least-squares"},
    "pairs": {"baselines": [1, 2]},
}


@pytest.fixture(scope="module")
def scan_and_result(small_scan_folder):
    scan = open_scan(small_scan_folder)
    return scan, Pipeline.from_config(FAST).run(scan)


def _without_timings(report: dict) -> dict:
    report = json.loads(json.dumps(to_jsonable(report)))
    report.pop("timings_s")
    return report


def test_a_run_on_an_opened_scan_carries_its_geometry_turn_check_and_report(scan_and_result):
    scan, result = scan_and_result
    assert result.scan is scan and result.geometry == scan.geometry
    np.testing.assert_array_equal(result.nominal_angles_deg, scan.nominal_angles_deg)
    # least-squares estimates no geometry: the refined geometry is the input one.
    assert result.refined_geometry == RefinedGeometry(scan.geometry, 0.0, ())
    assert result.refiner_choice == RefinerChoice()
    assert isinstance(result.turn_check, TurnCheck) and result.turn_check.pairs > 0
    assert result.turn_check.agree_fraction > 0.7 and not result.turn_check.reversed
    assert result.closing_view is None and result.angle_errors is None
    # In the nominal frame: estimated minus nominal is zero in the median.
    assert abs(np.median(result.estimated_deg - scan.nominal_angles_deg)) < 1e-9

    report = result.report()
    assert list(report) == ["pipeline", "geometry", "angles_deg", "n_keypoints", "pairs", "timings_s", "refiner",
                            "static_background_removed", "detect_binning", "estimated_deg", "scan", "nominal_deg", "against_nominal",
                            "turn_check", "gate"]
    assert report["gate"] == result.gate.to_dict() and report["pipeline"]["gate"] == "auto"
    assert report["pipeline"]["refiner"]["name"] == "least-squares"
    assert report["scan"]["format"] == "ctpipe" and report["against_nominal"]["views"] == 48
    assert report["turn_check"] == result.turn_check.to_dict()
    json.dumps(to_jsonable(report))

    summary = result.summary(described=True)
    assert summary.startswith("pipeline: sift -> brute-force -> ransac-1pt -> least-squares\npairs: ")
    assert "estimated minus nominal angles: RMS" in summary and "turn the other way" not in summary
    assert "\ngate: " in summary
    assert result.summary().startswith(f"ctpipe scan {scan.path}: 48 views")


def test_the_true_angles_score_a_result_and_join_its_report(scan_and_result):
    scan, result = scan_and_result
    scored = score_against_truth(result)
    assert result.angle_errors is None  # the result itself is left as it was
    assert scored.angle_errors.views["total"] == 48 and np.isfinite(scored.angle_errors.views["rms_deg"])
    np.testing.assert_array_equal(scored.angle_errors.true_angles_deg, scan.true_angles_deg)
    assert list(scored.report())[-1] == "angle_errors"
    assert list(scored.angle_columns())[-2:] == ["true_deg", "error_deg"]
    assert "against the true angles: RMS" in scored.summary()
    with pytest.raises(InputError, match="true_angles_deg: not given"):
        score_against_truth(dataclasses.replace(result, scan=None))


def test_the_cli_writes_what_the_run_reports(scan_and_result, small_scan_folder, tmp_path, capsys):
    import yaml

    from ctpipe.cli import main

    scan, result = scan_and_result
    (tmp_path / "fast.yaml").write_text(yaml.safe_dump(FAST))
    # --no-slices: the before/after slices are an extra of the CLI (tests/evaluate/test_before_after.py).
    assert main(["estimate", str(small_scan_folder), "--pipeline", str(tmp_path / "fast.yaml"),
                 "--out", str(tmp_path / "out"), "--no-slices"]) == 0
    written = json.loads((tmp_path / "out" / "result.json").read_text())
    assert _without_timings(written) == _without_timings(score_against_truth(result).report())
    summary = capsys.readouterr().out
    assert score_against_truth(result).summary(described=True) in summary


def test_nominal_angles_of_the_wrong_sign_are_told(scan_and_result):
    scan, _ = scan_and_result
    result = Pipeline.from_config(FAST).run(scan.projections, scan.geometry, nominal_angles_deg=-scan.nominal_angles_deg)
    assert result.scan is None and result.turn_check.reversed and result.turn_check.agree_fraction < 0.3
    assert "warning: the images turn the other way from the nominal angles" in result.summary(source="views.npy")
    assert result.summary(source="views.npy").startswith("projections views.npy: 48 views of 96 x 128 px")


def test_a_closing_view_is_reported_with_its_measured_turn(scan_and_result):
    scan, _ = scan_and_result
    recorded = scan.nominal_angles_deg + 0.01
    closing = dataclasses.replace(scan, closing_view=True, recorded_angles_deg=recorded)
    result = Pipeline.from_config(FAST).run(closing)
    nominal = scan.nominal_angles_deg
    assert result.closing_view == ClosingView(47, float(nominal[-1] - nominal[0]),
                                              float(result.angles_deg[-1] - result.angles_deg[0]),
                                              float(recorded[-1] - recorded[0]))
    report = result.report()
    assert report["closing_view"] == dataclasses.asdict(result.closing_view)
    assert report["against_recorded"]["views"] == 48
    replaced = ["refiner_deg"] if result.gate.chosen != "estimate" else []    # what the gate did not return
    assert list(result.angle_columns()) == ["angle_deg", "n_keypoints", "nominal_deg", "estimated_minus_nominal_deg",
                                            "recorded_deg", "estimated_minus_recorded_deg", *replaced]
    summary = result.summary(described=True)
    assert "closing view 47: " in summary and "estimated minus scanner's angle log: RMS" in summary


def test_bundle_adjustment_gives_the_refined_centre_of_rotation_and_tilt(scan_and_result):
    scan, _ = scan_and_result
    result = Pipeline.from_config({**FAST, "refiner": {"name": "bundle-adjustment", "estimate_u0": True,
                                                       "estimate_tilt": True}}).run(scan)
    refined = result.refined_geometry
    assert refined.refined == ("u0_px", "v0_px", "tilt_deg")
    assert refined.geometry.u0_px == result.refiner_info["u0_px"] != scan.geometry.u0_px
    assert refined.tilt_deg == result.refiner_info["tilt_deg"]
    assert dataclasses.replace(refined.geometry, u0_px=scan.geometry.u0_px, v0_px=scan.geometry.v0_px) == scan.geometry
    # On 24 noise draws of this 48-view, 128-pixel scan the fitted axis landed 0-2.8 px from the
    # truth, beyond 1 px on 10: so small a scan holds it loosely. A sanity bound, not an accuracy.
    assert abs(refined.geometry.u0_px - scan.geometry.u0_px) < 4.0 and abs(refined.tilt_deg) < 1.0
    vectors = result.cone_vectors()
    assert vectors.shape == (48, 12)
    assert f"geometry: u0 {refined.geometry.u0_px:.3f} px (was {scan.geometry.u0_px:.3f})" in result.summary()


def test_projection_matching_says_what_it_chose(scan_and_result):
    scan, _ = scan_and_result
    result = Pipeline.from_config({**FAST, "refiner": {"name": "projection-matching", "level_px": [64],
                                                       "iterations": [1]}}).run(scan)
    choice = result.refiner_choice
    assert choice.matched and choice.start == result.refiner_info["start"] and choice.skipped is None
    assert choice.matched_from in ("start", "nominal") and choice.chosen in ("start", "nominal", "matched")
    assert {"nominal", "matched"} <= set(choice.consistency_cost) == set(choice.held_out_z)
    assert choice.held_out_z["nominal"] == 0.0
    # The lowest held-out cost, where it beats the nominal angles' beyond noise; else the nominal angles.
    best = min(choice.consistency_cost, key=lambda k: (choice.consistency_cost[k], k != "matched"))
    assert choice.chosen == (best if choice.held_out_z[best] < -2.0 else "nominal")
    assert (f"refiner: projection matching from the {choice.matched_from} angles, kept the {choice.chosen} ones"
            in result.summary())


def test_refined_geometry_is_typed_on_the_solution_and_refiner_info_is_read_in_one_place():
    geometry = Geometry(source_to_object_mm=100.0, source_to_detector_mm=200.0, detector_cols=64, detector_rows=32,
                        pixel_pitch_u_mm=0.5, pixel_pitch_v_mm=0.5)
    solution = ScanSolution(np.zeros(2), (), {"iterations": 3}, u0_px=30.25, tilt_deg=0.5)
    refined = RefinedGeometry.from_solution(geometry, solution)
    assert refined.geometry.u0_px == 30.25 and refined.geometry.v0_px == geometry.v0_px
    assert refined.tilt_deg == 0.5 and refined.refined == ("u0_px", "tilt_deg")
    assert RefinedGeometry.from_solution(geometry, ScanSolution(np.zeros(2), ())) == RefinedGeometry(geometry)
    # The ball calibration's pose: the distance into the geometry, the axis offset beside it.
    posed = RefinedGeometry.from_solution(geometry, ScanSolution(np.zeros(2), (), u0_px=31.0,
                                                                 source_to_detector_mm=201.5, axis_offset_mm=-0.4))
    assert posed.geometry.source_to_detector_mm == 201.5 and posed.axis_offset_mm == -0.4
    assert posed.refined == ("u0_px", "source_to_detector_mm", "axis_offset_mm")
    skipped = RefinerChoice.from_info({"start": "nominal", "matching": "skipped: 8 views are too few"})
    assert not skipped.matched and skipped.skipped.startswith("skipped") and skipped.chosen is None
    assert TurnCheck.compute(np.array([[0, 1]]), np.array([np.nan]), np.array([0.0, 1.0])) == TurnCheck(0)
    assert TurnCheck(0).to_dict() == {"pairs": 0} and not TurnCheck(0).reversed


def test_a_turn_is_called_reversed_only_where_the_pairs_show_it_beyond_chance():
    """Pair angles that are guesses (a ball phantom's: a median of one inlier) disagree with the nominal steps about
    half the time; 19 of 32 disagreeing is no evidence of a reversed sign. Every pair disagreeing is."""
    nominal = np.arange(16) * 22.5
    pairs = np.array([(i, j) for i in range(16) for j in (i + 1, i + 2, i + 3) if j < 16][:32])
    signs = np.where(np.arange(32) < 19, -1.0, 1.0)
    guesses = TurnCheck.compute(pairs, signs * 170.0, nominal)
    assert guesses.agree_fraction < 0.5 and guesses.sign_p_value > 0.1 and not guesses.reversed
    flipped = TurnCheck.compute(pairs, -22.5 * (pairs[:, 1] - pairs[:, 0]), nominal)
    assert flipped.agree_fraction == 0.0 and flipped.sign_p_value < 1e-9 and flipped.reversed
    assert flipped.to_dict()["sign_p_value"] == flipped.sign_p_value
    # Ten pairs of ten disagreeing is the least that is told.
    assert TurnCheck.compute(pairs[:10], -np.ones(10), nominal).reversed
    assert not TurnCheck.compute(pairs[:9], -np.ones(9), nominal).reversed


def test_a_scan_brings_its_own_geometry_and_projections_need_one(scan_and_result):
    scan, _ = scan_and_result
    pipeline = Pipeline.from_config(FAST)
    with pytest.raises(InputError, match="geometry: a scan .* brings its own"):
        pipeline.run(scan, scan.geometry)
    with pytest.raises(InputError, match="nominal_angles_deg: a scan .* brings its own"):
        pipeline.run(scan, nominal_angles_deg=scan.nominal_angles_deg)
    with pytest.raises(InputError, match="geometry: missing"):
        pipeline.run(scan.projections)


def test_the_gate_returns_the_refiners_angles_only_where_the_projections_show_them_better(scan_and_result):
    scan, result = scan_and_result
    ungated = Pipeline.from_config({**FAST, "gate": "off"}).run(scan)
    assert ungated.gate is None and "gate" not in ungated.report() and "gate:" not in ungated.summary()
    gate = result.gate
    assert gate.decided
    if gate.chosen == "estimate":
        np.testing.assert_array_equal(result.angles_deg, ungated.angles_deg)
    else:
        np.testing.assert_allclose(result.angles_deg, gate.angles_deg - gate.angles_deg[0], atol=1e-12)
    # Every band it added was shown better, by more than the standard errors its round needed
    # (at least z: more for several bands tried at once and an estimated standard error).
    for band, step, needed in zip(gate.bands, gate.steps, gate.needed):
        assert step[band] < -needed[band] and needed[band] >= gate.z
    assert (gate.chosen == "nominal") == (not gate.bands)
    assert "gate" in result.report() and result.report()["gate"]["chosen"] == gate.chosen


def test_a_refiner_worse_than_the_nominal_angles_is_not_returned(small_scan_folder):
    scan = open_scan(small_scan_folder)
    pipeline = Pipeline.from_config(FAST)
    observations = pipeline.observe(scan.projections, scan.geometry, nominal_angles_deg=scan.nominal_angles_deg)
    shaken = np.deg2rad(scan.nominal_angles_deg + np.random.default_rng(0).normal(0.0, 2.0, scan.n_views))

    class Shaken(type(pipeline.refiner)):
        def refine(self, observations, *, rng):
            return ScanSolution(shaken - shaken[0], observations.estimates, {})

    bad = dataclasses.replace(pipeline, refiner=Shaken())
    result = bad.refine(observations)
    assert result.gate.chosen == "nominal" and "NOMINAL" in result.summary(described=True)
    np.testing.assert_allclose(result.angles_deg, scan.nominal_angles_deg - scan.nominal_angles_deg[0], atol=1e-9)
