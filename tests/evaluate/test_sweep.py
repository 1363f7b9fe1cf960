"""ctpipe experiment sweep: scenarios drawn from one seed, one row each, failures as rows."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import yaml

from ctpipe.cli import main
from ctpipe.errors import ConfigError
from ctpipe.evaluate.sweep import draw_scenario, load_sweep_settings, parse_sweep, run_sweep
from ctpipe.plugins import get_registry

#: Tiny scans (64^2, 24-40 views, a 32^3 grid): seconds per scenario. The short scan of 60 deg
#: cannot be reconstructed, so that draw is a failed row.
SWEEP = {
    "n": 3,
    "seed": 4,
    "base": {
        "phantom": "bead-cylinder",
        "scan": {"geometry": {"source_to_object_mm": 150.0, "source_to_detector_mm": 390.0, "detector_cols": 64,
                              "detector_rows": 64, "pixel_pitch_u_mm": 2.4, "pixel_pitch_v_mm": 2.4},
                 "angles": {"n_views": 24}, "jitter": [{"gaussian": {"sigma_deg": 0.5}}],
                 "noise": {"photons_per_pixel": 100000}},
        "reconstruction": {"grid_size": 32, "detector_binning": 1},
    },
    "draw": {"scan.angles.n_views": {"integer": [24, 40]},
             "scan.angles.range_deg": {"choice": [360.0, 60.0], "weights": [2, 1]}},
}


@pytest.fixture(scope="module")
def registry():
    return get_registry()


def test_scenarios_depend_only_on_the_seed_and_their_index(registry):
    settings = parse_sweep(SWEEP, registry)
    again = [draw_scenario(settings, k) for k in (2, 0, 1)]
    assert [draw_scenario(settings, k) for k in (2, 0, 1)] == again
    assert draw_scenario(settings, 0) != draw_scenario(settings, 1)
    counts = [draw_scenario(settings, k)[1]["scan.angles.n_views"] for k in range(200)]
    assert min(counts) == 24 and max(counts) == 40
    ranges = [draw_scenario(settings, k)[1]["scan.angles.range_deg"] for k in range(300)]
    assert 0.25 < ranges.count(60.0) / 300 < 0.42   # weights 2:1


def test_the_built_in_sweep_covers_the_classes_and_every_draw_is_a_valid_experiment(registry):
    from ctpipe.evaluate.validate import parse_validate

    settings = load_sweep_settings(None, registry)
    assert settings.n == 30
    drawn = [draw_scenario(settings, k) for k in range(settings.n)]
    for experiment, _ in drawn:
        parse_validate(experiment, registry, path="scenario")
    values = [d for _, d in drawn]
    assert {v["phantom"] for v in values} >= {"granular", "metal-insert", "bead-cylinder"}
    assert any(v["scan.angles.range_deg"] < 360 for v in values)
    assert min(v["scan.angles.n_views"] for v in values) < 32 and max(v["scan.angles.n_views"] for v in values) > 240


def test_a_sweep_runs_every_scenario_and_a_failed_one_is_a_row(registry, tmp_path):
    settings = parse_sweep(SWEEP, registry)
    report = run_sweep(settings)
    assert [row["scenario"] for row in report.rows] == [0, 1, 2]
    statuses = {row["drawn"]["scan.angles.range_deg"]: row["status"] for row in report.rows}
    assert statuses == {360.0: "ok", 60.0: "failed"}, report.rows
    failed = next(row for row in report.rows if row["status"] == "failed")
    assert "short scan must span at least" in failed["reason"] and "\n" not in failed["reason"]
    ok = next(row for row in report.rows if row["status"] == "ok")
    assert ok["nominal_rms_deg"] > 0.2 and np.isfinite(ok["estimated_rms_deg"]) and ok["seconds"] > 0
    assert report.summary()["failed"] == sum(r["status"] == "failed" for r in report.rows)


def test_cli_sweep_writes_table_plot_and_scenarios_that_rerun_alone(tmp_path):
    sweep = tmp_path / "sweep.yaml"
    sweep.write_text(yaml.safe_dump(SWEEP))
    out = tmp_path / "out"
    assert main(["experiment", "sweep", str(sweep), "--n", "2", "--out", str(out)]) == 0
    with open(out / "sweep.csv") as handle:
        rows = list(csv.DictReader(handle))
    assert [r["scenario"] for r in rows] == ["0", "1"]
    assert {"scan.angles.n_views", "status", "nominal_rms_deg", "estimated_rms_deg", "recovery_reference",
            "seconds", "reason"} <= set(rows[0])
    assert (out / "sweep.png").stat().st_size > 10_000
    assert json.loads((out / "sweep.json").read_text())["summary"]["scenarios"] == 2
    row = next(r for r in rows if r["status"] == "ok")
    scenario = out / "scenarios" / f"{int(row['scenario']):03d}.yaml"
    alone = tmp_path / "alone"
    assert main(["validate", str(scenario), "--out", str(alone), "--json"]) == 0
    report = json.loads((alone / "report.json").read_text())
    assert report["angle_errors"]["views"]["estimated"]["rms_deg"] == pytest.approx(float(row["estimated_rms_deg"]),
                                                                                   rel=1e-9)


@pytest.mark.parametrize("change, message", [
    ({"draw": {"scan.angles.n_views": {"uniform": [40, 24]}}}, r"sweep\.draw\.scan\.angles\.n_views\.uniform: low "
                                                             r"must not exceed high"),
    ({"draw": {"scan.angles.n_views": {"gauss": [1, 2]}}}, r"sweep\.draw\.scan\.angles\.n_views: give exactly one of"),
    ({"draw": {"volume.size": {"choice": [1]}}}, r"sweep\.draw\.volume\.size: must start with phantom, scan"),
    ({"draw": {"scan.noise.photons_per_pixel": {"loguniform": [0, 10]}}}, r"loguniform: bounds must be > 0"),
    ({"n": 0}, r"sweep\.n: must be a whole number from 1 to"),
    ({"base": {"phantom": "nope", "scan": {}}}, r"phantom 'nope': not a built-in phantom"),
    ({"draw": {"phantom": {"choice": ["a"], "weights": [1, 2]}}}, r"weights: must be a list of 1 numbers"),
])
def test_bad_sweeps_are_one_config_error_naming_the_key(registry, change, message):
    with pytest.raises(ConfigError, match=message):
        parse_sweep({**SWEEP, **change}, registry)


def test_cli_bad_sweep_is_one_line_exit_2_and_writes_nothing(tmp_path, capsys):
    sweep = tmp_path / "bad.yaml"
    sweep.write_text(yaml.safe_dump({**SWEEP, "draw": {"scan.angles.n_views": {"integer": [1.5, 3]}}}))
    out = tmp_path / "out"
    assert main(["experiment", "sweep", str(sweep), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "integer: bounds must be whole numbers" in err
    assert not out.exists()


def test_on_a_dask_cluster_the_rows_are_those_of_the_in_process_run(registry, dask_client):
    from ctpipe.execution import DaskExecutor

    settings = parse_sweep({**SWEEP, "draw": {"scan.angles.n_views": {"integer": [24, 40]}}}, registry)
    here = run_sweep(settings, n=2)
    there = run_sweep(settings, n=2, executor=DaskExecutor(dask_client))
    for a, b in zip(here.rows, there.rows):
        assert a["drawn"] == b["drawn"] and a["status"] == b["status"] == "ok"
        np.testing.assert_equal([a["estimated_rms_deg"], a["recovery_reference"]],
                                [b["estimated_rms_deg"], b["recovery_reference"]])


def test_worse_than_nominal_charges_a_reconstruction_only_beyond_what_the_truth_loses():
    from ctpipe.evaluate.sweep import worse_than_nominal

    assert worse_than_nominal(0.5, 0.4, 0.0, 0.0, 1.0)                 # farther from the truth
    assert worse_than_nominal(0.3, 0.4, -0.2, 0.0, 1.0)                # a visible loss against the jitter-free scan
    assert worse_than_nominal(0.3, 0.4, 0.0, -0.1, 1.0)                # against the phantom
    # Sparse views: the true angles reconstruct 5.8 dB below the regular nominal ones against the
    # jitter-free scan; an estimate that loses less than they do is not worse.
    assert not worse_than_nominal(0.33, 0.36, -2.2, 0.0, -5.8)
    assert worse_than_nominal(0.33, 0.36, -6.0, 0.0, -5.8)
    assert not worse_than_nominal(0.4, 0.4, 0.0, 0.0, None)


def test_the_summary_says_what_the_gate_did_to_the_refiners_answer(registry):
    from ctpipe.evaluate.sweep import SweepReport, load_sweep_settings

    settings = load_sweep_settings(None, registry)

    def row(nominal, ungated, returned):
        return {"status": "ok", "nominal_rms_deg": nominal, "ungated_rms_deg": ungated, "estimated_rms_deg": returned,
                "recovery_reference": 0.0, "visible_db": 1.0, "worse_than_nominal": False, "drawn": {}}

    report = SweepReport(settings, rows=[row(0.4, 0.1, 0.4),      # a closer answer held back
                                         row(0.4, 0.9, 0.4),      # a worse one kept out
                                         row(0.4, 0.1, 0.1)])     # passed as it was
    summary = report.summary()
    assert (summary["gate_held_back"], summary["gate_kept_out"]) == (1, 1)
    assert "the gate held back a closer answer on 1 and kept a worse one out on 1" in report.summary_line()
