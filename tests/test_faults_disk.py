"""A disk that fills up while results are written: one line, exit status 1, every earlier result intact.

Issue 24 and docs/errors.md. The disk is a real one of two megabytes (a tmpfs, mounted for each
test; the tests are skipped where mounting is not allowed), filled to a few kilobytes before the
write, so the kernel itself answers ENOSPC at whatever point a writer reaches it.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

from ctpipe.errors import OutputError


@pytest.fixture
def small_disk(tmp_path):
    """A folder on a 2 MB tmpfs of its own."""
    disk = tmp_path / "disk"
    disk.mkdir()
    if shutil.which("mount") is None or os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root and mount(8)")
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(disk)], capture_output=True)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {done.stderr.decode().strip()}")
    try:
        yield disk
    finally:
        subprocess.run(["umount", "-l", str(disk)], capture_output=True)


def fill(disk, leave_bytes: int = 8192) -> None:
    """Take all but about ``leave_bytes`` of the disk's free space with a file beside the results."""
    free = shutil.disk_usage(disk).free
    with open(disk / ".filler", "wb") as handle:
        handle.write(b"\0" * max(0, free - leave_bytes))


def listing(folder) -> dict:
    """Every file under ``folder`` (the filler aside) with its bytes."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file() and p.name != ".filler"}


def test_write_files_on_a_full_disk_keeps_the_previous_files(small_disk):
    from ctpipe.io.outputs import write_files

    write_files({small_disk / "angles.csv": lambda h: h.write(b"previous angles\n"),
                 small_disk / "report.json": lambda h: h.write(b"{}\n")})
    before = listing(small_disk)
    fill(small_disk)
    with pytest.raises(OutputError, match=r"report.json: no space left on the device while writing it "
                                          r"\([0-9.]+ MB free there\); nothing was replaced"):
        write_files({small_disk / "angles.csv": lambda h: h.write(b"new angles\n"),
                     small_disk / "report.json": lambda h: h.write(b"x" * 200_000)})
    assert listing(small_disk) == before   # both files as they were, no temporary left


def test_a_staged_folder_on_a_full_disk_keeps_the_previous_folder(small_disk):
    from ctpipe.io.outputs import staged_folder

    out = small_disk / "validate"
    with staged_folder(out) as tmp:
        (tmp / "report.json").write_text("previous")
    before = listing(small_disk)
    fill(small_disk)
    with pytest.raises(OutputError, match="validate: no space left on the device"):
        with staged_folder(out) as tmp:
            (tmp / "report.json").write_text("new")
            np.save(tmp / "volume.npy", np.zeros(100_000, np.float32))   # 400 kB: does not fit
    assert listing(small_disk) == before


def test_write_scan_on_a_full_disk_keeps_the_scan_it_was_to_replace(small_disk):
    from ctpipe.geometry import Geometry
    from ctpipe.io.scan_folder import read_scan, write_scan

    geometry = Geometry(source_to_object_mm=100.0, source_to_detector_mm=200.0, detector_cols=64,
                        detector_rows=48, pixel_pitch_u_mm=1.0, pixel_pitch_v_mm=1.0)
    write_scan(small_disk / "scan", np.ones((4, 48, 64), np.float32), geometry, np.arange(4) * 90.0)
    before = listing(small_disk)
    fill(small_disk, leave_bytes=64 * 1024)
    with pytest.raises(OutputError, match="scan: no space left on the device"):
        write_scan(small_disk / "scan", np.ones((40, 48, 64), np.float32), geometry, np.arange(40) * 9.0,
                   overwrite=True)
    assert listing(small_disk) == before
    assert len(read_scan(small_disk / "scan").projections) == 4


def test_the_cli_says_a_full_disk_in_one_line_with_status_1(small_disk, small_scan_folder, capsys):
    from ctpipe.cli import main

    out = small_disk / "keypoints.npz"
    image = str(small_scan_folder / "projections" / "proj_00000.tif")
    assert main(["detect", image, "--detector", "orb", "--out", str(out)]) == 0
    before = listing(small_disk)
    fill(small_disk, leave_bytes=0)
    capsys.readouterr()
    code = main(["detect", image, "--detector", "orb", "--set", "n_features=5000", "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 1, err
    assert err.count("\n") == 1 and err.startswith(f"ctpipe: error: {out}: no space left on the device"), err
    assert listing(small_disk) == before


def test_an_estimate_that_finds_no_room_leaves_no_empty_output_folder(small_disk, small_scan_folder):
    """Issue 36: the output folder made for the results goes again with them (a 300 kB disk, nearly full)."""
    disk = small_disk / "small"
    disk.mkdir()
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=300k", "tmpfs", str(disk)], capture_output=True)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {done.stderr.decode().strip()}")
    try:
        fill(disk, leave_bytes=16384)   # room for a file or two of the results, not for all of them
        run = subprocess.run([sys.executable, "-m", "ctpipe.cli", "estimate", str(small_scan_folder),
                              "--out", str(disk / "o")], capture_output=True, text=True)
        assert run.returncode == 1, run.stderr
        assert run.stderr.strip().splitlines()[-1].startswith("ctpipe: error: ")
        assert "no space left on the device" in run.stderr and "nothing was replaced" in run.stderr
        assert [p.name for p in disk.iterdir()] == [".filler"]
    finally:
        subprocess.run(["umount", "-l", str(disk)], capture_output=True)
