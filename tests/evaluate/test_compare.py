"""ctpipe experiment compare: pipelines on the same scans, paired statistics, broken ones as rows."""

from __future__ import annotations

import csv
import json
import math

import numpy as np
import pytest
import yaml

from ctpipe.cli import main
from ctpipe.config import parse_pipeline
from ctpipe.evaluate.compare import (BUILTIN_COMPARISONS, ComparedPipeline, CompareReport, CompareSettings,
                                     builtin_pipelines, file_scenarios, paired_comparison, run_compare)
from ctpipe.plugins import get_registry

#: A tiny scan (64^2, 24 views, a 32^3 grid): seconds per pipeline.
SCAN = {"geometry": {"source_to_object_mm": 150.0, "source_to_detector_mm": 390.0, "detector_cols": 64,
                     "detector_rows": 64, "pixel_pitch_u_mm": 2.4, "pixel_pitch_v_mm": 2.4},
        "angles": {"n_views": 24}, "jitter": [{"gaussian": {"sigma_deg": 0.5}}],
        "noise": {"photons_per_pixel": 100000}}
EXPERIMENT = {"phantom": "bead-cylinder", "scan": SCAN, "reconstruction": {"grid_size": 32, "detector_binning": 1},
              "seed": 4}
PAIRS = {"detector": {"name": "sift"}, "matcher": {"name": "brute-force", "ratio": 0.8},
         "estimator": {"name": "ransac-1pt", "sampson_threshold": 3.0e-3}, "refiner": {"name": "least-squares"}}
# Valid, and fails at run time on a scan of fewer than 30 views: it has no pair 30 views apart.
BROKEN = {**PAIRS, "pairs": {"baselines": [30]}}


@pytest.fixture(scope="module")
def registry():
    return get_registry()


# -------------------------------------------------------------------------------- paired statistics

def test_five_wins_and_a_tie_is_p_one_sixteenth_in_both_tests():
    # By hand: ties dropped, 5 wins of 5; sign test 2 * 0.5^5; every rank on one side: 2 / 2^5.
    first = [1.0, 1.0, 1.0, 1.0, 1.0, 0.3]
    second = [2.0, 3.0, 4.0, 5.0, 6.0, 0.3]
    stats = paired_comparison(first, second)
    assert (stats["scenarios"], stats["first_wins"], stats["second_wins"], stats["ties"]) == (6, 5, 0, 1)
    assert stats["sign_p"] == pytest.approx(0.0625)
    assert stats["wilcoxon_p"] == pytest.approx(0.0625)
    assert stats["better"] is None      # not below 0.05: six scenarios cannot show it


def test_a_mixed_case_by_hand():
    # log ratios 0.1 .. 0.5 and -0.6: ranks 1-5 for the first, 6 for the second. W- = 6;
    # subsets of {1..6} summing to 6 or less: 14 of 64, so p = 2 * 14 / 64. Sign: 5 of 6, p = 2 * 7 / 64.
    logs = np.array([0.1, 0.2, 0.3, 0.4, 0.5, -0.6])
    stats = paired_comparison(np.ones(6), np.exp(logs))
    assert (stats["first_wins"], stats["second_wins"]) == (5, 1)
    assert stats["wilcoxon_p"] == pytest.approx(28 / 64)
    assert stats["sign_p"] == pytest.approx(14 / 64)
    assert stats["median_log_ratio"] == pytest.approx(0.25)
    assert stats["better"] is None


def test_eight_of_eight_is_beyond_noise_and_failures_are_left_out():
    first = [0.5, 0.4, 0.3, 0.2, 0.9, 0.1, 0.7, 0.6, math.nan]
    second = [0.1, 0.2, 0.1, 0.1, 0.3, 0.05, 0.2, 0.3, 0.01]       # closer on all eight that both ran
    stats = paired_comparison(first, second)
    assert stats["scenarios"] == 8 and stats["second_wins"] == 8
    assert stats["wilcoxon_p"] == pytest.approx(2 / 256) and stats["sign_p"] == pytest.approx(2 / 256)
    assert stats["better"] == "second"
    swapped = paired_comparison(second, first)
    assert swapped["better"] == "first" and swapped["first_wins"] == 8


