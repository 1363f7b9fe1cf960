"""Nikon folders as real scanners wrote them (``../shared/real-metadata``), read value by value.

The metadata are byte for byte what Nikon XT H scanners and CT Pro 5.4 wrote; the projections
are placeholders (one small TIFF hard-linked under every name the metadata implies), so only the
reading of names, counts, geometry and angles is tested here. Skipped where the shared folder is
absent (set CTPIPE_REAL_METADATA to point at it elsewhere).
"""

import configparser
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

import ctpipe.io.nikon as nikon
from ctpipe.io.scans import open_scan

ROOT = Path(__file__).resolve().parents[2]
REAL = Path(os.environ.get("CTPIPE_REAL_METADATA", ROOT.parent / "shared" / "real-metadata"))
pytestmark = pytest.mark.skipif(not REAL.is_dir(), reason=f"{REAL} is absent (set CTPIPE_REAL_METADATA)")

LEGO = "meta-cli/nikon/Lego_alignment test_1 [2023-10-18 11.22.08]"
#: (folder, the .xtekct that describes it, the log the scanner wrote)
SETS = [
    ("nerf_data/cube", "ivan-cube.xtekct", "ivan-cube.ang"),
    ("nerf_data/pillars", "pillars.xtekct", "pillars.ang"),
    ("nerf_data/balls", "ivan-balls 3.xtekct", "ivan-balls 3.ang"),
    ("nerf_data/balls7", "ivan-balls-7.xtekct", "_ctdata.txt"),
    (LEGO, "Lego_alignment test_1.xtekct", "_ctdata.txt"),
]


def keys_of(xtekct: Path) -> dict:
    parser = configparser.ConfigParser(interpolation=None)
    parser.optionxform = str
    parser.read_string(xtekct.read_text(encoding="utf-8-sig", errors="replace"))
    return dict(parser["XTekCT"])


def logged_values(log: Path) -> np.ndarray:
    """The angle column of a scanner's log, parsed here independently of the reader."""
    lines = [line for line in log.read_text().splitlines() if line.strip()]
    body = lines[1:] if log.suffix == ".ang" else lines[3:]
    return np.array([float(line.replace(":", " ").split()[1]) for line in body])


def scanner_folder(tmp_path: Path, relative: str, n_images: int | None = None) -> Path:
    """A copy of a real folder's metadata with a placeholder TIFF under every projection name."""
    import tifffile

    folder = shutil.copytree(REAL / relative, tmp_path / Path(relative).name)
    keys = keys_of(next(folder.glob("*.xtekct")))
    log = folder / "_ctdata.txt" if (folder / "_ctdata.txt").exists() else next(folder.glob("*.ang"))
    n_images = len(logged_values(log)) if n_images is None else n_images
    rows, cols = int(keys["DetectorPixelsY"]), int(keys["DetectorPixelsX"])
    placeholder = tmp_path / "placeholder.tif"
    tifffile.imwrite(placeholder, np.full((rows, cols), 1000, np.uint16))
    for i in range(1, n_images + 1):
        os.link(placeholder, folder / f"{keys.get('InputName', keys['Name'])}_{i:04d}.tif")
    return folder


@pytest.mark.parametrize("relative, xtekct, log", SETS, ids=[s[0].split("/")[-1][:12] for s in SETS])
def test_a_real_nikon_folder_reads_as_the_scanner_wrote_it(tmp_path, relative, xtekct, log):
    keys = keys_of(REAL / relative / xtekct)
    values = logged_values(REAL / relative / log)
    projections, initial, step = int(keys["Projections"]), float(keys["InitialAngle"]), float(keys["AngularStep"])
    # Every real set has one log row and one image more than Projections: the image closing the turn.
    assert len(values) == projections + 1

    scan = open_scan(scanner_folder(tmp_path, relative))
    assert scan.format == "nikon" and Path(scan.metadata["xtekct"]).name == xtekct
    g = scan.geometry
    assert g.source_to_object_mm == float(keys["SrcToObject"])
    assert g.source_to_detector_mm == float(keys["SrcToDetector"])
    assert (g.detector_cols, g.detector_rows) == (int(keys["DetectorPixelsX"]), int(keys["DetectorPixelsY"]))
    assert (g.pixel_pitch_u_mm, g.pixel_pitch_v_mm) == (float(keys["DetectorPixelSizeX"]),
                                                         float(keys["DetectorPixelSizeY"]))
    axis_mm = float(keys.get("ObjectOffsetX", 0.0)) * g.source_to_detector_mm / g.source_to_object_mm
    assert g.u0_px == pytest.approx((g.detector_cols - 1) / 2 + axis_mm / g.pixel_pitch_u_mm, abs=1e-9)
    assert g.v0_px == pytest.approx((g.detector_rows - 1) / 2, abs=1e-9)

    # The closing image is a view, nominally one scan (Projections x AngularStep) after view 0.
    assert scan.closing_view and scan.n_views == projections + 1
    np.testing.assert_allclose(scan.nominal_angles_deg, initial + step * np.arange(projections + 1), atol=1e-12)
    assert scan.nominal_angles_deg[-1] - scan.nominal_angles_deg[0] == pytest.approx(projections * step, abs=1e-9)

    # The logs' sense: .ang runs against AngularStep (0, -1.406, ...), _ctdata.txt with it.
    sense = -1 if log.endswith(".ang") else 1
    assert np.sign(values[-1] - values[0]) == sense * np.sign(step)
    assert scan.metadata["angle_log_sense"] == sense and scan.angle_log.name == log
    np.testing.assert_allclose(scan.recorded_angles_deg, initial + sense * values, atol=1e-12)
    # Logged minus nominal: a few hundredths of a degree and a constant start offset, not a turn.
    difference = scan.recorded_angles_deg - scan.nominal_angles_deg
    assert np.ptp(difference) < 0.1 and abs(np.median(difference)) < 0.6


