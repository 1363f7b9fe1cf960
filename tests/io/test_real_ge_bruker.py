"""The GE/Waygate and Bruker SkyScan readers on the real scanners' metadata (``../shared/real-metadata``).

The public repositories publish the settings, logs and angle protocols but no projections, so each
test copies a scan's metadata into a temporary folder and writes placeholder projections beside it,
named, numbered and sized as the metadata says: one small zlib-compressed TIFF of the full detector
size, hard-linked once per view. The expected values are read from the metadata files here, with a
parser of the test's own, so that the reader is checked against the files rather than against itself.
"""

from __future__ import annotations

import math
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import tifffile

from ctpipe.io.scans import open_scan
from ctpipe.plugins import get_formats

ROOT = Path(__file__).resolve().parents[2]
REAL = Path(os.environ.get("CTPIPE_REAL_METADATA", ROOT.parent / "shared" / "real-metadata"))
GE = REAL / "meta-cli" / "ge"
BRUKER = REAL / "meta-cli" / "bruker"
GE_RUNS = sorted(p.name for p in GE.glob("FEG230530_*-run-files")) if GE.is_dir() else []
needs_ge = pytest.mark.skipif(not GE_RUNS, reason=f"real GE metadata not found at {GE} "
                                                  "(set CTPIPE_REAL_METADATA to the real-metadata folder)")
needs_bruker = pytest.mark.skipif(not BRUKER.is_dir(), reason=f"real Bruker metadata not found at {BRUKER} "
                                                              "(set CTPIPE_REAL_METADATA to the real-metadata folder)")
#: RotPos has 3 decimals in a .pcp.
ROTPOS_ATOL = 5e-4 + 1e-9


def ini(path: Path) -> dict[str, dict[str, str]]:
    """``sections[section][key] = value`` of an INI-like text file, as written (Windows text, Latin-1)."""
    sections: dict[str, dict[str, str]] = {}
    current: dict[str, str] = {}
    for line in path.read_bytes().decode("latin-1").splitlines():
        line = line.strip()
        if line.startswith("[") and line.endswith("]"):
            current = sections.setdefault(line[1:-1], {})
        elif "=" in line:
            key, _, value = line.partition("=")
            current[key.strip()] = value.strip()
    return sections


def placeholders(folder: Path, names: list[str], shape: tuple[int, int], image: np.ndarray | None = None) -> np.ndarray:
    """One compressed uint16 TIFF of ``shape``, linked under every name in ``folder``; returns its pixels."""
    if image is None:
        rows, cols = shape
        image = (1000 + (np.arange(rows)[:, None] * 7 + np.arange(cols)[None, :] * 3) % 2000).astype(np.uint16)
    first = folder / names[0]
    tifffile.imwrite(first, image, compression="zlib")
    for name in names[1:]:
        try:
            os.link(first, folder / name)
        except OSError:  # a filesystem without hard links
            os.symlink(first, folder / name)
    return image


def pcp_rows(path: Path) -> list[tuple[int, float]]:
    """(ImgNr, RotPos) of every row of a datos|x acquisition protocol."""
    lines = path.read_bytes().decode("latin-1").splitlines()
    columns = lines[1].split("\t")
    nr, rot = columns.index("ImgNr"), columns.index("RotPos")
    return [(int(f[nr]), float(f[rot])) for f in (line.split("\t") for line in lines[2:] if line.strip())]


@pytest.fixture(params=GE_RUNS)
def ge_run(request, tmp_path):
    """A real datos|x run's files with placeholder images 1 .. NumberImages + 1, as the scanner saves them."""
    source = GE / request.param
    folder = tmp_path / request.param
    shutil.copytree(source, folder)
    pca = next(folder.glob("*.pca"))
    settings = ini(pca)
    n_images = int(settings["CT"]["NumberImages"]) + 1  # a full turn: image N + 1 at 360
    names = [f"{pca.stem}{i:05d}.tif" for i in range(1, n_images + 1)]
    image = placeholders(folder, names, (int(settings["Image"]["DimY"]), int(settings["Image"]["DimX"])))
    return folder, pca, settings, image


