"""Time, peak memory and accuracy of the default ``ctpipe estimate`` per stage, at real scan sizes.

The scans are those of ``bench_streaming.py`` (written once, as a scanner writes them: 16-bit
Poisson counts and flat frames in TIFFs, 2,000 views over a full turn with 0.2 deg Gaussian
jitter): 512^2 and 2,048^2 pixels. Fewer views are evenly spaced views of the same files (a
``scan.yaml`` listing them), so every run covers a full turn. The 2,048^2 views are the 512^2 line
integrals magnified 4x, so they hold no finer detail than the 512^2 ones: detection binned to
1,024^2 loses less on them than on a real 2k panel.

Each run is a fresh process that does what ``ctpipe estimate SCAN --out DIR`` does with the
default pipeline, stage by stage, streaming the views from disk: open the scan, detect, match,
estimate every pair (``Pipeline.observe``), the whole-scan refiner and the gate
(``Pipeline.refine``), and the before/after reconstructions of the summary
(``ctpipe.evaluate.preview.before_after``). A thread samples the process's resident memory every
50 ms; printed per stage are its seconds and the peak resident memory during it, then the
per-view RMS angle error against the scan's true angles (and the nominal angles'). With
``--compare-full-detect`` each size larger than 1,024^2 runs again, on the fewest views asked for,
with detection on the full views (``preprocess: {detect_max_px: null}``), so a speed-up that costs
accuracy shows.

Never fails on time or memory: it prints them.

    python benchmarks/bench_default_estimate.py [--dir /tmp/ctpipe-streaming] [--sizes 512 2048]
                                               [--views 360 2000] [--compare-full-detect]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path


sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_streaming import subset, write_scan_once  # noqa: E402

STAGES = ("open", "detect", "match", "estimate", "refine", "preview")

# The child: the default pipeline on one scan folder, stage by stage, with a memory sampler.
CHILD = r"""
import json, sys, threading, time
import numpy as np

peaks, phase, stop = {}, ["start"], threading.Event()
page = __import__("os").sysconf("SC_PAGE_SIZE")

def sample():
    with open("/proc/self/statm") as statm:
        while not stop.is_set():
            statm.seek(0)
            rss = int(statm.read().split()[1]) * page
            peaks[phase[0]] = max(peaks.get(phase[0], 0), rss)
            time.sleep(0.05)

threading.Thread(target=sample, daemon=True).start()
seconds = {}
start = time.perf_counter()
phase[0] = "open"
from ctpipe.io import open_scan
from ctpipe.pipeline import Pipeline
from ctpipe.evaluate.preview import before_after
from ctpipe.evaluate.scoring import view_errors_deg
config = json.loads(sys.argv[2])
scan = open_scan(sys.argv[1])
pipeline = Pipeline.from_config(config)
seconds["open"] = time.perf_counter() - start
phase[0] = "observe"
observations = pipeline.observe(scan.projections, scan.geometry, nominal_angles_deg=scan.nominal_angles_deg)
seconds.update(observations.timings_s)
phase[0] = "refine"
start = time.perf_counter()
result = pipeline.refine(observations)
seconds["refine"] = time.perf_counter() - start
phase[0] = "preview"
start = time.perf_counter()
before_after(scan.projections, scan.geometry, scan.nominal_angles_deg, result.angles_deg + scan.nominal_angles_deg[0])
seconds["preview"] = time.perf_counter() - start
stop.set()
truth = scan.true_angles_deg
rms = lambda angles: float(np.sqrt(np.mean(view_errors_deg(angles, truth) ** 2)))
gate = result.gate
print(json.dumps({"seconds": seconds, "peak_mb": {k: v / 2**20 for k, v in peaks.items()},
                  "rms_deg": rms(result.angles_deg), "nominal_rms_deg": rms(scan.nominal_angles_deg),
                  "ungated_rms_deg": rms(gate.estimate_deg) if gate is not None else None,
                  "gate": None if gate is None else gate.chosen, "detect_binning": result.detect_binning}))
"""


def run(folder: Path, config: dict) -> dict:
    """The child's report, or ``{"error": ...}``."""
    proc = subprocess.run([sys.executable, "-c", CHILD, str(folder), json.dumps(config)], capture_output=True,
                          text=True, cwd=tempfile.gettempdir())
    if proc.returncode != 0:
        return {"error": (proc.stderr.strip().splitlines() or ["?"])[-1]}
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dir", type=Path, default=Path("/tmp/ctpipe-streaming"))
    parser.add_argument("--sizes", type=int, nargs="+", default=[512, 2048])
    parser.add_argument("--views", type=int, nargs="+", default=[360, 2000])
    parser.add_argument("--compare-full-detect", action="store_true",
                        help="run each size above 1024^2 again, on the fewest views, with detection on the full views")
    args = parser.parse_args(argv)
    args.dir.mkdir(parents=True, exist_ok=True)
    configs = {"default": {}}
    if args.compare_full_detect:
        configs["full-size detection"] = {"preprocess": {"detect_max_px": None}}
    # Warm the numba cache, so that no run below pays for compilation; its time is the compile.
    warm = run(subset(write_scan_once(args.dir / "scan-512", 512), 180), {})
    print("warm-up (compiles the numba kernels on a cold cache): 180 views of 512^2, "
          + (f"failed: {warm['error']}" if "error" in warm else f"{sum(warm['seconds'].values()):.1f} s"))
    print(f"{'pipeline':<20} {'views':>5} {'pixels':>7} {'bin':>3} "
          + " ".join(f"{s + ' s':>10}" for s in STAGES) + f" {'total s':>8} {'peak MB':>8} "
          + " ".join(f"{'peak ' + s:>13}" for s in ("observe", "refine", "preview"))
          + f" {'RMS deg':>8} {'nominal':>8} {'gate':>10}")
    for pixels in args.sizes:
        full = write_scan_once(args.dir / f"scan-{pixels}", pixels)
        for n_views in args.views:
            folder = subset(full, n_views)
            for name, config in configs.items():
                if name != "default" and (pixels <= 1024 or n_views != min(args.views)):
                    continue   # detection is at full size there anyway; the comparison on the fewest views
                report = run(folder, config)
                if "error" in report:
                    print(f"{name:<20} {n_views:>5} {pixels:>5}^2  failed: {report['error']}", flush=True)
                    continue
                seconds, peaks = report["seconds"], report["peak_mb"]
                print(f"{name:<20} {n_views:>5} {pixels:>5}^2 {report['detect_binning']:>3} "
                      + " ".join(f"{seconds.get(s, float('nan')):>10.1f}" for s in STAGES)
                      + f" {sum(seconds.values()):>8.1f} {max(peaks.values()):>8.0f} "
                      + " ".join(f"{peaks.get(s, float('nan')):>13.0f}" for s in ("observe", "refine", "preview"))
                      + f" {report['rms_deg']:>8.4f} {report['nominal_rms_deg']:>8.4f} {report['gate']:>10}",
                      flush=True)
    print(f"machine: {os.cpu_count()} cores")


if __name__ == "__main__":
    main()
