"""Where the parallel parts of a pipeline run: threads in this process, or a Dask cluster.

A pipeline run is mostly independent tasks (detect one view, match or estimate a chunk of
pairs) around one central solve. :class:`Pipeline <ctpipe.pipeline.Pipeline>` hands those
tasks to an executor and never cares where they run:

- :class:`ThreadExecutor`, the default: a thread pool in this process. OpenCV and numba
  release the GIL, so threads use every core without copying an image. A detector whose work
  holds the GIL (:attr:`ctpipe.stages.Detector.holds_gil`: the ball finder) detects large views
  on a :class:`ProcessPool` of fresh processes instead, one per core.
- :class:`DaskExecutor`: the workers of a ``dask.distributed`` cluster, a
  ``LocalCluster`` on this machine or a scheduler at an address (SLURM/PBS through
  dask-jobqueue, Kubernetes). Stages are pickled and shipped with each task; a scan opened
  from disk travels as its path (:meth:`ctpipe.io.scans.ViewStack.reference`), so each
  worker reads its own views and only features and pair results come back.

A worker that dies mid-run costs time, not results: Dask runs its tasks again on the others
(the values given with :meth:`~Executor.scatter` included, see :meth:`DaskExecutor.scatter`)
and every task's seed goes with it, so the angles are those of an undisturbed run. A run that
cannot go on -- a task whose workers keep dying, every worker gone, the scheduler gone -- stops
with one line (:class:`~ctpipe.errors.ClusterError`), not a traceback or a wait for ever.

Both backends take the same calls: :meth:`~Executor.scatter` places a value where tasks run,
:meth:`~Executor.submit` starts a task whose arguments may hold handles of earlier tasks
(lists and tuples of them too), :meth:`~Executor.gather` waits and returns results in order.
Every random choice is seeded per task by the caller, so the answer does not depend on the
backend, the number of workers or the order in which tasks finish.

Dask is optional (``pip install 'ctpipe[dask]'``); nothing here imports it until a
:class:`DaskExecutor` is made.
"""

from __future__ import annotations

import contextlib
import logging
import os
import pickle
import queue
import subprocess
import sys
import threading
import time
import uuid
import warnings
import weakref
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import FIRST_EXCEPTION, Future, ThreadPoolExecutor, wait
from typing import Any

from ctpipe._shared.resources import available_cores
from ctpipe._shared.worker import receive, send
from ctpipe.errors import ClusterError, InputError

__all__ = ["Executor", "ThreadExecutor", "DaskExecutor", "ProcessPool", "WorkerLost", "end_worker_processes",
           "available_cores", "INSTALL_DASK"]

#: The one line that tells how to get the Dask backend.
INSTALL_DASK = "pip install 'ctpipe[dask]'"

#: How often :meth:`DaskExecutor.gather` looks for finished tasks while it waits, seconds.
_POLL_S = 0.05

#: How long :meth:`DaskExecutor.gather` waits for the scheduler to say how many workers it has,
#: seconds. A scheduler that is gone would make the client try to connect for its whole connect
#: timeout (30 s); its loss is seen otherwise, and a check that got no answer is tried again.
_ASK_S = 2.0


class Executor:
    """Runs independent tasks; subclasses say where.

    Attributes
    ----------
    name : str
        ``"threads"`` or ``"dask"``, as reports name the backend.
    """

    name = "executor"

    @property
    def workers(self) -> int:
        """How many tasks run at once (the cluster's threads, summed over its workers)."""
        raise NotImplementedError

    def scatter(self, value: Any) -> Any:
        """A handle of ``value`` placed where tasks run, to pass to many tasks but send once."""
        raise NotImplementedError

    def submit(self, fn: Callable, *args: Any, name: str = "task") -> Any:
        """Start ``fn(*args)``; handles in ``args`` (or in lists/tuples there) stand for their values."""
        raise NotImplementedError

    def gather(self, handles: Sequence[Any], *, progress: Callable[[int], None] | None = None,
               weights: Sequence[int] | None = None) -> list:
        """The results of ``handles``, in their order.

        ``progress(weights[k])`` is called as task ``k`` finishes (weight 1 by default). The
        first task that fails cancels those not started and its exception is raised here, as
        it was raised in the task.
        """
        raise NotImplementedError

    def close(self) -> None:
        """Free the workers this executor started (not those it was only connected to)."""

    def __enter__(self) -> "Executor":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def describe(self) -> str:
        """One line for the terminal: where the tasks run."""
        return f"{self.name}: {self.workers} at once"


