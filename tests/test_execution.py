"""The execution layer: threads and Dask give the same answers; tasks, errors and scans travel right."""

from __future__ import annotations

import math
import operator
import os
import pickle
import re
import subprocess
import sys
import threading
import time
import warnings

import numpy as np
import pytest

from bead_rendering import render_beads
from ctpipe.builtin.beads import BeadDetector
from ctpipe.builtin.surf import SurfDetector
from ctpipe.errors import InputError
from ctpipe.execution import (INSTALL_DASK, DaskExecutor, Executor, ProcessPool, ThreadExecutor, WorkerLost,
                              end_worker_processes)
from ctpipe.geometry import Geometry
from ctpipe.io import StackReference, ViewStack, open_scan
from ctpipe.pipeline import Pipeline, _detect_on_processes

#: A features-only pipeline on ctpipe's own SURF (numba kernels), so both detector families are compared.
SURF_PIPELINE = {
    "detector": {"name": "surf"},
    "matcher": {"name": "brute-force", "ratio": 0.8, "mutual": True},
    "estimator": {"name": "ransac-1pt", "sampson_threshold": 3.0e-3},
    "refiner": {"name": "bundle-adjustment"},
    "pairs": {"baselines": [1, 2]},
}

#: The ball finder (which holds the GIL) before a pair stage that needs nothing of it.
BEADS_PIPELINE = {
    "detector": {"name": "beads"},
    "matcher": {"name": "all-pairs", "max_row_shift_px": 30.0},
    "estimator": {"name": "ransac-1pt", "hypotheses": "all", "min_consensus": 0.0, "one_to_one": True},
    "refiner": {"name": "bundle-adjustment"},
    "pairs": {"baselines": [1]},
    "preprocess": {"static_background": "off"},
}


def _run(pipeline, scan, executor=None):
    return pipeline.run(scan.projections, scan.geometry, nominal_angles_deg=scan.nominal_angles_deg,
                        executor=executor)


def assert_same_result(a, b):
    np.testing.assert_array_equal(a.angles_deg, b.angles_deg)
    np.testing.assert_array_equal(a.pair_angles_deg, b.pair_angles_deg)
    np.testing.assert_array_equal(a.n_keypoints, b.n_keypoints)
    np.testing.assert_array_equal(a.n_matches, b.n_matches)
    np.testing.assert_array_equal(a.n_inliers, b.n_inliers)
    assert a.pair_status == b.pair_status
    for mask_a, mask_b in zip(a.pair_inlier_masks, b.pair_inlier_masks):
        np.testing.assert_array_equal(mask_a, mask_b)


# ------------------------------------------------------------------------------------- threads

def test_thread_executor_returns_results_in_order_and_reports_progress_by_weight():
    seen = []
    with ThreadExecutor(2) as executor:
        handles = [executor.submit(lambda k: (time.sleep(0.01 * (5 - k)), k * k)[1], k) for k in range(5)]
        assert executor.gather(handles, progress=seen.append, weights=[1, 2, 3, 4, 5]) == [0, 1, 4, 9, 16]
    assert sorted(seen) == [1, 2, 3, 4, 5]


def test_thread_executor_passes_results_of_earlier_tasks_in_lists():
    with ThreadExecutor(2) as executor:
        first = [executor.submit(int, k) for k in range(4)]
        total = executor.submit(lambda values, extra: sum(values) + extra, first, executor.scatter(10))
        assert executor.gather([total]) == [16]


def test_a_failing_task_raises_its_own_error_and_cancels_the_rest():
    started = []
    lock = threading.Lock()

    def task(k):
        with lock:
            started.append(k)
        if k == 0:
            raise InputError("view 0: broken")
        time.sleep(0.05)
        return k

    with ThreadExecutor(1) as executor:
        handles = [executor.submit(task, k) for k in range(20)]
        with pytest.raises(InputError, match="view 0: broken"):
            executor.gather(handles)
    assert len(started) < 20


@pytest.mark.parametrize("bad", [0, -1, 1.5, True, "2"])
def test_thread_executor_refuses_a_bad_worker_count(bad):
    with pytest.raises(InputError, match="max_workers: must be a positive integer"):
        ThreadExecutor(bad)


def test_pipeline_refuses_something_that_is_not_an_executor(small_scan_folder):
    scan = open_scan(small_scan_folder)
    with pytest.raises(InputError, match="executor: must be a ctpipe.execution.Executor"):
        _run(Pipeline.from_config(SURF_PIPELINE), scan, executor="dask")


def test_the_thread_count_does_not_change_the_angles(small_scan_folder):
    scan = open_scan(small_scan_folder)
    pipeline = Pipeline.from_config(SURF_PIPELINE)
    with ThreadExecutor(1) as one, ThreadExecutor(3) as three:
        assert_same_result(_run(pipeline, scan, one), _run(pipeline, scan, three))


