"""Before/after slices and the truth-free measure of both angle sets (what ``ctpipe estimate`` shows)."""

import json
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from ctpipe.cli import main
from ctpipe.errors import InputError
from ctpipe.evaluate.preview import before_after, before_after_png
from ctpipe.recon import VolumeGrid, fdk

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "solve"))
from conjugate_scans import simulate_scan  # noqa: E402


@pytest.fixture(scope="module")
def scan():
    """180 views of the bead cylinder, 0.3 deg jitter (tests/solve/conjugate_scans.py)."""
    return simulate_scan("bead-cylinder")


def test_the_true_angles_are_shown_better_and_a_smooth_error_worse(scan):
    nominal = scan.nominal_angles_deg
    truth = before_after(scan.projections, scan.geometry, nominal, scan.true_angles_deg)
    wrong = before_after(scan.projections, scan.geometry, nominal, nominal + 0.6 * np.sin(np.deg2rad(nominal)))
    assert truth.scores["corrected"].z < -2.0 and truth.change < -0.1
    assert "the correction helped" in truth.verdict()
    assert wrong.scores["corrected"].z > 2.0 and wrong.change > 0.1
    assert "made it worse" in wrong.verdict()
    # Each reconstruction uses the axis column its own angles fit; the scan's axis is on u0.
    for comparison in (truth, wrong):
        for u0 in comparison.u0_px.values():
            assert abs(u0 - scan.geometry.u0_px) < 0.5


def test_the_nominal_angles_against_themselves_change_nothing(scan):
    comparison = before_after(scan.projections, scan.geometry, scan.nominal_angles_deg, scan.nominal_angles_deg + 3.0)
    assert comparison.max_change_deg == pytest.approx(0.0, abs=1e-9)
    assert "nothing changed" in comparison.verdict()
    np.testing.assert_array_equal(comparison.axial["nominal"], comparison.axial["corrected"])


def test_the_slices_are_fdk_of_the_scan_at_each_angle_set(scan):
    """The axial slice is the midplane of an FDK of the whole scan with those angles and that axis column."""
    comparison = before_after(scan.projections, scan.geometry, scan.nominal_angles_deg, scan.true_angles_deg)
    g = scan.geometry
    n = comparison.axial["corrected"].shape[0]
    assert comparison.binning == 1 and comparison.axial_voxel_mm == pytest.approx(
        g.pixel_pitch_u_mm * g.source_to_object_mm / g.source_to_detector_mm)
    geometry = g.__class__(**{**g.to_dict(), "u0_px": comparison.u0_px["corrected"]})
    volume = fdk(scan.projections, geometry, scan.true_angles_deg, VolumeGrid(n, 1, n, comparison.axial_voxel_mm))
    # v0 sits between two rows (47.5 of 96): the preview interpolates the midplane row, FDK its voxel.
    assert np.corrcoef(volume[0].ravel(), comparison.axial["corrected"].ravel())[0, 1] > 0.99
    # Sharper with the true angles than with the jittered ones: more energy at high frequency.
    def detail(image):
        return float(np.mean(np.diff(image, axis=0) ** 2) + np.mean(np.diff(image, axis=1) ** 2))

    assert detail(comparison.axial["corrected"]) > detail(comparison.axial["nominal"])


def test_binning_keeps_a_large_scan_under_the_budget(scan):
    comparison = before_after(scan.projections, scan.geometry, scan.nominal_angles_deg, scan.true_angles_deg,
                              max_side_px=32, budget_bytes=180 * 16 * 16 * 4)
    assert comparison.binning == 8
    assert comparison.vertical["corrected"].shape[1] <= 20


def test_a_short_scan_without_conjugate_rays_still_shows_slices():
    short = simulate_scan("bead-cylinder", **{"angles.range_deg": 100.0, "angles.n_views": 40})
    comparison = before_after(short.projections, short.geometry, short.nominal_angles_deg, short.true_angles_deg)
    assert not comparison.scores and "half a turn" in comparison.note
    assert "the projections' conjugate rays cannot judge the angles" in comparison.verdict()
    assert before_after_png(comparison, "short").startswith(b"\x89PNG")


