"""Bruker SkyScan scans: what write_bruker saves, open_scan reads back as ctpipe's reference folder does."""

import dataclasses

import numpy as np
import pytest
import tifffile

from ctpipe.errors import ConfigError, InputError
from ctpipe.geometry import Geometry
from ctpipe.io import bruker
from ctpipe.io.bruker import detect
from ctpipe.io.scans import open_scan
from ctpipe.testing import write_bruker
from ctpipe.testing.bruker import DEFAULT_REFERENCE_INTENSITY, flat_correct

from scan_helpers import estimate_angles, write_reference


def saved_counts(folder, n_views, prefix="scan_"):
    """The projections as the SkyScan folder stores them (uint16, flat-corrected)."""
    return np.stack([tifffile.imread(folder / f"{prefix}{i:08d}.tif") for i in range(n_views)])


def reversed_scan(raw):
    """The same acquisition played backwards: the object turns clockwise, ctpipe angles decrease."""
    return dataclasses.replace(raw, nominal_deg=raw.nominal_deg[::-1].copy(), true_deg=raw.true_deg[::-1].copy(),
                               intensities=raw.intensities[::-1].copy())


def small_scan(folder, n_views=6, rows=8, cols=10, **changes):
    """A tiny SkyScan folder (no estimation), for the log's keys and the hostile inputs."""
    geometry = Geometry(100.0, 250.0, cols, rows, 0.05, 0.05, u0_px=4.0, v0_px=3.0)
    rng = np.random.default_rng(1)
    flats = np.full((2, rows, cols), 10000.0)
    counts = rng.integers(2000, 9000, size=(n_views, rows, cols)).astype(np.uint16)
    args = dict(geometry=geometry, nominal_angles_deg=np.arange(n_views) * 2.0, intensities=counts, flats=flats)
    return write_bruker(folder, **{**args, **changes})


def log_text(folder, name="scan_.log"):
    """The log as written, line ends included (SkyScan writes Windows text)."""
    return (folder / name).read_bytes().decode("latin-1")


def edit_log(folder, old, new, name="scan_.log"):
    log = folder / name
    text = log_text(folder, name)
    assert old in text
    log.write_bytes(text.replace(old, new).encode("latin-1"))


def test_a_skyscan_scan_reads_back_with_the_simulation_geometry_angles_and_pixels(raw_scan, tmp_path):
    folder = write_bruker(tmp_path / "skyscan", geometry=raw_scan.geometry, nominal_angles_deg=raw_scan.nominal_deg,
                          recorded_angles_deg=raw_scan.true_deg, intensities=raw_scan.intensities,
                          flats=raw_scan.flats, darks=raw_scan.darks)
    log = log_text(folder)
    # The off-centre principal point (66.25, 45.5) travels through SkyScan's own offset keys.
    assert "Optical Axis (line)=45.5\r\n" in log and "Postalignment=-2.75\r\n" in log
    assert "Rotation Direction=CW" in log and "Flat Field Correction=ON" in log

    opened = open_scan(folder)
    assert opened.format == "bruker" and opened.geometry == raw_scan.geometry and opened.notes == ()
    np.testing.assert_array_equal(opened.nominal_angles_deg, raw_scan.nominal_deg)
    # The 2214's .info logs every view but the first, which is taken at the start angle.
    assert opened.angle_log == folder / "scan_.info"
    np.testing.assert_array_equal(opened.recorded_angles_deg[1:], raw_scan.true_deg[1:])
    assert opened.recorded_angles_deg[0] == raw_scan.nominal_deg[0]

    stored = saved_counts(folder, len(raw_scan.nominal_deg))
    np.testing.assert_array_equal(stored, flat_correct(raw_scan.intensities, raw_scan.flats, raw_scan.darks))
    reference = open_scan(write_reference(tmp_path / "ref", raw_scan, stored, white_level=DEFAULT_REFERENCE_INTENSITY))
    np.testing.assert_array_equal(np.asarray(opened.projections), np.asarray(reference.projections))


