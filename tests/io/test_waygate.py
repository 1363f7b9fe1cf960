"""GE/Waygate phoenix datos|x scans: written as the scanner writes them, read back as ctpipe's reference reads."""

import shutil

import numpy as np
import pytest
import tifffile

import ctpipe.io.waygate  # noqa: F401 (registers the format)
from ctpipe.cli import main
from ctpipe.errors import ConfigError, InputError
from ctpipe.io.scans import open_scan
from ctpipe.io.waygate import detect, open_waygate, write_waygate_angles
from ctpipe.testing import write_waygate

from scan_helpers import estimate_angles, write_reference

#: RotPos has 3 decimals in a .pcp, as datos|x writes it.
ROTPOS_ATOL = 5e-4 + 1e-9


def _write(raw, folder, **kwargs):
    return write_waygate(folder, geometry=raw.geometry, nominal_angles_deg=raw.nominal_deg,
                         recorded_angles_deg=raw.true_deg, intensities=raw.intensities, flats=raw.flats,
                         darks=raw.darks, **kwargs)


def _stored(folder, n_views, name="scan"):
    return np.stack([tifffile.imread(folder / f"{name}{i:05d}.tif") for i in range(1, n_views + 1)])


def _free_ray(folder, name="scan"):
    text = (folder / f"{name}.pca").read_bytes().decode("latin-1")
    line = next(x for x in text.splitlines() if x.startswith("FreeRay="))
    return float(line.split("=")[1])


@pytest.fixture(scope="module")
def scan(raw_scan, tmp_path_factory):
    # Detector shift on: NrPixelsX = DimX + 10, so a reader that took NrPixelsX for the width would fail.
    return _write(raw_scan, tmp_path_factory.mktemp("waygate") / "scan", detector_shift_px=5)


@pytest.fixture
def copy(scan, tmp_path):
    return shutil.copytree(scan, tmp_path / "scan")


def test_a_written_scan_reads_back_with_the_geometry_angles_and_pixels_of_the_reference(raw_scan, scan, tmp_path):
    opened = open_scan(scan)
    n = len(raw_scan.nominal_deg)
    assert opened.format == "waygate" and opened.path == scan
    assert opened.geometry == raw_scan.geometry  # 8 decimals in the .pca hold these values exactly
    # A full turn: image 121 at RotPos = first + 360 is read as the closing view.
    assert opened.closing_view and opened.n_views == n + 1
    np.testing.assert_array_equal(opened.nominal_angles_deg[:n], raw_scan.nominal_deg)
    assert opened.nominal_angles_deg[n] == raw_scan.nominal_deg[0] + 360.0
    np.testing.assert_allclose(opened.recorded_angles_deg[:n], raw_scan.true_deg, rtol=0, atol=ROTPOS_ATOL)
    assert opened.recorded_angles_deg[n] == pytest.approx(raw_scan.true_deg[0] + 360.0, abs=ROTPOS_ATOL)
    assert opened.angle_log == scan / "scan.pcp" and opened.true_angles_deg is None
    # The scanner stores offset/gain-corrected counts at the FreeRay level (its own flat correction).
    stored, free_ray = _stored(scan, n), _free_ray(scan)
    flat, dark = raw_scan.flats.mean(axis=0), raw_scan.darks.mean(axis=0)
    expected = (raw_scan.intensities - dark) / (flat - dark) * free_ray
    assert np.abs(stored - expected).max() <= 0.5 + 1e-9
    reference = open_scan(write_reference(tmp_path / "ref", raw_scan, stored, white_level=free_ray))
    assert reference.projections.shape == (n, *opened.projections.shape[1:])
    for view in range(n):
        np.testing.assert_array_equal(opened.projections[view], reference.projections[view])
    np.testing.assert_array_equal(opened.projections[n], reference.projections[0])


