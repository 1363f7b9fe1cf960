"""The ball-phantom pipeline end to end: a simulated ball bar, 16 views of 22.5 deg, every view within 0.02 deg."""

import json
import re
import shutil

import numpy as np
import pytest
import yaml

from ctpipe.cli import main
from ctpipe.evaluate.scoring import view_errors_deg
from ctpipe.pipeline import Pipeline
from ctpipe.sim import load_phantom, parse_scan_spec, simulate, write_simulated_scan

CONFIG = "configs/calibration-beads.yaml"


def _spec(n_views: int, seed: int):
    # The calibration experiment's geometry at half the pixels (same field of view): balls ~12 px.
    return parse_scan_spec({
        "geometry": {"source_to_object_mm": 250.0, "source_to_detector_mm": 500.0, "detector_cols": 256,
                     "detector_rows": 256, "pixel_pitch_u_mm": 0.4, "pixel_pitch_v_mm": 0.4},
        "angles": {"n_views": n_views, "range_deg": 360.0},
        "jitter": [{"gaussian": {"sigma_deg": 0.3}}, {"jumps": {"count": 1, "size_deg": 0.5}}],
        "noise": {"photons_per_pixel": 50000, "flat_frames": 4, "dark_frames": 2, "dark_counts": 100},
        "projector": {"kind": "analytic", "supersample": 2, "blur_px": 0.5}, "seed": seed})


@pytest.fixture(scope="module")
def ball_bar_scan():
    spec = _spec(16, 3)
    return simulate(load_phantom("ball-bar"), spec, rng=np.random.default_rng(3)), spec


def test_every_view_of_a_16_view_ball_bar_scan_within_two_hundredths_of_a_degree(ball_bar_scan, monkeypatch):
    from pathlib import Path

    monkeypatch.chdir(Path(__file__).resolve().parents[1])
    scan, _ = ball_bar_scan
    result = Pipeline.from_config(CONFIG).run(scan.projections, scan.geometry,
                                              nominal_angles_deg=scan.nominal_angles_deg)
    errors = view_errors_deg(result.angles_deg, scan.true_angles_deg)
    nominal = view_errors_deg(scan.nominal_angles_deg, scan.true_angles_deg)
    assert np.abs(nominal).max() > 0.3           # the stage errors are there to correct
    # Over 24 noise draws of this scan the worst view was 0.005-0.015 deg (median 0.009): a
    # hundredth is the typical worst view, not a bound every draw keeps (issue 34).
    assert np.abs(errors).max() < 0.02
    assert np.median(result.n_keypoints) == 7    # every ball of the bar, in most views
    balls = result.refiner_info["balls"]
    assert balls["kept"] and balls["balls"] == 7 and balls["rms_px"] < 0.1 < balls["nominal_rms_px"]
    assert "ball calibration, 7 balls followed through the views, the corrected angles kept" in result.summary()
    assert "the detector's lag" not in result.summary()      # no lag simulated, none said
    # Solid balls: no disc placed on a shell's inside, and the line does not speak of one; where some were, it says so.
    assert balls["shell_observations"] == 0 and "inner edge" not in result.summary()
    balls["shell_observations"] = 40
    assert (f"7 balls followed through the views (40 of the {balls['observations']} discs fitted placed on a hollow "
            f"or coated ball's inner edge, which no clip or neighbour beyond the rim moves), the corrected angles "
            f"kept" in result.summary())
    # No disc left out as a gross error, and the line does not speak of one; where some were, it says how many.
    assert balls["left_out"] == 0 and "left out" not in result.summary()
    balls["left_out"] = 3
    assert "moves; 3 disc(s) left out as gross errors, pixels off their ball" in result.summary()
    # Balls hidden within others' discs placed on a second look: said where there were some.
    assert ("hidden within others" in result.summary()) == (balls["hidden_discs_placed"] > 0)
    balls["hidden_discs_placed"] = 2
    assert "; 2 disc(s) of balls hidden within others' placed on their rims where the balls put them)" in \
        result.summary()