@contextlib.contextmanager
def one_blas_thread_per_task(executor: Executor) -> Iterator[None]:
    """While many tasks run on threads of this process, each one's matrix products on one BLAS thread.

    OpenBLAS spreads every product over all cores; products started from several threads at once
    then contend for them. Matching 160 pairs of 1500 SIFT descriptors (a product and a scan each)
    on 16 threads took as long as on one (1.6 s against 1.7 s, the device tool's 16-core H200
    machine); on a 2-core machine 1.4 s on 4 threads against 0.8 s with one BLAS thread each.
    Elsewhere (one worker, a cluster's processes) nothing changes.
    """
    if not isinstance(executor, ThreadExecutor) or executor.workers < 2:
        yield
        return
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):
        yield


class ThreadExecutor(Executor):
    """A thread pool in this process: the default backend.

    Parameters
    ----------
    max_workers : int, optional
        Threads; default the cores this process may use.
    """

    name = "threads"

    def __init__(self, max_workers: int | None = None) -> None:
        if max_workers is not None and (isinstance(max_workers, bool) or not isinstance(max_workers, int)
                                        or max_workers < 1):
            raise InputError(f"max_workers: must be a positive integer, got {max_workers!r}")
        self._workers = max_workers or available_cores()
        self._pool: ThreadPoolExecutor | None = None

    @property
    def workers(self) -> int:
        return self._workers

    def scatter(self, value: Any) -> Any:
        return value   # one process: every task sees the object itself

    def submit(self, fn: Callable, *args: Any, name: str = "task") -> Future:
        if self._pool is None:
            self._pool = ThreadPoolExecutor(max_workers=self._workers, thread_name_prefix="ctpipe")
        # A task that waits for an earlier task's handle cannot deadlock the pool: the pool
        # starts tasks in the order they were submitted, so the earlier one is running or done.
        return self._pool.submit(_call_resolved, fn, args)

    def gather(self, handles: Sequence[Future], *, progress=None, weights=None) -> list:
        handles = list(handles)
        weight = dict(zip(map(id, handles), weights)) if weights is not None else {}
        pending = set(handles)
        while pending:
            done, pending = wait(pending, return_when=FIRST_EXCEPTION)
            for future in done:
                if future.exception() is not None:
                    for other in pending:
                        other.cancel()
                    raise future.exception()
                if progress is not None:
                    progress(weight.get(id(future), 1))
        return [future.result() for future in handles]

    def close(self, *, wait: bool = True) -> None:
        """Shut the pool down; with ``wait`` False (an interrupted run) do not wait for running tasks."""
        if self._pool is not None:
            self._pool.shutdown(wait=wait, cancel_futures=True)
            self._pool = None

    def __exit__(self, exc_type, *exc) -> None:
        # Ctrl-C, SIGTERM or an error: cancel what has not started and leave running tasks behind,
        # instead of waiting minutes for a detection to end (the program exits without them).
        self.close(wait=exc_type is None)


#: Threads of BLAS, OpenMP and numba each worker process may use: one (as many processes as cores).
_SINGLE_THREADED = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS")

#: The worker processes of the pools still open, which an interrupted ``ctpipe`` command ends
#: (:func:`end_worker_processes`).
_LIVE_POOLS: "weakref.WeakSet[ProcessPool]" = weakref.WeakSet()


class WorkerLost(RuntimeError):
    """A worker process of a :class:`ProcessPool` could not be started, or ended mid-task (killed, out of memory);
    ``done`` holds ``{index: result}`` of the tasks that finished."""

    def __init__(self, message: str, done: dict | None = None) -> None:
        super().__init__(message)
        self.done = {} if done is None else done