def test_estimate_equals_the_reference_and_moves_with_the_angle_log(raw_scan, copy, tmp_path, capsys):
    # Without its closing image the scan is the reference's 120 views (the closing view's pairing is the pair
    # graph's, tested there).
    (copy / "scan00121.tif").unlink()
    stored, free_ray = _stored(copy, len(raw_scan.nominal_deg)), _free_ray(copy)
    reference = write_reference(tmp_path / "ref", raw_scan, stored, white_level=free_ray)
    estimate = estimate_angles(copy, tmp_path, capsys)
    np.testing.assert_array_equal(estimate, estimate_angles(reference, tmp_path, capsys))
    # Sign: the images turn the way the nominal angles count (slope +1, not -1), and their
    # view-to-view steps follow the RotPos log as read (a reader that negated RotPos would give a
    # correlation near -0.6). The steps, not the departures from nominal: this fast pipeline's
    # error (about 1.3 deg RMS) accumulates over the turn and exceeds the 0.4 deg jitter, so the
    # departures correlate only about 0.36.
    opened = open_waygate(copy)
    assert not opened.closing_view and opened.n_views == len(raw_scan.nominal_deg)
    nominal = opened.nominal_angles_deg - opened.nominal_angles_deg[0]
    recorded = opened.recorded_angles_deg - opened.recorded_angles_deg[0]
    assert np.polyfit(nominal, estimate, 1)[0] > 0.9
    assert np.corrcoef(np.diff(estimate), np.diff(recorded))[0, 1] > 0.5
    assert np.corrcoef(estimate - nominal, recorded - nominal)[0, 1] > 0.2


def test_the_off_centre_principal_point_survives_cx_cy_and_the_detector_shift_margin(raw_scan, scan):
    text = (scan / "scan.pca").read_text()
    assert "cx=66.25000000" in text and "cy=45.50000000" in text
    assert "NrPixelsX=138" in text and "DimX=128" in text and "Amplitude=5" in text
    geometry = open_waygate(scan / "scan.pca").geometry  # the .pca itself opens the same scan
    assert (geometry.u0_px, geometry.v0_px) == (66.25, 45.5) != ((128 - 1) / 2, (96 - 1) / 2)
    assert geometry.detector_cols == 128 and geometry.detector_rows == 96


def test_a_full_turn_has_one_image_more_at_360_read_as_the_closing_view_when_it_is_there(raw_scan, copy):
    assert (copy / "scan00121.tif").is_file() and not (copy / "scan00122.tif").exists()
    np.testing.assert_array_equal(tifffile.imread(copy / "scan00121.tif"), tifffile.imread(copy / "scan00001.tif"))
    last = (copy / "scan.pcp").read_text().splitlines()[-1].split("\t")
    assert last[0] == "121" and float(last[1]) == pytest.approx(raw_scan.true_deg[0] + 360, abs=ROTPOS_ATOL)
    opened = open_waygate(copy)
    assert opened.closing_view and opened.n_views == 121
    assert opened.nominal_angles_deg[-1] == 360.0 and opened.recorded_angles_deg[-1] == float(last[1])
    # Without its file: the 120 views of NumberImages, as before.
    (copy / "scan00121.tif").rename(copy / "kept.tif")
    opened = open_waygate(copy)
    assert not opened.closing_view and opened.n_views == 120 and len(opened.recorded_angles_deg) == 120
    # With its file but no .pcp row for it: not read, and said.
    (copy / "kept.tif").rename(copy / "scan00121.tif")
    pcp = (copy / "scan.pcp").read_bytes()
    (copy / "scan.pcp").write_bytes(pcp[:pcp.rstrip().rindex(b"\r\n") + 2])
    opened = open_waygate(copy)
    assert not opened.closing_view and opened.n_views == 120
    assert any("scan00121.tif closes the turn, but scan.pcp has no row ImgNr 121" in note for note in opened.notes)
    # Not a full turn: image NumberImages + 1 does not repeat image 1, and is not read.
    _edit("RotationSector=360.00000000", "RotationSector=180.00000000")(copy)
    opened = open_waygate(copy)
    assert not opened.closing_view and opened.n_views == 120 and opened.nominal_angles_deg[-1] == 119 * 1.5
    assert any("scan00121.tif (image NumberImages + 1) is not read" in note for note in opened.notes)


def test_reads_settings_and_protocol_laid_out_as_datos_x_writes_them(copy):
    # Windows ANSI text with a micro sign, sections ctpipe does not read, empty values, and a
    # protocol with a space inside its Time column, as in the public datos|x 2.4.0 files.
    pca = copy / "scan.pca"
    text = pca.read_text().replace("SystemName=ctpipe simulation", "SystemName=GE Phoenix v|tome|x m \u00b5CT")
    text += "\r\n[AutoScO]\r\nActive=1\r\nImageString=30:60:90:120\r\n\r\n[Net]\r\nEnable=0\r\nIP=\r\n"
    pca.write_bytes(text.encode("latin-1"))
    pcp = copy / "scan.pcp"
    lines = pcp.read_text().splitlines()
    assert lines[1].split("\t")[-1] == "Time" and " " in lines[2].split("\t")[-1]
    pcp.write_text("\n".join(lines) + "\n")  # LF line ends read as well as CRLF
    opened = open_scan(copy)
    assert opened.format == "waygate" and opened.metadata["settings"]["[Image] FreeRay"] == str(int(_free_ray(copy)))


