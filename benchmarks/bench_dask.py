"""Dask scaling: one scan on threads, on LocalClusters of 1, 2 and 4 worker processes, and projected to 32.

Writes, once (cached in ``--dir``), one simulated scan folder of the granular sample as a
scanner records it: 360 views of 384^2 pixels over a full turn, 0.2 deg Gaussian jitter,
Poisson counts (10^5 photons) with flat and dark frames (``--quick``: 120 views of 256^2). A
second folder lists the first 24 views of the same files; it is the warm-up scan.

The feature pipeline (SIFT, brute-force, ``ransac-1pt``, ``least-squares``, baseline 1 with
the seam closed) runs on that scan, opened from disk, so that workers read their own views:

a. in this process with the default :class:`ctpipe.execution.ThreadExecutor` (the peer);
b. on a LocalCluster of 1, 2 and 4 worker processes (one thread each, no dashboard). Cluster
   start-up and one warm-up run on the small scan (imports and numba/OpenCV set-up in every
   worker) are timed apart; the timed run is the next one (the fastest of ``--repeat``).

Printed per run: wall seconds of each phase as ``Pipeline.run`` reports them (detect, match,
estimate, refine) and in all; speed-up against the 1-worker cluster and parallel efficiency
(speed-up / workers), for the parallel phases (detect + match + estimate) and in all; and
each run against the peer. The angles of every run are compared bit for bit (np.array_equal)
and the result printed. ``--default-pipeline`` adds the default pipeline (SIFT and
projection matching, whose refiner is one central task) on the same backends.

c. Past this machine's cores: for N in 1, 2, 4, ... 32 the views are split into N slices;
   each slice's detection, and the matching and estimation of the pairs that start in it,
   runs in its own process pinned to one core (``os.sched_setaffinity``), slice after slice
   so they do not contend. The projected wall time of an N-worker cluster is the static
   background (one task before detection) + the longest slice's detection + the longest
   slice's matching + estimation (the pipeline waits for every view's features before it
   matches) + the serial part measured in the real run of the 1-worker cluster: its refine,
   and the client and scheduler overhead (its parallel phases less the same work in one
   pinned process). That is Amdahl's law with a measured serial part, not a run on N cores.

OpenCV gets ``--opencv-threads`` threads per process (default 1, through
``OPENCV_FOR_THREADS_NUM``, which the workers inherit): with OpenCV's default of one thread
per core, a "1-worker" cluster already uses every core and nothing would scale. Never fails
on time; the default run takes about 8.5 minutes on the 2-core development machine, the
projection most of it (each N runs the whole scan on one core); ``--quick`` about 2.

    python benchmarks/bench_dask.py [--dir /tmp/ctpipe-bench-dask] [--quick] [--workers 1 2 4]
                                    [--project 1 2 4 8 16 32] [--default-pipeline] [--repeat 1]
                                    [--opencv-threads 1]
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np
import yaml

#: The feature pipeline: the parallel phases dominate, the refiner works from the pairs alone.
FEATURES = {
    "detector": {"name": "sift"},
    "matcher": {"name": "brute-force", "ratio": 0.8, "mutual": True},
    "estimator": {"name": "ransac-1pt", "hypotheses": "all", "scoring": "msac", "sampson_threshold": 1.0e-3},
    "refiner": {"name": "least-squares"},
    "pairs": {"baselines": [1], "loop_closure": True},
    "seed": 0,
}
#: The default pipeline (configs/default.yaml) with the Sampson threshold of this detector.
DEFAULT = {**FEATURES, "refiner": {"name": "projection-matching"}}
PHASES = ("detect", "match", "estimate", "refine")
PARALLEL = ("detect", "match", "estimate")
WARM_UP_VIEWS = 24


# ---------------------------------------------------------------------------------------------
# The scan

def scan_spec(n_views: int, pixels: int) -> dict:
    pitch = 0.8 * 512 / pixels   # the `ctpipe validate` detector, 410 mm wide at every size
    return {
        "geometry": {"source_to_object_mm": 150.0, "source_to_detector_mm": 390.0, "detector_cols": pixels,
                     "detector_rows": pixels, "pixel_pitch_u_mm": pitch, "pixel_pitch_v_mm": pitch},
        "angles": {"n_views": n_views, "range_deg": 360.0, "start_deg": 0.0},
        "jitter": [{"gaussian": {"sigma_deg": 0.2}}],
        "noise": {"photons_per_pixel": 100000, "flat_frames": 4, "dark_frames": 2, "dark_counts": 100},
        "projector": {"kind": "analytic", "supersample": 1, "blur_px": 0.5},
        "seed": 0,
    }


def write_scan_once(folder: Path, n_views: int, pixels: int) -> Path:
    """The simulated scan folder (simulated and written only if ``folder`` has no scan.yaml)."""
    if (folder / "scan.yaml").is_file():
        return folder
    from ctpipe.sim import load_phantom, parse_scan_spec, simulate, write_simulated_scan

    phantom = load_phantom("granular")
    spec = parse_scan_spec(scan_spec(n_views, pixels))
    start = time.perf_counter()
    scan = simulate(phantom, spec, rng=np.random.default_rng(0))
    write_simulated_scan(folder, scan, phantom=phantom, spec=spec, seed=0, overwrite=True)
    print(f"wrote {folder}: {n_views} views of {pixels}^2 in {time.perf_counter() - start:.0f} s", flush=True)
    return folder


def warm_up_scan(full: Path, n_views: int) -> Path:
    """A scan folder of the first ``n_views`` views of ``full``, listing its files."""
    folder = full.parent / f"{full.name}-first{n_views}"
    document = yaml.safe_load((full / "scan.yaml").read_text())
    for kind in ("projections", "flats", "darks"):
        entry = document.get(kind)
        if not entry:
            continue
        files = entry["files"]
        if isinstance(files, str):
            files = [files.format(index=i) for i in range(entry["count"])]
        if kind == "projections":
            files = files[:n_views]
        document[kind] = {**{k: v for k, v in entry.items() if k not in ("files", "count")},
                          "files": [f"../{full.name}/{name}" for name in files]}
    document["angles"] = {k: v[:n_views] for k, v in document["angles"].items()}
    folder.mkdir(exist_ok=True)
    (folder / "scan.yaml").write_text(yaml.safe_dump(document, default_flow_style=None, width=100))
    return folder


# ---------------------------------------------------------------------------------------------
# Real runs

def run_scan(pipeline, folder: Path, executor) -> tuple[dict, np.ndarray]:
    """(seconds per phase and in all, angles) of one pipeline run on the scan at ``folder``."""
    from ctpipe.io import open_scan

    scan = open_scan(folder)
    start = time.perf_counter()
    result = pipeline.run(scan.projections, scan.geometry, nominal_angles_deg=scan.nominal_angles_deg,
                          executor=executor)
    seconds = {phase: result.timings_s.get(phase, float("nan")) for phase in PHASES}
    seconds["total"] = time.perf_counter() - start
    return seconds, result.angles_deg


def best_of(repeat: int, pipeline, folder: Path, executor) -> tuple[dict, np.ndarray]:
    """The fastest of ``repeat`` runs (by total), with its angles; every run's angles must agree."""
    runs = [run_scan(pipeline, folder, executor) for _ in range(repeat)]
    for _, angles in runs[1:]:
        if not np.array_equal(angles, runs[0][1], equal_nan=True):
            print(f"  angles NOT identical between repeats on {executor.describe()}")
    return min(runs, key=lambda run: run[0]["total"])