def test_estimate_on_a_ball_scan_folder_needs_only_the_pipeline(ball_bar_scan, tmp_path, capsys, monkeypatch):
    from pathlib import Path

    scan, spec = ball_bar_scan
    phantom = load_phantom("ball-bar")
    folder = write_simulated_scan(tmp_path / "balls", scan, phantom=phantom, spec=spec, seed=3)
    config = Path(__file__).resolve().parents[1] / CONFIG
    capsys.readouterr()
    assert main(["estimate", str(folder), "--pipeline", str(config), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["angle_errors"]["views"]["max_deg"] < 0.02
    assert report["pipeline"]["detector"]["name"] == "beads"


def test_the_calibration_experiments_parse():
    from pathlib import Path

    from ctpipe.evaluate.validate import load_validate_settings
    from ctpipe.plugins import get_registry

    root = Path(__file__).resolve().parents[1] / "configs" / "experiments"
    for name in ("calibration-16-views.yaml", "calibration-32-views.yaml"):
        settings = load_validate_settings(root / name, get_registry())
        assert settings.pipeline.detector.name == "beads"
    assert yaml.safe_load((root.parent / "calibration-beads.yaml").read_text())["matcher"]["name"] == "all-pairs"


def test_the_built_in_ball_pipeline_is_configs_calibration_beads():
    from pathlib import Path

    from ctpipe.config import BALL_PHANTOM_PIPELINE, load_yaml, parse_pipeline
    from ctpipe.plugins import get_registry

    registry = get_registry()
    written = load_yaml(Path(__file__).resolve().parents[1] / CONFIG)
    assert parse_pipeline(written, registry) == parse_pipeline(BALL_PHANTOM_PIPELINE, registry)


def test_the_default_estimate_recognises_a_ball_phantom_and_says_so(ball_bar_scan, tmp_path, capsys):
    scan, spec = ball_bar_scan
    folder = write_simulated_scan(tmp_path / "balls", scan, phantom=load_phantom("ball-bar"), spec=spec, seed=3)
    capsys.readouterr()
    assert main(["estimate", str(folder), "--out", str(tmp_path / "out")]) == 0
    said = capsys.readouterr()
    assert "ctpipe: a ball phantom (9 views show 7 (" in said.err and "running the ball calibration" in said.err
    assert "ball calibration, 7 balls followed through the views, the corrected angles kept" in said.out
    # The before/after line names the measure that decided, whatever the conjugate rays make of the scan.
    verdict = next(line for line in said.out.splitlines() if line.startswith("before/after"))
    assert re.match(r"before/after: the balls' reprojection RMS \d+\.\d{3} px with the nominal angles, \d+\.\d{3} px "
                    r"with the corrected ones \(a ball phantom's measure, the one that decides\); beside it \(not a "
                    r"ball phantom's measure\), the projections' conjugate rays cannot judge the angles "
                    r"\(\d+ views have a view half a turn apart to compare with, too few", verdict)


def test_a_nikon_ball_scan_clipped_flat_at_its_white_level_is_calibrated_by_the_default_estimate(ball_bar_scan,
                                                                                                 tmp_path, capsys):
    """The issue's real scan as the scanner leaves it: a Nikon folder (``.xtekct``, CT Pro's ``.ang``, one uint16
    TIFF a view), the counts flat-corrected to ``WhiteLevel`` and the detector full at 90 % of the open beam, its
    flats too, so that the background reads ``WhiteLevel`` flat; the stage logged as commanded."""
    from ctpipe.io.nikon import read_xtekct
    from ctpipe.io.scans import open_scan
    from ctpipe.testing import write_nikon

    scan, _ = ball_bar_scan
    full = 0.9 * float(np.mean(scan.flats))
    folder = write_nikon(tmp_path / "nikon", geometry=scan.geometry, nominal_angles_deg=scan.nominal_angles_deg,
                         recorded_angles_deg=scan.nominal_angles_deg, intensities=np.minimum(scan.intensities, full),
                         flats=np.minimum(scan.flats, full), darks=scan.darks, white_level=50000.0, angle_log="ang")
    assert read_xtekct(folder / "scan.xtekct")["WhiteLevel"] == "50000.0"
    # The open beam reads WhiteLevel exactly, so its line integrals read 0: flat.
    assert np.mean(np.asarray(open_scan(folder).projections[0]) == 0) > 0.5
    capsys.readouterr()
    assert main(["estimate", str(folder), "--out", str(tmp_path / "out"), "--no-slices"]) == 0
    said = capsys.readouterr()
    assert "ctpipe: a ball phantom (" in said.err and "running the ball calibration" in said.err
    assert "ball calibration, 7 balls followed through the views, the corrected angles kept" in said.out
    # The pairs' angles on look-alike balls are guesses, as often of one sign as the other: no "reversed" warning.
    assert "turn the other way" not in said.out
    assert "views have an angle; the ball calibration does not use them: it follows every ball from the nominal" \
        in said.out
    report = json.loads((tmp_path / "out" / "result.json").read_text())
    errors = view_errors_deg(np.array(report["estimated_deg"]), scan.true_angles_deg)
    assert np.abs(view_errors_deg(scan.nominal_angles_deg, scan.true_angles_deg)).max() > 0.3
    assert np.abs(errors).max() < 0.02
    # The angle log written beside the results, put in the scan's folder, is read back as the corrected angles.
    shutil.copy(tmp_path / "out" / "scan.ang", folder / "scan.ang")
    np.testing.assert_allclose(open_scan(folder).recorded_angles_deg, report["estimated_deg"], atol=1e-4)


def _estimate_with_an_offset_detector(tmp_path, capsys, **spec_changes) -> str:
    """The ball bar, 16 views, its axis 1 px off and its detector tilted 0.5 deg, estimated as a user would; checks
    that the nominal angles come back with that axis and tilt in ``result.json`` and the geometry vectors, and returns
    what the summary said."""
    spec = parse_scan_spec({**_spec(16, 5).to_dict(), **spec_changes,
                            "misalignment": {"cor_offset_px": 1.0, "tilt_deg": 0.5}})
    scan = simulate(load_phantom("ball-bar"), spec, rng=np.random.default_rng(5))
    folder = write_simulated_scan(tmp_path / "balls", scan, phantom=load_phantom("ball-bar"), spec=spec, seed=5)
    capsys.readouterr()
    assert main(["estimate", str(folder), "--out", str(tmp_path / "out"), "--no-slices"]) == 0
    said = capsys.readouterr().out
    report = json.loads((tmp_path / "out" / "result.json").read_text())
    np.testing.assert_allclose(report["estimated_deg"], scan.nominal_angles_deg, atol=1e-9)
    refined = report["refined_geometry"]
    # The simulator's tilt is the ball calibration's with the opposite sign (its camera convention).
    assert refined["geometry"]["u0_px"] == pytest.approx(scan.geometry.u0_px + 1.0, abs=0.05)
    assert refined["tilt_deg"] == pytest.approx(-0.5, abs=0.02)
    vectors = np.loadtxt(tmp_path / "out" / "geometry_vectors.csv", delimiter=",", skiprows=1)
    assert np.abs(vectors[:, 10]).max() > 1e-4     # the detector's v axis leans: the tilt is in the vectors
    # The plane's standard errors are said, and the pose the balls show no different from the scan's, which is kept.
    line = next(text for text in said.splitlines() if text.startswith("geometry: u0"))
    assert " (standard errors " in line and "deg); the axis on the source's perpendicular" in line
    assert refined["geometry"]["source_to_detector_mm"] == scan.geometry.source_to_detector_mm
    return said


def test_a_right_stage_and_an_offset_detector_give_the_nominal_angles_and_the_detector(tmp_path, capsys):
    """A lab's check of a scanner whose stage is right: the nominal angles, and the axis and tilt the balls show."""
    said = _estimate_with_an_offset_detector(tmp_path, capsys, jitter=[])
    assert "the nominal angles returned" in said
    assert "detector: with the nominal angles, the fitted detector explains the balls better" in said


def test_angles_refused_on_one_view_still_write_the_detector_the_corrected_angles_fit(tmp_path, capsys, monkeypatch):
    """A jittered stage, the balls made to disagree on one view (its jackknife three times the bar): the nominal
    angles come back, and the axis and tilt the corrected angles fit are written and said in the summary."""
    from ctpipe.solve import balls

    real = balls._jackknife_se

    def jackknife(*args, **kwargs):
        se, n, detector_se, refits, rests = real(*args, **kwargs)
        se[5] = 0.06
        return se, n, detector_se, refits, rests

    monkeypatch.setattr(balls, "_jackknife_se", jackknife)
    said = _estimate_with_an_offset_detector(tmp_path, capsys)
    assert "the nominal angles returned: the balls disagree on view 5's angle" in said
    assert "detector: fitted with the corrected angles, which are not returned" in said


def test_a_sample_is_not_taken_for_a_ball_phantom():
    from ctpipe.features import looks_like_ball_phantom
    from ctpipe.sim import parse_scan_spec

    spec = parse_scan_spec({**_spec(3, 0).to_dict(), "noise": None, "jitter": []})
    for name in ("granular", "shepp-logan-3d", "metal-insert"):
        views = simulate(load_phantom(name), spec, rng=np.random.default_rng(0)).projections
        yes, why = looks_like_ball_phantom(views)
        assert not yes, f"{name}: {why}"


def test_a_drifting_source_spot_is_fitted_per_view_and_written_into_the_geometry(tmp_path, capsys):
    """A bead cloud whose projections drift (a walk and a 0.8 px jump): each view's shift comes out in the summary,
    result.json and the geometry vectors, as the simulator drew it (less what the balls' positions take)."""
    from ctpipe.io.corrected import cone_vectors
    from ctpipe.solve.reprojection import _axis_part, _shift_gauge

    spec = parse_scan_spec({**_spec(16, 3).to_dict(),
                            "misalignment": {"drift": {"walk_px": 0.05, "jumps": 1, "jump_px": 0.8}}})
    scan = simulate(load_phantom("bead-cloud-10"), spec, rng=np.random.default_rng(3))
    folder = write_simulated_scan(tmp_path / "beads", scan, phantom=load_phantom("bead-cloud-10"), spec=spec, seed=3)
    capsys.readouterr()
    assert main(["estimate", str(folder), "--out", str(tmp_path / "out"), "--no-slices"]) == 0
    said = capsys.readouterr().out
    assert "each view's projection shifted by up to" in said
    assert "a detector that drifts: no source spot's parallax" in said   # the simulator's drift moves the detector
    report = json.loads((tmp_path / "out" / "result.json").read_text())
    refined = report["refined_geometry"]
    shifts = np.array(refined["view_shifts_px"])
    assert "view_shifts_px" in refined["refined"] and shifts.shape == (16, 2)
    truth = scan.true_detector_offsets_px
    theta = np.deg2rad(scan.true_angles_deg)

    def gauge_free(s):
        """Less projection matching's gauge (what the balls' positions take) and the axis column's part."""
        return _shift_gauge(s, theta) - [_axis_part(s[:, 0], theta), 0.0]

    assert np.abs(truth).max() > 0.5 and np.abs(gauge_free(shifts) - gauge_free(truth)).max() < 0.05
    vectors = np.loadtxt(tmp_path / "out" / "geometry_vectors.csv", delimiter=",", skiprows=1)[:, 1:]
    geometry = scan.geometry.__class__(**refined["geometry"])
    # The spot's share of the drift goes into the vectors as what it is: the balls' parallax says the detector's.
    assert 0.0 <= refined["drift_spot_share"] <= 0.05
    np.testing.assert_allclose(vectors, cone_vectors(geometry, report["estimated_deg"], tilt_deg=refined["tilt_deg"],
                                                     shifts_px=shifts, spot_share=refined["drift_spot_share"]),
                               atol=1e-3)
    assert not np.allclose(vectors, cone_vectors(geometry, report["estimated_deg"], tilt_deg=refined["tilt_deg"]),
                           atol=1e-3)


def test_the_summary_warns_of_a_detectors_lag_with_the_ball_it_pulls_most():
    from ctpipe.pipeline import _lag_warning

    line = _lag_warning({"lag_shown": True, "lag_p_value": 1.3e-32, "lag_pull_px": [-0.06, None, 0.3036, 0.02]})
    assert line.startswith("warning: the balls' discs are pulled towards where they were the view before (up to "
                           "+0.30 px, ball 2; F test p 1.3e-32): the detector's lag (afterglow)")
    assert "\n" not in line
