"""Faults during a long run: a stopped run stops at once and leaves every output as it was.

Issue 24 and docs/errors.md. The long work here is a detection that would take a minute
(patched to sleep in the worker threads, as a long OpenCV or numba call holds them): Ctrl-C and
SIGTERM must end ``ctpipe`` within two seconds all the same, with exit status 130 and 143.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

# The real console entry point with one long call patched in; the first call leaves a mark so the
# test knows the long work has started. "threads": every detection sleeps a minute in the worker
# threads. Otherwise "module:function" is replaced by a numba loop of about a minute, compiled as
# ctpipe's kernels are, run in the thread that called it: a compiled call holds its thread until
# it returns, and Python handles a signal only between two calls of the main thread (and only
# when no other thread holds the GIL).
LONG_CALL = """
import sys, time
from pathlib import Path

mark, patch = Path(sys.argv[1]), sys.argv[2]
if patch == "threads":
    import ctpipe.builtin.opencv_detectors as detectors

    def slow(self, image):
        mark.touch()
        time.sleep(60)

    detectors.SiftDetector.detect = slow
else:
    import importlib
    from ctpipe._shared.jit import njit   # as ctpipe's kernels are compiled

    @njit(cache=False)
    def spin(n):
        total = 0.0
        for i in range(n):
            total += (i % 7) * 1e-9
        return total

    spin(10)   # compiled before the mark

    def long_call(*args, **kwargs):
        mark.touch()
        return spin(10**12)

    module, name = patch.split(":")
    owner = importlib.import_module(module)
    *path, name = name.split(".")
    for part in path:
        owner = getattr(owner, part)
    setattr(owner, name, long_call)
