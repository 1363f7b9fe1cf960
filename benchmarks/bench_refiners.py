"""Refiners against view count: the pair graph (``least-squares``) and ``bundle-adjustment``.

Every row refines the same synthetic scan (:func:`ctpipe.solve.simulated.synthetic_scan`):
points projected over a full turn with 0.2 px noise, 20 % wrong matches (which the pair
verification caught), tracks of 3-12 views, pairs at baselines 1 and 2 with the seam closed. Prints seconds,
observations, the maximum angle error and, per refiner, the scaling exponent of the time
(least squares fit of log seconds against log views). Figures only; nothing is asserted.

    python benchmarks/bench_refiners.py [--views 360 1440 2880] [--points-per-view 10] [--seed 0]

A further refiner (e.g. projection matching) is one more entry in ``REFINERS``: a name and a
function ``(SyntheticScan) -> (angles_rad, info)``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from ctpipe.builtin.bundle import BundleAdjustmentRefiner
from ctpipe.builtin.refiners import LeastSquaresRefiner
from ctpipe.solve.simulated import SyntheticScan, synthetic_scan


def _stage(refiner):
    def run(scan: SyntheticScan):
        solution = refiner.refine(scan.observations, rng=np.random.default_rng(0))
        return solution.angles_rad, solution.info
    return run


#: name -> function of a SyntheticScan returning (angles_rad, info); add projection matching here.
REFINERS = {
    "least-squares": _stage(LeastSquaresRefiner()),
    "bundle-adjustment": _stage(BundleAdjustmentRefiner()),
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--views", type=int, nargs="+", default=[360, 1440, 2880])
    parser.add_argument("--points-per-view", type=float, default=10.0,
                        help="new points entering the field per view (observations ~ 7.5 x this x views)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    print(f"{'refiner':20s} {'views':>6s} {'observations':>12s} {'seconds':>8s} {'max err deg':>11s} {'rms err deg':>11s}")
    times = {name: [] for name in REFINERS}
    for n_views in args.views:
        scan = synthetic_scan(n_views, int(args.points_per_view * n_views), rng=args.seed, noise_px=0.2,
                              outlier_fraction=0.2, outliers_verified=False, track_length=(3, 12))
        n_obs = sum(len(f) for f in scan.observations.features)
        for name, run in REFINERS.items():
            start = time.perf_counter()
            angles, info = run(scan)
            seconds = time.perf_counter() - start
            times[name].append(seconds)
            error = np.rad2deg(angles - scan.true_angles_rad)
            used = info.get("observations", n_obs)
            print(f"{name:20s} {n_views:6d} {used:12d} {seconds:8.2f} {np.nanmax(np.abs(error)):11.3f} "
                  f"{np.sqrt(np.nanmean(error**2)):11.3f}", flush=True)
    if len(args.views) > 1:
        for name, seconds in times.items():
            exponent = np.polyfit(np.log(args.views), np.log(seconds), 1)[0]
            print(f"{name}: time ~ views^{exponent:.2f}")


if __name__ == "__main__":
    main()