def test_the_estimate_is_the_reference_folders_and_turns_the_way_the_nominal_angles_do(raw_scan, tmp_path, capsys):
    folder = write_bruker(tmp_path / "skyscan", geometry=raw_scan.geometry, nominal_angles_deg=raw_scan.nominal_deg,
                          recorded_angles_deg=raw_scan.true_deg, intensities=raw_scan.intensities,
                          flats=raw_scan.flats, darks=raw_scan.darks)
    reference = write_reference(tmp_path / "ref", raw_scan, saved_counts(folder, len(raw_scan.nominal_deg)),
                                white_level=DEFAULT_REFERENCE_INTENSITY, geometry=open_scan(folder).geometry)
    estimate = estimate_angles(folder, tmp_path, capsys)
    np.testing.assert_array_equal(estimate, estimate_angles(reference, tmp_path, capsys))
    # The images turn +3 deg a view, as the reader's nominal angles say (a flipped sign gives -3).
    assert np.polyfit(np.arange(len(estimate)), estimate, 1)[0] == pytest.approx(3.0, rel=0.05)
    assert np.mean(np.diff(estimate) > 0) > 0.95
    recorded = open_scan(folder).recorded_angles_deg - raw_scan.nominal_deg
    nominal = raw_scan.nominal_deg - raw_scan.nominal_deg[0]
    assert np.corrcoef(estimate - nominal, recorded - recorded[0])[0, 1] > 0.25


def test_a_scan_turning_the_other_way_is_logged_cc_and_its_estimate_decreases(raw_scan, tmp_path, capsys):
    raw = reversed_scan(raw_scan)
    folder = write_bruker(tmp_path / "skyscan", geometry=raw.geometry, nominal_angles_deg=raw.nominal_deg,
                          recorded_angles_deg=raw.true_deg, intensities=raw.intensities, flats=raw.flats,
                          darks=raw.darks)
    log = log_text(folder)
    assert "Rotation Direction=CC" in log and "Rotation Step (deg)=3.000" in log
    assert "Scanning Start Angle=-357.000" in log
    # In the scanner's sense the turntable goes forwards: the .info angles increase from -357.
    achieved = [float(line.rsplit(" ", 1)[-1][:-1]) for line in log_text(folder, "scan_.info").splitlines()[1:]]
    np.testing.assert_array_equal(achieved, -raw.true_deg[1:])
    opened = open_scan(folder)
    np.testing.assert_array_equal(opened.nominal_angles_deg, raw.nominal_deg)
    np.testing.assert_array_equal(opened.recorded_angles_deg[1:], raw.true_deg[1:])
    estimate = estimate_angles(folder, tmp_path, capsys)
    assert np.polyfit(np.arange(len(estimate)), estimate, 1)[0] == pytest.approx(-3.0, rel=0.05)
    errors = estimate - (raw.true_deg - raw.true_deg[0])
    assert np.sqrt(np.mean((errors - np.median(errors)) ** 2)) < 3.0
    # The estimate follows the logged jitter (0.4 deg), not its mirror: the fast pipeline pins 120 views
    # of 96 x 128 pixels to about a degree, so the correlation is modest (0.39), but far from 0 or < 0.
    nominal = opened.nominal_angles_deg - opened.nominal_angles_deg[0]
    recorded = opened.recorded_angles_deg - opened.recorded_angles_deg[0]
    assert np.corrcoef(estimate - nominal, recorded - nominal)[0, 1] > 0.25