sys.argv = ["ctpipe", *sys.argv[3:]]
from ctpipe.cli import entry
entry()
"""

# (patch, command line after "ctpipe"): {scan} is a small scan folder, {out} the output path.
COMMANDS = {
    "estimate": ("threads", ["estimate", "{scan}", "--out", "{out}"]),
    "detect": ("ctpipe.builtin.surf:SurfDetector.detect", ["detect", "{scan}/projections/proj_00000.tif",
                                                                "--detector", "surf", "--out", "{out}.npz"]),
    "simulate": ("ctpipe.sim.simulator:simulate", ["simulate", "bead-cylinder", "--scan", "{spec}",
                                                   "--out", "{out}"]),
    "validate": ("ctpipe.sim.simulator:simulate", ["validate", "--out", "{out}"]),
    "sweep": ("ctpipe.sim.simulator:simulate", ["experiment", "sweep", "--n", "2", "--out", "{out}"]),
    # In the worker processes of a pool (forked: they inherit the patch).
    "synthetic": ("ctpipe.evaluate.experiments:_run_block", ["experiment", "synthetic", "--reps", "1", "--jobs", "2",
                                                             "--out", "{out}"]),
}


def _as_from_a_terminal() -> None:
    """In a test's child: SIGINT's default back, and a process group of its own.

    A shell ignores SIGINT in its background jobs, and Python then leaves it ignored; a test run in
    the background would pass that on, where a terminal's Ctrl-C meets the default. The group lets
    the test kill whatever the command started (a pool's, a cluster's processes) at the end.
    """
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    os.setpgrp()


def _signal_once_marked(command: list[str], mark: Path, sig: int, what: str) -> tuple[int, str, float, str]:
    """Start ``command``, send ``sig`` once ``mark`` exists: (exit status, stderr, seconds to end, the mark's text).

    The command's processes (a pool's, a cluster's) are killed at the end, whatever happened.
    """
    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=_as_from_a_terminal)
    try:
        deadline = time.monotonic() + 120
        while not mark.exists():
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, f"{what} never started"
            time.sleep(0.02)
        marked = mark.read_text()
        time.sleep(0.2)
        sent = time.monotonic()
        proc.send_signal(sig)
        _, stderr = proc.communicate(timeout=30)
        return proc.returncode, stderr, time.monotonic() - sent, marked
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()


@pytest.mark.parametrize("command", sorted(COMMANDS))
@pytest.mark.parametrize("sig, code, said", [(signal.SIGTERM, 143, "ctpipe: terminated"),
                                             (signal.SIGINT, 130, "ctpipe: interrupted")])
def test_a_signal_ends_a_command_within_two_seconds_during_a_long_call(tmp_path, tmp_path_factory, small_scan_folder,
                                                                       command, sig, code, said):
    import yaml

    from tests.conftest import SMALL_SCAN

    patch, argv = COMMANDS[command]
    mark, out = tmp_path / "working", tmp_path / "out"
    spec = tmp_path_factory.mktemp("spec") / "scan.yaml"
    spec.write_text(yaml.safe_dump(SMALL_SCAN))
    argv = [a.format(scan=small_scan_folder, out=out, spec=spec) for a in argv]
    returncode, stderr, took, _ = _signal_once_marked([sys.executable, "-c", LONG_CALL, str(mark), patch, *argv],
                                                      mark, sig, "the long call")
    assert returncode == code and stderr.strip().endswith(said), stderr
    assert "Traceback" not in stderr
    assert took < 2.0, f"ended {took:.1f} s after the signal"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["working"]  # no output, no temporary left


# `ctpipe estimate --dask` on a LocalCluster, its client held in a long wait for the tasks (as
# for a long detection on the workers); the mark holds the workers' process ids.
DASK_RUN = """
import os, sys, time
from pathlib import Path
import ctpipe.execution as execution

mark = Path(sys.argv[1])

def gather(self, handles, **kwargs):
    pids = self.client.run(os.getpid)
    Path(str(mark) + ".tmp").write_text(" ".join(str(pid) for pid in pids.values()))
    os.replace(str(mark) + ".tmp", mark)
    time.sleep(120)

execution.DaskExecutor.gather = gather
sys.argv = ["ctpipe", *sys.argv[2:]]
from ctpipe.cli import entry
entry()
"""


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/status") as status:
            return not any(line.startswith("State:") and "Z" in line.split()[1] for line in status)
    except FileNotFoundError:
        return False


@pytest.mark.parametrize("sig, code", [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_a_signal_ends_a_run_on_a_local_cluster_and_its_workers(tmp_path, small_scan_folder, sig, code):
    pytest.importorskip("distributed")
    if not Path("/proc/self/status").exists():
        pytest.skip("reads process states from /proc")
    mark, out = tmp_path / "workers", tmp_path / "out"
    returncode, stderr, took, marked = _signal_once_marked(
        [sys.executable, "-c", DASK_RUN, str(mark), "estimate", str(small_scan_folder), "--dask", "--out", str(out)],
        mark, sig, "the cluster")
    workers = [int(pid) for pid in marked.split()]
    assert workers
    assert returncode == code and "Traceback" not in stderr, stderr
    assert took < 2.0, f"ended {took:.1f} s after the signal"
    deadline = time.monotonic() + 10
    while any(_alive(pid) for pid in workers) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(_alive(pid) for pid in workers), "a worker outlived the run"
    assert not out.exists()


def test_discard_pending_removes_what_other_threads_had_not_committed(tmp_path):
    import threading

    from ctpipe.io.outputs import atomic_write, discard_pending, pending

    (tmp_path / "result.json").write_text("previous")
    started, release = threading.Event(), threading.Event()

    def write(handle):
        handle.write(b"half")
        started.set()
        release.wait(10)

    failed = []

    def writer():
        try:
            atomic_write(tmp_path / "result.json", write)
        except OSError as exc:  # its temporary is gone: it can only fail, never half-replace the result
            failed.append(exc)

    worker = threading.Thread(target=writer, daemon=True)
    worker.start()
    assert started.wait(10)
    folder = tmp_path / ".staged.tmp"
    folder.mkdir()
    with pending(folder):
        discard_pending()
        assert not folder.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["result.json"]  # the worker's temporary is gone
    assert (tmp_path / "result.json").read_text() == "previous"
    release.set()
    worker.join(10)
    assert failed and (tmp_path / "result.json").read_text() == "previous"


# Real work, nothing patched: a simulation, an estimate and a validate of simulated scans, each
# signalled while it computes. When the work has begun is read off the run itself: the lines it
# prints, or the CPU time its process has used (machine-independent enough that the signal lands
# in the same stage on a faster or slower host).
GRANULAR_360 = {   # 360 views of 256 x 192: detection ~5 s, the projection-matching refiner ~45 s (2 cores)
    "geometry": {"source_to_object_mm": 250.0, "source_to_detector_mm": 500.0, "detector_cols": 256,
                 "detector_rows": 192, "pixel_pitch_u_mm": 0.4, "pixel_pitch_v_mm": 0.4},
    "angles": {"n_views": 360}, "jitter": [{"gaussian": {"sigma_deg": 0.2}}], "seed": 0}
GRANULAR_1000 = {**GRANULAR_360, "angles": {"n_views": 1000},   # projected for ~70 s (2 cores)
                 "geometry": {**GRANULAR_360["geometry"], "detector_cols": 512, "detector_rows": 512,
                              "pixel_pitch_u_mm": 0.2, "pixel_pitch_v_mm": 0.2},
                 "projector": {"supersample": 2, "blur_px": 0.5}}
# FDK of 120 views onto a 384^3 grid: ~6 s, after a second of bundle adjustment.
FDK_EXPERIMENT = {"phantom": "granular", "scan": {**GRANULAR_360, "angles": {"n_views": 120}},
                  "pipeline": {"refiner": {"name": "bundle-adjustment"}, "pairs": {"baselines": [1, 2]}},
                  "reconstruction": {"grid_size": 384, "detector_binning": 1}}


def _cpu_s(pid: int) -> float:
    """CPU seconds (user + system) process ``pid`` has used so far."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _signal_mid_run(command: list[str], begun, sig: int, cwd: Path) -> tuple[int, str, float]:
    """Start ``command``; send ``sig`` once ``begun(stdout, stderr, pid)`` is true: (exit status, stderr, seconds to end)."""
    import threading

    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=cwd,
                            preexec_fn=_as_from_a_terminal)
    said = {"out": [], "err": []}
    readers = [threading.Thread(target=lambda stream, lines: lines.extend(stream), args=(stream, said[name]),
                                daemon=True) for name, stream in (("out", proc.stdout), ("err", proc.stderr))]
    for reader in readers:
        reader.start()
    try:
        deadline = time.monotonic() + 300
        while not begun("".join(said["out"]), "".join(said["err"]), proc.pid):
            assert proc.poll() is None, f"ended before the signal: {''.join(said['err'])}"
            assert time.monotonic() < deadline, "the work never began"
            time.sleep(0.02)
        sent = time.monotonic()
        proc.send_signal(sig)
        proc.wait(timeout=30)
        took = time.monotonic() - sent
        for reader in readers:
            reader.join(5)
        return proc.returncode, "".join(said["err"]), took
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()


