"""Zeiss Xradia .txrm scans: written as the scanner writes them, read back as ctpipe's reference folder reads."""

import dataclasses
import struct
import threading

import numpy as np
import olefile
import pytest

from ctpipe.errors import InputError
from ctpipe.io._ole import StreamReader
from ctpipe.io.scans import open_scan
from ctpipe.io.zeiss import detect, open_zeiss
from ctpipe.testing import write_compound_file, write_zeiss

from scan_helpers import estimate_angles, simulate_raw_scan, write_reference

#: float32 keeps an angle below 360 deg to 2e-5 deg, and a pixel pitch to 1e-7 of itself.
ANGLE_ATOL_DEG = 2e-5
PITCH_RTOL = 1e-6


def _centred(raw):
    """raw_scan with its principal point's row at the detector centre: a .txrm has no key for a vertical offset."""
    return dataclasses.replace(raw.geometry, v0_px=None)


def _write(folder, raw, **changes):
    args = dict(geometry=_centred(raw), nominal_angles_deg=raw.nominal_deg, recorded_angles_deg=raw.true_deg,
                intensities=raw.intensities, flats=raw.flats)
    return write_zeiss(folder, **{**args, **changes})


def _streams(file):
    with olefile.OleFileIO(str(file)) as ole:
        return {"/".join(path): ole.openstream(path).read() for path in ole.listdir()}


def _rewrite(file, streams):
    with open(file, "wb") as handle:
        write_compound_file(handle, streams)
    return file


@pytest.fixture(scope="module")
def txrm(raw_scan, tmp_path_factory):
    return _write(tmp_path_factory.mktemp("zeiss") / "scan", raw_scan)


@pytest.fixture(scope="module")
def reference(raw_scan, txrm, tmp_path_factory):
    """The ctpipe scan folder of the same counts, flat, geometry and nominal angles as the .txrm reads."""
    opened = open_scan(txrm)
    flat = np.frombuffer(_streams(txrm)["ReferenceData/Image"], "<f4").reshape(raw_scan.geometry.shape)
    raw = dataclasses.replace(raw_scan, nominal_deg=opened.nominal_angles_deg)
    return write_reference(tmp_path_factory.mktemp("zeiss") / "ref", raw, raw_scan.intensities, flats=flat[None],
                           geometry=opened.geometry)


def test_a_written_txrm_reads_back_with_the_geometry_angles_and_views_of_the_reference(raw_scan, txrm, reference):
    opened, ref = open_scan(txrm), open_scan(reference)
    assert opened.format == "zeiss" and opened.path == txrm and opened.angle_log is None
    got, want = opened.geometry, _centred(raw_scan)
    for name in ("source_to_object_mm", "source_to_detector_mm", "detector_cols", "detector_rows", "u0_px", "v0_px"):
        assert getattr(got, name) == getattr(want, name), name
    for name in ("pixel_pitch_u_mm", "pixel_pitch_v_mm"):
        assert getattr(got, name) == pytest.approx(getattr(want, name), rel=PITCH_RTOL)
    np.testing.assert_allclose(opened.recorded_angles_deg, raw_scan.true_deg, rtol=0, atol=ANGLE_ATOL_DEG)
    # No commanded angles in a .txrm: evenly spaced from the first to the last logged one.
    logged = raw_scan.true_deg.astype(np.float32).astype(np.float64)
    np.testing.assert_array_equal(opened.nominal_angles_deg, np.linspace(logged[0], logged[-1], len(logged)))
    assert any("nominal angles: evenly spaced" in note for note in opened.notes)
    assert opened.true_angles_deg is None and opened.projections.shape == ref.projections.shape
    for view in range(opened.n_views):
        np.testing.assert_array_equal(opened.projections[view], ref.projections[view])
    np.testing.assert_array_equal(open_scan(txrm.parent).projections[7], ref.projections[7])


def test_estimate_on_the_txrm_equals_the_estimate_on_the_reference_folder(txrm, reference, tmp_path, capsys):
    np.testing.assert_array_equal(estimate_angles(txrm, tmp_path, capsys), estimate_angles(reference, tmp_path, capsys))


def test_the_logged_angles_turn_the_way_the_images_do(tmp_path, capsys):
    # ImageInfo/Angles is read with its sign (Zeiss counts as CIL and ctpipe do). The fast pipeline's
    # error accumulates smoothly along the scan (about 2 deg over 120 views), which swamps a log jitter
    # of 0.4 deg; so the jitter is 1 deg here and the comparison is of the view-to-view steps, where
    # the log's jitter lives: a flipped sign would make the correlation about -0.85.
    raw = simulate_raw_scan(jitter=[{"gaussian": {"sigma_deg": 1.0}}])
    opened = open_scan(_write(tmp_path / "scan", raw))
    nominal = opened.nominal_angles_deg - opened.nominal_angles_deg[0]
    recorded = opened.recorded_angles_deg - opened.recorded_angles_deg[0]
    estimate = estimate_angles(opened.path, tmp_path, capsys)
    assert np.corrcoef(np.diff(estimate - nominal), np.diff(recorded - nominal))[0, 1] > 0.5


