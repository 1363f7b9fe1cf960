"""``ctpipe simulate`` / ``estimate DIR`` / ``validate`` end to end on a small scan (128^2, 64^3)."""

from __future__ import annotations

import csv
import json
import math
import subprocess
import sys

import numpy as np
import pytest
import yaml

from ctpipe.errors import ConfigError
from ctpipe.geometry import Geometry
from ctpipe.plugins import get_registry
from ctpipe.evaluate.validate import (bin_detector, load_validate_settings, parse_validate, run_validate,
                                      write_validate_outputs)
from ctpipe.evaluate.scoring import view_errors_deg

# 120 views >= pi/2 x 64: enough for the 64^3 grid that the jitter, not the sampling, dominates.
SCAN = {
    "geometry": {"source_to_object_mm": 130.0, "source_to_detector_mm": 300.0, "detector_cols": 128,
                 "detector_rows": 128, "pixel_pitch_u_mm": 1.6, "pixel_pitch_v_mm": 1.6},
    "angles": {"n_views": 120, "range_deg": 360.0},
    "jitter": [{"gaussian": {"sigma_deg": 0.4}}, {"jumps": {"count": 2, "size_deg": 2.0}}],
    "noise": {"photons_per_pixel": 100000, "flat_frames": 4, "dark_frames": 2, "dark_counts": 100},
    "projector": {"kind": "analytic", "supersample": 1, "blur_px": 0.5},
    "seed": 1,
}
PIPELINE = {
    "detector": {"name": "sift"},
    "matcher": {"name": "brute-force", "ratio": 0.8, "mutual": True},
    "estimator": {"name": "ransac-1pt", "hypotheses": "all", "scoring": "msac", "sampson_threshold": 3.0e-3},
    "refiner": {"name": "least-squares", "weighting": "inliers"},
    "pairs": {"baselines": [1, 2]},
}
EXPERIMENT = {"phantom": "bead-cylinder", "scan": SCAN, "pipeline": PIPELINE,
              "reconstruction": {"grid_size": 64, "detector_binning": 2}, "seed": 3}


def run_cli(*args):
    proc = subprocess.run([sys.executable, "-m", "ctpipe.cli", *args], capture_output=True, text=True, timeout=300)
    return proc.returncode, proc.stdout, proc.stderr


@pytest.fixture(scope="module")
def report():
    registry = get_registry()
    return run_validate(parse_validate(EXPERIMENT, registry), registry)


def test_the_jitter_is_visible_and_the_true_angles_reconstruct_best(report):
    for reference in ("phantom", "reference"):
        m = report.metrics[reference]
        assert m["true"]["psnr_db"] > m["nominal"]["psnr_db"]
        assert m["true"]["ssim"] > m["nominal"]["ssim"]
        assert m["true"]["relative_rmse"] < m["nominal"]["relative_rmse"]
    # Against the jitter-free scan the geometric error is all that is left: several dB.
    m = report.metrics["reference"]
    assert m["true"]["psnr_db"] - m["nominal"]["psnr_db"] > 5.0


def test_recovery_is_the_share_of_the_psnr_gap_and_the_verdict_says_so(report):
    for reference, m in report.metrics.items():
        expected = ((m["estimated"]["psnr_db"] - m["nominal"]["psnr_db"])
                    / (m["true"]["psnr_db"] - m["nominal"]["psnr_db"]))
        assert report.recovery[reference] == pytest.approx(expected)
    gain = report.metrics["reference"]["estimated"]["psnr_db"] - report.metrics["reference"]["nominal"]["psnr_db"]
    verdict = report.verdict()
    assert verdict.startswith("verdict: the jitter is visible")
    assert ("improve on" if gain > 0 else "are worse than") in verdict
    assert f"{100.0 * report.recovery['reference']:.0f} %" in verdict


def test_angle_tables_score_the_nominal_angles_against_the_jitter_and_the_pipeline_per_pair(report):
    views, pairs = report.angle_tables["views"], report.angle_tables["pairs"]
    jitter = report.true_deg - report.nominal_deg
    assert views["nominal"]["total"] == 120 and views["nominal"]["estimated"] == 120
    # The nominal error is the jitter with its median (the unobservable common offset) removed.
    assert views["nominal"]["mae_deg"] == pytest.approx(np.mean(np.abs(jitter - np.median(jitter))), rel=1e-6)
    # The pipeline estimates every pair of 3 deg steps to well under a step; a full turn pairs
    # its seam too (loop closure), so every view has two successors.
    assert pairs["estimated"]["estimated"] == pairs["estimated"]["total"] == 2 * 120
    assert pairs["estimated"]["median_deg"] < 0.6
    assert set(pairs["estimated"]) >= {"mae_deg", "std_deg", "min_deg", "q25_deg", "median_deg", "q75_deg",
                                       "max_deg"}