class ProcessPool:
    """Fresh Python processes, each running one task at a time: for tasks that hold the GIL.

    Threads share one interpreter lock. A task that spends its time in Python and in numpy's small
    calls runs no faster on two threads than on one: the ball finder
    (:class:`ctpipe.builtin.beads.BeadDetector`) holds the lock for about 70 % of its time, and nine
    views of a 2000^2 ball scan took 15.1 s on two threads against 17.5 s on one (2 cores; its
    fits' numba kernels release the lock, the rest does not). Each process has its own.

    The processes are started as ``python -c`` running :func:`ctpipe._shared.worker.serve`, not
    through :mod:`multiprocessing`, whose children import the caller's main script again (a user's
    script without an ``if __name__ == "__main__":`` guard would run its own top level again in
    every child, as the :mod:`multiprocessing` documentation warns). They find the modules this
    process found (its ``sys.path``), use one thread each for BLAS, OpenMP and numba (as many
    processes as cores), and end when the pool closes its pipes (or is closed, or this process
    dies: their reading end sees the end of file). Tasks and their results travel pickled through
    the pipes: a function importable by name, its arguments, and what it returns; the warnings a
    task raises are raised again here, under this process's filters, and what it prints goes to
    standard error.

    Parameters
    ----------
    workers : int
        Processes to start (at the first :meth:`map`).
    """

    #: Whether processes can be started here: the pipes are handed to them by descriptor (``pass_fds``), which
    #: POSIX systems (Linux, macOS) allow and Windows does not; there a pipeline detects on threads.
    supported = os.name == "posix"

    def __init__(self, workers: int) -> None:
        if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
            raise InputError(f"workers: must be a positive integer, got {workers!r}")
        self.workers = workers
        self._processes: list[tuple[subprocess.Popen, Any, Any]] = []
        _LIVE_POOLS.add(self)

    def _start(self) -> None:
        env = dict(os.environ, **{name: "1" for name in _SINGLE_THREADED})
        env["PYTHONPATH"] = os.pathsep.join(p for p in sys.path if p)
        code = "import sys; from ctpipe._shared.worker import serve; serve(int(sys.argv[1]), int(sys.argv[2]))"
        for _ in range(self.workers - len(self._processes)):
            task_r, task_w = os.pipe()
            reply_r, reply_w = os.pipe()
            try:
                # What a task prints goes to this process's standard error: its output stays the command's own.
                process = subprocess.Popen([sys.executable, "-c", code, str(task_r), str(reply_w)],
                                           pass_fds=(task_r, reply_w), env=env, stdin=subprocess.DEVNULL, stdout=2)
            except OSError as exc:
                for fd in (task_r, task_w, reply_r, reply_w):
                    os.close(fd)
                raise WorkerLost(f"a worker process could not be started: {exc}") from exc
            os.close(task_r)
            os.close(reply_w)
            self._processes.append((process, os.fdopen(task_w, "wb"), os.fdopen(reply_r, "rb")))

    def map(self, fn: Callable, arguments: Sequence[tuple], *,
            progress: Callable[[int], None] | None = None) -> list:
        """``[fn(*args) for args in arguments]``, run on the worker processes, in order.

        The first task that raises stops the others from starting, and its exception is raised
        here. ``progress(1)`` is called in this thread as each task ends. Raises
        :class:`WorkerLost` where a process cannot be started, a task cannot be sent to one (it does
        not pickle, or the process cannot import what it holds) or a process ends mid-task, with the
        results of the tasks that finished.
        """
        self._start()
        todo = queue.SimpleQueue()
        for index in range(len(arguments)):
            todo.put(index)
        replies = queue.SimpleQueue()
        stop = threading.Event()

        def feed(inbox, outbox) -> None:
            # Each reply: (index, ok, value, warnings raised); ok None where the process, not the task, failed.
            while not stop.is_set():
                try:
                    index = todo.get_nowait()
                except queue.Empty:
                    return
                try:
                    args = arguments[index]
                except Exception as exc:   # making the task's arguments (reading its view) failed: its own error
                    replies.put((index, False, exc, []))
                    return
                try:
                    task = pickle.dumps((fn, args), protocol=pickle.HIGHEST_PROTOCOL)
                except Exception as exc:
                    replies.put((index, None, _lost(f"task {index} could not be sent to a worker process", exc), []))
                    return
                try:
                    send(inbox, task)
                    ok, value, raised = pickle.loads(receive(outbox))
                except Exception as exc:   # a broken pipe, the end of file, a reply that cannot be read
                    replies.put((index, None, _lost("a worker process ended mid-task", exc), []))
                    return
                if ok is None:   # the process could not unpickle the task (a class it cannot import)
                    value = _lost(f"task {index} could not be read in a worker process", value)
                replies.put((index, ok, value, raised))

        feeders = [threading.Thread(target=feed, args=(inbox, outbox), name="ctpipe-process", daemon=True)
                   for _, inbox, outbox in self._processes]
        for feeder in feeders:
            feeder.start()
        done: dict[int, Any] = {}
        try:
            while len(done) < len(arguments):
                try:
                    index, ok, value, raised = replies.get(timeout=0.5)
                except queue.Empty:
                    if not any(feeder.is_alive() for feeder in feeders):
                        raise WorkerLost("the worker processes ended before their tasks did", done)
                    continue
                if ok is None:
                    raise WorkerLost(str(value), done) from value.__cause__
                for message, category in raised:
                    warnings.warn(message, category, stacklevel=2)
                if not ok:
                    raise value
                done[index] = value
                if progress is not None:
                    progress(1)
        except BaseException:
            stop.set()
            self.close()
            raise
        return [done[index] for index in range(len(arguments))]

    def close(self) -> None:
        """End the processes: their pipes closed, any still running a task killed."""
        processes, self._processes = self._processes, []
        for process, inbox, outbox in processes:
            for stream in (inbox, outbox):
                with contextlib.suppress(OSError):
                    stream.close()
            if process.poll() is None:
                try:
                    process.wait(timeout=0.5)   # an idle worker reads the end of file and returns
                except subprocess.TimeoutExpired:
                    process.kill()
                    process.wait()

    def __enter__(self) -> "ProcessPool":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _lost(what: str, cause: BaseException) -> WorkerLost:
    """``WorkerLost`` saying ``what`` and its cause, the cause attached (a feeder thread's, raised in the caller's)."""
    lost = WorkerLost(f"{what} ({type(cause).__name__}: {cause})")
    lost.__cause__ = cause
    return lost