def run_backends(name: str, config: dict, folder: Path, warm: Path, workers: list[int], repeat: int) -> dict:
    """{backend: (seconds, angles)} for threads and each LocalCluster; prints start-up and warm-up."""
    from ctpipe.execution import DaskExecutor, ThreadExecutor
    from ctpipe.pipeline import Pipeline

    pipeline = Pipeline.from_config(config)
    runs = {}
    print(f"\n[{name}] start-up and warm-up (the warm-up run is the {warm.name} scan):", flush=True)
    with ThreadExecutor() as executor:
        start = time.perf_counter()
        run_scan(pipeline, warm, executor)
        print(f"  threads ({executor.workers}): warm-up {time.perf_counter() - start:.1f} s", flush=True)
        runs[f"threads ({executor.workers})"] = best_of(repeat, pipeline, folder, executor)
    for n in workers:
        start = time.perf_counter()
        executor = DaskExecutor.connect(n_workers=n, threads_per_worker=1, processes=True, dashboard=False)
        try:
            started = time.perf_counter() - start
            start = time.perf_counter()
            run_scan(pipeline, warm, executor)
            warmed = time.perf_counter() - start
            print(f"  {executor.describe()}: start-up {started:.1f} s, warm-up {warmed:.1f} s", flush=True)
            runs[f"dask {n} worker{'s' if n > 1 else ''}"] = best_of(repeat, pipeline, folder, executor)
        finally:
            executor.close()
    return runs