def test_outputs_are_written_and_readable(report, tmp_path):
    out = tmp_path / "val"
    written = write_validate_outputs(report, out)
    assert sorted(p.name for p in written) == ["angle_errors.png", "angles.csv", "report.json", "slices.png"]
    data = json.loads((out / "report.json").read_text())
    assert set(data) >= {"settings", "angle_errors", "reconstruction", "timings_s", "versions", "verdict"}
    assert data["reconstruction"]["recovery"]["reference"] == pytest.approx(report.recovery["reference"])
    with open(out / "angles.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == 120
    np.testing.assert_allclose([float(r["true_deg"]) for r in rows], report.true_deg)
    for png in ("slices.png", "angle_errors.png"):
        assert (out / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not list(out.glob("*.tmp*"))


def test_without_jitter_the_verdict_refuses_to_judge():
    registry = get_registry()
    scan = {**SCAN, "jitter": [], "angles": {"n_views": 40, "range_deg": 360.0}}
    settings = parse_validate({**EXPERIMENT, "scan": scan, "reconstruction": {"grid_size": 24, "detector_binning": 4}},
                              registry)
    report = run_validate(settings, registry)
    assert math.isnan(report.recovery["reference"])
    assert "not visible" in report.verdict()
    assert any("recovery is undefined" in note for note in report.notes)


def test_the_built_in_default_meets_the_issue_geometry():
    settings = load_validate_settings(None, get_registry())
    geometry, grid = settings.scan.geometry, settings.reconstruction.grid_size
    assert settings.phantom_ref == "granular" and settings.source == "built-in default"
    assert settings.scan.n_views >= math.pi / 2 * grid and grid >= 128
    # A 1 deg turn moves a feature at the top of the sample, at the edge of the object's
    # circle, by y * x * sin(1 deg) / SOD pixels vertically: about 1-2 px.
    top_px = settings.phantom.half_height_mm * geometry.source_to_detector_mm / geometry.source_to_object_mm
    top_px /= geometry.pixel_pitch_v_mm
    shift = top_px * settings.phantom.radius_mm * math.sin(math.radians(1.0)) / geometry.source_to_object_mm
    assert 1.0 <= shift <= 2.0


@pytest.mark.parametrize("change, message", [
    ({"phantoms": "granular"}, "experiment.phantoms: unknown key; allowed: phantom, scan, pipeline"),
    ({"phantom": "no-such-phantom"}, "no-such-phantom"),
    ({"reconstruction": {"grid_size": 4}}, "experiment.reconstruction.grid_size: must be an integer >= 8"),
    ({"reconstruction": {"filter": "butterworth"}}, "unknown filter 'butterworth'; allowed: ram-lak"),
    ({"reconstruction": {"detector_binning": 3}}, "detector_binning: must divide the detector size 128 x 128, got 3"),
    ({"pipeline": {**PIPELINE, "detector": {"name": "nope"}}}, "experiment.pipeline.detector.name: unknown detector"),
])
def test_bad_experiments_name_what_is_wrong(change, message):
    with pytest.raises(ConfigError) as info:
        parse_validate({**EXPERIMENT, **change}, get_registry())
    assert message in str(info.value) and "\n" not in str(info.value)


def test_binning_keeps_the_rays():
    """A binned detector sees a point where the full one does, in normalised coordinates."""
    geometry = Geometry(200.0, 400.0, 64, 48, 0.5, 0.5, u0_px=30.3, v0_px=20.7)
    image = np.zeros((1, 48, 64), np.float32)
    image[0, 17:19, 40:42] = 1.0  # a 2 x 2 spot centred on pixel (40.5, 17.5)
    binned, coarse = bin_detector(image, geometry, 2)
    assert binned.shape == (1, 24, 32) and binned.dtype == np.float32
    assert binned.sum() == pytest.approx(image.sum() / 4)
    rows, cols = np.nonzero(binned[0])
    spot = np.array([[cols.mean(), rows.mean()]])
    np.testing.assert_allclose(coarse.pixels_to_normalised(spot), geometry.pixels_to_normalised(np.array([[40.5, 17.5]])))


def test_cli_simulate_then_estimate_the_scan_folder(tmp_path):
    spec = {**SCAN, "angles": {"n_views": 6, "range_deg": 15.0}, "jitter": [{"gaussian": {"sigma_deg": 0.3}}]}
    (tmp_path / "scan.yaml").write_text(yaml.safe_dump(spec))
    code, out, err = run_cli("simulate", "bead-cylinder", "--scan", str(tmp_path / "scan.yaml"),
                             "--out", str(tmp_path / "scan"))
    assert code == 0, err
    assert "6 views of 128 x 128 written" in out
    written = yaml.safe_load((tmp_path / "scan" / "scan.yaml").read_text())
    truth = np.array(written["angles"]["true_deg"])
    pipeline = tmp_path / "p.yaml"
    pipeline.write_text(yaml.safe_dump(PIPELINE))
    code, out, err = run_cli("estimate", str(tmp_path / "scan"), "--pipeline", str(pipeline), "--json")
    assert code == 0, err
    result = json.loads(out)
    # Scored against the true angles the folder carries (3 deg steps; on 128^2 the vertical
    # motion that carries the angle is a fraction of a pixel, so only loosely).
    errors = np.array(result["angles_deg"]) - (truth - truth[0])
    errors -= np.median(errors)
    assert result["angle_errors"]["views"]["mae_deg"] == pytest.approx(np.mean(np.abs(errors)))
    assert result["angle_errors"]["views"]["max_deg"] < 2.0
    # A second run refuses to overwrite the folder, in one line.
    code, _, err = run_cli("simulate", "bead-cylinder", "--scan", str(tmp_path / "scan.yaml"),
                           "--out", str(tmp_path / "scan"))
    assert code == 2 and err.count("\n") == 1 and "exists and is not empty" in err


def test_cli_validate_json(tmp_path):
    small = {**EXPERIMENT, "reconstruction": {"grid_size": 32, "detector_binning": 4},
             "scan": {**SCAN, "angles": {"n_views": 60, "range_deg": 360.0}}}
    (tmp_path / "e.yaml").write_text(yaml.safe_dump(small))
    code, out, err = run_cli("validate", str(tmp_path / "e.yaml"), "--json", "--out", str(tmp_path / "res"))
    assert code == 0, err
    data = json.loads(out)
    assert data["settings"]["reconstruction"]["grid_size"] == 32
    assert (tmp_path / "res" / "report.json").exists()


@pytest.mark.parametrize("text, message", [
    ("phantom: granular\nscan: [\n", "not valid YAML"),
    ("phantom: granular\n", "experiment: missing"),
])
def test_cli_validate_bad_yaml_exits_2_and_writes_nothing(tmp_path, text, message):
    (tmp_path / "e.yaml").write_text(text)
    code, out, err = run_cli("validate", str(tmp_path / "e.yaml"), "--out", str(tmp_path / "res"))
    assert code == 2 and out == ""
    assert err.startswith("ctpipe: error: ") and err.count("\n") == 1 and "Traceback" not in err
    assert not (tmp_path / "res").exists()


def test_cli_simulate_refuses_an_out_that_is_a_file_before_projecting(tmp_path):
    (tmp_path / "scan.yaml").write_text(yaml.safe_dump(SCAN))
    (tmp_path / "taken").write_text("not a folder")
    code, out, err = run_cli("simulate", "bead-cylinder", "--scan", str(tmp_path / "scan.yaml"),
                             "--out", str(tmp_path / "taken"))
    assert code == 2 and out == "" and err.count("\n") == 1
    assert "taken: exists and is not a folder" in err
    assert (tmp_path / "taken").read_text() == "not a folder"


def test_cli_estimate_of_a_missing_path_says_so_rather_than_asking_for_a_geometry(tmp_path):
    code, _, err = run_cli("estimate", str(tmp_path / "nope"))
    assert code == 2 and err.count("\n") == 1 and "nope: no such file or scan folder" in err


# --- a bad estimate is reported, never fatal ------------------------------------------------

# 24 views on a 64^2 detector and a 24^3 grid: seconds, enough to reconstruct and score.
TINY = {**EXPERIMENT, "scan": {**SCAN, "angles": {"n_views": 24, "range_deg": 360.0},
                               "geometry": {**SCAN["geometry"], "detector_cols": 64, "detector_rows": 64,
                                            "pixel_pitch_u_mm": 3.2, "pixel_pitch_v_mm": 3.2}},
        "reconstruction": {"grid_size": 24, "detector_binning": 2}}


def _fake_pipeline(monkeypatch, make_angles):
    """Replace the pipeline's run by one that returns ``make_angles(nominal, truth)`` as the view
    angles, with exact consecutive pair angles from the truth (so pair-chained is exact)."""
    from ctpipe.pipeline import Pipeline, ScanResult
    from ctpipe.solve.graph import view_pairs

    seen = {}

    def run(self, projections, geometry, *, nominal_angles_deg=None, pairs=None, progress=None):
        nominal = np.asarray(nominal_angles_deg)
        truth = seen["truth"]
        pairs = view_pairs(len(nominal), (1,), nominal)
        exact = np.mod(truth[pairs[:, 1]] - truth[pairs[:, 0]] + 180.0, 360.0) - 180.0
        n = len(pairs)
        return ScanResult(pairs=pairs, pair_angles_deg=exact, pair_inlier_masks=tuple(np.ones(5, bool) for _ in range(n)),
                          n_matches=np.full(n, 5), n_inliers=np.full(n, 5), residuals=np.zeros(n),
                          pair_status=("ok",) * n, angles_deg=make_angles(nominal, truth - truth[0]),
                          n_keypoints=np.full(len(nominal), 9), timings_s={}, refiner_info={"fake": True})

    import ctpipe.sim.simulator as simulate_module

    real_simulate = simulate_module.simulate

    def simulate(phantom, spec, *, rng, jitter=True, progress=None):
        scan = real_simulate(phantom, spec, rng=rng, jitter=jitter, progress=progress)
        if jitter:
            seen["truth"] = scan.true_angles_deg
        return scan

    monkeypatch.setattr(simulate_module, "simulate", simulate)
    monkeypatch.setattr(Pipeline, "run", run)


def _swap_views(nominal, truth):
    angles = truth.copy()
    angles[[5, 6]] = angles[[6, 5]]
    angles[[15, 17]] = angles[[17, 15]]
    return angles


def _nan_views(nominal, truth):
    angles = truth.copy()
    angles[10:14] = np.nan
    return angles


@pytest.mark.parametrize("make_angles, expected", [
    (lambda nominal, truth: truth * 411.0 / np.ptp(truth), "the estimated angles span 411 deg over a 360 deg scan"),
    (_nan_views, "4 of 24 views have no estimated angle"),
    (_swap_views, "turn the wrong way against the truth: the estimate reorders views"),
    (lambda nominal, truth: np.full_like(truth, np.nan), "the pipeline estimated no view angle"),
])
def test_validate_reports_a_bad_estimate_instead_of_dying(monkeypatch, tmp_path, make_angles, expected):
    _fake_pipeline(monkeypatch, make_angles)
    registry = get_registry()
    report = run_validate(parse_validate(TINY, registry), registry)
    assert expected in report.verdict()
    written = write_validate_outputs(report, tmp_path)
    assert sorted(p.name for p in written) == ["angle_errors.png", "angles.csv", "report.json", "slices.png"]
    data = json.loads((tmp_path / "report.json").read_text())
    assert any(expected in problem for problem in data["estimate_problems"])
    assert data["pipeline"]["refiner"] == {"fake": True}
    assert data["reconstruction"]["metrics"]["reference"]["estimated"]["psnr_db"] is not None
    # The consecutive pair angles are exact, so chaining them recovers the truth.
    assert data["angle_errors"]["views"]["pair-chained"]["rms_deg"] < 1e-9


def test_a_short_scan_whose_estimate_spans_more_than_a_turn_is_scored_as_failed(monkeypatch, tmp_path):
    # The nominal short scan is Parker-weighted; the estimate, 2.2 times too wide, spans more
    # than 360 deg, which a Parker-weighted reconstruction cannot take.
    _fake_pipeline(monkeypatch, lambda nominal, truth: truth * 2.2)
    registry = get_registry()
    short = {**TINY, "scan": {**TINY["scan"], "angles": {"n_views": 24, "range_deg": 240.0}}}
    report = run_validate(parse_validate(short, registry), registry)
    assert "estimated" in report.failed and "estimated" not in report.volumes
    assert "the estimated angles could not be reconstructed (FDK refused" in report.verdict()
    assert "the estimate diverged" in report.verdict()
    assert math.isnan(report.recovery["reference"])
    write_validate_outputs(report, tmp_path)
    data = json.loads((tmp_path / "report.json").read_text())
    assert "short_scan" in data["reconstruction"]["failed"]["estimated"]
    assert any("failed:" in line for line in report.summary_lines())


def test_report_has_rms_pair_chained_and_the_refiner(report, tmp_path):
    views = report.angle_tables["views"]
    gate = report.pipeline_result.gate
    held_back = gate is not None and gate.decided and gate.chosen != "estimate"
    assert set(views) == {"nominal", "pair-chained", "estimated"} | ({"before the gate"} if held_back else set())
    if held_back:   # the refiner's own angles are scored too, and shown in the summary
        errors = view_errors_deg(gate.estimate_deg, report.true_deg)
        assert views["before the gate"]["rms_deg"] == pytest.approx(np.sqrt(np.mean(errors**2)))
        assert any(line.strip().startswith("before the gate") for line in report.summary_lines())
    for table in views.values():
        assert table["rms_deg"] >= table["mae_deg"] > 0
    # The default refiner closes the loop over baselines 1 and 2; chaining consecutive pairs
    # without loop closure accumulates their errors.
    assert views["estimated"]["rms_deg"] < views["pair-chained"]["rms_deg"]
    assert report.pipeline_result.refiner_info["loss"] == "soft-l1"
    lines = report.summary_lines()
    assert any(line.strip().startswith("pair-chained") and "RMS" in line for line in lines)
    write_validate_outputs(report, tmp_path)
    data = json.loads((tmp_path / "report.json").read_text())
    assert data["pipeline"]["refiner"]["pairs_used"] == 2 * 120
    with open(tmp_path / "angles.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert list(rows[0]) == ["view", "nominal_deg", "true_deg", "estimated_relative_deg", "nominal_error_deg",
                             "estimated_error_deg", "pair_chained_error_deg"]
    chained = np.array([float(r["pair_chained_error_deg"] or "nan") for r in rows])
    np.testing.assert_allclose(chained, report.view_errors["pair-chained"])


def test_estimate_problems_are_empty_for_a_good_estimate():
    from ctpipe.evaluate.validate import estimate_problems

    truth = np.arange(360) * 1.0 + np.random.default_rng(0).normal(0, 0.2, 360)
    assert estimate_problems(truth + np.random.default_rng(1).normal(0, 0.05, 360), truth, 360.0) == []
    drift = estimate_problems(truth * 0.97, truth, 360.0)
    assert len(drift) == 1 and "drifts by -10.78 deg" in drift[0]


# --- refused before the first projection ----------------------------------------------------

# TINY reconstructs from 32 binned columns of 6.4 mm, the outermost 15.5 columns from the centre,
# 300 mm from the source: a fan angle of 2 atan(15.5 x 6.4 / 300) = 36.59 deg.
@pytest.mark.parametrize("change, message", [
    ({"angles": {"n_views": 24, "range_deg": 150.0}},
     "experiment.scan.angles.range_deg: a short scan must span at least 216.59 deg (180 + fan angle 36.59 deg "
     "of this geometry), got 150 deg"),
    ({"angles": {"n_views": 3, "range_deg": 360.0}, "jitter": [{"jumps": {"count": 5, "size_deg": 1.0}}]},
     "experiment.scan.jitter: cannot be drawn for 3 views: jumps.count: 5 jumps need at least 6 views, got 3"),
])
def test_experiments_fdk_or_the_simulation_would_refuse_are_refused_at_parse_time(change, message):
    with pytest.raises(ConfigError) as info:
        parse_validate({**TINY, "scan": {**TINY["scan"], **change}}, get_registry())
    assert str(info.value) == message


def test_cli_refuses_a_150_deg_short_scan_before_simulating(tmp_path, monkeypatch, capsys):
    import ctpipe.sim.simulator
    from ctpipe.cli import main

    def no_simulation(*args, **kwargs):
        raise AssertionError("the experiment was simulated before it was checked")

    monkeypatch.setattr(ctpipe.sim.simulator, "simulate", no_simulation)
    experiment = {**TINY, "scan": {**TINY["scan"], "angles": {"n_views": 24, "range_deg": 150.0}}}
    (tmp_path / "e.yaml").write_text(yaml.safe_dump(experiment))
    code = main(["validate", str(tmp_path / "e.yaml"), "--out", str(tmp_path / "res")])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "Traceback" not in err
    assert "range_deg: a short scan must span at least 216.59 deg" in err and "got 150 deg" in err
    assert not (tmp_path / "res").exists()


def test_every_experiment_in_configs_experiments_parses_and_says_what_it_is():
    from pathlib import Path

    folder = Path(__file__).parents[2] / "configs" / "experiments"
    experiments = sorted(folder.glob("*.yaml"))
    assert len(experiments) >= 8
    registry = get_registry()
    for path in experiments:
        settings = load_validate_settings(path, registry)       # includes check_experiment
        assert settings.source == str(path)
        assert path.read_text().startswith("# "), f"{path.name}: no comment header describing the experiment"