def _after(text: str, stream: str = "out", cpu_s: float = 0.0):
    """``begun`` for :func:`_signal_mid_run`: once ``text`` was printed and the process has used ``cpu_s`` more."""
    seen = {}

    def begun(out: str, err: str, pid: int) -> bool:
        if text not in (out if stream == "out" else err):
            return False
        seen.setdefault("cpu", _cpu_s(pid))
        return _cpu_s(pid) >= seen["cpu"] + cpu_s

    return begun


@pytest.fixture(scope="module")
def granular_360(tmp_path_factory):
    import yaml

    from ctpipe.io.scan_folder import write_scan
    from ctpipe.sim import load_phantom, parse_scan_spec, simulate

    spec = parse_scan_spec(GRANULAR_360)
    scan = simulate(load_phantom("granular"), spec, rng=np.random.default_rng(0))
    folder = tmp_path_factory.mktemp("granular")
    (folder / "scan-1000.yaml").write_text(yaml.safe_dump(GRANULAR_1000))
    (folder / "fdk.yaml").write_text(yaml.safe_dump(FDK_EXPERIMENT))
    write_scan(folder / "scan", scan.projections, spec.geometry, scan.nominal_angles_deg, scan.true_angles_deg)
    return folder


REAL_RUNS = {
    # (arguments after "ctpipe", when the work has begun, where it then is)
    "simulate": (["simulate", "granular", "--scan", "scan-1000.yaml", "--out", "{out}"],
                 lambda out, err, pid: _cpu_s(pid) >= 6.0, "projecting the 1,000 views"),
    "estimate-detect": (["estimate", "scan", "--out", "{out}"], _after("nominal angles:"), "detecting keypoints"),
    "estimate-refine": (["estimate", "scan", "--out", "{out}"], _after("nominal angles:", cpu_s=30.0),
                        "in the projection-matching refiner"),
    "validate-fdk": (["validate", "fdk.yaml", "--out", "{out}"], _after("ctpipe: reconstructing (FDK", "err"),
                     "reconstructing by FDK"),
}


@pytest.mark.parametrize("run, sig, code, said", [
    ("simulate", signal.SIGTERM, 143, "ctpipe: terminated"),
    ("estimate-detect", signal.SIGINT, 130, "ctpipe: interrupted"),
    ("estimate-refine", signal.SIGTERM, 143, "ctpipe: terminated"),
    ("validate-fdk", signal.SIGINT, 130, "ctpipe: interrupted"),
])
def test_a_signal_ends_a_real_long_run_within_two_seconds(granular_360, run, sig, code, said):
    if not Path("/proc/self/stat").exists():
        pytest.skip("reads the run's CPU time from /proc")
    argv, begun, where = REAL_RUNS[run]
    out = f"out-{run}"
    before = sorted(p.name for p in granular_360.iterdir())
    returncode, stderr, took = _signal_mid_run([sys.executable, "-m", "ctpipe.cli", *[a.format(out=out) for a in argv]],
                                               begun, sig, granular_360)
    assert returncode == code and stderr.strip().endswith(said), stderr
    assert "Traceback" not in stderr
    assert took < 2.0, f"ended {took:.1f} s after the signal, {where}"
    assert sorted(p.name for p in granular_360.iterdir()) == before   # no output, no temporary left


