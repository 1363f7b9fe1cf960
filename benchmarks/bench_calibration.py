"""Per-view angle accuracy of the ball-phantom pipeline on simulated calibration scans.

For each built-in ball phantom (``ball-bar``: 7 balls, ``bead-cloud-10``, ``bead-cloud-30``),
16 and 32 views per turn (22.5 and 11.25 deg steps) and a few seeds, simulates the scan of
``configs/experiments/calibration-16-views.yaml`` (source 250 mm from the axis, 500 mm from a
512^2 detector of 0.2 mm pixels; 0.2 deg Gaussian stage error plus one 0.5 deg jump; 50,000
photons per pixel, Poisson noise, 0.5 px blur; balls overlapping in some views), runs
``configs/calibration-beads.yaml`` on its projections and prints the per-view angle error after
the common offset (:func:`ctpipe.evaluate.scoring.view_errors_deg`): the largest and the RMS
over every view of every seed, and the nominal angles' for comparison. The issue's bar is
every view within 0.02 deg (goal 0.005 deg). Also the time per scan (warm).

Never fails on time; exits with status 1 when a view is beyond 0.02 deg, so a regression shows.

    python benchmarks/bench_calibration.py [--seeds 3] [--phantoms ball-bar bead-cloud-10 bead-cloud-30]
                                           [--views 16 32] [--jitter-deg 0.2]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from calibration_scans import simulate_calibration_scan  # noqa: E402

from ctpipe.evaluate.scoring import view_errors_deg  # noqa: E402
from ctpipe.pipeline import Pipeline  # noqa: E402

PIPELINE = Path(__file__).resolve().parents[1] / "configs" / "calibration-beads.yaml"
BAR_DEG = 0.02


def run(phantom: str, n_views: int, seed: int, jitter_deg: float) -> dict:
    scan, _ = simulate_calibration_scan(phantom, n_views, jitter_deg=jitter_deg, seed=seed)
    pipeline = Pipeline.from_config(PIPELINE)
    start = time.perf_counter()
    result = pipeline.run(scan.projections, scan.geometry, nominal_angles_deg=scan.nominal_angles_deg)
    seconds = time.perf_counter() - start
    errors = view_errors_deg(result.angles_deg, scan.true_angles_deg)
    nominal = view_errors_deg(scan.nominal_angles_deg, scan.true_angles_deg)
    return {"errors": errors, "nominal": nominal, "seconds": seconds,
            "balls": float(np.median(result.n_keypoints)), "inliers": float(np.median(result.n_inliers)),
            "tracks": result.refiner_info.get("tracks"), "rms_px": result.refiner_info.get("rms_px_after")}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--phantoms", nargs="+", default=["ball-bar", "bead-cloud-10", "bead-cloud-30"])
    parser.add_argument("--views", type=int, nargs="+", default=[16, 32])
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--jitter-deg", type=float, default=0.2)
    args = parser.parse_args(argv)
    run(args.phantoms[0], args.views[0], 0, args.jitter_deg)   # warm the numba cache and OpenCV
    print(f"{'phantom':<14} {'views':>5} {'step':>6} {'balls':>5} {'inliers':>7} {'tracks':>6} {'BA px':>6} "
          f"{'max err deg':>11} {'RMS deg':>8} {'nominal max':>11} {'s/scan':>7}")
    worst = 0.0
    for phantom in args.phantoms:
        for n_views in args.views:
            runs = [run(phantom, n_views, seed, args.jitter_deg) for seed in range(args.seeds)]
            errors = np.concatenate([r["errors"] for r in runs])
            nominal = np.concatenate([r["nominal"] for r in runs])
            finite = np.isfinite(errors)
            largest = float(np.abs(errors).max()) if finite.all() else float("inf")
            worst = max(worst, largest)
            rms = float(np.sqrt(np.mean(errors[finite] ** 2))) if finite.any() else float("nan")
            print(f"{phantom:<14} {n_views:>5} {360 / n_views:>6.2f} {np.median([r['balls'] for r in runs]):>5.0f} "
                  f"{np.median([r['inliers'] for r in runs]):>7.0f} {np.median([r['tracks'] or 0 for r in runs]):>6.0f} "
                  f"{np.median([r['rms_px'] or np.nan for r in runs]):>6.3f} {largest:>11.4f} {rms:>8.4f} "
                  f"{np.abs(nominal).max():>11.3f} {np.mean([r['seconds'] for r in runs]):>7.2f}", flush=True)
    print(f"worst view over everything: {worst:.4f} deg (bar {BAR_DEG} deg)")
    return 0 if worst <= BAR_DEG else 1


if __name__ == "__main__":
    sys.exit(main())