def test_rotation_direction_cc_negates_the_steps_and_is_assumed_when_absent(tmp_path):
    folder = small_scan(tmp_path / "s")
    np.testing.assert_array_equal(open_scan(folder).nominal_angles_deg, np.arange(6) * 2.0)
    edit_log(folder, "Rotation Direction=CW", "Rotation Direction=CC")
    np.testing.assert_array_equal(open_scan(folder).nominal_angles_deg, -np.arange(6) * 2.0)
    edit_log(folder, "Rotation Direction=CC\r\n", "")
    opened = open_scan(folder)
    np.testing.assert_array_equal(opened.nominal_angles_deg, -np.arange(6) * 2.0)
    assert any("no Rotation Direction" in note for note in opened.notes)
    turned = bruker.open_bruker(folder, rotation_direction="CW")
    np.testing.assert_array_equal(turned.nominal_angles_deg, np.arange(6) * 2.0)
    with pytest.raises(InputError, match="rotation_direction: must be 'CC', 'CW' or None"):
        bruker.open_bruker(folder, rotation_direction="ccw")


def test_the_achieved_angles_of_a_2214_info_file_become_the_recorded_angles(tmp_path):
    folder = small_scan(tmp_path / "s")  # CW, 6 views of 2 deg
    # Only this is known of the real file: lines holding "achieved angle" end with the angle (and a unit
    # sign), views 1 .. N-1, then the reference views of the drift compensation.
    views = [f"Projection {i}: target {2 * i}.0000\u00b0, achieved angle {2.01 * i:.4f}\u00b0" for i in range(1, 6)]
    lines = ["Scan started", *views, "Drift compensation scan", "Projection 0: achieved angle 0.5000\u00b0"]
    (folder / "scan_.info").write_bytes("\r\n".join(lines).encode("latin-1"))
    opened = open_scan(folder)
    np.testing.assert_allclose(opened.recorded_angles_deg, [0, 2.01, 4.02, 6.03, 8.04, 10.05], atol=1e-12)
    edit_log(folder, "Rotation Direction=CW", "Rotation Direction=CC")
    np.testing.assert_allclose(open_scan(folder).recorded_angles_deg, -np.array([0, 2.01, 4.02, 6.03, 8.04, 10.05]),
                               atol=1e-12)
    (folder / "scan_.info").write_bytes("\r\n".join(lines[:4]).encode("latin-1"))
    opened = open_scan(folder)
    assert opened.recorded_angles_deg is None and opened.angle_log is None
    assert any("3 'achieved angle' lines for 6 views" in note for note in opened.notes)
    turned = "\r\n".join(f"Projection {i}: achieved angle {2 * i + 180}.0000\u00b0" for i in range(1, 6))
    (folder / "scan_.info").write_bytes(turned.encode("latin-1"))
    assert any("stray up to 180 deg" in note for note in open_scan(folder).notes)
    (folder / "scan_.info").write_bytes(b"Projection 1: achieved angle\r\n")
    with pytest.raises(ConfigError, match=r"scan_\.info: line 1: an 'achieved angle' line must end with the angle"):
        open_scan(folder)


def test_optical_axis_and_postalignment_give_the_principal_point(tmp_path):
    folder = small_scan(tmp_path / "s")  # 8 x 10, u0 4.0 -> Postalignment 0.50, v0 3
    assert open_scan(folder).geometry.u0_px == 4.0
    edit_log(folder, "Optical Axis (line)=    3", "Optical Axis (line)=  6")
    edit_log(folder, "Postalignment=0.50", "Postalignment=-1.50")
    geometry = open_scan(folder).geometry
    assert (geometry.u0_px, geometry.v0_px) == (4.5 + 1.5, 6.0)
    edit_log(folder, "[Reconstruction]\r\nPostalignment=-1.50\r\n", "")
    opened = open_scan(folder)
    assert opened.geometry.u0_px == 4.5 and any("Postalignment" in note for note in opened.notes)


def test_image_rotation_is_said_with_its_lean_over_the_rows_and_not_applied(tmp_path):
    folder = small_scan(tmp_path / "s")  # 8 rows; the writer logs Image Rotation=0.00000: no note
    assert not any("Image Rotation" in note for note in open_scan(folder).notes)
    before = open_scan(folder).geometry
    edit_log(folder, "Image Rotation=0.00000", "Image Rotation=-30.0")  # large, so that 8 rows lean 4.6 px
    opened = open_scan(folder)
    assert opened.geometry == before
    assert any("Image Rotation=-30 deg" in note and "not applied" in note and "over the 8 rows the axis would "
               "lean 4.6 px" in note for note in opened.notes)
    edit_log(folder, "Image Rotation=-30.0", "Image Rotation=tilted")
    opened = open_scan(folder)  # never applied, so a broken value is said, not refused
    assert opened.geometry == before and any("Image Rotation='tilted' is not a number" in n for n in opened.notes)


