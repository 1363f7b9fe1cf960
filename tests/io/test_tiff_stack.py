"""A plain TIFF stack with a YAML beside it reads back as the ctpipe scan folder of the same data."""

import numpy as np
import pytest
import tifffile
import yaml

from ctpipe.errors import ConfigError, InputError
from ctpipe.io import open_scan

from scan_helpers import estimate_angles, write_reference


def _write_stack(folder, raw, *, multipage=False, **settings):
    folder.mkdir()
    if multipage:
        tifffile.imwrite(folder / "stack.tif", raw.intensities)
    else:
        for i, view in enumerate(raw.intensities):
            tifffile.imwrite(folder / f"proj_{i:04d}.tif", view)
    for i, frame in enumerate(raw.flats):
        tifffile.imwrite(folder / f"flat_{i}.tif", frame)
    for i, frame in enumerate(raw.darks):
        tifffile.imwrite(folder / f"dark_{i}.tif", frame)
    document = {"geometry": raw.geometry.to_dict(), "angles": {"nominal_deg": raw.nominal_deg.tolist(),
                                                                "recorded_deg": raw.true_deg.tolist()},
                "values": "intensities", "flats": "flat_*.tif", "darks": "dark_*.tif", **settings}
    (folder / "scanner.yml").write_text(yaml.safe_dump(document))
    return folder


@pytest.mark.parametrize("multipage", [False, True])
def test_a_tiff_stack_reads_back_as_the_reference_folder(raw_scan, tmp_path, multipage):
    stack = open_scan(_write_stack(tmp_path / "stack", raw_scan, multipage=multipage))
    reference = open_scan(write_reference(tmp_path / "ref", raw_scan, raw_scan.intensities, flats=raw_scan.flats,
                                          darks=raw_scan.darks))
    assert stack.format == "tiff-yaml" and stack.geometry == raw_scan.geometry
    np.testing.assert_array_equal(stack.nominal_angles_deg, raw_scan.nominal_deg)
    np.testing.assert_array_equal(stack.recorded_angles_deg, raw_scan.true_deg)
    for view in (0, 50, 119):
        np.testing.assert_array_equal(stack.projections[view], reference.projections[view])


def test_estimate_on_a_tiff_stack_equals_estimate_on_the_reference_folder(raw_scan, tmp_path, capsys):
    folder = _write_stack(tmp_path / "stack", raw_scan)
    reference = write_reference(tmp_path / "ref", raw_scan, raw_scan.intensities, flats=raw_scan.flats,
                                darks=raw_scan.darks)
    np.testing.assert_array_equal(estimate_angles(folder, tmp_path, capsys),
                                  estimate_angles(reference, tmp_path, capsys))


def test_evenly_spaced_angles_from_a_range(raw_scan, tmp_path):
    folder = _write_stack(tmp_path / "stack", raw_scan, angles={"range_deg": 360.0, "start_deg": 10.0})
    np.testing.assert_allclose(open_scan(folder).nominal_angles_deg, 10.0 + 3.0 * np.arange(120))


@pytest.mark.parametrize("settings, error, message", [
    ({"values": "counts"}, ConfigError, "values: must be 'intensities' or 'line_integrals', got 'counts'"),
    ({"angles": {"nominal_deg": [0.0, 1.0]}}, InputError, "2 angles for 120 projections"),
    ({"angles": {}}, ConfigError, "needs nominal_deg"),
    ({"flats": "nothing_*.tif"}, InputError, "no file matches flats pattern 'nothing_*.tif'"),
    ({"flats": None, "projections": "proj_*.tif"}, ConfigError, "intensities need flats"),
    ({"white_level": -3}, ConfigError, "white_level: must be a number > 0"),
    ({"colour": "red"}, ConfigError, "colour"),
])
def test_bad_settings_say_what_is_wrong(raw_scan, tmp_path, settings, error, message):
    folder = _write_stack(tmp_path / "stack", raw_scan, **settings)
    with pytest.raises(error, match=message.replace("(", r"\(").replace(")", r"\)").replace("*", r"\*")):
        open_scan(folder)


def test_a_view_of_the_wrong_size_is_named_when_read(raw_scan, tmp_path):
    folder = _write_stack(tmp_path / "stack", raw_scan)
    tifffile.imwrite(folder / "proj_0007.tif", np.zeros((10, 10), np.uint16))
    stack = open_scan(folder)
    with pytest.raises(InputError, match=r"view 7 of \d+ has shape \(10, 10\), the others \(96, 128\)"):
        stack.projections[7]