def test_the_file_holds_what_cil_and_dxchange_read_in_zeiss_units_and_signs(raw_scan, txrm):
    streams, n = _streams(txrm), len(raw_scan.true_deg)
    rows, cols = raw_scan.geometry.shape

    def unpack(key, fmt):  # as dxchange's _read_ole_struct does: the stream must be exactly that long
        return struct.unpack(fmt, streams[key])

    assert unpack("ImageInfo/ImageWidth", "<I") == (cols,) and unpack("ImageInfo/ImageHeight", "<I") == (rows,)
    assert unpack("ImageInfo/NoOfImages", "<I") == (n,) and unpack("ImageInfo/DataType", "<1I") == (5,)
    assert unpack("ImageInfo/AcquisitionMode", "<i") == (0,) and unpack("ImageInfo/XrayGeometry", "<i") == (1,)
    np.testing.assert_array_equal(unpack("ImageInfo/Angles", f"<{n}f"), raw_scan.true_deg.astype(np.float32))
    source, detector = unpack("ImageInfo/StoRADistance", f"<{n}f"), unpack("ImageInfo/DtoRADistance", f"<{n}f")
    assert source[0] == -130.0 and detector[0] == 170.0
    # CIL: "Pixelsize loaded in metadata is really the voxel size in um"; the detector pixel is it times
    # the magnification, in um.
    (voxel_um,) = unpack("ImageInfo/PixelSize", "<f")
    detector_pixel_um = (abs(source[0]) + abs(detector[0])) / abs(source[0]) * voxel_um
    assert detector_pixel_um == pytest.approx(raw_scan.geometry.pixel_pitch_u_mm * 1000, rel=PITCH_RTOL)
    assert unpack("AutoRecon/CenterShift", "<f") == ((cols - 1) / 2 - raw_scan.geometry.u0_px,)
    for key in ("Alignment/X-Shifts", "Alignment/Y-Shifts", "ImageInfo/XPosition", "ImageInfo/ZPosition"):
        assert unpack(key, f"<{n}f") == (0.0,) * n
    np.testing.assert_array_equal(np.frombuffer(streams["ReferenceData/Image"], "<f4").reshape(rows, cols),
                                  raw_scan.flats.mean(axis=0).astype(np.float32))
    assert unpack("ReferenceData/DataType", "<1I") == (10,)
    # 100 images per storage, numbered from 1, as dxchange's ImageData{ceil(i / 100)}/Image{i}.
    assert "ImageData1/Image100" in streams and "ImageData2/Image101" in streams and "ImageData1/Image0" not in streams
    for view in (0, 99, 100, n - 1):
        stored = np.frombuffer(streams[f"ImageData{int(np.ceil((view + 1) / 100.0))}/Image{view + 1}"], "<u2")
        np.testing.assert_array_equal(stored.reshape(rows, cols), raw_scan.intensities[view])
    with olefile.OleFileIO(str(txrm), raise_defects=olefile.DEFECT_UNSURE):
        pass  # olefile finds nothing wrong in the compound file, even the least defects


def test_an_off_centre_axis_goes_through_center_shift_and_a_vertical_offset_is_refused(raw_scan, tmp_path):
    geometry = dataclasses.replace(_centred(raw_scan), u0_px=60.0)
    file = _write(tmp_path / "scan", raw_scan, geometry=geometry)
    assert struct.unpack("<f", _streams(file)["AutoRecon/CenterShift"]) == (3.5,)
    assert open_scan(file).geometry.u0_px == 60.0
    with pytest.raises(InputError, match=r"geometry.v0_px: a .txrm has no key for a vertical offset.*47.5, got 45.5"):
        _write(tmp_path / "other", raw_scan, geometry=raw_scan.geometry)


def test_alignment_shifts_are_noted_and_not_applied(raw_scan, txrm, tmp_path):
    n = len(raw_scan.true_deg)
    shifted = open_scan(_write(tmp_path / "scan", raw_scan, x_shifts_px=np.linspace(-2, 3, n),
                               y_shifts_px=np.zeros(n)))
    assert any("Alignment/X-Shifts, Y-Shifts are not zero (largest |x| 3 px)" in note for note in shifted.notes)
    np.testing.assert_array_equal(shifted.projections[5], open_scan(txrm).projections[5])
    assert not any("Alignment" in note for note in open_scan(txrm).notes)