def test_conjugate_rays_that_cross_nothing_that_turns_do_not_judge(scan):
    """A midplane on a flat background (a ball phantom's, clipped, its balls above and below): the
    conjugate rays read the same to rounding at any angles, and a change relative to that is a ratio
    of rounding errors (a real ball scan's summary said 1.6e18 % worse). No verdict from them."""
    views = np.array(scan.projections, dtype=np.float32, copy=True)
    middle = int(round(scan.geometry.v0_px))
    views[:, middle - 8:middle + 9, :] = 0.0
    comparison = before_after(views, scan.geometry, scan.nominal_angles_deg, scan.true_angles_deg)
    assert not comparison.scores and comparison.change is None
    assert "read the same to rounding" in comparison.note
    assert "conjugate rays cannot judge" in comparison.verdict()
    assert comparison.u0_px == {"nominal": scan.geometry.u0_px, "corrected": scan.geometry.u0_px}


def test_too_few_views_paired_half_a_turn_apart_do_not_judge(scan):
    """23 views of the same scan (every eighth): the true angles, yet too few terms for the measure's standard error to
    be checked. The scores are kept for result.json; the verdict does not judge by them."""
    from ctpipe.evaluate.preview import MIN_PAIRED_VIEWS

    views = np.asarray(scan.projections)[::8][:23]
    nominal, truth = scan.nominal_angles_deg[::8][:23], scan.true_angles_deg[::8][:23]
    comparison = before_after(views, scan.geometry, nominal, truth)
    assert comparison.scores and 0 < comparison.paired_views < MIN_PAIRED_VIEWS and not comparison.judges
    verdict = comparison.verdict()
    assert verdict.startswith(f"before/after: the projections' conjugate rays cannot judge the angles "
                              f"({comparison.paired_views} views have a view half a turn apart to compare with, "
                              "too few")
    assert "helped" not in verdict and "worse" not in verdict
    assert comparison.to_dict()["judges"] is False
    # The full scan judges, as before.
    assert before_after(scan.projections, scan.geometry, scan.nominal_angles_deg, scan.true_angles_deg).judges


def test_bad_angles_are_one_line(scan):
    with pytest.raises(InputError, match="corrected_deg: must be 180 finite angles"):
        before_after(scan.projections, scan.geometry, scan.nominal_angles_deg, scan.nominal_angles_deg[:-1])


def test_estimate_writes_the_picture_and_the_measure(tmp_path, small_scan_folder, capsys):
    pipeline = tmp_path / "fast.yaml"
    pipeline.write_text(yaml.safe_dump({"refiner": {"name": "least-squares"}, "pairs": {"baselines": [1, 2]}}))
    out = tmp_path / "out"
    assert main(["estimate", str(small_scan_folder), "--pipeline", str(pipeline), "--out", str(out)]) == 0
    summary = capsys.readouterr().out
    assert "before/after: " in summary and "before_after.png" in summary
    assert summary.count("conjugate rays") == 1     # the gate line does not repeat the measure
    assert (out / "before_after.png").read_bytes().startswith(b"\x89PNG")
    report = json.loads((out / "result.json").read_text())
    assert set(report["before_after"]["scores"]) == {"nominal", "corrected"}
    assert main(["estimate", str(small_scan_folder), "--pipeline", str(pipeline), "--out", str(tmp_path / "o2"),
                 "--no-slices"]) == 0
    assert not (tmp_path / "o2" / "before_after.png").exists()
    assert "before_after" not in json.loads((tmp_path / "o2" / "result.json").read_text())


def test_both_angle_sets_get_the_same_slice_grid_when_they_fit_different_axis_columns(scan, monkeypatch):
    """Each set reconstructs at the axis column it fits; the slices must still be comparable.

    A 17-view 2000^2 ball scan fitted columns 2.7 px apart, and its vertical slices came out 251 and
    256 voxels wide: ``ctpipe estimate`` ended in a traceback while drawing their difference.
    """
    import dataclasses

    import ctpipe.evaluate.preview as preview

    fitted = preview.conjugate_ray_costs

    def apart(*args, **kwargs):
        scores = fitted(*args, **kwargs)
        shift = {"nominal": -40.0, "corrected": 35.0}   # far enough apart to change the field of view
        return {label: dataclasses.replace(score, u0_px=score.u0_px + shift[label]) for label, score in scores.items()}

    monkeypatch.setattr(preview, "conjugate_ray_costs", apart)
    comparison = before_after(scan.projections, scan.geometry, scan.nominal_angles_deg, scan.true_angles_deg)
    assert comparison.u0_px["corrected"] - comparison.u0_px["nominal"] == pytest.approx(75.0, abs=1.0)
    for cut in (comparison.axial, comparison.vertical):
        assert cut["nominal"].shape == cut["corrected"].shape
    assert before_after_png(comparison, "apart").startswith(b"\x89PNG")
