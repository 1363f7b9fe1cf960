"""The ball finder's rims fitted ray by ray against the same rims fitted all together, in one run.

Where the clip cuts a ball's rim, the ball finder places it by fitting a blurred sphere's profile
along each ray (:func:`ctpipe.features.ball_edges._uncut_rim`): once with the shape free on a
sample of the rays, then with the shape held on every ray (:func:`ball_edges._held_shape_fit`).
Held, each ray's fit is its own, and a round evaluates only the rays still moving. The peer is
the fit as it was (:func:`all_rays_every_round`, kept here): every ray evaluated in every round
until the last had settled, which on a 36-view hardened scan went on to the thirtieth round for
2-5 % of the rays. Both detect the same simulated views (``bench_ball_phantom_mixed.py --solid
--saturation 0.9``: seven solid balls, 2000^2, a clip at 90 % of the open beam), alternately for
``--repeats`` rounds, and the run prints each round's seconds, their ratio and how far apart the
two place the discs (px).

    python benchmarks/bench_ball_rims.py [--views 6] [--seed 2001] [--repeats 2]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from bench_ball_phantom_mixed import simulate_scan
from ctpipe.builtin.beads import BeadDetector
from ctpipe.features import ball_edges


def all_rays_every_round(values, use, radii, rims, shape, *, sloped):
    """The held-shape fit as :func:`ball_edges._blurred_fit` made it before: the same Gauss-Newton steps per ray, a
    step that raises a ray's sum of squares refused and its next one halved, but every ray evaluated in every round
    until no ray's step reaches ``_FIT_SETTLED_PX``."""
    weight = use.astype(np.float64)
    count = np.maximum(weight.sum(axis=1), 1.0)
    shape = np.array(shape, dtype=np.float64)
    rims = np.array(rims, dtype=np.float64)
    background_of = ball_edges._background_projection(weight, radii, sloped)

    def residual(at):
        model, slope = ball_edges._blurred_profile(at, shape, radii)
        rest, background = background_of((values - model) * weight)
        return rest, background, slope

    res, background, slope = residual(rims)
    sse = (res ** 2).sum(axis=1)
    room = np.ones(len(rims))
    for _ in range(ball_edges._FIT_ROUNDS):
        jr, _ = background_of(slope * weight)
        step = np.clip((res * jr).sum(axis=1) / ((jr * jr).sum(axis=1) + 1e-12), -1.0, 1.0) * room
        trial = residual(rims + step)
        trial_sse = (trial[0] ** 2).sum(axis=1)
        better = trial_sse < sse
        room = np.where(better, 1.0, 0.5 * room)
        done = np.abs(step).max(initial=0.0) < ball_edges._FIT_SETTLED_PX
        rims = np.where(better, rims + step, rims)
        res = np.where(better[:, None], trial[0], res)
        background = np.where(better, trial[1], background)
        slope = np.where(better[:, None], trial[2], slope)
        sse = np.where(better, trial_sse, sse)
        if done:
            break
    return shape, background, np.where(np.isfinite(sse), rims, np.nan), np.sqrt(sse / count)


def detect(detector, views):
    """Every view's discs and the seconds they took."""
    start = time.perf_counter()
    found = [detector.detect(view) for view in views]
    return found, time.perf_counter() - start


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--views", type=int, default=6)
    parser.add_argument("--seed", type=int, default=2001)
    parser.add_argument("--repeats", type=int, default=2)
    args = parser.parse_args(argv)

    start = time.perf_counter()
    scan, _, _ = simulate_scan(args.views, 0.5, None, args.seed, saturation=0.9, solid=True)
    views = [np.ascontiguousarray(view) for view in scan.projections]
    print(f"{len(views)} views of {scan.geometry.detector_cols}x{scan.geometry.detector_rows} simulated in "
          f"{time.perf_counter() - start:.1f} s")
    detector = BeadDetector()
    detector.detect(views[0])                      # numba's kernels loaded (or compiled) before the clock
    held = ball_edges._held_shape_fit
    apart = 0.0
    for round_ in range(args.repeats):
        ray_by_ray, ray_s = detect(detector, views)
        ball_edges._held_shape_fit = all_rays_every_round
        try:
            together, together_s = detect(detector, views)
        finally:
            ball_edges._held_shape_fit = held
        same = all(len(a.xy) == len(b.xy) for a, b in zip(ray_by_ray, together))
        if same:
            apart = max([apart] + [float(np.abs(a.xy - b.xy).max(initial=0.0)) for a, b in zip(ray_by_ray, together)])
        print(f"round {round_ + 1}: ray by ray {ray_s:.1f} s, all together {together_s:.1f} s "
              f"({together_s / ray_s:.2f}x); {sum(len(f.xy) for f in ray_by_ray)} discs, "
              f"{'the same discs' if same else 'NOT the same discs'}")
    print(f"the discs' centres at most {apart:.5f} px apart (float32 centres: a last bit is 0.00006 px at 1000 px)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