def print_runs(name: str, runs: dict, truth: np.ndarray) -> None:
    """The table of phases, speed-ups and efficiencies, and whether the angles are identical."""
    from ctpipe.evaluate.scoring import view_errors_deg

    reference = next((seconds for label, (seconds, _) in runs.items() if label == "dask 1 worker"), None)
    peer = next(seconds for label, (seconds, _) in runs.items() if label.startswith("threads"))
    print(f"\n[{name}] warm timings, seconds; speed-up and efficiency against the 1-worker cluster "
          f"(parallel = detect + match + estimate); 'vs threads' = threads total / this total")
    print(f"{'backend':<15} {'detect':>7} {'match':>7} {'estim.':>7} {'refine':>7} {'total':>7} "
          f"{'par. speed-up':>13} {'par. eff.':>9} {'speed-up':>8} {'eff.':>5} {'vs threads':>10}")
    for label, (seconds, _) in runs.items():
        parallel = sum(seconds[p] for p in PARALLEL)
        n = int(label.split()[1]) if label.startswith("dask") else int(label.split("(")[1].rstrip(")"))
        row = f"{label:<15} " + " ".join(f"{seconds[p]:>7.2f}" for p in PHASES) + f" {seconds['total']:>7.2f}"
        if reference is not None:
            par_speedup = sum(reference[p] for p in PARALLEL) / parallel
            speedup = reference["total"] / seconds["total"]
            row += f" {par_speedup:>12.2f}x {par_speedup / n:>9.2f} {speedup:>7.2f}x {speedup / n:>5.2f}"
        row += f" {peer['total'] / seconds['total']:>9.2f}x"
        print(row)
    first_label, (_, first) = next(iter(runs.items()))
    same = {label: np.array_equal(first, angles, equal_nan=True) for label, (_, angles) in runs.items()}
    if all(same.values()):
        print(f"angles bitwise identical (np.array_equal) across all {len(runs)} runs: yes")
    else:
        for label, (_, angles) in runs.items():
            if not same[label]:
                print(f"angles NOT identical: {label} against {first_label}, max |difference| "
                      f"{np.nanmax(np.abs(angles - first)):.3g} deg")
    errors = view_errors_deg(first, truth)
    print(f"RMS error against the true angles ({first_label}): {np.sqrt(np.nanmean(errors ** 2)):.4f} deg, "
          f"{int(np.isnan(errors).sum())} views without an angle")


# ---------------------------------------------------------------------------------------------
# The projection: slices of the scan, each in a process pinned to one core

