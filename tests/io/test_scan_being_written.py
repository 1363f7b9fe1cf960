"""A scan folder the scanner is still writing is detected and not read half (issue 24, docs/errors.md)."""

import os
import shutil
import threading
import time

import numpy as np
import pytest

from ctpipe.cli import main
from ctpipe.errors import InputError
from ctpipe.io import open_scan


def _copy(folder, tmp_path, name="scan"):
    copy = tmp_path / name
    shutil.copytree(folder, copy, copy_function=shutil.copy)   # files written now, as a scanner's
    return copy


def _age(folder, seconds: float) -> None:
    """Make every file under ``folder`` look written ``seconds`` ago."""
    then = time.time() - seconds
    for path in folder.rglob("*"):
        os.utime(path, (then, then))


def test_fresh_files_with_views_still_missing_are_a_scan_being_written(small_scan_folder, tmp_path):
    scan = _copy(small_scan_folder, tmp_path)
    for k in (45, 46, 47):
        (scan / "projections" / f"proj_{k:05d}.tif").unlink()
    with pytest.raises(InputError, match=r"proj_00045.tif: no such file; .* count must match the files present; its "
                                         r"newest image was written \d+ s ago: the scan is most likely still being "
                                         r"written; run again when the scanner has finished$"):
        open_scan(scan)
    # The same folder an hour later is a scan that lacks views.
    _age(scan, 3600)
    with pytest.raises(InputError, match=r"count must match the files present$"):
        open_scan(scan)


def test_view_files_refuse_fresh_files_with_views_still_missing(small_scan_folder, tmp_path):
    """What every reader with a file per view (Bruker, Waygate, NSI, ...) checks when it opens a scan."""
    from ctpipe.io.scans import ViewFiles

    scan = _copy(small_scan_folder, tmp_path)
    files = tuple(sorted((scan / "projections").iterdir()))
    for file in files[45:]:
        file.unlink()
    with pytest.raises(InputError, match=r"projections: is still being written: 3 of 48 view files are not there yet "
                                         r"\(the first: proj_00045.tif\) and the newest was written \d+ s ago; run again "
                                         r"when the scanner has finished$"):
        ViewFiles(files)
    _age(scan, 3600)
    read = ViewFiles(files)   # an hour later: a scan that lacks views, named when one is read
    with pytest.raises(InputError, match=r"proj_00045.tif: no such file"):
        read(45)


def test_a_view_that_changes_after_the_scan_was_opened_is_not_read(small_scan_folder, tmp_path):
    scan = _copy(small_scan_folder, tmp_path)
    stack = open_scan(scan).projections
    view = scan / "projections" / "proj_00005.tif"
    with open(view, "ab") as handle:
        handle.write(b"\0" * 100)
    with pytest.raises(InputError, match=r"proj_00005.tif: grew from \d+ to \d+ bytes since the scan was opened: the "
                                         r"scan is being written or replaced while it is read"):
        stack[5]
    np.testing.assert_array_equal(stack[4], open_scan(small_scan_folder).projections[4])   # the others read on


def test_estimate_on_a_folder_the_scanner_is_writing_stops_in_one_line(small_scan_folder, tmp_path, capsys):
    """The scanner's way: settings, flats and darks first, then one view after another."""
    scan = tmp_path / "scan"
    views = sorted((small_scan_folder / "projections").iterdir())
    shutil.copytree(small_scan_folder, scan, ignore=lambda folder, names: names if folder.endswith("projections")
                    else [])
    started, checked = threading.Event(), threading.Event()

    def scanner():
        for k, view in enumerate(views):
            shutil.copy(view, scan / "projections" / view.name)
            if k == 5:
                started.set()
                checked.wait(30)   # a slow view: however slow this machine, the scan is unfinished when read
            time.sleep(0.1)

    writing = threading.Thread(target=scanner, daemon=True)
    writing.start()
    try:
        assert started.wait(30)
        out = tmp_path / "out"
        capsys.readouterr()
        assert main(["estimate", str(scan), "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "still being written" in err and "run again when the scanner has finished" \
            in err, err
        assert not out.exists()
    finally:
        checked.set()
        writing.join(30)