def test_units_from_position_info_and_a_multi_reference(raw_scan, txrm, tmp_path):
    streams = _streams(txrm)
    streams["PositionInfo/AxisUnits"] = b"um\x00um\x00um\x00rad\x00um\x00um\x00"
    streams["ImageInfo/Angles"] = np.deg2rad(np.frombuffer(streams["ImageInfo/Angles"], "<f4")).astype("<f4").tobytes()
    for key in ("ImageInfo/StoRADistance", "ImageInfo/DtoRADistance"):
        streams[key] = (np.frombuffer(streams[key], "<f4") * 1000).astype("<f4").tobytes()
    flat = np.frombuffer(streams.pop("ReferenceData/Image"), "<f4")
    for key in [k for k in streams if k.startswith("ReferenceData/")]:
        del streams[key]
    streams |= {"MultiReferenceData/Image1": (flat - 10).astype("<f4").tobytes(),
                "MultiReferenceData/Image2": (flat + 10).astype("<f4").tobytes(),
                "MultiReferenceData/DataType": struct.pack("<I", 10)}
    scan = open_scan(_rewrite(tmp_path / "scan.txrm", streams))
    original = open_scan(txrm)
    assert scan.geometry.source_to_object_mm == pytest.approx(130.0, rel=1e-6)
    assert scan.geometry.pixel_pitch_u_mm == pytest.approx(1.6, rel=PITCH_RTOL)
    np.testing.assert_allclose(scan.recorded_angles_deg, original.recorded_angles_deg, rtol=0, atol=1e-4)
    assert any("the mean of the 2 MultiReferenceData images" in note for note in scan.notes)
    np.testing.assert_allclose(scan.projections[3], original.projections[3], atol=1e-5)


