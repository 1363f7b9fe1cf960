"""The ball finder's views on worker processes against the same views on threads, in one run.

The ball finder (``beads``, :class:`ctpipe.builtin.beads.BeadDetector`) holds the GIL for most of
its time, so a pipeline on threads detects large views on a :class:`ctpipe.execution.ProcessPool`
instead (:attr:`ctpipe.stages.Detector.holds_gil`). This runs the detect, match and estimate
stages of ``configs/calibration-beads.yaml`` on an issue-34 ball scan (seven solid balls at
2000^2, ``bench_ball_phantom_mixed.py --solid``) twice, alternately on processes and on threads
(the peer: the pipeline's detection as it was, ``ThreadExecutor`` threads), for ``--repeats``
rounds, and prints each round's seconds, their ratio and whether the two found the same balls to
the last bit. The first round includes starting the processes and loading numba's cache in each.
Last, the peak resident memory of the largest worker process (sampled from ``/proc`` while they
run: a child's own ``ru_maxrss`` keeps what it shared with this process before it started
Python) and of this one (which holds the scan, and detects on threads): what each further core's
process costs.

    python benchmarks/bench_ball_detection_processes.py [--views 36] [--seed 2001] [--repeats 2] [--workers N]
"""

from __future__ import annotations

import argparse
import os
import resource
import threading
import time

import numpy as np

import ctpipe.pipeline as pipeline_module
from bench_ball_phantom_mixed import PIPELINE, simulate_scan
from ctpipe.execution import ThreadExecutor, available_cores
from ctpipe.pipeline import Pipeline


class ChildrenMemory(threading.Thread):
    """The largest peak resident memory (``VmHWM``, KiB) of this process's children, sampled every 0.2 s from
    ``/proc`` while running (Linux; stays 0 elsewhere)."""

    def __init__(self) -> None:
        super().__init__(daemon=True)
        self.peak_kib = 0
        self._done = threading.Event()

    def run(self) -> None:
        if not os.path.isdir("/proc"):
            return
        me = str(os.getpid())
        while not self._done.wait(0.2):
            for pid in filter(str.isdigit, os.listdir("/proc")):
                try:
                    with open(f"/proc/{pid}/status") as status:
                        fields = dict(line.split(":", 1) for line in status if ":" in line)
                except OSError:
                    continue            # gone meanwhile
                if fields.get("PPid", "").strip() == me and "VmHWM" in fields:
                    self.peak_kib = max(self.peak_kib, int(fields["VmHWM"].split()[0]))

    def stop(self) -> int:
        self._done.set()
        self.join()
        return self.peak_kib


def observe(pipeline, scan, nominal, workers: int, processes: bool):
    """The observations and the detect stage's seconds, on processes or (with ``processes`` False) on threads."""
    saved = pipeline_module._PROCESS_MIN_PIXELS
    pipeline_module._PROCESS_MIN_PIXELS = saved if processes else np.iinfo(np.int64).max
    try:
        with ThreadExecutor(workers) as executor:
            observations = pipeline.observe(scan.projections, scan.geometry, nominal_angles_deg=nominal,
                                            executor=executor)
    finally:
        pipeline_module._PROCESS_MIN_PIXELS = saved
    return observations, observations.timings_s["detect"]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--views", type=int, default=36)
    parser.add_argument("--seed", type=int, default=2001)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--workers", type=int, default=available_cores(), help="threads, or processes (default: cores)")
    args = parser.parse_args(argv)

    start = time.perf_counter()
    scan, nominal, _ = simulate_scan(args.views, 0.5, None, args.seed, saturation=0.9, solid=True)
    print(f"{args.views} views of {scan.geometry.detector_cols}x{scan.geometry.detector_rows} simulated in "
          f"{time.perf_counter() - start:.1f} s; {args.workers} workers")
    pipeline = Pipeline.from_config(PIPELINE)
    same = True
    children = ChildrenMemory()
    children.start()
    for round_ in range(args.repeats):
        on_processes, processes_s = observe(pipeline, scan, nominal, args.workers, processes=True)
        on_threads, threads_s = observe(pipeline, scan, nominal, args.workers, processes=False)
        same &= all(np.array_equal(a.xy, b.xy) and np.array_equal(a.size, b.size)
                    for a, b in zip(on_processes.features, on_threads.features))
        balls = sum(len(f.xy) for f in on_processes.features)
        print(f"round {round_ + 1}: detect on processes {processes_s:.1f} s, on threads {threads_s:.1f} s "
              f"({threads_s / processes_s:.2f}x); {balls} discs, {balls / args.views:.1f} a view")
    print(f"the same discs on processes and on threads, to the last bit: {'yes' if same else 'NO'}")
    worker_mib = children.stop() / 1024
    own_mib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024        # KiB on Linux
    print(f"peak resident memory: the largest worker process "
          f"{f'{worker_mib:.0f} MiB' if worker_mib else 'not measured (no /proc)'}; this process (the scan, "
          f"{scan.projections.nbytes / 2 ** 20:.0f} MiB of it, and the threads' detection) {own_mib:.0f} MiB")
    return 0 if same else 1


if __name__ == "__main__":
    raise SystemExit(main())