def test_nothing_to_compare_is_p_one():
    stats = paired_comparison([math.nan, 0.2], [0.1, 0.2])
    assert (stats["scenarios"], stats["ties"], stats["sign_p"], stats["wilcoxon_p"], stats["better"]) == (
        1, 1, 1.0, 1.0, None)


def _report(registry, rows, scenarios):
    config = parse_pipeline(PAIRS, registry)
    pipelines = tuple(ComparedPipeline(name, name, config) for name in ("a", "b"))
    settings = CompareSettings(pipelines, tuple((label, {}, kind) for label, kind in scenarios), "test")
    return CompareReport(settings, rows=rows)


def test_pairs_are_tested_over_all_scenarios_and_per_class(registry):
    scenarios = [(f"{k:03d}", "beads" if k < 8 else "granular") for k in range(10)]
    rows = []
    for k, (label, kind) in enumerate(scenarios):
        a, b = (0.5, 0.1) if kind == "beads" else (0.2, 0.3)
        common = {"scenario": label, "class": kind, "nominal_rms_deg": 0.4, "seconds": 1.0}
        rows += [{**common, "pipeline": "a", "status": "ok", "estimated_rms_deg": a, "ungated_rms_deg": 2 * a},
                 {**common, "pipeline": "b", "status": "ok" if k != 9 else "failed",
                  "estimated_rms_deg": b if k != 9 else None, "ungated_rms_deg": 0.01 if k != 9 else None}]
    report = _report(registry, rows, scenarios)
    pair, = report.pairs()
    assert pair["failed"] == {"a": 0, "b": 1}
    assert (pair["all"]["first_wins"], pair["all"]["second_wins"], pair["all"]["scenarios"]) == (1, 8, 9)
    assert pair["classes"]["beads"]["better"] == "second"
    assert pair["classes"]["granular"]["better"] is None
    # Before the gate, b's own angles are closer on all nine: 2 / 2^9 in both tests.
    assert (pair["before_gate"]["second_wins"], pair["before_gate"]["better"]) == (9, "second")
    assert pair["before_gate"]["wilcoxon_p"] == pytest.approx(2 / 512)
    line = next(line for line in report.summary_lines() if line.startswith("a vs b, all scenarios"))
    assert "a closer on 1, b on 8, tied on 0 of 9" in line and "failed: b 1" in line


# ------------------------------------------------------------------------------------- end to end

def test_every_pipeline_runs_on_the_same_scans_and_a_broken_one_is_a_row(registry, tmp_path):
    files = []
    for seed in (4, 5):
        path = tmp_path / f"scan{seed}.yaml"
        path.write_text(yaml.safe_dump({**EXPERIMENT, "seed": seed, "pipeline": {"refiner": "nonsense"}}))
        files.append(path)
    pipelines = []
    for name, mapping in (("pairs", PAIRS), ("broken", BROKEN),
                          ("baseline-2", {**PAIRS, "pairs": {"baselines": [1, 2]}})):
        path = tmp_path / f"{name}.yaml"
        path.write_text(yaml.safe_dump(mapping))
        pipelines.append(str(path))
    out = tmp_path / "out"
    assert main(["experiment", "compare", *pipelines, "--scenario", *map(str, files), "--out", str(out)]) == 0
    with open(out / "compare.csv") as handle:
        rows = list(csv.DictReader(handle))
    assert [(r["scenario"], r["pipeline"]) for r in rows] == [
        (s, p) for s in ("scan4", "scan5") for p in ("pairs", "broken", "baseline-2")]
    for row in rows:
        assert row["class"] == "bead-cylinder"
        if row["pipeline"] == "broken":
            assert row["status"] == "failed" and "no view pairs: 24 views" in row["reason"]
            assert "\n" not in row["reason"]
        else:
            assert row["status"] == "ok", row["reason"]
            assert float(row["detect_s"]) > 0 and float(row["refine_s"]) >= 0 and float(row["seconds"]) > 0
            assert 0 < int(row["views_estimated"]) <= 24
    # One simulation per scenario: every pipeline saw the same nominal and true angles.
    for scenario in ("scan4", "scan5"):
        nominal = {r["nominal_rms_deg"] for r in rows if r["scenario"] == scenario and r["status"] == "ok"}
        assert len(nominal) == 1
    saved = json.loads((out / "compare.json").read_text())
    assert [(p["first"], p["second"]) for p in saved["pairs"]] == [
        ("pairs", "broken"), ("pairs", "baseline-2"), ("broken", "baseline-2")]
    assert saved["pairs"][0]["failed"] == {"pairs": 0, "broken": 2}
    summary = (out / "summary.txt").read_text()
    assert "pairs vs baseline-2, all scenarios:" in summary and "broken: 0/2 ran" in summary
    assert (out / "compare.png").stat().st_size > 10_000
    assert sorted(p.name for p in (out / "scenarios").iterdir()) == ["scan4.yaml", "scan5.yaml"]
    # A scenario written out re-runs alone with a compared pipeline: the same scan, the same estimate.
    experiment = yaml.safe_load((out / "scenarios" / "scan4.yaml").read_text())
    experiment["pipeline"] = PAIRS
    alone = tmp_path / "alone.yaml"
    alone.write_text(yaml.safe_dump(experiment))
    assert main(["validate", str(alone), "--out", str(tmp_path / "alone"), "--json"]) == 0
    views = json.loads((tmp_path / "alone" / "report.json").read_text())["angle_errors"]["views"]
    first = next(r for r in rows if r["scenario"] == "scan4" and r["pipeline"] == "pairs")
    assert views["nominal"]["rms_deg"] == pytest.approx(float(first["nominal_rms_deg"]), rel=1e-12)
    assert views["estimated"]["estimated"] == int(first["views_estimated"])


