"""Opening scans lazily: a view read through ViewStack is bitwise the view of the stack read whole."""

import os
import time

import numpy as np
import pytest

from ctpipe.errors import InputError
from ctpipe.io import ViewStack, open_scan, read_scan
from ctpipe.pipeline import Pipeline

from scan_helpers import FAST_PIPELINE, estimate_angles, write_reference


def test_a_scan_folder_opened_lazily_reads_the_views_read_scan_reads(raw_scan, tmp_path):
    folder = write_reference(tmp_path / "scan", raw_scan, raw_scan.intensities, flats=raw_scan.flats,
                             darks=raw_scan.darks)
    whole, lazy = read_scan(folder), open_scan(folder)
    assert lazy.format == "ctpipe" and lazy.geometry == whole.geometry
    assert lazy.projections.shape == whole.projections.shape
    np.testing.assert_array_equal(lazy.nominal_angles_deg, whole.nominal_angles_deg)
    np.testing.assert_array_equal(lazy.true_angles_deg, whole.true_angles_deg)
    for view in (0, 17, -1):
        np.testing.assert_array_equal(lazy.projections[view], whole.projections[view])
    np.testing.assert_array_equal(np.asarray(lazy.projections), whole.projections)


def test_the_pipeline_gives_the_same_angles_on_a_view_stack_as_on_the_array(raw_scan, tmp_path):
    folder = write_reference(tmp_path / "scan", raw_scan, raw_scan.intensities, flats=raw_scan.flats,
                             darks=raw_scan.darks)
    whole, lazy = read_scan(folder), open_scan(folder)
    pipeline = Pipeline.from_config(FAST_PIPELINE)
    on_array = pipeline.run(whole.projections, whole.geometry, nominal_angles_deg=whole.nominal_angles_deg)
    on_stack = pipeline.run(lazy.projections, lazy.geometry, nominal_angles_deg=lazy.nominal_angles_deg)
    np.testing.assert_array_equal(on_stack.angles_deg, on_array.angles_deg)


def test_cli_estimate_on_a_scan_folder_scores_against_its_true_angles(raw_scan, tmp_path, capsys):
    folder = write_reference(tmp_path / "scan", raw_scan, raw_scan.intensities, flats=raw_scan.flats,
                             darks=raw_scan.darks)
    angles = estimate_angles(folder, tmp_path, capsys)
    truth = raw_scan.true_deg - raw_scan.true_deg[0]
    errors = angles - truth
    # 120 views of 96 x 128 pixels pin the angles only to a degree or so; a reader that flipped the
    # nominal angles' sign would be off by up to 360 deg.
    assert np.sqrt(np.mean((errors - np.median(errors)) ** 2)) < 3.0


def test_view_stack_says_what_is_wrong():
    read = lambda i: np.ones((4, 5), np.uint16)  # noqa: E731
    with pytest.raises(InputError, match="flat fields or a positive white level"):
        ViewStack(read, 3, (4, 5), values="intensities")
    with pytest.raises(InputError, match="dark >= flat"):
        ViewStack(read, 3, (4, 5), values="intensities", flats=np.zeros((4, 5)), darks=np.ones((4, 5)))
    stack = ViewStack(read, 3, (4, 6), values="intensities", white_level=100.0, name="scanX")
    with pytest.raises(InputError, match=r"scanX: view 0 of \d+ has shape \(4, 5\), the others \(4, 6\)"):
        stack[0]
    with pytest.raises(InputError, match="view 3 out of range: the scan has 3 views"):
        ViewStack(read, 3, (4, 5))[3]
    nan = ViewStack(lambda i: np.full((4, 5), np.nan, np.float32), 2, (4, 5), name="scanY")
    with pytest.raises(InputError, match="scanY: view 1"):
        nan[1]


def test_open_scan_lists_the_formats_it_knows(tmp_path):
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(InputError, match="not a scan in any format ctpipe reads.*ctpipe: a folder with scan.yaml"):
        open_scan(tmp_path)
    with pytest.raises(InputError, match="no such file or folder"):
        open_scan(tmp_path / "nope")


def test_projection_matching_on_a_view_stack_never_reads_the_stack_whole(raw_scan, tmp_path, monkeypatch):
    folder = write_reference(tmp_path / "scan", raw_scan, raw_scan.intensities, flats=raw_scan.flats,
                             darks=raw_scan.darks)
    whole, lazy = read_scan(folder), open_scan(folder)
    config = {**FAST_PIPELINE, "refiner": {"name": "projection-matching", "level_px": [24, 48],
                                           "iterations": [2, 1], "max_voxels": 48}}
    on_array = Pipeline.from_config(config).run(whole.projections, whole.geometry,
                                                nominal_angles_deg=whole.nominal_angles_deg)

    def whole_stack(*args, **kwargs):
        raise AssertionError("the whole stack was read into memory")

    monkeypatch.setattr(ViewStack, "__array__", whole_stack)
    on_stack = Pipeline.from_config(config).run(lazy.projections, lazy.geometry,
                                                nominal_angles_deg=lazy.nominal_angles_deg)
    np.testing.assert_array_equal(on_stack.angles_deg, on_array.angles_deg)
    # The levels are reported at the detector's own scale (binned 4 then 2), not the shared pre-binning.
    assert [level["binning"] for level in on_stack.refiner_info["matching"]["levels"]] == [4, 2]


def test_view_files_read_check_and_pickle(tmp_path):
    import pickle

    import tifffile

    from ctpipe.io.scans import ViewFiles

    tifffile.imwrite(tmp_path / "v0.tif", np.zeros((4, 6), np.uint16))
    tifffile.imwrite(tmp_path / "v1.tif", np.zeros((4, 5), np.uint16))
    for name in ("v0.tif", "v1.tif"):   # written an hour ago: v{2} is missing, not still to come
        os.utime(tmp_path / name, (time.time() - 3600, time.time() - 3600))
    read = ViewFiles((tmp_path / "v0.tif", tmp_path / "v1.tif", tmp_path / "v{2}.tif"), (4, 6),
                     missing="{file}: no such file ({number} of {count} in {log})",
                     wrong_shape="{file}: {got} but {log} says {rows} x {cols}", context={"log": "a{b}.log"})
    assert read(0).shape == (4, 6)
    with pytest.raises(InputError, match=r"v1\.tif: \(4, 5\) but a\{b\}\.log says 4 x 6$"):
        read(1)
    with pytest.raises(InputError, match=r"v\{2\}\.tif: no such file \(3 of 3 in a\{b\}\.log\)$"):
        pickle.loads(pickle.dumps(read))(2)
    assert ViewFiles((tmp_path / "v1.tif",))(0).shape == (4, 5)   # no shape: ViewStack checks it