def test_a_sub_scan_takes_its_own_post_alignment(tmp_path):
    folder = small_scan(tmp_path / "s", prefix="part~01")
    edit_log(folder, "Postalignment=0.50", "Sub-scan post alignment [0]=0.000000\r\n"
             "Sub-scan post alignment [1]=1.500000", name="part~01.log")
    assert open_scan(folder).geometry.u0_px == 4.5 - 1.5


def test_the_pitch_is_nrecons_image_pixel_size_and_a_camera_pixel_that_disagrees_is_said(tmp_path):
    folder = small_scan(tmp_path / "s")  # 0.05 mm at SDD 250, SOD 100: Image Pixel Size 20 um
    assert "Image Pixel Size (um)=20.000000" in log_text(folder)
    edit_log(folder, "Camera Pixel Size (um)=50.00", "Camera Pixel Size (um)=27.00")
    edit_log(folder, "Camera binning=1x1", "Camera binning=2x2")
    opened = open_scan(folder)
    assert opened.geometry.pixel_pitch_u_mm == opened.geometry.pixel_pitch_v_mm == 0.05
    assert any("Camera Pixel Size x binning is 54 um" in note for note in opened.notes)


def test_opening_reads_the_log_and_one_view_only(tmp_path, monkeypatch):
    import ctpipe.io.arrays

    folder = small_scan(tmp_path / "s")
    calls = []
    real = ctpipe.io.arrays.read_array
    monkeypatch.setattr(ctpipe.io.arrays, "read_array", lambda *a, **k: calls.append(a) or real(*a, **k))
    opened = open_scan(folder)
    assert len(calls) == 1
    opened.projections[4]
    assert len(calls) == 2


@pytest.mark.parametrize("old, new, error, message", [
    ("Camera binning=1x1", "Camera binning 1x1", ConfigError, r"scan_\.log: line 15: .* neither '\[Section\]'"),
    ("Object to Source (mm)=100.00000\r\n", "", ConfigError, r"scan_\.log: \[Acquisition\] Object to Source \(mm\): "
                                                             r"missing"),
    ("Rotation Step (deg)=2.000", "Rotation Step (deg)=two", ConfigError, r"\] Rotation Step \(deg\): must be a "
                                                                           r"number"),
    ("Rotation Step (deg)=2.000", "Rotation Step (deg)=0", ConfigError, r"Rotation Step \(deg\): must be a finite "
                                                                         r"number > 0"),
    ("Rotation Direction=CW", "Rotation Direction=UP", ConfigError, r"\] Rotation Direction: must be CC or CW"),
    ("Camera to Source (mm)=250.00000", "Camera to Source (mm)=90", ConfigError, r"must exceed Object to Source"),
    ("Number Of Rows=    8", "Number Of Rows=eight", ConfigError, r"\] Number of Rows: must be a whole number"),
    ("Number Of Files=    6", "Number Of Files=7", InputError, r"scan_00000006\.tif: no such file; scan_\.log says "
                                                               r"Number of Files=7"),
    ("Number Of Files=    6", "Number Of Files=5", InputError, r"scan_00000005\.tif: exists, but .*scan_\.log says "
                                                               r"Number of Files=5"),
    ("Image Format=TIFF", "Image Format=BMP", InputError, r"scan_\.log: \[Acquisition\] Image Format=BMP"),
    ("Flat Field Correction=ON", "Flat Field Correction=MAYBE", ConfigError, r"Flat Field Correction: must be ON"),
])
def test_a_bad_log_is_refused_naming_the_file_and_the_key(tmp_path, old, new, error, message):
    folder = small_scan(tmp_path / "s")
    edit_log(folder, old, new)
    with pytest.raises(error, match=message):
        open_scan(folder)


