"""Nikon / X-Tek scans: written as the scanner and CT Pro leave them, read back as the simulation's own scan.

The reference is ctpipe's scan folder holding the counts the scanner saves (its flat correction
applied, scaled to WhiteLevel) with the simulation's geometry and angles; the Nikon scan must
give the same geometry, angles, views (bitwise) and estimated angles.
"""

import shutil

import numpy as np
import pytest

import ctpipe.io.nikon as nikon
from ctpipe.errors import ConfigError, InputError
from ctpipe.io.scans import open_scan
from ctpipe.testing import write_nikon

from scan_helpers import estimate_angles, simulate_raw_scan, write_reference

WHITE = 60000.0


def scanner_counts(raw, white=WHITE):
    """What a Nikon scanner saves: (I - mean dark) / (mean flat - mean dark) * WhiteLevel, rounded to uint16."""
    dark = raw.darks.astype(np.float64).mean(axis=0)
    flat = raw.flats.astype(np.float64).mean(axis=0)
    corrected = (raw.intensities.astype(np.float64) - dark) / (flat - dark) * white
    return np.clip(np.round(corrected), 0, 65535).astype(np.uint16)


def write(folder, raw, **changes):
    kwargs = dict(geometry=raw.geometry, nominal_angles_deg=raw.nominal_deg, recorded_angles_deg=raw.true_deg,
                  intensities=raw.intensities, flats=raw.flats, darks=raw.darks, white_level=WHITE)
    return write_nikon(folder, **{**kwargs, **changes})


def test_a_nikon_scan_reads_back_as_the_scan_the_simulation_acquired(raw_scan, tmp_path, capsys):
    folder = write(tmp_path / "nikon", raw_scan)
    reference = write_reference(tmp_path / "ref", raw_scan, scanner_counts(raw_scan), white_level=WHITE)
    opened, ref = open_scan(folder), open_scan(reference)
    assert opened.format == "nikon" and opened.geometry == raw_scan.geometry
    np.testing.assert_array_equal(opened.nominal_angles_deg, raw_scan.nominal_deg)
    np.testing.assert_array_equal(opened.recorded_angles_deg, raw_scan.true_deg)
    assert opened.angle_log == folder / "_ctdata.txt"
    assert opened.projections.shape == ref.projections.shape
    for view in range(len(raw_scan.nominal_deg)):
        np.testing.assert_array_equal(opened.projections[view], ref.projections[view])

    angles = estimate_angles(folder, tmp_path, capsys)
    np.testing.assert_array_equal(angles, estimate_angles(reference, tmp_path, capsys))
    # The estimate chains view pairs, so its error wanders (a random walk); the log's jitter is
    # white. View-to-view moves compare like with like: they follow the log's, sign included.
    nominal = raw_scan.nominal_deg - raw_scan.nominal_deg[0]
    recorded = opened.recorded_angles_deg - opened.recorded_angles_deg[0]
    assert np.corrcoef(np.diff(angles - nominal), np.diff(recorded - nominal))[0, 1] > 0.5


def test_the_angle_log_counts_like_angular_step_and_is_read_with_ctpipes_sign(tmp_path, capsys):
    # Jitter large enough for the fast pipeline to see it view by view.
    raw = simulate_raw_scan(jitter=[{"gaussian": {"sigma_deg": 1.5}}])
    start = 40.20631  # a real scan's InitialAngle: its logs start near 0 all the same
    folder = write(tmp_path / "nikon", raw, nominal_angles_deg=raw.nominal_deg + start,
                   recorded_angles_deg=raw.true_deg + start)
    keys = nikon.read_xtekct(folder / "scan.xtekct")
    assert float(keys["InitialAngle"]) == start and float(keys["AngularStep"]) == 3.0
    logged = np.array([float(line.split("\t")[1]) for line in
                       (folder / "_ctdata.txt").read_text().splitlines()[3:]])
    np.testing.assert_allclose(logged, raw.true_deg, atol=1e-12)  # counted from InitialAngle, not negated

    opened = open_scan(folder)
    np.testing.assert_allclose(opened.nominal_angles_deg, raw.nominal_deg + start, atol=1e-12)
    np.testing.assert_allclose(opened.recorded_angles_deg, raw.true_deg + start, atol=1e-12)
    angles = estimate_angles(folder, tmp_path, capsys)
    nominal = opened.nominal_angles_deg - opened.nominal_angles_deg[0]
    recorded = opened.recorded_angles_deg - opened.recorded_angles_deg[0]
    assert np.corrcoef(angles - nominal, recorded - nominal)[0, 1] > 0.5
    assert np.corrcoef(np.diff(angles - nominal), np.diff(recorded - nominal))[0, 1] > 0.8