def end_worker_processes() -> None:
    """Kill the processes of every open :class:`ProcessPool` at once (an interrupted ``ctpipe`` command)."""
    for pool in list(_LIVE_POOLS):
        for process, _, _ in pool._processes:
            with contextlib.suppress(OSError):
                process.kill()


def _resolved(value: Any) -> Any:
    if isinstance(value, Future):
        return value.result()
    if type(value) in (list, tuple):
        return type(value)(_resolved(v) for v in value)
    return value


def _call_resolved(fn: Callable, args: tuple) -> Any:
    return fn(*(_resolved(a) for a in args))


class DaskExecutor(Executor):
    """The workers of a ``dask.distributed`` cluster.

    Make one with :meth:`connect`, or wrap a ``distributed.Client`` you already have.

    Parameters
    ----------
    client : distributed.Client
    owns_cluster : bool
        Close the client's cluster on :meth:`close` (True when :meth:`connect` started it).
    dashboard : bool, optional
        Whether the scheduler serves the dashboard; None: ask the scheduler.
    no_workers_timeout_s : float or None
        How long a run waits for new workers once every worker of the cluster is gone, before
        it stops with a :class:`~ctpipe.errors.ClusterError`; None: as long as it takes. The
        nannies of a LocalCluster start a killed worker again within seconds; a batch system
        may take longer. A cluster that has not had a worker yet (its jobs still queued) is
        waited for however long it takes.
    """

    name = "dask"

    def __init__(self, client, *, owns_cluster: bool = False, dashboard: bool | None = None,
                 no_workers_timeout_s: float | None = 60.0) -> None:
        self.client = client
        self._owns_cluster = owns_cluster
        self._dashboard = dashboard
        self.no_workers_timeout_s = no_workers_timeout_s
        self._run = uuid.uuid4().hex[:8]
        self._count = 0
        self._checked: set[str] = set()
        self._workers_seen: float | None = None   # when the cluster last had a worker (time.monotonic)
        self._next_check = 0.0
        self._scheduler_lost = False   # said in one line; the client's own complaints are not repeated

    @classmethod
    def connect(cls, address: str | None = None, *, n_workers: int | None = None, threads_per_worker: int = 1,
                processes: bool = True, dashboard: bool = True, timeout_s: float = 30.0) -> "DaskExecutor":
        """Connect to the scheduler at ``address``, or start a LocalCluster sized to this machine.

        Parameters
        ----------
        address : str, optional
            A scheduler's address (``tcp://host:8786``) or a scheduler file (JSON, as
            ``dask-scheduler --scheduler-file`` and dask-jobqueue write). None: a LocalCluster.
        n_workers : int, optional
            LocalCluster only: worker processes, default one per core this process may use.
        threads_per_worker : int
            LocalCluster only. One thread per process by default: detectors are numba and
            OpenCV code that already use a core's worth each, and processes share no GIL.
        processes : bool
            LocalCluster only: worker processes (True) or threads of this process.
        dashboard : bool
            LocalCluster only: serve the dashboard at ``:8787`` (a free port if that is taken). It
            needs bokeh (in the ``dask`` extra); without it no link is given.
        timeout_s : float
            How long to wait for the scheduler.

        Raises
        ------
        InputError
            Dask is not installed (the message says how to install it), or no scheduler
            answers at ``address``.
        """
        distributed = import_distributed()
        if address is None:
            import importlib.util

            n_workers = n_workers or available_cores()
            # OpenCV ignores OMP_NUM_THREADS (which Dask sets to 1) and would start a thread per
            # core in every worker process; give it the worker's own threads.
            env = {"env": {"OPENCV_FOR_THREADS_NUM": str(threads_per_worker)}} if processes else {}
            with distributed_quiet():
                cluster = distributed.LocalCluster(
                    n_workers=n_workers, threads_per_worker=threads_per_worker, processes=processes,
                    dashboard_address=":8787" if dashboard else ":0", **env)
            served = dashboard and importlib.util.find_spec("bokeh") is not None
            return cls(distributed.Client(cluster), owns_cluster=True, dashboard=served)
        try:
            if address.endswith(".json") or os.path.isfile(address):
                client = distributed.Client(scheduler_file=address, timeout=timeout_s)
            else:
                client = distributed.Client(address, timeout=timeout_s)
        except (OSError, TimeoutError, ValueError) as exc:
            raise InputError(f"--dask {address}: no Dask scheduler answers there ({str(exc).splitlines()[0]}); "
                             f"give a scheduler address such as tcp://host:8786 or a scheduler file") from None
        return cls(client)

    @property
    def workers(self) -> int:
        return max(1, sum(self.client.nthreads().values()))

    @property
    def dashboard_link(self) -> str | None:
        """Where the cluster's dashboard is served, or None without one."""
        if self._dashboard is False:
            return None
        try:
            # The scheduler lists its HTTP server as "dashboard" even without bokeh to draw it.
            served = self._dashboard or "dashboard" in self.client.scheduler_info().get("services", {})
            return self.client.dashboard_link if served else None
        except Exception:  # an old scheduler, or one that went away: no link rather than no run
            return None

    def describe(self) -> str:
        n_processes = len(self.client.nthreads())
        where = "a LocalCluster" if self._owns_cluster else f"the scheduler at {self.client.scheduler.address}"
        link = self.dashboard_link
        return (f"dask: {n_processes} workers, {self.workers} threads on {where}"
                + (f"; dashboard {link}" if link else ""))

    def scatter(self, value: Any) -> Any:
        """A handle of ``value``: the result of a task that returns it, which Dask can make again.

        Not ``client.scatter``: scattered data has no task to make it again. Dask keeps one copy
        of it once no task waits for it (its memory manager drops the others, broadcast or not),
        and when the worker that holds the copy dies, the value is gone and every task that
        needs it is cancelled, those Dask would otherwise run again included. A task's result
        lost with its worker is made again where it is needed; the scheduler keeps the task,
        and so the value, as long as the handle lives. The cost: a stack in memory is held by
        the scheduler too while the run lasts (a scan opened from disk is only its path).
        """
        with warnings.catch_warnings():
            # Dask warns of a large task, asking for it to be sent once and shared: which this is.
            warnings.filterwarnings("ignore", message="Sending large graph", category=UserWarning)
            return self.submit(_given, value, name="scatter")

    def submit(self, fn: Callable, *args: Any, name: str = "task") -> Any:
        self._check_imports({getattr(fn, "__module__", None), *(type(a).__module__ for a in args)})
        # Readable keys: the dashboard groups tasks by the part before the last hyphen.
        self._count += 1
        return self.client.submit(fn, *args, key=f"ctpipe-{name}-{self._run}{self._count:x}", pure=False)

    def gather(self, handles: Sequence[Any], *, progress=None, weights=None) -> list:
        from distributed import as_completed

        handles = list(handles)
        weight = dict(zip((h.key for h in handles), weights)) if weights is not None else {}
        try:
            finished = as_completed(handles)
            while not finished.is_empty():
                ready = finished.next_batch(block=False)
                if not ready:
                    # Dask waits for ever for a worker to run the tasks on: look whether any is left.
                    self._check_workers_left()
                    time.sleep(_POLL_S)
                for future in ready:
                    if future.status == "error":
                        _raise_task_error(future)
                    if future.status == "cancelled":
                        reason = _cancelled_reason(future)
                        self._scheduler_lost = reason == _SCHEDULER_LOST
                        raise ClusterError(_cancelled(future, reason))
                    if progress is not None:
                        progress(weight.get(future.key, 1))
            return self.client.gather(handles)
        except BaseException:
            self.client.cancel(handles)
            raise

    def _check_workers_left(self) -> None:
        """Raise ClusterError once every worker has been gone ``no_workers_timeout_s`` (asks at most every second)."""
        now = time.monotonic()
        if self.no_workers_timeout_s is None or now < self._next_check:
            return
        self._next_check = now + min(1.0, self.no_workers_timeout_s / 4)
        if self.client.status != "running":
            return   # the connection to the scheduler is lost: the client cancels the tasks, which gather says
        try:
            workers = self.client.nthreads(callback_timeout=_ASK_S)
        except OSError:  # no answer now (TimeoutError is an OSError): the client reconnects or cancels the tasks
            return
        if workers:
            self._workers_seen = now
        elif self._workers_seen is not None and now - self._workers_seen >= self.no_workers_timeout_s:
            raise ClusterError(_all_gone(self.client.scheduler.address, f"none for {now - self._workers_seen:.0f} s"))

    def _check_imports(self, modules: set) -> None:
        """Refuse to send a task whose code a worker cannot import.

        Stages and task functions are pickled by module name; a worker that lacks the module
        (a plugin installed on the client only) would fail to unpack the task, which Dask
        does not report as the task's error, and the run would wait forever. Each module is
        checked once, on the workers connected at that moment.
        """
        modules = {m for m in modules if m and m not in ("__main__", "builtins")} - self._checked
        if not modules:
            return
        # A worker that died meanwhile cannot answer; Dask runs its tasks on the others.
        try:
            found = self.client.run(_missing_modules, sorted(modules), on_error="return")
        except OSError as exc:   # the scheduler went away as the tasks were being sent
            self._scheduler_lost = True
            raise ClusterError(_scheduler_gone(self.client.scheduler.address, str(exc).splitlines()[0])) from None
        for worker, missing in found.items():
            if missing and not isinstance(missing, BaseException):
                raise InputError(f"the Dask worker at {worker} cannot import {', '.join(missing)}: every worker "
                                 f"needs the ctpipe and the plugins the client has, at the same versions")
        self._checked |= modules

    def close(self) -> None:
        cluster = self.client.cluster if self._owns_cluster else None
        # Closing a client that lost its scheduler stops its attempts to reconnect, which it logs
        # as an error with a traceback: the run has already said the scheduler is gone.
        with distributed_quiet(logging.CRITICAL) if self._scheduler_lost else contextlib.nullcontext():
            self.client.close()
        if cluster is not None:
            cluster.close()