# Issue 36: a scan folder being written is many files, added one after another by the command's
# thread while the main thread, signalled, removes the temporary folder. "writing" lets the real
# writer run and marks the 200th file, so the signal lands while files keep coming.
WRITING = """
import sys
from pathlib import Path

import tifffile

mark, real, written = Path(sys.argv[1]), tifffile.imwrite, [0]

def imwrite(*args, **kwargs):
    written[0] += 1
    if written[0] == 200:
        mark.touch()
    return real(*args, **kwargs)

tifffile.imwrite = imwrite
sys.argv = ["ctpipe", *sys.argv[2:]]
from ctpipe.cli import entry
entry()
"""

#: 3,000 small views: a second or more of writing files on 2 cores, projected in a moment.
MANY_SMALL_VIEWS = {"geometry": {"source_to_object_mm": 130.0, "source_to_detector_mm": 300.0, "detector_cols": 48,
                                 "detector_rows": 32, "pixel_pitch_u_mm": 4.0, "pixel_pitch_v_mm": 4.0},
                    "angles": {"n_views": 3000}, "jitter": [{"gaussian": {"sigma_deg": 0.2}}], "seed": 0}


@pytest.fixture(scope="module")
def many_small_views(tmp_path_factory):
    import yaml

    spec = tmp_path_factory.mktemp("spec") / "many.yaml"
    spec.write_text(yaml.safe_dump(MANY_SMALL_VIEWS))
    return spec


def _contents(folder: Path) -> dict:
    """Every file and folder under ``folder``, hidden ones too, with each file's modification time."""
    return {str(p.relative_to(folder)): None if p.is_dir() else p.stat().st_mtime_ns for p in folder.rglob("*")}


@pytest.mark.parametrize("overwrite", [False, True])
@pytest.mark.parametrize("sig, code", [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_a_simulation_stopped_while_it_writes_leaves_nothing_beside_its_output(tmp_path, many_small_views, overwrite,
                                                                                sig, code):
    from ctpipe.cli import main

    work, out = tmp_path / "work", tmp_path / "work" / "out"
    work.mkdir()
    argv = ["simulate", "bead-cylinder", "--scan", str(many_small_views), "--out", str(out)]
    before: dict = {}
    if overwrite:
        assert main(argv) == 0
        before = _contents(work)
        argv.append("--overwrite")
    mark = tmp_path / "writing"
    returncode, stderr, _, _ = _signal_once_marked([sys.executable, "-c", WRITING, str(mark), *argv], mark, sig,
                                                   "the writing")
    assert returncode == code and "Traceback" not in stderr, stderr
    # Nothing of the stopped run, hidden or not; a replaced scan exactly as it was.
    assert _contents(work) == before
    assert sorted(p.name for p in work.iterdir()) == (["out"] if overwrite else [])


def test_a_run_killed_outright_leaves_a_temporary_the_next_run_names_with_the_command_that_removes_it(
        tmp_path, many_small_views):
    """SIGKILL (or a power cut) runs no clean-up: the next run into the same place says what is left, and how to remove it."""
    work = tmp_path / "work"
    work.mkdir()
    argv = ["simulate", "bead-cylinder", "--scan", str(many_small_views), "--out", str(work / "out")]
    mark = tmp_path / "writing"
    returncode, _, _, _ = _signal_once_marked([sys.executable, "-c", WRITING, str(mark), *argv], mark, signal.SIGKILL,
                                              "the writing")
    assert returncode == -signal.SIGKILL
    (left,) = work.iterdir()
    assert left.name.startswith(".out.ctpipe-") and left.name.endswith(".tmp")
    again = subprocess.run([sys.executable, "-m", "ctpipe.cli", *argv], capture_output=True, text=True)
    assert again.returncode == 0, again.stderr
    (note,) = [line for line in again.stderr.splitlines() if left.name in line]
    assert "killed" in note and "remove with: " in note
    subprocess.run(note.split("remove with: ")[1], shell=True, check=True)
    assert sorted(p.name for p in work.iterdir()) == ["out"]


def test_a_temporary_of_a_run_still_going_is_not_named_a_leftover(tmp_path):
    from ctpipe.io.outputs import leftovers

    live = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        ours = tmp_path / f".out.ctpipe-{live.pid}-abc.tmp"
        ours.mkdir()
        gone = tmp_path / ".out.ctpipe-999999999-abc.tmp"
        gone.mkdir()
        (tmp_path / ".other.ctpipe-999999999-abc.tmp").mkdir()   # beside another output: not this one's
        assert leftovers(tmp_path / "out") == [gone]
    finally:
        live.kill()
        live.wait()