def test_views_read_from_several_threads_are_the_views_read_in_turn(txrm):
    scan = open_scan(txrm)
    expected = [scan.projections.raw(i).copy() for i in range(scan.n_views)]
    got = [None] * scan.n_views

    def work(start):
        for i in range(start, scan.n_views, 4):
            got[i] = scan.projections.raw(i)

    threads = [threading.Thread(target=work, args=(k,)) for k in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert all(np.array_equal(a, b) for a, b in zip(got, expected))


def test_a_fragmented_sector_chain_is_followed_and_a_broken_one_named():
    chain = StreamReader._chain
    np.testing.assert_array_equal(chain(None, np.array([2, 0xFFFFFFFE, 1], np.uint32), 0, 3, "s"), [0, 2, 1])
    with pytest.raises(OSError, match="s: sector chain does not end after 2 sectors"):
        chain(None, np.array([1, 0], np.uint32), 0, 2, "s")
    with pytest.raises(OSError, match="s: sector chain leaves the allocation table"):
        chain(None, np.array([5, 0], np.uint32), 0, 2, "s")


def test_detect_takes_txrm_and_txm_files_and_folders_holding_one(txrm, tmp_path):
    assert detect(txrm) and detect(txrm.parent)
    (tmp_path / "notes.txt").write_text("x")
    assert not detect(tmp_path) and not detect(tmp_path / "notes.txt")
    (tmp_path / "recon.TXM").write_bytes(b"x")
    assert detect(tmp_path) and detect(tmp_path / "recon.TXM")


def _broken(txrm, tmp_path, change, name="scan.txrm"):
    streams = _streams(txrm)
    change(streams)
    return _rewrite(tmp_path / name, streams)


def _set(key, value):
    return lambda streams: streams.__setitem__(key, value)


def _drop(key):
    return lambda streams: streams.pop(key)


def _more_images(streams):
    for key in ("ImageInfo/ImagesTaken", "ImageInfo/NoOfImages"):
        streams[key] = struct.pack("<I", 121)


@pytest.mark.parametrize("change, message", [
    (_drop("ImageInfo/PixelSize"), r"scan.txrm: no ImageInfo/PixelSize stream; a Zeiss .txrm scan has one"),
    (_set("ImageInfo/ImageWidth", b"\x80\x00"),
     r"scan.txrm: ImageInfo/ImageWidth must hold a 4-byte unsigned integer, got 2"),
    (_set("ImageInfo/ImagesTaken", struct.pack("<I", 121)),
     r"scan.txrm: ImageInfo/ImagesTaken says 121 images but ImageInfo/NoOfImages 120; no more can be taken"),
    (_more_images, r"scan.txrm: no ImageData2/Image121 stream; ImageInfo/ImagesTaken says 121 images"),
    (_set("ImageInfo/Angles", np.zeros(119, "<f4").tobytes()),
     r"scan.txrm: ImageInfo/Angles holds 119 values for 120 images; there must be one per image"),
    (_drop("ImageData1/Image7"), r"scan.txrm: no ImageData1/Image7 stream; ImageInfo/ImagesTaken says 120 images"),
    (_set("ImageData1/Image3", np.zeros((96, 127), "<u2").tobytes()),
     r"scan.txrm: ImageData1/Image3 holds 24384 bytes, but a 96 x 128 uint16 image .* takes 24576"),
    (_set("ImageInfo/DataType", struct.pack("<I", 3)),
     r"scan.txrm: ImageInfo/DataType is 3; ctpipe reads 5 \(uint16\), 10"),
    (_drop("ReferenceData/Image"), r"scan.txrm: no ReferenceData/Image stream \(the flat field\)"),
    (_set("ReferenceData/Image", np.zeros(5, "<f4").tobytes()),
     r"scan.txrm: ReferenceData/Image holds 20 bytes, but a 96 x 128"),
    (_set("ImageInfo/AcquisitionMode", struct.pack("<i", 1)),
     r"scan.txrm: is a Zeiss reconstruction .* give the .txrm"),
    (_set("ImageInfo/XrayGeometry", struct.pack("<i", 0)),
     r"scan.txrm: ImageInfo/XrayGeometry is 0, a parallel-beam scan"),
    (_set("ImageInfo/DtoRADistance", np.zeros(120, "<f4").tobytes()),
     r"scan.txrm: ImageInfo/ImageWidth, .* make no cone-beam geometry: .*source_to_detector_mm must exceed"),
    (_set("PositionInfo/AxisUnits", b"um\x00um\x00um\x00deg\x00furlong\x00mm\x00"),
     r"scan.txrm: PositionInfo/AxisUnits gives 'Source Z' the unit 'furlong'; ctpipe knows um"),
])
def test_a_damaged_txrm_is_refused_naming_the_file_and_the_stream(txrm, tmp_path, change, message):
    with pytest.raises(InputError, match=message):
        open_scan(_broken(txrm, tmp_path, change))


def test_files_that_are_no_scan_are_refused_in_one_line(txrm, tmp_path):
    (tmp_path / "junk.txrm").write_bytes(b"not a compound file at all" * 40)
    with pytest.raises(InputError, match=r"junk.txrm: not an OLE compound file"):
        open_scan(tmp_path / "junk.txrm")
    cut = tmp_path / "cut" / "scan.txrm"
    cut.parent.mkdir()
    cut.write_bytes(txrm.read_bytes()[:-1000])
    with pytest.raises(InputError, match=r"scan.txrm: the file ends inside ReferenceData/Image \(48152 of its 49152"):
        open_scan(cut)
    cut.write_bytes(txrm.read_bytes())
    scan = open_scan(cut)
    cut.write_bytes(txrm.read_bytes()[:txrm.stat().st_size // 2])  # damaged after it was opened
    with pytest.raises(InputError, match=r"scan.txrm: ImageData2/Image120: the file ends inside the stream"):
        scan.projections[119]
    recon = _broken(txrm, tmp_path, lambda s: s.pop("ImageInfo/AcquisitionMode"), name="volume.txm")
    with pytest.raises(InputError, match=r"volume.txm: is a Zeiss reconstruction \(a volume; ImageInfo/Acquisition"):
        open_scan(recon)
    folder = tmp_path / "two"
    folder.mkdir()
    for name in ("a.txrm", "b.txrm"):
        (folder / name).write_bytes(txrm.read_bytes())
    with pytest.raises(InputError, match=r"two: holds 2 .txrm files \(a.txrm, b.txrm\); give the one to open"):
        open_zeiss(folder)


def test_write_zeiss_refuses_what_a_txrm_cannot_hold(raw_scan, txrm, tmp_path):
    with pytest.raises(InputError, match=r"exists and is not an empty folder"):
        _write(txrm.parent, raw_scan)
    with pytest.raises(InputError, match=r"darks: a .txrm keeps no dark frame"):
        _write(tmp_path / "a", raw_scan, darks=raw_scan.darks)
    with pytest.raises(InputError, match=r"intensities: a .txrm stores uint16 or float32 images .* got int32"):
        _write(tmp_path / "b", raw_scan, intensities=raw_scan.intensities.astype(np.int32))
    with pytest.raises(InputError, match=r"recorded_angles_deg: 119 angles for 120 projections"):
        _write(tmp_path / "c", raw_scan, recorded_angles_deg=raw_scan.true_deg[:-1])
    with pytest.raises(InputError, match=r"pixel_pitch_u_mm and pixel_pitch_v_mm must be equal"):
        _write(tmp_path / "d", raw_scan, geometry=dataclasses.replace(_centred(raw_scan), pixel_pitch_v_mm=1.7))
    assert not any((tmp_path / name).exists() for name in "abcd")
