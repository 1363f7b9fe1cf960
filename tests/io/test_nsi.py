"""North Star Imaging efX-CT projects: the real .nsipro of ../shared/real-metadata, a small self-made one, and bad input."""

import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import tifffile

import ctpipe.io.nsi  # noqa: F401 (registers the format)
from ctpipe.cli import main
from ctpipe.errors import ConfigError, InputError
from ctpipe.io.nsi import detect, open_nsi, read_nsipro
from ctpipe.io.scans import open_scan

ROOT = Path(__file__).resolve().parents[2]
REAL_METADATA = Path(os.environ.get("CTPIPE_REAL_METADATA", ROOT.parent / "shared" / "real-metadata"))
REAL_NSIPRO = REAL_METADATA / "meta-cli" / "nsi" / "Plastic Part 6-5-2024.nsipro"
needs_real = pytest.mark.skipif(not REAL_NSIPRO.is_file(),
                                reason=f"real NSI metadata not found at {REAL_NSIPRO} "
                                       "(set CTPIPE_REAL_METADATA to the real-metadata folder)")


def _expected_view(stored, flat, dark, flip_h=False, flip_v=False, clockwise_deg=0):
    """-log((I - dark) / (flat - dark)), oriented as <Correction> says: flips, then clockwise quarter turns."""
    line = -np.log((stored.astype(np.float64) - dark) / (flat.astype(np.float64) - dark))
    if flip_v:
        line = line[::-1, :]
    if flip_h:
        line = line[:, ::-1]
    for _ in range(clockwise_deg // 90):
        line = line[::-1, :].T  # one clockwise quarter turn, written without np.rot90
    return line


# --- (a) the real project -----------------------------------------------------------------------

@pytest.fixture(scope="module")
def real_scan(tmp_path_factory):
    """The real .nsipro beside placeholder radiographs (one TIFF hard-linked 1200 times) and calibration images."""
    if not REAL_NSIPRO.is_file():
        pytest.skip(f"real NSI metadata not found at {REAL_NSIPRO}")
    folder = tmp_path_factory.mktemp("nsi-real") / "Plastic Part 6-5-2024"
    radiographs = folder / "Radiographs-Plastic Part 6-5-2024"
    radiographs.mkdir(parents=True)
    shutil.copyfile(REAL_NSIPRO, folder / REAL_NSIPRO.name)
    rows, cols = 1420, 1420  # <height pixels>, <width pixels>
    rng = np.random.default_rng(3)
    stored = rng.integers(20000, 30000, size=(rows, cols)).astype(np.uint16)
    stored[:10, :40] = 5000  # a dark corner, to see where the orientation takes it
    first = radiographs / "Plastic Part 6-5-2024-radio00000.tif"
    tifffile.imwrite(first, stored)
    for i in range(1, 1200):  # <Numbering start>0, <number>1200; the digit count is this test's choice
        os.link(first, radiographs / f"Plastic Part 6-5-2024-radio{i:05d}.tif")
    corrections = folder / "Corrections"
    corrections.mkdir()
    flat = np.full((rows, cols), 41000, np.uint16)
    dark = np.full((rows, cols), 2800, np.uint16)
    tifffile.imwrite(corrections / "gain0.tif", flat)
    tifffile.imwrite(corrections / "offset.tif", dark)
    return folder, stored, flat, dark


@needs_real
def test_the_real_project_gives_the_geometry_its_calibrated_vectors_say(real_scan):
    folder = real_scan[0]
    scan = open_scan(folder)
    assert scan.format == "nsi" and scan.path == folder and detect(folder) and detect(folder / REAL_NSIPRO.name)
    g = scan.geometry
    # <Geometry><Result>: source 0 0 -381.851307738696, center 0 0 0, normal 0 0 1, horizontal -1 0 0,
    # reference 213.565 212.710883031907 393.681773885091; <Object Radiograph><pitch>0.3 0.3.
    assert g.source_to_object_mm == pytest.approx(381.851307738696, abs=1e-9)
    assert g.source_to_detector_mm == pytest.approx(393.681773885091 + 381.851307738696, abs=1e-9)
    assert (g.pixel_pitch_u_mm, g.pixel_pitch_v_mm) == (0.3, 0.3)
    assert g.u0_px == pytest.approx(213.565 / 0.3, abs=1e-9)
    assert g.v0_px == pytest.approx(212.710883031907 / 0.3, abs=1e-9)
    assert (g.detector_rows, g.detector_cols) == (1420, 1420)  # <width pixels>, <height pixels>, rotated 270
    # The nominal <Setup> distances (382.136, 774.891) are kept, not used.
    assert scan.metadata["setup"] == {"source_to_object_mm": 382.136, "source_to_detector_mm": 774.891}


@needs_real
def test_the_real_project_has_1200_views_of_0_3_deg_counting_up(real_scan):
    folder = real_scan[0]
    scan = open_nsi(folder / REAL_NSIPRO.name)
    # <number>1200, <angleStep>0.3, <clockwise>False: +i * 0.3 deg, no closing view, no angle log.
    assert scan.n_views == 1200 and not scan.closing_view
    np.testing.assert_array_equal(scan.nominal_angles_deg, 0.3 * np.arange(1200))
    assert scan.nominal_angles_deg[-1] == pytest.approx(359.7)
    assert scan.recorded_angles_deg is None and scan.angle_log is None
    assert scan.metadata["clockwise"] is False and scan.metadata["correction_rotate_deg"] == 270
    assert any("leans 0.011 deg" in note and "0.27 px" in note for note in scan.notes)


@needs_real
def test_the_real_project_reads_views_turned_270_deg_with_gain0_and_offset(real_scan):
    folder, stored, flat, dark = real_scan
    scan = open_scan(folder)
    assert scan.metadata["flat"] == str(folder / "Corrections" / "gain0.tif")
    assert scan.metadata["dark"] == str(folder / "Corrections" / "offset.tif")
    view = scan.projections[1199]
    expected = _expected_view(stored, flat, dark, clockwise_deg=270)
    np.testing.assert_allclose(view, expected, rtol=1e-6, atol=1e-6)
    # 270 deg clockwise takes the stored top-left corner (rows 0-9, cols 0-39) to the bottom-left.
    assert view[-40:, :10].min() > 2.8 and view[:40, :10].max() < 1.0 and view[-40:, 10:].max() < 1.0


@needs_real
def test_every_key_of_the_real_project_is_read_by_its_path():
    values = read_nsipro(REAL_NSIPRO)
    assert values["<Object Radiograph><file>"] == r"Radiographs-Plastic Part 6-5-2024\Plastic Part 6-5-2024-radio*.tif"
    assert values["<CT Project Configuration><Technique Configuration><Setup><fixturing>"] == ""
    assert values["<CT Project Configuration><Technique Configuration><Setup><phys filter>"] == '0.040" Cu'
    assert values["<CT Project Configuration><Technique Configuration><Detector><width pixels>"] == "1420"
    assert values["<Volume><file>"] == r"Reconstruction\Plastic Part 6-5-2024.nsihdr"
    assert values["<Geometry><Processed><clockwise>"] == "False"


# --- (b) a small project written here -----------------------------------------------------------

# The real file's structure, cut down to the keys the reader uses and a few it must skip.
TEMPLATE = """<NSI Reconstruction Project>
  <version>2.0
  <Project Name>part
  <Project Folder>D:\\Scans\\part
  <Object Radiograph>
    <file>Radiographs-part\\part-radio*.tif
    <pitch>0.5 0.5
    <sort numerically>False
    <number>{number}
    <angleStep>{step}
  </Object Radiograph>
  <Correction>
    <flipH>True
    <flipV>False
    <rotate>90
  </Correction>
  <Computation>
    <radio binning>1
  </Computation>
  <Geometry>
    <Processed>
      <clockwise>True
    </Processed>
    <Result>
      <source>0 0 -100
      <axis>0 -1 0
      <center>-0.2 0 0
      <reference>1.5 1.5 150
      <normal>0 0 1
      <horizontal>-1 0 0
    </Result>
  </Geometry>
  <CT Project Configuration>
    <Rotation range>360
    <Numbering start>1
    <Technique Configuration>
      <Detector>
        <pixel width microns>500
        <pixel height microns>500
        <width pixels>8
        <height pixels>6
      </Detector>
      <Setup>
        <source to detector distance>250
        <source to table distance>100
        <fixturing>
      </Setup>
    </Technique Configuration>
    <Flat Field Status>
      <Offset>
        <filename>D:\\Scans\\part\\Corrections\\offset.tif
      </Offset>
      <Gain>
        <id>1
        <filename>D:\\Scans\\part\\Corrections\\gain1.tif
      </Gain>
      <Gain>
        <id>0
        <filename>D:\\Scans\\part\\Corrections\\gain0.tif
      </Gain>
    </Flat Field Status>
  </CT Project Configuration>
</NSI Reconstruction Project>
"""
N_VIEWS, STEP = 12, 30.0


def _write_project(folder, *, n_files=N_VIEWS + 1):
    """A 12-view full turn stored as 6 x 8 uint16 radiographs radio0001 .. radio0013 (the last one closes it)."""
    rng = np.random.default_rng(11)
    (folder / "Radiographs-part").mkdir(parents=True)
    (folder / "Corrections").mkdir()
    flat = rng.integers(50000, 60000, size=(6, 8)).astype(np.uint16)
    dark = rng.integers(100, 300, size=(6, 8)).astype(np.uint16)
    tifffile.imwrite(folder / "Corrections" / "gain0.tif", flat)
    tifffile.imwrite(folder / "Corrections" / "offset.tif", dark)
    tifffile.imwrite(folder / "Corrections" / "gain1.tif", np.full((6, 8), 1, np.uint16))  # not the flat
    views = rng.integers(1000, 40000, size=(n_files, 6, 8)).astype(np.uint16)
    for i, view in enumerate(views):
        tifffile.imwrite(folder / "Radiographs-part" / f"part-radio{i + 1:04d}.tif", view)
    text = TEMPLATE.format(number=N_VIEWS, step=f"{STEP:g}")
    (folder / "part.nsipro").write_bytes(text.replace("\n", "\r\n").encode("ascii"))
    return views, flat, dark


@pytest.fixture
def project(tmp_path):
    folder = tmp_path / "part"
    views, flat, dark = _write_project(folder)
    return folder, views, flat, dark


def test_a_written_project_reads_back_pixel_for_pixel(project):
    folder, views, flat, dark = project
    scan = open_scan(folder)
    assert scan.format == "nsi" and scan.projections.shape == (N_VIEWS + 1, 8, 6)  # rotate 90: rows <-> cols
    for i in (0, 5, N_VIEWS):
        expected = _expected_view(views[i], flat, dark, flip_h=True, clockwise_deg=90)
        np.testing.assert_allclose(scan.projections[i], expected, rtol=1e-6, atol=1e-7)
    # The flat is the <Gain> whose <id> is 0, not the first one listed.
    assert scan.metadata["flat"].endswith("gain0.tif")


def test_geometry_from_the_vectors_with_an_axis_off_the_central_ray(project):
    geometry = open_nsi(project[0]).geometry
    assert (geometry.source_to_object_mm, geometry.source_to_detector_mm) == (100.0, 250.0)
    # u0 = (source - reference) . h / pitch + d * SDD / SOD / pitch = 1.5 / 0.5 + 0.2 * 2.5 / 0.5; v0 = 1.5 / 0.5.
    assert geometry.u0_px == pytest.approx(4.0, abs=1e-12) and geometry.v0_px == pytest.approx(3.0, abs=1e-12)
    assert (geometry.detector_cols, geometry.detector_rows) == (6, 8)


def test_clockwise_counts_down_and_the_extra_image_closes_the_turn(project):
    scan = open_nsi(project[0])
    assert scan.closing_view and scan.n_views == N_VIEWS + 1
    np.testing.assert_array_equal(scan.nominal_angles_deg, -STEP * np.arange(N_VIEWS + 1))
    assert scan.nominal_angles_deg[-1] == scan.nominal_angles_deg[0] - 360.0
    assert any("closing view at -360 deg" in note for note in scan.notes)
    assert any("axis passes 0.2 mm off the central ray" in note for note in scan.notes)


def test_without_the_closing_image_there_is_no_closing_view(tmp_path):
    _write_project(tmp_path / "p", n_files=N_VIEWS)
    scan = open_nsi(tmp_path / "p")
    assert not scan.closing_view and scan.n_views == N_VIEWS


def test_clockwise_false_counts_up(project):
    folder = project[0]
    _edit("<clockwise>True", "<clockwise>False")(folder)
    np.testing.assert_array_equal(open_nsi(folder).nominal_angles_deg, STEP * np.arange(N_VIEWS + 1))


def test_the_stack_pickles_and_reads_the_same(project):
    import pickle

    stack = open_nsi(project[0]).projections
    np.testing.assert_array_equal(pickle.loads(pickle.dumps(stack))[3], stack[3])


# --- (c) bad input ------------------------------------------------------------------------------

def _edit(old, new, file="part.nsipro"):
    def edit(folder):
        path = folder / file
        text = path.read_bytes().decode("ascii")
        assert old in text, old
        path.write_bytes(text.replace(old, new, 1).encode("ascii"))
    return edit


def _remove(file):
    return lambda folder: (folder / file).unlink()


def _second_project(folder):
    shutil.copy(folder / "part.nsipro", folder / "other.nsipro")


HOSTILE = [
    (_edit("    <angleStep>30\r\n", ""), ConfigError, r"part.nsipro: <Object Radiograph><angleStep>: missing"),
    (_edit("<angleStep>30", "<angleStep>abc"), ConfigError, r"<Object Radiograph><angleStep>: must be a number > 0, got 'abc'"),
    (_edit("<clockwise>True", "<clockwise>maybe"), ConfigError, r"<Geometry><Processed><clockwise>: must be True or False"),
    (_edit("<rotate>90", "<rotate>45"), ConfigError, r"<Correction><rotate>: must be 0, 90, 180 or 270"),
    (_edit("<axis>0 -1 0", "<axis>1 -0.2 0"), ConfigError, r"<Geometry><Result><axis>: the rotation axis must run along"),
    (_edit("<source>0 0 -100", "<source>0 0"), ConfigError, r"<Geometry><Result><source>: must be 3 numbers"),
    (_edit("<width pixels>8", "<width pixels>"), ConfigError, r"<Detector><width pixels>: must be an integer >= 1"),
    (_edit("</NSI Reconstruction Project>", ""), ConfigError, r"part.nsipro: ends before </NSI Reconstruction Project>"),
    (_edit("  </Correction>", "  </Corection>"), ConfigError, r"part.nsipro: line \d+: '</Corection>' closes no open"),
    (_edit("<NSI Reconstruction Project>", "<Other Project>"), ConfigError, r"starts with <Other Project>, not <NSI"),
    (_edit("<id>0", "<id>2"), ConfigError, r"<Flat Field Status><Gain> with <id>0: missing"),
    (_remove("Radiographs-part/part-radio0004.tif"), InputError, r"part-radio0004.tif: no such file; <Object Radiograph><number>=12"),
    (_edit("<number>12", "<number>14"), InputError, r"part-radio0014.tif: no such file; <Object Radiograph><number>=14 in part.nsipro but only 13"),
    (_edit("<number>12", "<number>10"), InputError, r"part-radio0011.tif: exists, but <Object Radiograph><number>=10"),
    (_edit("<Numbering start>1", "<Numbering start>0"), InputError, r"part-radio0000.tif: no such file"),
    (_edit("Radiographs-part\\part", "Radiographs-gone\\part"), InputError, r"Radiographs-gone: no such folder \(<Object Radiograph><file>"),
    (_remove("Corrections/gain0.tif"), InputError, r"gain0.tif: no such file \(<CT Project Configuration><Flat Field Status><Gain><filename>"),
    (_edit("<source>0 0 -100", "<source>0 0 200"), ConfigError, r"<center> must lie beyond <source>"),
    (_second_project, InputError, r"part: holds 2 .nsipro files \(other.nsipro, part.nsipro\)"),
]


@pytest.mark.parametrize("mutate, error, match", HOSTILE, ids=[str(i) for i in range(len(HOSTILE))])
def test_bad_input_is_one_line_naming_the_file_and_the_key(project, mutate, error, match):
    folder = project[0]
    mutate(folder)
    with pytest.raises(error, match=match) as info:
        open_nsi(folder)
    assert "\n" not in str(info.value)


def test_a_radiograph_of_the_wrong_size_is_named_when_read(project):
    folder = project[0]
    tifffile.imwrite(folder / "Radiographs-part" / "part-radio0005.tif", np.zeros((6, 7), np.uint16))
    scan = open_nsi(folder)
    with pytest.raises(InputError, match=r"part-radio0005.tif: must be a 6 x 8 image \(<height pixels> x <width "
                                         r"pixels> in .*part.nsipro\), got shape \(6, 7\)"):
        scan.projections[4]


def test_a_calibration_image_of_the_wrong_size_is_refused_at_open(project):
    folder = project[0]
    tifffile.imwrite(folder / "Corrections" / "offset.tif", np.zeros((8, 6), np.uint16))
    with pytest.raises(InputError, match=r"offset.tif: must be a 6 x 8 image"):
        open_nsi(folder)


def test_detect_looks_at_names_only(project, tmp_path):
    folder = project[0]
    assert detect(folder) and detect(folder / "part.nsipro")
    assert not detect(folder / "Radiographs-part") and not detect(tmp_path / "nope")


def test_cli_says_what_is_wrong_in_one_line_and_writes_nothing(project, tmp_path, capsys):
    folder = project[0]
    _edit("    <angleStep>30\r\n", "")(folder)
    out = tmp_path / "out"
    assert main(["estimate", str(folder), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "part.nsipro: <Object Radiograph><angleStep>: missing" in err[0]
    assert not out.exists()