# ------------------------------------------------------------------------------------- processes


def test_a_process_pool_runs_tasks_in_other_processes_in_order_and_reports_progress():
    seen = []
    with ProcessPool(2) as pool:
        assert pool.map(math.hypot, [(3.0, 4.0), (5.0, 12.0), (8.0, 15.0)], progress=seen.append) == [5.0, 13.0, 17.0]
        pids = pool.map(os.getpid, [()] * 4)
    assert seen == [1, 1, 1]
    assert os.getpid() not in pids and 1 <= len(set(pids)) <= 2


def test_a_failing_process_task_raises_its_own_error_and_the_pool_ends_its_processes():
    pool = ProcessPool(2)
    with pytest.raises(ZeroDivisionError):
        pool.map(operator.truediv, [(1.0, 2.0), (1.0, 0.0), (3.0, 4.0)])
    assert pool._processes == []


def test_warnings_a_process_task_raises_are_raised_here():
    with ProcessPool(1) as pool, pytest.warns(UserWarning, match="careful"):
        assert pool.map(warnings.warn, [("careful", UserWarning)]) == [None]


def test_a_worker_process_that_dies_mid_task_is_named_with_the_tasks_done():
    with ProcessPool(1) as pool, pytest.raises(WorkerLost, match="ended mid-task") as lost:
        pool.map(os._exit, [(3,)])
    assert lost.value.done == {}


def test_a_task_that_does_not_pickle_is_named_with_the_tasks_done():
    with ProcessPool(1) as pool, pytest.raises(WorkerLost, match="task 1 could not be sent") as lost:
        pool.map(operator.neg, [(1.0,), (threading.Lock(),)])
    assert lost.value.done == {0: -1.0}


def test_a_task_a_worker_process_cannot_import_is_named_and_the_pool_runs_again(monkeypatch):
    nowhere = type("Nowhere", (), {"__module__": "__main__", "__neg__": lambda self: -1.0})
    monkeypatch.setattr(sys.modules["__main__"], "Nowhere", nowhere, raising=False)   # pickles here, not there
    with ProcessPool(1) as pool:
        with pytest.raises(WorkerLost, match="task 0 could not be read in a worker process.*Nowhere"):
            pool.map(operator.neg, [(nowhere(),)])
        assert pool.map(operator.neg, [(2.0,)]) == [-2.0]


def _warn_many(times: int) -> int:
    """A task for the worker processes (this module is importable there: they get this process's ``sys.path``)."""
    for _ in range(times):
        warnings.warn("the same warning", UserWarning)
    return times


def test_a_warning_raised_many_times_by_a_process_task_comes_back_once():
    with ProcessPool(1) as pool, warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")   # every warning raised here recorded (recwarn's "default" would merge them)
        assert pool.map(_warn_many, [(500,)]) == [500]
    assert sum(str(w.message) == "the same warning" for w in caught) == 1


def test_end_worker_processes_kills_the_open_pools_processes():
    pool = ProcessPool(2)
    pool._start()
    processes = [process for process, _, _ in pool._processes]
    end_worker_processes()
    assert all(process.wait(timeout=10) != 0 for process in processes)
    pool.close()


def test_a_script_without_a_main_guard_is_not_run_again_in_the_worker_processes(tmp_path):
    script = tmp_path / "unguarded.py"
    script.write_text("import os\nfrom ctpipe.execution import ProcessPool\nprint('top level ran', flush=True)\n"
                      "with ProcessPool(2) as pool:\n    print(len(set(pool.map(os.getpid, [()] * 4))) >= 1)\n"
                      "    pool.map(print, [('printed by a worker',)])\n")
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.count("top level ran") == 1 and "True" in out.stdout
    # What a task prints stays out of the command's own output.
    assert "printed by a worker" in out.stderr and "printed by a worker" not in out.stdout


@pytest.fixture(scope="module")
def ball_views():
    """Three 1024^2 views of six balls: a megapixel each, so the ball finder runs on processes."""
    geometry = Geometry(source_to_object_mm=150.0, source_to_detector_mm=600.0, detector_cols=1024,
                        detector_rows=1024, pixel_pitch_u_mm=0.2, pixel_pitch_v_mm=0.2)
    rng = np.random.default_rng(11)
    centres = np.column_stack([rng.uniform(-15, 15, 6), rng.uniform(-15, 15, 6), rng.uniform(-15, 15, 6)])
    return render_beads(geometry, [0.0, 30.0, 60.0], centres, np.full(6, 2.0)), geometry