@pytest.mark.parametrize("offset_keys, key, value_mm", [
    ("object_offset", "ObjectOffsetX", 2.75 * 1.6 * 130.0 / 300.0),
    ("centre_of_rotation", "CentreOfRotationTop", 2.75 * 1.6),
    ("detector_offset", "DetectorOffsetX", -2.75 * 1.6),
])
def test_an_off_centre_principal_point_survives_each_offset_key(raw_scan, tmp_path, offset_keys, key, value_mm):
    folder = write(tmp_path / offset_keys, raw_scan, offset_keys=offset_keys)
    keys = nikon.read_xtekct(folder / "scan.xtekct")
    # CIL's signs: the axis at -ObjectOffsetX (CentreOfRotation at the detector), the detector
    # centre at -DetectorOffsetX and +DetectorOffsetY; stored columns run towards -x, rows down.
    assert float(keys[key]) == pytest.approx(value_mm, abs=1e-12)
    assert float(keys["DetectorOffsetY"]) == pytest.approx((45.5 - 47.5) * 1.6, abs=1e-12)
    assert open_scan(folder).geometry == raw_scan.geometry


def test_the_principal_point_column_is_where_the_images_turn(raw_scan, tmp_path):
    scan = open_scan(write(tmp_path / "nikon", raw_scan))
    cols = np.arange(scan.geometry.detector_cols)
    centres = [np.sum(view.sum(axis=0) * cols) / np.sum(view) for view in scan.projections]
    # Over a full turn the mass of the object circles the axis: its mean column is the axis's.
    assert abs(np.mean(centres) - scan.geometry.u0_px) < 0.5
    mirrored = (scan.geometry.detector_cols - 1) - scan.geometry.u0_px  # what a flipped offset sign would give
    assert abs(np.mean(centres) - mirrored) > 4.0


# --------------------------------------------------------------------------- small scans for the file tests


@pytest.fixture(scope="module")
def small_scan(tmp_path_factory, raw_scan):
    """Six views of the shared acquisition, as a Nikon scan (copied by each test that damages it)."""
    views = slice(0, 6)
    folder = tmp_path_factory.mktemp("nikon") / "small"
    return write_nikon(folder, geometry=raw_scan.geometry, nominal_angles_deg=raw_scan.nominal_deg[views],
                       recorded_angles_deg=raw_scan.true_deg[views], intensities=raw_scan.intensities[views],
                       flats=raw_scan.flats, darks=raw_scan.darks, white_level=WHITE)


@pytest.fixture
def scan(small_scan, tmp_path):
    return shutil.copytree(small_scan, tmp_path / "scan")


def edit(file, old, new):
    text = file.read_text()
    assert old in text
    file.write_text(text.replace(old, new))


def test_detect_knows_a_nikon_folder_and_its_xtekct_file(scan, tmp_path):
    assert nikon.detect(scan) and nikon.detect(scan / "scan.xtekct")
    assert not nikon.detect(scan / "scan_0001.tif") and not nikon.detect(tmp_path / "nope")
    assert open_scan(scan / "scan.xtekct").format == "nikon"


