"""``ctpipe estimate SCAN... [--dask [ADDRESS]]``: batches, a broken scan among them, the Dask flag."""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from ctpipe.cli import _batch_outputs, _is_address, _scan_paths, main

FAST = {
    "detector": {"name": "sift"},
    "matcher": {"name": "brute-force", "ratio": 0.8, "mutual": True},
    "estimator": {"name": "ransac-1pt", "sampson_threshold": 3.0e-3},
    "refiner": {"name": "least-squares"},
    "pairs": {"baselines": [1, 2]},
}


@pytest.fixture()
def batch(tmp_path, small_scan_folder):
    """Three scan folders, the middle one broken (a projection file missing), and a fast pipeline YAML."""
    folders = [shutil.copytree(small_scan_folder, tmp_path / "scans" / name) for name in ("a", "b-broken", "c")]
    (folders[1] / "projections" / "proj_00007.tif").unlink()
    pipeline = tmp_path / "fast.yaml"
    pipeline.write_text(yaml.safe_dump(FAST))
    return folders, pipeline, tmp_path / "out"


def _angles(folder: Path) -> np.ndarray:
    return np.array(json.loads((folder / "result.json").read_text())["angles_deg"], dtype=float)


def test_a_batch_finishes_every_good_scan_and_reports_the_broken_one(batch, capsys):
    folders, pipeline, out = batch
    code = main(["estimate", *map(str, folders), "--pipeline", str(pipeline), "--out", str(out)])
    captured = capsys.readouterr()
    assert code == 2
    assert sorted(p.name for p in out.iterdir()) == ["a", "c"]   # nothing at all for the broken scan
    for name in ("a", "c"):
        assert {"angles.csv", "result.json", "geometry_vectors.csv"} <= {p.name for p in (out / name).iterdir()}
    assert "batch: 2 of 3 scans estimated, 1 failed:" in captured.out
    failure = [line for line in captured.err.splitlines() if "FAILED" in line]
    assert len(failure) == 1 and "b-broken" in failure[0] and "proj_00007.tif: no such file" in failure[0]
    assert "Traceback" not in captured.err

    # Each scan's answer is the one it gets alone.
    code = main(["estimate", str(folders[0]), "--pipeline", str(pipeline), "--out", str(out / "alone")])
    assert code == 0
    np.testing.assert_array_equal(_angles(out / "a"), _angles(out / "alone"))


def test_a_batch_on_a_dask_scheduler_gives_the_in_process_answers(batch, dask_client, capsys):
    folders, pipeline, out = batch
    address = dask_client.scheduler.address
    good = [str(folders[0]), str(folders[2])]
    assert main(["estimate", *good, "--pipeline", str(pipeline), "--out", str(out / "here"), "--json"]) == 0
    here = json.loads(capsys.readouterr().out)
    code = main(["estimate", *map(str, folders), "--pipeline", str(pipeline), "--out", str(out / "there"),
                 "--json", "--dask", address])
    captured = capsys.readouterr()
    there = json.loads(captured.out)
    assert code == 2 and there["failed"] == 1
    assert [entry["status"] for entry in there["scans"]] == ["ok", "failed", "ok"]
    assert "no such file" in there["scans"][1]["error"]
    assert f"the scheduler at {address}" in captured.err
    for a, b in zip(here["scans"], (there["scans"][0], there["scans"][2])):
        np.testing.assert_array_equal(a["report"]["angles_deg"], b["report"]["angles_deg"])
    np.testing.assert_array_equal(_angles(out / "here" / "a"), _angles(out / "there" / "a"))


def test_a_quoted_glob_makes_the_batch_and_an_empty_one_is_an_error(batch, capsys):
    folders, pipeline, out = batch
    pattern = str(folders[0].parent / "[ac]")
    assert main(["estimate", pattern, "--pipeline", str(pipeline), "--out", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["a", "c"]
    capsys.readouterr()
    assert main(["estimate", str(folders[0].parent / "z*"), "--pipeline", str(pipeline)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "z*: the pattern matches no scan" in err


def test_dask_flag_without_dask_says_how_to_install_it_in_one_line(batch, capsys, monkeypatch):
    folders, pipeline, out = batch
    monkeypatch.setitem(sys.modules, "distributed", None)
    assert main(["estimate", str(folders[0]), "--dask", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err == "ctpipe: error: the Dask backend needs dask.distributed, which is not installed: " \
                  "pip install 'ctpipe[dask]'\n"
    assert not out.exists()


def test_a_batch_refuses_a_geometry_file(batch, capsys):
    folders, pipeline, out = batch
    assert main(["estimate", str(folders[0]), str(folders[2]), "--geometry", str(pipeline)]) == 2
    assert "--geometry goes with one projection stack" in capsys.readouterr().err


def test_dask_takes_an_address_but_gives_a_scan_back():
    assert _is_address("tcp://10.0.0.1:8786") and _is_address("node12:8786") and _is_address("scheduler.json")
    assert not _is_address("scans/day1") and not _is_address("sample.txrm")
    assert _scan_paths(["b", "c"], "a") == [Path("a"), Path("b"), Path("c")]
    assert _scan_paths(["b", "b"], "tcp://h:1") == [Path("b")]


def test_scans_with_one_name_get_their_parents_name(tmp_path):
    x, y = tmp_path / "x" / "scan", tmp_path / "y" / "scan"
    for folder in (x, y):
        folder.mkdir(parents=True)
    outs = _batch_outputs([x, y, tmp_path / "z.txrm"], "out")
    assert outs == {x: Path("out/x-scan"), y: Path("out/y-scan"), tmp_path / "z.txrm": Path("out/z")}