def _given(value: Any) -> Any:
    """``value``: the task behind :meth:`DaskExecutor.scatter`'s handles."""
    return value


def _stage(key) -> str:
    """The task kind in a DaskExecutor key (``ctpipe-detect-...`` -> ``detect``), or the key."""
    parts = str(key).split("-")
    return parts[1] if len(parts) > 2 and parts[0] == "ctpipe" else str(key)


def _all_gone(address: str, how_long: str) -> str:
    return (f"every Dask worker of the scheduler at {address} is gone ({how_long}): the run cannot go on; "
            f"start workers again (their logs say why they ended) and run it again")


def _raise_task_error(future) -> None:
    """Raise the exception of a failed task: its own, or one line when Dask gave the task up."""
    from distributed.scheduler import KilledWorker, NoWorkerError

    try:
        future.result()
    except KilledWorker as exc:
        # The same task killed its worker again and again (or the cluster is falling apart):
        # Dask stops trying after allowed-failures + 1 deaths instead of killing every worker.
        raise ClusterError(
            f"the Dask workers running a {_stage(exc.task)} task died while running it: "
            f"{exc.allowed_failures + 1} died, the last at {exc.last_worker.address}, and Dask gives a task up then "
            f"(distributed.scheduler.allowed-failures); that worker's log says why, most often too little memory "
            f"for a task (give each worker more, or fewer threads)") from None
    except NoWorkerError as exc:   # the scheduler's own distributed.scheduler.no-workers-timeout
        raise ClusterError(_all_gone(future.client.scheduler.address, f"none for {exc.timeout:.0f} s")) from None