@pytest.mark.parametrize("relative, xtekct, log", SETS, ids=[s[0].split("/")[-1][:12] for s in SETS])
def test_angles_written_back_have_the_rows_and_sense_of_the_scanners_file(tmp_path, relative, xtekct, log):
    scan = open_scan(scanner_folder(tmp_path, relative))
    name, blob = nikon._corrected_angle_log(scan, scan.recorded_angles_deg)
    assert name == f"{keys_of(REAL / relative / xtekct)['Name']}.ang"
    lines = blob.decode("ascii").splitlines()
    values = logged_values(REAL / relative / log)
    assert lines[0] == "Proj\tAngle(deg)" and len(lines) - 1 == len(values)
    written = np.array([float(line.split(":\t")[1]) for line in lines[1:]])
    # Written in the .ang sense (against AngularStep), counted from InitialAngle: for an .ang set
    # the scanner's own values come back; for a _ctdata.txt set, their negatives.
    np.testing.assert_allclose(written, values if log.endswith(".ang") else -values, atol=1e-9)


def test_the_closing_image_missing_from_the_folder_reads_projections_views(tmp_path):
    folder = scanner_folder(tmp_path, "nerf_data/cube", n_images=256)
    scan = open_scan(folder)
    assert not scan.closing_view and scan.n_views == 256
    assert scan.recorded_angles_deg[-1] == pytest.approx(358.593, abs=1e-12)
    assert any("row 257 for an image that closes the turn, which is not in the folder" in n for n in scan.notes)
    # Written back, the .ang has the scanner's 257 rows all the same, the last one turn after the first.
    name, blob = nikon._corrected_angle_log(scan, scan.recorded_angles_deg)
    lines = blob.decode("ascii").splitlines()
    assert len(lines) == 258 and lines[-1] == "257:\t-360.0"


def test_an_ang_and_a_ctdata_log_of_one_scan_read_alike(tmp_path):
    # The cube scan's .ang, with the _ctdata.txt the scanner would log beside it: the same angles
    # counted the other way, under the three header lines.
    folder = scanner_folder(tmp_path, "nerf_data/cube")
    values = logged_values(folder / "ivan-cube.ang")
    rows = [f"{i + 1}\t{-v:08.4f}\t{2.0 * i:.4f}" for i, v in enumerate(values)]
    (folder / "_ctdata.txt").write_text("\r\n".join(["Projections\tFrames\tExposure(ms)", "256\t1\t354.00",
                                                     "Projection\tAngle(deg)\tTime(s)", *rows]) + "\r\n")
    with_both = open_scan(folder)
    assert with_both.angle_log.name == "ivan-cube.ang"
    assert any(n.startswith("_ctdata.txt is read too and agrees with ivan-cube.ang within 0 deg")
               for n in with_both.notes)
    (folder / "ivan-cube.ang").unlink()
    ctdata_only = open_scan(folder)
    assert ctdata_only.angle_log.name == "_ctdata.txt" and ctdata_only.metadata["angle_log_sense"] == 1
    np.testing.assert_allclose(ctdata_only.recorded_angles_deg, with_both.recorded_angles_deg, atol=1e-12)


def test_the_two_xtekct_files_of_the_lego_scan_are_one_acquisition(tmp_path):
    folder = scanner_folder(tmp_path, LEGO)
    scan = open_scan(folder)
    assert Path(scan.metadata["xtekct"]).name == "Lego_alignment test_1.xtekct"
    assert any("Lego_alignment test_1_01.xtekct beside Lego_alignment test_1.xtekct: the same acquisition" in n
               for n in scan.notes)
    # 1571 images over 1570 x 0.2299575 = 361.03 deg: the last five repeat the first five poses.
    from ctpipe.solve.graph import turn_pairs

    assert turn_pairs(scan.nominal_angles_deg).tolist() == [[i, 1566 + i] for i in range(5)]
