"""The view-graph solver on a large scan: 3,000 views, baselines 1, 2 and 4 with the seam pairs.

Pair angles are the true turns plus N(0, 0.002^2) deg noise, with 1 % of the pairs slipped by
2-10 deg. Prints, for every loss, the time of one solve (best of ``--repeat``), the reweighted
iterations it took and the per-view RMS error against the truth.

    python benchmarks/bench_graph.py [--views 3000] [--repeat 3] [--seed 0]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from ctpipe.solve.graph import solve_pair_graph, unwrap_pair_angles_deg, view_pairs
from ctpipe.solve.losses import LOSSES


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--views", type=int, default=3000)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    nominal = np.arange(args.views) * 360.0 / args.views
    truth = nominal + rng.normal(0.0, 0.02, args.views)
    pairs = view_pairs(args.views, (1, 2, 4), nominal)
    turns = np.mod(truth[pairs[:, 1]] - truth[pairs[:, 0]] + 180.0, 360.0) - 180.0
    measured = turns + rng.normal(0.0, 0.002, len(pairs))
    slipped = rng.choice(len(pairs), len(pairs) // 100, replace=False)
    measured[slipped] += rng.choice([-1.0, 1.0], len(slipped)) * rng.uniform(2.0, 10.0, len(slipped))
    measured = unwrap_pair_angles_deg(pairs, measured, nominal)
    print(f"{args.views} views, {len(pairs)} pairs ({len(slipped)} slipped)")
    for loss in LOSSES:
        best = np.inf
        for _ in range(args.repeat):
            start = time.perf_counter()
            solution = solve_pair_graph(args.views, pairs, measured, loss=loss, scale_deg=0.01)
            best = min(best, time.perf_counter() - start)
        error = solution.angles_deg - (truth - truth[0])
        rms = float(np.sqrt(np.mean((error - np.median(error)) ** 2)))
        print(f"  {loss:<8} {1e3 * best:8.1f} ms  {solution.n_iterations:3d} iterations  per-view RMS {rms:.4f} deg")


if __name__ == "__main__":
    main()