#: Dask's reason for the futures its client cancels when the connection to the scheduler is lost.
_SCHEDULER_LOST = "scheduler-connection-lost"


def _scheduler_gone(address: str, how: str) -> str:
    return (f"the Dask scheduler at {address} is gone ({how}): the run cannot go on; start the scheduler and its "
            f"workers again (their logs say why it ended) and run it again")


def _cancelled_reason(future) -> str:
    """Why Dask cancelled ``future``, as its ``FutureCancelledError`` says."""
    from distributed.client import FutureCancelledError

    try:
        future.result()
    except FutureCancelledError as exc:
        return exc.reason
    except Exception as exc:   # distributed before 2024.4: a CancelledError without a reason
        return type(exc).__name__
    return "not cancelled"


def _cancelled(future, reason: str) -> str:
    """The line for a task cancelled by someone else than this run: the scheduler's loss, most often.

    The client cancels every future at once when its connection to the scheduler is lost (reason
    :data:`_SCHEDULER_LOST`); the results are gone with the scheduler, so the run cannot go on.
    A task cancelled otherwise (by another client, or from the dashboard) is named with Dask's
    reason.
    """
    address = future.client.scheduler.address
    if reason == _SCHEDULER_LOST:
        return _scheduler_gone(address, "the connection to it was lost mid-run")
    return (f"a {_stage(future.key)} task of this run was cancelled on the Dask cluster at {address} ({reason}), "
            f"not by ctpipe: the run cannot go on; run it again")