def test_a_scenario_that_fails_at_run_time_is_a_row_for_every_pipeline(registry, monkeypatch):
    import ctpipe.evaluate.validate as validate

    def cannot(*args, **kwargs):
        raise MemoryError

    monkeypatch.setattr(validate, "simulate_experiment", cannot)
    config = parse_pipeline(PAIRS, registry)
    settings = CompareSettings(tuple(ComparedPipeline(n, n, config) for n in ("a", "b")),
                               (("s", dict(EXPERIMENT), "bead-cylinder"),), "test")
    report = run_compare(settings)
    assert [(r["pipeline"], r["status"], r["reason"]) for r in report.rows] == [
        ("a", "failed", "scenario: out of memory"), ("b", "failed", "scenario: out of memory")]


def test_the_built_in_comparisons_differ_in_one_stage_only(registry):
    for name, stage in (("detectors", "detector"), ("refiners", "refiner")):
        pipelines = builtin_pipelines(name, registry)
        assert len(pipelines) == 3 and name in BUILTIN_COMPARISONS
        configs = [p.config.to_dict() for p in pipelines]
        assert len({json.dumps(c[stage], sort_keys=True) for c in configs}) == 3
        rest = [{k: v for k, v in c.items() if k != stage} for c in configs]
        assert all(r == rest[0] for r in rest)
    assert {p.name for p in builtin_pipelines("detectors", registry)} == {"surf", "orb", "sift"}


def test_scenario_files_keep_their_relative_paths(registry, tmp_path):
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "scan.yaml").write_text(yaml.safe_dump(SCAN))
    path = tmp_path / "sub" / "e.yaml"
    path.write_text(yaml.safe_dump({**EXPERIMENT, "scan": "scan.yaml"}))
    (label, experiment, kind), = file_scenarios([path], registry)
    assert (label, kind) == ("e", "bead-cylinder")
    assert experiment["scan"] == str(tmp_path / "sub" / "scan.yaml")


def test_on_a_dask_cluster_the_rows_are_those_of_the_in_process_run(registry, dask_client):
    from ctpipe.execution import DaskExecutor

    config = parse_pipeline(PAIRS, registry)
    settings = CompareSettings(tuple(ComparedPipeline(n, n, config) for n in ("a", "b")),
                               (("s", dict(EXPERIMENT), "bead-cylinder"),), "test")
    here = run_compare(settings)
    there = run_compare(settings, executor=DaskExecutor(dask_client))
    for a, b in zip(here.rows, there.rows):
        assert a["status"] == b["status"] == "ok"
        np.testing.assert_equal([a["estimated_rms_deg"], a["recovery_reference"]],
                                [b["estimated_rms_deg"], b["recovery_reference"]])