def test_an_ang_file_is_read_and_written_in_ct_pros_layout(small_scan, raw_scan, tmp_path):
    folder = write(tmp_path / "ang", raw_scan, nominal_angles_deg=raw_scan.nominal_deg + 10.0,
                   recorded_angles_deg=raw_scan.true_deg + 10.0, angle_log="ang")
    lines = (folder / "scan.ang").read_text().splitlines()
    assert lines[0] == "Proj\tAngle(deg)" and len(lines) == 1 + len(raw_scan.true_deg)
    number, angle = lines[1].split(":\t")
    # Counted from InitialAngle and against AngularStep, as the scanners' own .ang files run.
    assert number == "1" and float(angle) == pytest.approx(-raw_scan.true_deg[0], abs=1e-12)
    opened = open_scan(folder)
    assert opened.angle_log == folder / "scan.ang"
    np.testing.assert_allclose(opened.recorded_angles_deg, raw_scan.true_deg + 10.0, atol=1e-12)

    # Corrected angles handed back to CT Pro: InitialAngle comes from the .xtekct beside the file.
    scan = shutil.copytree(small_scan, tmp_path / "scan")
    corrected = np.array([0.1, 3.2, 5.9, 9.05, 12.0, 15.1])
    assert nikon.write_nikon_angles(scan / "scan.ang", corrected) == scan / "scan.ang"
    reopened = open_scan(scan)
    np.testing.assert_array_equal(reopened.recorded_angles_deg, corrected)
    # Both logs are read; the corrected .ang and the scanner's _ctdata.txt differ by the jitter.
    assert any(note.startswith("_ctdata.txt is read too and agrees with scan.ang within") for note in reopened.notes)
    with pytest.raises(InputError, match=r"scan\.ang: exists"):
        nikon.write_nikon_angles(scan / "scan.ang", corrected)
    with pytest.raises(InputError, match=r"must be a \.ang file name"):
        nikon.write_nikon_angles(scan / "scan.txt", corrected)


def test_a_leaning_axis_is_averaged_and_said(scan):
    file = scan / "scan.xtekct"
    edit(file, "ObjectOffsetX=", "Unused=")
    edit(file, "ObjectRoll=0.0", "ObjectRoll=0.05\nCentreOfRotationTop=4.8\nCentreOfRotationBottom=4.0")
    opened = open_scan(scan)
    assert opened.geometry.u0_px == pytest.approx(63.5 + 4.4 / 1.6)
    assert any("leans by +0.50 px" in note for note in opened.notes)
    assert any("ObjectRoll=0.05" in note for note in opened.notes)


def test_no_angle_log_means_no_recorded_angles(scan):
    (scan / "_ctdata.txt").unlink()
    opened = open_scan(scan)
    assert opened.recorded_angles_deg is None and opened.angle_log is None
    assert any("recorded angles are unknown" in note for note in opened.notes)


def test_a_malformed_xtekct_is_refused_naming_the_file(scan):
    file = scan / "scan.xtekct"
    file.write_text("this is not\nan ini file\n")
    with pytest.raises(ConfigError, match=r"scan\.xtekct: not a readable \.xtekct \(INI\) file"):
        open_scan(scan)
    file.write_text("[Xrays]\nXraykV=90\n")
    with pytest.raises(ConfigError, match=r"scan\.xtekct: no \[XTekCT\] section"):
        open_scan(scan)


def test_a_missing_or_bad_key_is_named(scan):
    file = scan / "scan.xtekct"
    edit(file, "WhiteLevel=", "WhiteLevelX=")
    with pytest.raises(ConfigError, match=r"scan\.xtekct: \[XTekCT\] WhiteLevel: missing"):
        open_scan(scan)
    edit(file, "WhiteLevelX=", "WhiteLevel=")
    edit(file, "SrcToObject=130.0", "SrcToObject=abc")
    with pytest.raises(ConfigError, match=r"\[XTekCT\] SrcToObject: must be a finite number > 0 \(mm\), got 'abc'"):
        open_scan(scan)
    edit(file, "SrcToObject=abc", "SrcToObject=400.0")
    with pytest.raises(ConfigError, match=r"scan\.xtekct: geometry: source_to_detector_mm must exceed"):
        open_scan(scan)