def test_calib_value_is_reported_not_applied_and_a_missing_log_is_said(raw_scan, tmp_path):
    folder = _write(raw_scan, tmp_path / "s", calib_value=28.524)
    opened = open_waygate(folder)
    assert opened.geometry.u0_px == 66.25 and opened.metadata["calib_value"] == 28.524
    # 28.524 px of 1.6 mm at magnification 300 / 130: 19.777 mm at the object.
    note = next(note for note in opened.notes if "CalibValue" in note)
    assert "CalibValue=28.524" in note and "not applied" in note and "19.777 mm" in note
    assert "cx +28.524 or cx -28.524" in note
    (folder / "s.pcp").unlink()
    opened = open_waygate(folder)
    assert opened.recorded_angles_deg is None and opened.angle_log is None
    assert opened.closing_view  # the closing view needs its image, not the protocol
    assert any("no s.pcp" in note for note in opened.notes)


def test_corrected_angles_are_written_as_a_new_protocol_the_reader_reads(raw_scan, copy, tmp_path):
    corrected = raw_scan.true_deg - raw_scan.true_deg[0] + 0.0123
    out = write_waygate_angles(tmp_path / "corrected.pcp", corrected)
    with pytest.raises(InputError, match="corrected.pcp: exists; .* never overwritten"):
        write_waygate_angles(out, corrected)
    with pytest.raises(InputError, match="must be a .pcp file name"):
        write_waygate_angles(tmp_path / "corrected.txt", corrected)
    with pytest.raises(InputError, match="angles_deg: angles must be finite"):
        write_waygate_angles(tmp_path / "nan.pcp", [0.0, np.nan])
    shutil.copy(out, copy / "scan.pcp")
    np.testing.assert_allclose(open_waygate(copy).recorded_angles_deg, corrected, rtol=0, atol=ROTPOS_ATOL)


def test_corrected_angles_go_back_with_as_many_rows_as_the_scanners_protocol(raw_scan, copy):
    from ctpipe.plugins import get_formats

    write = get_formats()["waygate"].corrected_angle_log
    scanner_rows = (copy / "scan.pcp").read_text().splitlines()[2:]
    opened = open_waygate(copy)  # with its closing view: 121 views, 121 rows
    corrected = np.append(raw_scan.true_deg, raw_scan.true_deg[0] + 359.9) + 0.01
    name, data = write(opened, corrected)
    rows = [line.split("\t") for line in data.decode("ascii").splitlines()[2:]]
    assert name == "scan.pcp" and len(rows) == len(scanner_rows) == 121
    np.testing.assert_allclose([float(r[1]) for r in rows], corrected, rtol=0, atol=ROTPOS_ATOL)
    # Read without the closing image (120 views), the row of image 121 is still written: view 0's corrected
    # angle one turn (the scanner's own RotPos step from image 1 to 121) later.
    (copy / "scan00121.tif").unlink()
    opened = open_waygate(copy)
    name, data = write(opened, corrected[:120])
    rows = [line.split("\t") for line in data.decode("ascii").splitlines()[2:]]
    assert [r[0] for r in rows] == [str(i) for i in range(1, 122)]
    step = float(scanner_rows[120].split("\t")[1]) - float(scanner_rows[0].split("\t")[1])
    assert float(rows[120][1]) == pytest.approx(corrected[0] + step, abs=ROTPOS_ATOL)


def test_detect_looks_at_names_and_first_bytes_only(scan, tmp_path):
    assert detect(scan) and detect(scan / "scan.pca")
    assert not detect(scan / "scan00001.tif") and not detect(tmp_path / "nope")
    (tmp_path / "components.pca").write_bytes(b"\x93NUMPY principal components")
    assert not detect(tmp_path) and not detect(tmp_path / "components.pca")


def test_the_writer_refuses_what_a_pca_cannot_say(raw_scan, tmp_path):
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("")
    with pytest.raises(InputError, match="full: exists and is not empty"):
        _write(raw_scan, tmp_path / "full")
    with pytest.raises(InputError, match="nominal_angles_deg: a .pca can only say"):
        write_waygate(tmp_path / "n", geometry=raw_scan.geometry, nominal_angles_deg=raw_scan.true_deg,
                      recorded_angles_deg=None, intensities=raw_scan.intensities, flats=raw_scan.flats)


def _edit(old, new, file="scan.pca"):
    def edit(folder):
        path = folder / file
        text = path.read_bytes().decode("latin-1")  # bytes as they are: CRLF line ends kept
        assert old in text, old
        path.write_bytes(text.replace(old, new, 1).encode("latin-1"))
    return edit