def test_the_ball_finder_detects_large_views_on_processes_as_on_threads(ball_views, monkeypatch):
    projections, geometry = ball_views
    calls = []
    real_map = ProcessPool.map
    monkeypatch.setattr(ProcessPool, "map", lambda self, *a, **k: calls.append(self.workers) or real_map(self, *a, **k))
    pipeline = Pipeline.from_config(BEADS_PIPELINE)
    with ThreadExecutor(1) as one, ThreadExecutor(2) as two:
        on_threads = pipeline.observe(projections, geometry, executor=one)
        on_processes = pipeline.observe(projections, geometry, executor=two)
    assert calls == [2]
    assert sum(len(f.xy) for f in on_threads.features) >= 15
    for a, b in zip(on_threads.features, on_processes.features):
        np.testing.assert_array_equal(a.xy, b.xy)
        np.testing.assert_array_equal(a.size, b.size)


class _Elsewhere(Executor):
    """An executor whose tasks run in other processes already (as a Dask cluster's)."""

    workers = 4


@pytest.mark.parametrize("detector, executor, shape, factor, views, expected", [
    (BeadDetector(), ThreadExecutor(2), (1024, 1024), 1, 3, True),
    (BeadDetector(), ThreadExecutor(2), (2048, 2048), 2, 3, True),     # binned to a megapixel
    (BeadDetector(), ThreadExecutor(2), (2048, 2048), 4, 3, False),    # binned below it
    (BeadDetector(), ThreadExecutor(2), (1000, 1000), 1, 3, False),    # under a megapixel: starting costs more
    (BeadDetector(), ThreadExecutor(1), (1024, 1024), 1, 3, False),    # one worker: nothing to run beside
    (BeadDetector(), ThreadExecutor(2), (1024, 1024), 1, 1, False),    # one view
    (BeadDetector(), _Elsewhere(), (2048, 2048), 1, 3, False),         # on a cluster's processes already
    (SurfDetector(), ThreadExecutor(2), (2048, 2048), 1, 3, False),    # numba kernels that let go of the GIL
])
def test_only_a_detector_that_holds_the_gil_goes_to_processes_and_only_on_large_views(detector, executor, shape,
                                                                                       factor, views, expected):
    assert _detect_on_processes(detector, executor, shape, factor, views) is expected


def test_where_processes_cannot_be_started_the_ball_finder_stays_on_threads(monkeypatch):
    monkeypatch.setattr(ProcessPool, "supported", False)   # Windows: no pipes handed over by descriptor
    assert not _detect_on_processes(BeadDetector(), ThreadExecutor(2), (2048, 2048), 1, 3)


def test_where_the_processes_cannot_start_the_views_are_detected_on_threads_with_a_warning(ball_views,
                                                                                          monkeypatch):
    projections, geometry = ball_views
    pipeline = Pipeline.from_config(BEADS_PIPELINE)
    with ThreadExecutor(1) as one:
        expected = pipeline.observe(projections[:2], geometry, executor=one)
    monkeypatch.setattr(sys, "executable", "/nonexistent/python")
    with ThreadExecutor(2) as two, pytest.warns(RuntimeWarning, match="could not be started.*on threads"):
        got = pipeline.observe(projections[:2], geometry, executor=two)
    for a, b in zip(expected.features, got.features):
        np.testing.assert_array_equal(a.xy, b.xy)


# ------------------------------------------------------------------------------ scans by name

def test_an_opened_scan_travels_as_its_path_and_reopens_to_the_same_views(small_scan_folder):
    stack = open_scan(small_scan_folder).projections
    reference = stack.reference()
    assert isinstance(reference, StackReference) and reference.format == "ctpipe"
    assert reference.shape == stack.shape
    blob = pickle.dumps(reference)
    assert len(blob) < 1000   # a name, not images
    reopened = pickle.loads(blob).open()
    for index in (0, 17, len(stack) - 1):
        np.testing.assert_array_equal(reopened[index], stack[index])


def test_a_reference_to_a_scan_that_is_not_there_says_the_filesystem_must_be_shared(tmp_path):
    reference = StackReference("ctpipe", str(tmp_path / "elsewhere"), (10, 4, 4))
    with pytest.raises(InputError, match="cannot be read here.*filesystem they share"):
        reference.open()


def test_a_reference_to_a_scan_changed_on_disk_is_refused(small_scan_folder):
    reference = open_scan(small_scan_folder).projections.reference()
    changed = StackReference(reference.format, reference.path, (47, *reference.shape[1:]))
    with pytest.raises(InputError, match="changed on disk since it was opened"):
        changed.open()


def _read_zeros(index):
    return np.zeros((4, 5), np.float32)


