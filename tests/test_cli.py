import json
import subprocess
import sys

import numpy as np
import pytest
import yaml

from ctpipe.cli import main


def run_cli(*args):
    """Run the real console entry point in a subprocess (exit code, stdout, stderr)."""
    proc = subprocess.run([sys.executable, "-m", "ctpipe.cli", *args], capture_output=True, text=True, timeout=300)
    return proc.returncode, proc.stdout, proc.stderr


def test_plugins_json_lists_every_kind():
    code, out, _ = run_cli("plugins", "--json")
    assert code == 0
    stages = json.loads(out)["stages"]
    kinds = [s["kind"] for s in stages]
    assert kinds.count("detector") >= 5 and kinds.count("matcher") >= 2
    assert kinds.count("estimator") >= 4 and kinds.count("refiner") >= 1
    assert all(set(s) == {"kind", "name", "plugin", "description"} for s in stages)


def test_plugins_block_plugin(capsys):
    assert main(["--block-plugin", "ctpipe.builtin.matchers", "plugins"]) == 0
    assert "brute-force" not in capsys.readouterr().out


@pytest.fixture()
def scan_files(tmp_path, bead_scan):
    projections, geometry, truth = bead_scan
    np.save(tmp_path / "projections.npy", projections)
    (tmp_path / "geometry.yaml").write_text(yaml.safe_dump({"geometry": geometry.to_dict()}))
    return tmp_path, truth


def test_estimate_writes_angles_and_prints_json(scan_files):
    tmp_path, truth = scan_files
    out = tmp_path / "result"
    code, stdout, _ = run_cli("estimate", str(tmp_path / "projections.npy"), "--geometry",
                              str(tmp_path / "geometry.yaml"), "--json", "--out", str(out))
    assert code == 0
    report = json.loads(stdout)
    np.testing.assert_allclose(report["angles_deg"], truth, atol=0.15)
    assert (out / "angles.csv").read_text().startswith("view,angle_deg,n_keypoints\n")
    assert json.loads((out / "result.json").read_text())["pipeline"]["estimator"]["name"] == "ransac-1pt"


@pytest.mark.parametrize("pipeline_text, message", [
    ("estimator: {name: ransac-1pt, sampson_threshold: -1}\n",
     "ctpipe: error: pipeline.estimator.sampson_threshold: must be a number > 0 and <= 1, got -1"),
    ("detector: {name: nope}\n", "ctpipe: error: pipeline.detector.name: unknown detector 'nope'; registered"),
    ("detector: [sift\n", "not valid YAML"),
])
def test_bad_config_exits_2_with_one_line_and_writes_nothing(scan_files, pipeline_text, message):
    tmp_path, _ = scan_files
    (tmp_path / "bad.yaml").write_text(pipeline_text)
    out = tmp_path / "never"
    code, stdout, stderr = run_cli("estimate", str(tmp_path / "projections.npy"), "--geometry",
                                   str(tmp_path / "geometry.yaml"), "--pipeline", str(tmp_path / "bad.yaml"),
                                   "--out", str(out))
    assert code == 2
    assert stderr.count("\n") == 1 and message in stderr and "Traceback" not in stderr
    assert not out.exists()


def test_bad_projections_exit_2(scan_files):
    tmp_path, _ = scan_files
    bad = np.load(tmp_path / "projections.npy")
    bad[0, 3, 3] = np.nan
    np.save(tmp_path / "nan.npy", bad)
    np.save(tmp_path / "flat.npy", bad[0])
    for name, message in (("nan.npy", "NaN or infinite pixels"), ("flat.npy", "3-D array"),
                          ("missing.npy", "no such file")):
        code, _, stderr = run_cli("estimate", str(tmp_path / name), "--geometry", str(tmp_path / "geometry.yaml"))
        assert code == 2 and message in stderr and stderr.count("\n") == 1


def test_usage_errors_are_one_line(capsys):
    with pytest.raises(SystemExit) as info:
        main(["experiment", "synthetic", "--reps", "0"])
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--reps: must be an integer >= 1, got '0'" in err


def test_experiment_synthetic_json_and_outputs(tmp_path):
    out = tmp_path / "synthetic"
    code, stdout, _ = run_cli("experiment", "synthetic", "--reps", "3", "--jobs", "1", "--json", "--out", str(out))
    assert code == 0
    summary = json.loads(stdout)
    entry = summary["estimators"]["ransac-1pt"]
    assert len(entry["angles_deg"]) == len(entry["mae_deg"]) == len(entry["failures"]) == 21
    assert {"ransac-1pt", "histogram", "median", "opencv-5pt-usac"} <= set(summary["estimators"])
    assert sorted(p.name for p in out.iterdir()) == ["angle_sweep.png", "near_sweep.png", "noise_sweep.png",
                                                     "summary.json", "synthetic.csv", "tables.md"]


def test_experiment_results_do_not_depend_on_the_number_of_workers():
    from ctpipe.evaluate.experiments import load_synthetic_settings, run_synthetic

    settings = load_synthetic_settings()
    one = run_synthetic(settings, reps=2, jobs=1).summary()
    two = run_synthetic(settings, reps=2, jobs=2).summary()
    assert one["estimators"]["ransac-1pt"]["mae_deg"] == pytest.approx(two["estimators"]["ransac-1pt"]["mae_deg"])


def test_bad_experiment_config_exits_2(tmp_path):
    (tmp_path / "exp.yaml").write_text("reps: 3\n")
    code, _, stderr = run_cli("experiment", "synthetic", "--config", str(tmp_path / "exp.yaml"))
    assert code == 2 and stderr.startswith("ctpipe: error: experiment.cylinder: missing")