def _remove(file):
    return lambda folder: (folder / file).unlink()


def _resize(folder):
    tifffile.imwrite(folder / "scan00005.tif", np.zeros((95, 128), np.uint16))


def _second_pca(folder):
    shutil.copy(folder / "scan.pca", folder / "other.pca")


HOSTILE = [
    (_edit("[CT]", "this is not ini\n[CT]"), ConfigError, r"scan.pca: line \d+: 'this is not ini' is neither"),
    (_edit("FOD=", "XFOD="), ConfigError, r"scan.pca: \[Geometry\] FOD: missing"),
    (_edit("FDD=300.00000000", "FDD=abc"), ConfigError, r"scan.pca: \[Geometry\] FDD: must be a number > 0, got 'abc'"),
    (_edit("[Xray]", "[Xray]\r\nVoltage=91"), ConfigError, r"scan.pca: line \d+: \[Xray\] voltage appears twice"),
    (_edit("FreeRay=", "FreeRay=0\nOld="), ConfigError, r"\[Image\] FreeRay: must be a number > 0, got '0'"),
    (_edit("NumberImages=120", "NumberImages=130"), InputError, r"scan00122.tif: no such file; \[CT\] NumberImages=130"),
    (_edit("NumberImages=120", "NumberImages=100"), InputError, r"scan00102.tif: exists, but \[CT\] NumberImages=100"),
    (_edit("NumberImages=120", "NumberImages=0"), ConfigError, r"\[CT\] NumberImages: must be an integer >= 1"),
    (_edit("RotationSector=360", "RotationSector=-360"), ConfigError, r"\[CT\] RotationSector: must be in \(0, 360\]"),
    (_edit("MirrorX=0", "MirrorX=1"), ConfigError, r"\[Image\] MirrorX=1: rotated or mirrored images are not read"),
    (_edit("[Trajectory]\r\nActive=0", "[Trajectory]\r\nActive=1"), ConfigError, r"\[Trajectory\] Active=1"),
    (_edit("Binning=0", "Binning=1"), None, None),  # VoxelSizeX gives the pitch: read, with a note
    (lambda f: (_edit("Binning=0", "Binning=1")(f), _edit("VoxelSizeX=", "Old=")(f)), ConfigError,
     r"\[Detector\] Binning=1 without \[Geometry\] VoxelSizeX"),
    (_edit("FOD=130.00000000", "FOD=400.00000000"), InputError, r"scan.pca: geometry: source_to_detector_mm must exceed"),
    (_remove("scan00017.tif"), InputError, r"scan00017.tif: no such file; \[CT\] NumberImages=120 .* only 16"),
    (_second_pca, InputError, r"scan: holds 2 .pca files \(other.pca, scan.pca\)"),
    (_edit("\r\n7\t", "\r\n#7\t", "scan.pcp"), ConfigError, r"scan.pcp: line 9: ImgNr, RotPos, Use must be numbers"),
    (_edit("\r\n7\t", "\r\n6\t", "scan.pcp"), ConfigError, r"scan.pcp: line 9: ImgNr 6 appears twice"),
    (_edit("\r\n7\t", "\r\n700\t", "scan.pcp"), InputError, r"scan.pcp: no row for ImgNr 7; 1 of the 120 images"),
    (_edit("ImgNr\tRotPos", "Nr\tPos", "scan.pcp"), ConfigError, r"scan.pcp: no tab-separated column header"),
]


@pytest.mark.parametrize("mutate, error, match", HOSTILE, ids=[str(i) for i in range(len(HOSTILE))])
def test_hostile_inputs_name_the_file_and_the_key(copy, mutate, error, match):
    mutate(copy)
    if error is None:
        opened = open_waygate(copy)
        assert opened.geometry.pixel_pitch_u_mm == pytest.approx(1.6, rel=1e-7)
        assert any("Binning=1" in note for note in opened.notes)
        return
    with pytest.raises(error, match=match):
        open_waygate(copy)


def test_a_projection_of_the_wrong_size_is_named_when_read(copy):
    _resize(copy)
    opened = open_waygate(copy)
    with pytest.raises(InputError, match=r"scan00005.tif: must be a 96 x 128 image \(\[Image\] DimY x DimX in .*scan.pca\), "
                                         r"got shape \(95, 128\)"):
        opened.projections[4]


def test_cli_says_what_is_wrong_in_one_line(copy, capsys):
    _edit("FOD=", "XFOD=")(copy)
    assert main(["estimate", str(copy)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "scan.pca: [Geometry] FOD: missing" in err[0]