def _missing_modules(names: list[str]) -> list[str]:
    """Those of ``names`` this process cannot import (run on each worker)."""
    import importlib.util

    missing = []
    for name in names:
        try:
            found = importlib.util.find_spec(name) is not None
        except (ImportError, ValueError):
            found = False
        if not found:
            missing.append(name)
    return missing


def import_distributed():
    """``distributed``, or an InputError saying in one line how to install it."""
    try:
        import distributed
    except ImportError:
        raise InputError(f"the Dask backend needs dask.distributed, which is not installed: {INSTALL_DASK}") from None
    return distributed


class distributed_quiet:
    """Silence distributed's messages below ``level`` for a block (by default its start-up chatter: port taken, ...)."""

    def __init__(self, level: int = logging.ERROR) -> None:
        self._level = level

    def __enter__(self):
        # distributed's own configuration gives some of its loggers a level (distributed.client:
        # warning), which a level on their parent would not override.
        names = [name for name in logging.root.manager.loggerDict if name.startswith("distributed.")]
        self._loggers = [logging.getLogger(name) for name in ("distributed", "bokeh", *names)]
        self._levels = [logger.level for logger in self._loggers]
        for logger in self._loggers:
            logger.setLevel(self._level)
        return self

    def __exit__(self, *exc) -> None:
        for logger, level in zip(self._loggers, self._levels):
            logger.setLevel(level)