def test_a_count_that_disagrees_with_the_files_is_refused(scan):
    file = scan / "scan.xtekct"
    # Six images for Projections=5 are five and the one closing the scan; for 4, one too many.
    edit(file, "Projections=6", "Projections=4")
    with pytest.raises(InputError, match=r"scan_0006\.tif: exists, but scan\.xtekct says Projections=4; there must be "
                                         r"4 projection files, or 5 with the image that closes the turn"):
        open_scan(scan)
    edit(file, "Projections=4", "Projections=7")
    with pytest.raises(InputError, match=r"scan_0007\.tif: no such file; scan\.xtekct says Projections=7"):
        open_scan(scan)
    edit(file, "Projections=7", "Projections=6")
    log = scan / "_ctdata.txt"
    log.write_text("\n".join(log.read_text().splitlines()[:-1]))
    with pytest.raises(InputError, match=r"_ctdata\.txt: lists 5 angles but the \.xtekct says Projections=6"):
        open_scan(scan)
    log.write_text(log.read_text() + "\n6\tnot-a-number\t0.0")
    with pytest.raises(InputError, match=r"_ctdata\.txt: line 9: expected '<projection> <angle> <time>'"):
        open_scan(scan)


def test_a_missing_projection_is_named(scan):
    (scan / "scan_0004.tif").unlink()
    with pytest.raises(InputError, match=r"scan_0004\.tif: no such file; .* projection 4 is missing"):
        open_scan(scan)


def test_an_image_of_the_wrong_size_is_named(scan):
    import tifffile

    tifffile.imwrite(scan / "scan_0003.tif", np.zeros((95, 128), np.uint16))
    opened = open_scan(scan)
    with pytest.raises(InputError, match=r"scan_0003\.tif: must be a 96 x 128 image \(DetectorPixelsY x "
                                         r"DetectorPixelsX in scan\.xtekct\), got shape \(95, 128\)"):
        opened.projections[2]
    tifffile.imwrite(scan / "scan_0001.tif", np.zeros((96, 127), np.uint16))
    with pytest.raises(InputError, match=r"scan_0001\.tif: must be a 96 x 128 image"):
        open_scan(scan)


def test_the_writers_refuse_what_a_nikon_scan_cannot_hold(small_scan, raw_scan, tmp_path):
    with pytest.raises(InputError, match="exists and is not an empty folder"):
        write(small_scan, raw_scan)
    with pytest.raises(InputError, match="nominal_angles_deg: must be uniformly spaced"):
        write(tmp_path / "a", raw_scan, nominal_angles_deg=raw_scan.true_deg)
    with pytest.raises(InputError, match="offset_keys: must be one of object_offset"):
        write(tmp_path / "b", raw_scan, offset_keys="sideways")
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()
    with pytest.raises(InputError, match="initial_angle_deg not given and 0 .xtekct files"):
        nikon.write_nikon_angles(tmp_path / "x.ang", [0.0, 1.0])


def test_several_xtekct_files_in_one_folder_ask_which(scan):
    # CT Pro's second reconstruction of the same acquisition differs in its Output* keys only.
    text = (scan / "scan.xtekct").read_text()
    (scan / "scan_01.xtekct").write_text(text.replace("OutputName=scan", "OutputName=scan_01"))
    opened = open_scan(scan)
    assert opened.metadata["xtekct"] == str(scan / "scan.xtekct") and opened.n_views == 6
    assert any(note.startswith("scan_01.xtekct beside scan.xtekct: the same acquisition") for note in opened.notes)
    (scan / "scan_01.xtekct").write_text(text.replace("Projections=6", "Projections=5"))
    with pytest.raises(InputError, match=r"holds 2 \.xtekct files \(scan\.xtekct, scan_01\.xtekct\) of different "
                                         r"scans; open the one you mean"):
        open_scan(scan)
    assert open_scan(scan / "scan.xtekct").n_views == 6