def test_missing_projections_and_wrong_image_sizes_are_refused_naming_the_file(tmp_path):
    folder = small_scan(tmp_path / "s")
    (folder / "scan_00000003.tif").unlink()
    with pytest.raises(InputError, match=r"scan_00000003\.tif: no such file; scan_\.log says Number of Files=6 but "
                                         r"only 3"):
        open_scan(folder)
    folder = small_scan(tmp_path / "t")
    tifffile.imwrite(folder / "scan_00000002.tif", np.ones((7, 10), np.uint16))
    opened = open_scan(folder)
    with pytest.raises(InputError, match=r"scan_00000002\.tif: is an image of shape \(7, 10\) but scan_\.log says "
                                         r"Number of Rows=8, Number of Columns=10"):
        opened.projections[2]
    tifffile.imwrite(folder / "scan_00000000.tif", np.ones((8, 11), np.uint16))
    with pytest.raises(InputError, match=r"scan_00000000\.tif: is an image of shape \(8, 11\)"):
        open_scan(folder)


def test_a_folder_with_several_logs_asks_for_one_and_the_log_itself_opens(tmp_path):
    folder = small_scan(tmp_path / "s", prefix="part~00")
    (folder / "part.log").write_bytes((folder / "part~00.log").read_bytes())
    assert detect(folder) and detect(folder / "part.log")
    with pytest.raises(InputError, match=r"holds 2 SkyScan logs \(part\.log, part~00\.log\); .* open one of them"):
        open_scan(folder)
    opened = open_scan(folder / "part.log")
    assert opened.format == "bruker" and opened.metadata["prefix"] == "part~00" and len(opened.projections) == 6


def test_detect_wants_a_log_that_starts_with_system(tmp_path):
    (tmp_path / "notes.log").write_text("2024-01-01 started\n[System]\n[Acquisition]\n")
    assert not detect(tmp_path) and not detect(tmp_path / "notes.log")
    (tmp_path / "scan.log").write_text("[System]\nScanner=SkyScan1272\n[Acquisition]\nNumber Of Files=1\n")
    assert detect(tmp_path / "scan.log")
    with pytest.raises(ConfigError, match=r"scan\.log: \[Acquisition\] Number of Rows: missing"):
        open_scan(tmp_path / "scan.log")


def test_the_writer_refuses_what_a_skyscan_cannot_record(tmp_path):
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("x")
    with pytest.raises(InputError, match="exists and is not an empty folder"):
        small_scan(tmp_path / "full")
    with pytest.raises(InputError, match="recorded_angles_deg: must be None or 6 finite angles"):
        small_scan(tmp_path / "a", recorded_angles_deg=np.arange(5.0))
    with pytest.raises(InputError, match="must be evenly spaced"):
        small_scan(tmp_path / "b", nominal_angles_deg=np.array([0, 1, 2, 4, 5, 6.0]))
    with pytest.raises(InputError, match="one pixel size"):
        small_scan(tmp_path / "c", geometry=Geometry(100.0, 250.0, 10, 8, 0.05, 0.06))
    assert not any(p.name.startswith(("a", "b", "c")) for p in tmp_path.iterdir())


def test_flat_correction_scales_to_the_white_level_as_the_scanner_saves_it():
    counts = np.array([[[1100, 600, 5]]], np.uint16)
    flats = np.array([[[2100, 1100, 100]], [[2100, 1100, 100]]])
    darks = np.array([[[100, 100, 100]]])
    np.testing.assert_array_equal(flat_correct(counts, flats, darks, white_level=1000.0), [[[500, 500, 1000]]])
    assert flat_correct(np.full((1, 1, 1), 70000), np.ones((1, 1)), white_level=60000.0)[0, 0, 0] == 65535


def test_the_module_registers_the_format():
    from ctpipe.plugins import get_formats

    assert get_formats()["bruker"].open is bruker.open_bruker
