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
from ctpipe.validate import bin_detector, load_validate_settings, parse_validate, run_validate, write_validate_outputs

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