def test_a_closing_image_is_estimated_as_a_view_one_measured_turn_after_view_0(raw_scan, tmp_path, capsys):
    """A full turn saved as real scanners save it: Projections + 1 images, the last one turn on.

    The closing image is taken 0.3 deg past one turn: the estimate must measure that from the
    images (pair (0, V)), not assume the turn is exactly 360 deg.
    """
    from ctpipe.sim import load_phantom
    from ctpipe.sim.acquisition import beer_lambert
    from ctpipe.sim.simulator import project_phantom

    closing_true = raw_scan.true_deg[0] + 360.3
    line_integrals = project_phantom(load_phantom("bead-cylinder"), raw_scan.geometry, [closing_true], blur_px=0.5)
    expected = beer_lambert(line_integrals, 20000, 100)
    closing = np.random.default_rng(9).poisson(expected).astype(np.uint16)
    step = raw_scan.nominal_deg[1] - raw_scan.nominal_deg[0]
    folder = write(tmp_path / "closing", raw_scan, intensities=np.concatenate([raw_scan.intensities, closing]),
                   nominal_angles_deg=np.append(raw_scan.nominal_deg, raw_scan.nominal_deg[-1] + step),
                   recorded_angles_deg=np.append(raw_scan.true_deg, closing_true))
    keys = nikon.read_xtekct(folder / "scan.xtekct")
    n = len(raw_scan.nominal_deg)
    assert int(keys["Projections"]) == n and (folder / f"scan_{n + 1:04d}.tif").is_file()
    scan = open_scan(folder)
    assert scan.closing_view and scan.n_views == n + 1 and scan.nominal_angles_deg[-1] == 360.0

    angles = estimate_angles(folder, tmp_path, capsys)
    assert len(angles) == n + 1
    assert angles[-1] - angles[0] == pytest.approx(360.3, abs=0.1)


def test_estimate_says_what_it_read_before_the_long_work(raw_scan, tmp_path, capsys, monkeypatch):
    import ctpipe.pipeline
    from ctpipe.cli import main

    step = raw_scan.nominal_deg[1] - raw_scan.nominal_deg[0]
    folder = write(tmp_path / "said", raw_scan, intensities=np.concatenate([raw_scan.intensities,
                                                                            raw_scan.intensities[:1]]),
                   nominal_angles_deg=np.append(raw_scan.nominal_deg, raw_scan.nominal_deg[-1] + step),
                   recorded_angles_deg=np.append(raw_scan.true_deg, raw_scan.true_deg[0] + 360.0), angle_log="ang")
    said = []

    def stop(*args, **kwargs):  # the long work: record what was on stdout by then, and stop
        said.append(capsys.readouterr().out)
        raise KeyboardInterrupt

    monkeypatch.setattr(ctpipe.pipeline.Pipeline, "run", stop)
    assert main(["estimate", str(folder)]) == 130
    lines = said[0].splitlines()
    assert lines[0] == (f"nikon scan {folder}: 121 views (120 and the closing view, 360 deg after view 0, paired "
                        "with it) of 96 x 128 px, pixels 1.6 x 1.6 mm")
    assert lines[1].startswith("geometry: source to axis 130 mm, source to detector 300 mm (magnification 2.308), "
                               "principal point u0 66.25 px, v0 45.50 px")
    assert lines[2] == "nominal angles: 0 .. 360 deg in steps of +3 deg"
    assert lines[3].startswith("logged angles (scan.ang): ") and "turning with the nominal ones" in lines[3]
    assert any("scan.ang counts against AngularStep" in line for line in lines[4:])