def background_views(n_views: int, pixels: int) -> np.ndarray:
    """The views whose median is the static background, as ``Pipeline`` picks them (up to 90, <= 512 MiB)."""
    count = int(min(n_views, 90, max(16, 512 * 2**20 // (pixels * pixels * 4))))
    return np.unique(np.linspace(0, n_views - 1, count).round().astype(int))


def _pin(core: int) -> None:
    os.sched_setaffinity(0, {core})
    import cv2

    cv2.setNumThreads(1)   # one core: one OpenCV thread, whatever --opencv-threads says


def _time_background(folder: str, views: np.ndarray, core: int):
    """(seconds, background) of the static background's median, read and computed on one core."""
    _pin(core)
    from ctpipe.io import open_scan

    stack = open_scan(folder).projections
    start = time.perf_counter()
    background = np.median(np.asarray(stack[views], dtype=np.float32), axis=0)
    return time.perf_counter() - start, background


def _time_slice(folder: str, config: dict, views: list[int], pairs: np.ndarray, seeds: list, background,
                core: int) -> tuple[float, float, float]:
    """(detect, match, estimate) seconds of one slice of views and its pairs, in this process, on one core."""
    _pin(core)
    from ctpipe.io import open_scan
    from ctpipe.pipeline import Pipeline

    scan = open_scan(folder)
    stack, geometry = scan.projections, scan.geometry
    pipeline = Pipeline.from_config(config)

    def detect(view: int):
        image = stack[view]
        return pipeline.detector.detect(image if background is None else image - background)

    # Views of other slices that this slice's pairs need: on a cluster their features come from
    # the worker that detected them, so they are detected here untimed (the first one, or one of
    # this slice's own views, also warms the process up).
    features = {view: detect(view) for view in sorted(set(pairs.ravel().tolist()) - set(views))}
    if not features:
        detect(views[0])
    start = time.perf_counter()
    features.update({view: detect(view) for view in views})
    detect_s = time.perf_counter() - start

    start = time.perf_counter()
    points = []
    for i, j in pairs:
        m = pipeline.matcher.match(features[i], features[j])
        points.append((geometry.pixels_to_normalised(features[i].xy[m.index_ab[:, 0]]),
                       geometry.pixels_to_normalised(features[j].xy[m.index_ab[:, 1]])))
    match_s = time.perf_counter() - start

    start = time.perf_counter()
    for (q_a, q_b), seed in zip(points, seeds):
        pipeline.estimator.estimate(q_a, q_b, rng=np.random.default_rng(seed))
    return detect_s, match_s, time.perf_counter() - start


def view_pairs_of(config: dict, scan) -> np.ndarray:
    """The pairs ``Pipeline.run`` estimates on ``scan`` with ``config``."""
    from ctpipe.solve.graph import view_pairs

    return view_pairs(len(scan.projections), tuple(config["pairs"]["baselines"]), scan.nominal_angles_deg,
                      loop_closure=config["pairs"]["loop_closure"])


def project(config: dict, folder: Path, reference: dict, counts: list[int]) -> None:
    """Time slices of the scan in pinned processes, one after another, and print the projected scaling."""
    import multiprocessing

    from ctpipe.io import open_scan

    scan = open_scan(folder)
    n_views, pixels = len(scan.projections), scan.geometry.detector_cols
    pairs = view_pairs_of(config, scan)
    seeds = np.random.SeedSequence(config["seed"]).spawn(len(pairs))
    core = max(os.sched_getaffinity(0))
    # A fork server that has imported ctpipe but run nothing (no threads): each slice is a fresh
    # process forked from it, without paying the imports again.
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload(["numpy", "cv2", "ctpipe.pipeline", "ctpipe.io", "ctpipe.builtin"])

    def in_process(fn, *args):
        with context.Pool(1) as pool:
            return pool.apply(fn, args)

    background_s, background = in_process(_time_background, str(folder), background_views(n_views, pixels), core)
    print(f"\n[projection] slices of the {n_views} views, each in its own process pinned to core {core}, one "
          f"after another; static background (median of {len(background_views(n_views, pixels))} views, one task "
          f"before detection) {background_s:.2f} s", flush=True)
    rows = {}
    for n in counts:
        if n > n_views:
            continue
        slices = [s.tolist() for s in np.array_split(np.arange(n_views), n)]
        owner = np.empty(n_views, dtype=int)
        for k, views in enumerate(slices):
            owner[views] = k
        times = []
        for k, views in enumerate(slices):
            mine = np.flatnonzero(owner[pairs[:, 0]] == k)
            times.append(in_process(_time_slice, str(folder), config, views, pairs[mine], [seeds[i] for i in mine],
                                    background, core))
        rows[n] = np.array(times)
        print(f"  N = {n:>2}: {n} slices timed", flush=True)

    single = rows[min(rows)].sum(axis=0)   # all the work in one pinned process (N = 1)
    measured_parallel = sum(reference[p] for p in PARALLEL)
    overhead = max(0.0, measured_parallel - background_s - float(single.sum()))
    serial = reference["refine"] + overhead
    print(f"serial part, from the 1-worker cluster's real run: refine {reference['refine']:.2f} s + client and "
          f"scheduler overhead {overhead:.2f} s (its detect + match + estimate, {measured_parallel:.2f} s, less "
          f"the same work in one pinned process, {background_s + single.sum():.2f} s)")
    print("projected wall time of an N-worker cluster = background + max(slice detect) + max(slice match) + "
          "max(slice estimate) + serial part")
    print(f"{'N':>3} {'views/slice':>11} {'max detect':>10} {'max match':>9} {'max estim.':>10} {'parallel':>8} "
          f"{'projected':>9} {'par. speed-up':>13} {'par. eff.':>9} {'speed-up':>8} {'eff.':>5}")
    first = None
    for n, times in rows.items():
        longest = times.max(axis=0)
        parallel = background_s + float(longest.sum())
        total = parallel + serial
        first = first or (parallel, total)
        print(f"{n:>3} {n_views / n:>11.1f} {longest[0]:>10.2f} {longest[1]:>9.2f} {longest[2]:>10.2f} "
              f"{parallel:>8.2f} {total:>9.2f} {first[0] / parallel:>12.2f}x {first[0] / parallel / n:>9.2f} "
              f"{first[1] / total:>7.2f}x {first[1] / total / n:>5.2f}")
    print(f"This is a projection from measured per-slice times on one core (Amdahl's law with the measured serial "
          f"part), not a run on N cores: it leaves out what many workers add (transfers of features, a busier "
          f"scheduler, a shared filesystem serving N readers). Amdahl's limit here: "
          f"{first[1] / (background_s + serial):.0f}x.")


# ---------------------------------------------------------------------------------------------

def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dir", type=Path, default=Path("/tmp/ctpipe-bench-dask"))
    parser.add_argument("--quick", action="store_true", help="120 views of 256^2 instead of 360 of 384^2")
    parser.add_argument("--views", type=int, help="views of the scan (default 360, --quick 120)")
    parser.add_argument("--pixels", type=int, help="detector rows = cols (default 384, --quick 256)")
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2, 4], help="LocalCluster sizes to run")
    parser.add_argument("--project", type=int, nargs="*", default=[1, 2, 4, 8, 16, 32],
                        help="slice counts N for the projection (none: skip it)")
    parser.add_argument("--default-pipeline", action="store_true",
                        help="also run the default pipeline (projection matching: a central serial solve)")
    parser.add_argument("--repeat", type=int, default=1,
                        help="timed runs per backend; the fastest is reported (the machine may be shared)")
    parser.add_argument("--opencv-threads", type=int, default=1,
                        help="OpenCV threads per process (0: OpenCV's default, one per core)")
    args = parser.parse_args(argv)
    # Before OpenCV is imported here or in any worker (they inherit the environment).
    if args.opencv_threads > 0:
        os.environ["OPENCV_FOR_THREADS_NUM"] = str(args.opencv_threads)
    n_views = args.views or (120 if args.quick else 360)
    pixels = args.pixels or (256 if args.quick else 384)
    workers = sorted(set(args.workers) | {1})

    args.dir.mkdir(parents=True, exist_ok=True)
    folder = write_scan_once(args.dir / f"granular-{n_views}x{pixels}", n_views, pixels)
    warm = warm_up_scan(folder, WARM_UP_VIEWS)
    cores = len(os.sched_getaffinity(0))
    print(f"scan: {folder} ({n_views} views of {pixels}^2, granular, full turn, 0.2 deg jitter, Poisson counts with "
          f"flats and darks); machine: {os.cpu_count()} cores, {cores} usable, load average "
          f"{os.getloadavg()[0]:.2f}; OpenCV threads per process: {args.opencv_threads or 'default'}", flush=True)
    print("features pipeline: " + ", ".join(f"{k} {v['name']}" for k, v in FEATURES.items() if isinstance(v, dict)
                                            and "name" in v) + f", baselines {FEATURES['pairs']['baselines']}")

    from ctpipe.io import open_scan

    scan = open_scan(folder)
    truth = scan.true_angles_deg
    pairs = len(view_pairs_of(FEATURES, scan))
    print(f"{pairs} view pairs; the warm-up scan has {len(open_scan(warm).projections)} views")
    start = time.perf_counter()
    runs = run_backends("features", FEATURES, folder, warm, workers, args.repeat)
    print_runs("features", runs, truth)
    if args.project:
        project(FEATURES, folder, runs["dask 1 worker"][0], sorted(set(args.project)))
    if args.default_pipeline:
        runs = run_backends("default", DEFAULT, folder, warm, workers, args.repeat)
        print_runs("default", runs, truth)
    print(f"\nbenchmark wall time {time.perf_counter() - start:.0f} s; load average now {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
