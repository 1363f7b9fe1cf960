"""Refiners against view count: the pair graph (``least-squares``), ``bundle-adjustment`` and projection matching.

Every row refines the same synthetic scan (:func:`ctpipe.solve.simulated.synthetic_scan`):
points projected over a full turn with 0.2 px noise, 20 % wrong matches (which the pair
verification caught), tracks of 3-12 views, pairs at baselines 1 and 2 with the seam closed. Prints seconds,
observations, the maximum angle error and, per refiner, the scaling exponent of the time
(least squares fit of log seconds against log views). Figures only; nothing is asserted.

    python benchmarks/bench_refiners.py [--views 360 1440 2880] [--points-per-view 10] [--seed 0]

A further feature refiner is one more entry in ``REFINERS``: a name and a function
``(SyntheticScan) -> (angles_rad, info)``.

Projection matching works on pixels, not tracks: its rows simulate the granular sample on a
small detector (``--detector``, default 256^2 pixels, 0.2 deg jitter) at the same view counts
and time :func:`ctpipe.solve.reprojection.projection_matching` with the refiner's
default levels (binned to 128 then 256 pixels a side), started from the nominal angles.

    python benchmarks/bench_refiners.py --detector 256 --projection-views 360 1440 2880
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from ctpipe.builtin.bundle import BundleAdjustmentRefiner
from ctpipe.builtin.refiners import LeastSquaresRefiner
from ctpipe.evaluate.scoring import view_errors_deg
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


def bench_projection_matching(views: list[int], detector: int, seed: int) -> None:
    """Time projection matching on simulated projections of the granular sample."""
    from ctpipe.builtin.projection_matching import ProjectionMatchingRefiner
    from ctpipe.sim.phantoms import load_phantom
    from ctpipe.sim.scan_spec import parse_scan_spec
    from ctpipe.sim.simulator import simulate
    from ctpipe.solve.reprojection import matching_levels, projection_matching

    defaults = ProjectionMatchingRefiner()
    phantom = load_phantom("granular")
    pitch = 0.8 * 512 / detector
    levels = matching_levels((detector, detector), defaults.iterations, level_px=defaults.level_px)
    print(f"\nprojection matching, granular sample on {detector}^2 pixels of {pitch:.2f} mm, (binning, iterations) "
          f"{levels}, from the nominal angles")
    print(f"{'views':>6s} {'simulate s':>10s} {'match s':>8s} {'warm-up s':>9s} {'nominal rms':>11s} {'rms err deg':>11s}")
    seconds = []
    for n_views in views:
        spec = parse_scan_spec({
            "geometry": {"source_to_object_mm": 150.0, "source_to_detector_mm": 390.0, "detector_cols": detector,
                         "detector_rows": detector, "pixel_pitch_u_mm": pitch, "pixel_pitch_v_mm": pitch},
            "angles": {"n_views": n_views, "range_deg": 360.0}, "jitter": [{"gaussian": {"sigma_deg": 0.2}}],
            "noise": {"photons_per_pixel": 100000, "flat_frames": 4, "dark_frames": 2, "dark_counts": 100},
            "projector": {"kind": "analytic", "supersample": 1, "blur_px": 0.5}, "seed": seed})
        start = time.perf_counter()
        scan = simulate(phantom, spec, rng=np.random.default_rng(seed))
        simulated = time.perf_counter() - start
        # A first call on a few views compiles (or loads) the numba kernels: reported apart.
        start = time.perf_counter()
        projection_matching(scan.projections[:40], scan.geometry, scan.nominal_angles_deg[:40], binning=[4],
                            iterations=[1])
        warm_up = time.perf_counter() - start
        start = time.perf_counter()
        result = projection_matching(scan.projections, scan.geometry, scan.nominal_angles_deg,
                                     binning=[b for b, _ in levels], iterations=[n for _, n in levels],
                                     band_px=(defaults.band_low_px, defaults.band_high_px),
                                     max_voxels=defaults.max_voxels, filter=defaults.filter,
                                     max_step_deg=defaults.max_step_deg)
        seconds.append(time.perf_counter() - start)
        truth = scan.true_angles_deg
        err = lambda a: np.sqrt(np.mean(view_errors_deg(a, truth) ** 2))
        print(f"{n_views:6d} {simulated:10.1f} {seconds[-1]:8.2f} {warm_up:9.2f} {err(scan.nominal_angles_deg):11.3f} "
              f"{err(result.angles_deg):11.3f}", flush=True)
    if len(views) > 1:
        print(f"projection-matching: time ~ views^{np.polyfit(np.log(views), np.log(seconds), 1)[0]:.2f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--views", type=int, nargs="+", default=[360, 1440, 2880])
    parser.add_argument("--points-per-view", type=float, default=10.0,
                        help="new points entering the field per view (observations ~ 7.5 x this x views)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--detector", type=int, default=256, help="projection matching: detector pixels per side")
    parser.add_argument("--projection-views", type=int, nargs="*", default=[360, 1440, 2880],
                        help="projection matching: view counts (none: skip)")
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
    if args.projection_views:
        bench_projection_matching(args.projection_views, args.detector, args.seed)


if __name__ == "__main__":
    main()