@needs_ge
def test_a_real_datos_x_run_opens_with_its_geometry_pixels_and_calib_value_note(ge_run):
    folder, pca, settings, image = ge_run
    g, scan = settings["Geometry"], open_scan(folder)
    assert scan.format == "waygate" and scan.metadata["name"] == pca.stem
    geometry = scan.geometry
    assert geometry.source_to_object_mm == float(g["FOD"])
    assert geometry.source_to_detector_mm == float(g["FDD"])
    assert geometry.magnification == pytest.approx(float(g["Magnification"]), rel=1e-8)
    assert (geometry.detector_rows, geometry.detector_cols) == (int(settings["Image"]["DimY"]),
                                                                int(settings["Image"]["DimX"]))
    # The detector-shift margin: the stored images are NrPixelsX - 2 Amplitude wide (2014 of 2024).
    margin = 2 * int(settings["DetectorShift"]["Amplitude"])
    assert geometry.detector_cols == int(settings["Detector"]["NrPixelsX"]) - margin
    assert geometry.pixel_pitch_u_mm == float(settings["Detector"]["PixelsizeX"])
    assert geometry.pixel_pitch_v_mm == float(settings["Detector"]["PixelsizeY"])
    assert geometry.pixel_pitch_u_mm / geometry.magnification == pytest.approx(float(g["VoxelSizeX"]), rel=1e-6)
    # u0/v0 are cx/cy, CalibValue not added (its sign is undocumented); cx is the middle of the stored image.
    assert (geometry.u0_px, geometry.v0_px) == (float(g["cx"]), float(g["cy"]))
    assert geometry.u0_px == (geometry.detector_cols - 1) / 2
    # The pixels: line integrals of the FreeRay level, the closing view the same image as view 0.
    free_ray = float(settings["Image"]["FreeRay"])
    np.testing.assert_allclose(scan.projections[0], -np.log(image / free_ray), rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(scan.projections[scan.n_views - 1], scan.projections[0])
    # CalibValue: the evidence the reader's docstring rests on, and the note. datos|x rec takes it over
    # as CorrectionValue (a float32 round trip) ...
    calib = float(g["CalibValue"])
    pcr = ini(pca.with_suffix(".pcr"))["Reconstruction Settings"]
    assert np.float32(float(pcr["CorrectionValue"])) == np.float32(calib) and calib != 0
    # ... and it scales with the magnification: 0.2-0.31 mm at the object in every run.
    assert 0.2 < calib * float(g["VoxelSizeX"]) < 0.31
    assert scan.metadata["calib_value"] == calib
    note = next(note for note in scan.notes if "CalibValue" in note)
    assert f"CalibValue={calib:g}" in note and "not applied" in note
    assert f"{calib * geometry.pixel_pitch_u_mm / geometry.magnification:.3f} mm" in note


@needs_ge
def test_a_real_full_turn_has_its_closing_view_the_protocols_angles_and_as_many_corrected_rows(ge_run):
    folder, pca, settings, _ = ge_run
    n = int(settings["CT"]["NumberImages"])
    sector = float(settings["CT"]["RotationSector"])
    scanner_rows = pcp_rows(pca.with_suffix(".pcp"))
    assert sector == 360.0 and [nr for nr, _ in scanner_rows] == list(range(1, n + 2))
    scan = open_scan(folder)
    assert scan.closing_view and scan.n_views == n + 1 and scan.projections.shape[0] == n + 1
    np.testing.assert_allclose(scan.nominal_angles_deg, np.arange(n + 1) * sector / n, rtol=0, atol=1e-9)
    assert scan.nominal_angles_deg[-1] == scan.nominal_angles_deg[0] + 360.0
    np.testing.assert_array_equal(scan.recorded_angles_deg, [rot for _, rot in scanner_rows])
    # The sense: RotPos counts up with ImgNr and is taken with ctpipe's sign, as the nominal angles.
    assert np.all(np.diff(scan.recorded_angles_deg) > 0)
    np.testing.assert_allclose(scan.recorded_angles_deg, scan.nominal_angles_deg, rtol=0, atol=ROTPOS_ATOL)
    assert scan.angle_log == pca.with_suffix(".pcp")
    # Corrected angles go back with the scanner's rows.
    write = get_formats()["waygate"].corrected_angle_log
    corrected = scan.recorded_angles_deg + 0.0125
    name, data = write(scan, corrected)
    assert name == pca.with_suffix(".pcp").name
    rows = [line.split("\t") for line in data.decode("ascii").splitlines()[2:]]
    assert [int(r[0]) for r in rows] == [nr for nr, _ in scanner_rows]
    np.testing.assert_allclose([float(r[1]) for r in rows], corrected, rtol=0, atol=ROTPOS_ATOL)
    # Without image N + 1 the scan is the N views of NumberImages, and the scanner's row N + 1 is still
    # written (view 0 one turn later).
    (folder / f"{pca.stem}{n + 1:05d}.tif").unlink()
    scan = open_scan(folder)
    assert not scan.closing_view and scan.n_views == n and len(scan.recorded_angles_deg) == n
    _, data = write(scan, scan.recorded_angles_deg + 0.0125)
    rows = [line.split("\t") for line in data.decode("ascii").splitlines()[2:]]
    assert len(rows) == len(scanner_rows) == n + 1
    assert float(rows[-1][1]) == pytest.approx(scanner_rows[0][1] + 0.0125 + 360.0, abs=ROTPOS_ATOL)


# --- Bruker SkyScan ---------------------------------------------------------------------------


def skyscan_folder(tmp_path: Path, source: Path, digits: int | None = None):
    """A copy of a SkyScan folder's logs with placeholder projections; (log, acquisition keys, image)."""
    folder = tmp_path / source.name
    shutil.copytree(source, folder)
    log = next(folder.glob("*.log"))
    keys = {k.lower(): v for k, v in ini(log)["Acquisition"].items()}
    prefix = keys["filename prefix"]
    digits = int(keys.get("filename index length", digits or 8))
    count = int(keys["number of files"])
    shape = (int(keys["number of rows"]), int(keys["number of columns"]))
    image = placeholders(folder, [f"{prefix}{i:0{digits}d}.tif" for i in range(count)], shape)
    return log, ini(log), image


def check_skyscan_geometry(scan, sections):
    acq = {k.lower(): v for k, v in sections["Acquisition"].items()}
    geometry = scan.geometry
    sod, sdd = float(acq["object to source (mm)"]), float(acq["camera to source (mm)"])
    assert (geometry.source_to_object_mm, geometry.source_to_detector_mm) == (sod, sdd)
    assert (geometry.detector_rows, geometry.detector_cols) == (int(acq["number of rows"]),
                                                                int(acq["number of columns"]))
    # NRecon's pitch: Image Pixel Size at the axis, times the magnification.
    pitch = float(acq["image pixel size (um)"]) / 1000 * sdd / sod
    assert geometry.pixel_pitch_u_mm == geometry.pixel_pitch_v_mm == pytest.approx(pitch, rel=1e-12)
    assert geometry.v0_px == float(acq["optical axis (line)"])
    return acq


def check_image_rotation_note(scan, acq):
    rotation, rows = float(acq["image rotation"]), int(acq["number of rows"])
    lean = rows * math.tan(math.radians(abs(rotation)))
    note = next(note for note in scan.notes if "Image Rotation" in note)
    assert f"Image Rotation={rotation:g} deg" in note and "not applied" in note
    assert f"over the {rows} rows the axis would lean {lean:.1f} px" in note
    return lean


@needs_bruker
@pytest.mark.parametrize("digits", [8, 4])
def test_the_real_skyscan_1173_log_opens_value_by_value(tmp_path, digits):
    log, sections, image = skyscan_folder(tmp_path, BRUKER / "skyscan_1173", digits)
    scan = open_scan(log.parent)
    assert scan.format == "bruker" and scan.metadata["log"] == str(log)
    acq = check_skyscan_geometry(scan, sections)
    cols = int(acq["number of columns"])
    assert scan.geometry.u0_px == (cols - 1) / 2 - float(sections["Reconstruction"]["Postalignment"])
    # 1200 views of 0.2 deg, Rotation Direction=CC: ctpipe's angles decrease; no per-view log.
    count, step = int(acq["number of files"]), float(acq["rotation step (deg)"])
    assert acq["rotation direction"] == "CC" and scan.n_views == count and not scan.closing_view
    np.testing.assert_allclose(scan.nominal_angles_deg, -step * np.arange(count), rtol=0, atol=1e-9)
    assert scan.recorded_angles_deg is None and scan.angle_log is None
    # No Reference Intensity in this log: the white level is 2**Depth.
    assert scan.metadata["white_level"] == 2.0 ** int(acq["depth (bits)"])
    np.testing.assert_allclose(scan.projections[count - 1], -np.log(image / 65536.0), rtol=1e-6, atol=1e-6)
    assert check_image_rotation_note(scan, acq) == pytest.approx(6.6, abs=0.05)
    assert any("Random Movement=ON" in note for note in scan.notes)
    assert any("thermal-shift table" in note for note in scan.notes)


@needs_bruker
def test_the_real_skyscan_1272_sub_scan_opens_value_by_value(tmp_path):
    log, sections, image = skyscan_folder(tmp_path, BRUKER / "skyscan_1272" / "DRP_P21_3")
    assert log.name == "DRP_P21_3.log"  # the log of sub-scan DRP_P21_3~00, named without ~00
    scan = open_scan(log.parent)
    acq = check_skyscan_geometry(scan, sections)
    # Sub-scan ~00 takes "Sub-scan post alignment [0]" (NRecon writes no plain Postalignment here).
    assert "Postalignment" not in sections["Reconstruction"]
    shift = float(sections["Reconstruction"]["Sub-scan post alignment [0]"])
    assert scan.geometry.u0_px == (int(acq["number of columns"]) - 1) / 2 - shift
    count, step = int(acq["number of files"]), float(acq["rotation step (deg)"])
    assert scan.n_views == count and not scan.closing_view
    np.testing.assert_allclose(scan.nominal_angles_deg, -step * np.arange(count), rtol=0, atol=1e-9)
    assert scan.metadata["white_level"] == float(acq["reference intensity"])
    np.testing.assert_allclose(scan.projections[0], -np.log(image / 57000.0), rtol=1e-6, atol=1e-6)
    assert check_image_rotation_note(scan, acq) == pytest.approx(0.9, abs=0.05)
    assert any("sub-scan DRP_P21_3~00 of a connected scan of 2" in note for note in scan.notes)
    # NRecon's reconstruction log repeats the acquisition's keys: nothing there the reader misses.
    rec = ini(log.parent / "DRP_P21_3_Rec" / "DRP_P21_3_rec.log")
    assert rec["Acquisition"]["Image Rotation"] == sections["Acquisition"]["Image Rotation"]
    key = "Sub-scan post alignment [0]"
    assert rec["Reconstruction"][key] == sections["Reconstruction"][key]