def test_a_stack_built_from_a_function_pickles_whole():
    stack = ViewStack(_read_zeros, 3, (4, 5))
    assert stack.reference() is None
    copy = pickle.loads(pickle.dumps(stack))
    assert copy.shape == (3, 4, 5) and np.array_equal(copy[2], stack[2])


# ---------------------------------------------------------------------------------------- Dask

def test_without_dask_the_dask_backend_says_how_to_install_it(monkeypatch):
    monkeypatch.setitem(sys.modules, "distributed", None)
    with pytest.raises(InputError, match=re.escape(f"not installed: {INSTALL_DASK}") + "$"):
        DaskExecutor.connect()


def test_no_scheduler_at_the_address_is_one_clear_error():
    pytest.importorskip("distributed")
    with pytest.raises(InputError, match="no Dask scheduler answers there"):
        DaskExecutor.connect("tcp://127.0.0.1:9", timeout_s=1)


@pytest.mark.parametrize("config", [None, SURF_PIPELINE], ids=["default", "surf-bundle"])
def test_a_two_worker_local_cluster_gives_the_angles_of_the_in_process_run(small_scan_folder, dask_client, config):
    scan = open_scan(small_scan_folder)
    pipeline = Pipeline.from_config(config)
    here = _run(pipeline, scan)
    there = _run(pipeline, scan, DaskExecutor(dask_client))
    assert_same_result(here, there)
    assert np.isfinite(there.angles_deg).all()
    assert _without_timings(there.refiner_info) == _without_timings(here.refiner_info)


def _without_timings(info):
    if isinstance(info, dict):
        return {k: _without_timings(v) for k, v in info.items() if k != "seconds"}
    if isinstance(info, list):
        return [_without_timings(v) for v in info]
    return info


def test_on_a_cluster_the_client_reads_no_view(small_scan_folder, dask_client, monkeypatch):
    scan = open_scan(small_scan_folder)
    expected = _run(Pipeline.from_config(None), scan)

    def refuse(*args, **kwargs):
        raise AssertionError("the client read a view")

    # Workers are other processes: only the client's ViewStack is patched.
    for name in ("__getitem__", "raw", "__array__"):
        monkeypatch.setattr(ViewStack, name, refuse)
    result = _run(Pipeline.from_config(None), scan, DaskExecutor(dask_client))
    np.testing.assert_array_equal(result.angles_deg, expected.angles_deg)


def test_an_in_memory_stack_runs_on_the_cluster_too(small_scan_folder, dask_client):
    scan = open_scan(small_scan_folder)
    projections = np.asarray(scan.projections)
    pipeline = Pipeline.from_config(SURF_PIPELINE)
    here = pipeline.run(projections, scan.geometry, nominal_angles_deg=scan.nominal_angles_deg)
    there = pipeline.run(projections, scan.geometry, nominal_angles_deg=scan.nominal_angles_deg,
                         executor=DaskExecutor(dask_client))
    assert_same_result(here, there)


def test_a_bad_view_read_on_a_worker_is_the_users_error_on_the_client(small_scan_folder, dask_client, tmp_path):
    import shutil

    folder = shutil.copytree(small_scan_folder, tmp_path / "scan")
    scan = open_scan(folder)
    (folder / "projections" / sorted(p.name for p in (folder / "projections").iterdir())[30]).write_bytes(b"not a tiff")
    with pytest.raises(InputError, match="proj_00030"):
        _run(Pipeline.from_config(SURF_PIPELINE), scan, DaskExecutor(dask_client))
    assert dask_client.run(lambda: 1)   # the cluster is still up for the next scan


def test_a_stage_module_missing_on_the_workers_is_named(dask_client, tmp_path, monkeypatch):
    (tmp_path / "client_only_stage.py").write_text("def detect():\n    return 1\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    import client_only_stage

    executor = DaskExecutor(dask_client)
    with pytest.raises(InputError, match="the Dask worker at .* cannot import client_only_stage: every worker needs"):
        executor.gather([executor.submit(client_only_stage.detect)])
    sys.modules.pop("client_only_stage")


def test_many_thread_tasks_get_one_blas_thread_each_and_one_task_keeps_them_all():
    from threadpoolctl import threadpool_info

    from ctpipe.execution import one_blas_thread_per_task

    def blas_threads():
        return [pool["num_threads"] for pool in threadpool_info() if pool["user_api"] == "blas"]

    before = blas_threads()
    assert before   # numpy's own BLAS
    with ThreadExecutor(max_workers=2) as run_on, one_blas_thread_per_task(run_on):
        assert all(n == 1 for n in blas_threads())
    assert blas_threads() == before
    with ThreadExecutor(max_workers=1) as run_on, one_blas_thread_per_task(run_on):
        assert blas_threads() == before
