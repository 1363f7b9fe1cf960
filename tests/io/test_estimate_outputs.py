"""ctpipe estimate on a vendor scan writes corrected angles the scanner's software reads back."""

import csv
import json

import numpy as np
import yaml

from ctpipe.cli import main
from ctpipe.io import open_scan
from ctpipe.testing import write_nikon

from scan_helpers import FAST_PIPELINE


def test_estimate_on_a_nikon_scan_writes_every_output_and_a_readable_angle_file(raw_scan, tmp_path, capsys):
    folder = write_nikon(tmp_path / "nikon", geometry=raw_scan.geometry, nominal_angles_deg=raw_scan.nominal_deg,
                         recorded_angles_deg=raw_scan.true_deg, intensities=raw_scan.intensities,
                         flats=raw_scan.flats, darks=raw_scan.darks, name="part")
    pipeline = tmp_path / "fast.yaml"
    pipeline.write_text(yaml.safe_dump(FAST_PIPELINE))
    out = tmp_path / "out"
    capsys.readouterr()
    assert main(["estimate", str(folder), "--pipeline", str(pipeline), "--out", str(out)]) == 0
    summary = capsys.readouterr().out
    assert summary.startswith(f"nikon scan {folder}: 120 views of 96 x 128 px")
    assert "estimated minus scanner's angle log: RMS" in summary
    assert ("written: angles.csv, angles.png, before_after.png, geometry_vectors.csv, part.ang, result.json"
            in summary)
    assert len(summary.splitlines()) < 25

    with open(out / "angles.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == 120 and list(rows[0])[:3] == ["view", "angle_deg", "n_keypoints"]
    estimated = np.array([float(r["angle_deg"]) for r in rows])
    recorded = np.array([float(r["recorded_deg"]) for r in rows])
    np.testing.assert_allclose(recorded, raw_scan.true_deg, atol=1e-6)
    np.testing.assert_allclose([float(r["estimated_minus_recorded_deg"]) for r in rows], estimated - recorded)
    # In the nominal angles' frame: estimated minus nominal is zero in the median.
    assert abs(np.median(estimated - raw_scan.nominal_deg)) < 1e-9
    report = json.loads((out / "result.json").read_text())
    assert report["scan"]["format"] == "nikon" and report["against_recorded"]["views"] == 120
    vectors = np.loadtxt(out / "geometry_vectors.csv", delimiter=",", skiprows=1)
    assert vectors.shape == (120, 13)

    # The corrected .ang, put where CT Pro looks for it, reads back as the estimated angles.
    (folder / "_ctdata.txt").unlink()
    (folder / "part.ang").write_bytes((out / "part.ang").read_bytes())
    np.testing.assert_allclose(open_scan(folder).recorded_angles_deg, estimated, atol=1e-4)


def test_a_scan_whose_angle_sign_is_reversed_is_told_so(raw_scan, tmp_path, capsys):
    from ctpipe.io import write_scan

    folder = write_scan(tmp_path / "reversed", raw_scan.intensities, raw_scan.geometry, -raw_scan.nominal_deg,
                        flats=raw_scan.flats, darks=raw_scan.darks, values="intensities")
    pipeline = tmp_path / "fast.yaml"
    pipeline.write_text(yaml.safe_dump(FAST_PIPELINE))
    capsys.readouterr()
    assert main(["estimate", str(folder), "--pipeline", str(pipeline)]) == 0
    summary = capsys.readouterr().out
    assert "warning: the images turn the other way from the nominal angles" in summary
    # The right sign draws no warning.
    right = write_scan(tmp_path / "right", raw_scan.intensities, raw_scan.geometry, raw_scan.nominal_deg,
                       flats=raw_scan.flats, darks=raw_scan.darks, values="intensities")
    assert main(["estimate", str(right), "--pipeline", str(pipeline)]) == 0
    assert "turn the other way" not in capsys.readouterr().out
