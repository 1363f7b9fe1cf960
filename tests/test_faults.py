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


def _signal_once_marked(command: list[str], mark: Path, sig: int, what: str) -> tuple[int, str, float, str]:
    """Start ``command``, send ``sig`` once ``mark`` exists: (exit status, stderr, seconds to end, the mark's text).

    A shell ignores SIGINT in its background jobs, and Python then leaves it ignored; a test run in
    the background would pass that on. A terminal's Ctrl-C meets the default: give it back. The
    command's processes (a pool's, a cluster's) are killed at the end, whatever happened.
    """
    def child() -> None:
        signal.signal(signal.SIGINT, signal.SIG_DFL)
        os.setpgrp()   # a group of its own, so that a failed test leaves no process of it behind

    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=child)
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
