"""The ball calibration's bundle adjustment: its Jacobian by grouped forward differences, against scipy's own.

``calibrate_balls`` on synthetic discs (ellipse centres of balls at random places, 0.02 px of
noise, dust, nominal angles off by up to 2 deg), timed as it runs, where each adjustment's
Jacobian steps the columns that share no disc row together and gives the gauge row's slope
(``_forward_differences`` in ``ctpipe/solve/balls.py``); and, in the same run, the peer: the same
calibration with every adjustment handed to ``scipy.optimize.least_squares`` as before, the
Jacobian's structure (gauge row included) as ``jac_sparsity`` for scipy's own sparse differences
(and so lsmr's inexact trust-region steps, where ctpipe hands a Jacobian this small dense for exact
ones: ``_DENSE_JACOBIAN_ENTRIES``).
Prints the median wall time of each over ``--runs``, their ratio, the residual evaluations each
made, and how far the two calibrations' angles lie apart (less their common turn). Never fails on
time.

    python benchmarks/bench_ball_adjustment.py [--views 36] [--balls 9] [--runs 3] [--seed 0]
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import scipy.optimize

from ctpipe.evaluate.scoring import view_errors_deg
from ctpipe.geometry import Geometry
from ctpipe.solve.balls import calibrate_balls, ellipse_centres

#: The issue's class of scanner: 2000^2 of 0.2 mm at magnification 5.8.
GEOMETRY = Geometry(source_to_object_mm=150.0, source_to_detector_mm=870.0, detector_cols=2000, detector_rows=2000,
                    pixel_pitch_u_mm=0.2, pixel_pitch_v_mm=0.2)


def synthetic_scan(views: int, balls: int, seed: int):
    """(detections per view, nominal angles, true angles): balls 8-17 mm from the axis at heights within 18 mm,
    discs at their ellipse centres with 0.02 px of noise and two dust specks a view."""
    rng = np.random.default_rng(seed)
    distance, azimuth = rng.uniform(8.0, 17.0, balls), rng.uniform(0.0, 2.0 * np.pi, balls)
    centres = np.column_stack([distance * np.cos(azimuth), rng.uniform(-18.0, 18.0, balls),
                               distance * np.sin(azimuth)])
    radius_mm = 2.75
    truth = np.linspace(0.0, 360.0, views, endpoint=False)
    nominal = truth + rng.uniform(-2.0, 2.0, views)
    detections = []
    for angle in np.deg2rad(truth):
        uv = ellipse_centres(centres, np.full(balls, radius_mm), np.full(balls, angle), GEOMETRY, 1001.0,
                             GEOMETRY.v0_px, np.deg2rad(-0.3))
        uv = uv + rng.normal(0.0, 0.02, uv.shape)
        depth = np.sin(angle) * centres[:, 0] + np.cos(angle) * centres[:, 2] + GEOMETRY.source_to_object_mm
        radius_px = radius_mm * GEOMETRY.source_to_detector_mm / (GEOMETRY.pixel_pitch_u_mm * depth)
        found = np.column_stack([uv, radius_px, np.zeros(balls)])
        dust = np.column_stack([rng.uniform(0, 2000, (2, 2)), np.full(2, 80.0), np.zeros(2)])
        detections.append(np.vstack([found, dust])[rng.permutation(balls + 2)])
    return detections, nominal, truth


class _Peer:
    """``scipy.optimize.least_squares`` as the adjustment called it before (``peer``): a Jacobian callable replaced
    by its structure at the start (``jac_sparsity``), for scipy's sparse forward differences. Either way, counts the
    evaluations of the discs' model (:func:`ellipse_centres`) made inside it: scipy's and the Jacobian's own."""

    def __init__(self, original, peer: bool):
        self.original, self.peer, self.inside, self.evaluations = original, peer, False, 0

    def __call__(self, fun, x0, *args, jac="2-point", **kwargs):
        if self.peer and callable(jac):
            kwargs["jac_sparsity"] = jac(np.asarray(x0, dtype=np.float64)) != 0
            jac = "2-point"
        self.inside = True
        try:
            return self.original(fun, x0, *args, jac=jac, **kwargs)
        finally:
            self.inside = False


def _timed(detections, nominal, *, peer: bool, runs: int):
    """Median seconds of ``runs`` calibrations, the model's evaluations in one, and the last calibration."""
    import ctpipe.solve.balls as balls_module

    original_fit, original_centres = scipy.optimize.least_squares, balls_module.ellipse_centres
    wrapper = _Peer(original_fit, peer)

    def counted_centres(*args, **kwargs):
        wrapper.evaluations += wrapper.inside
        return original_centres(*args, **kwargs)

    scipy.optimize.least_squares = wrapper
    balls_module.ellipse_centres = counted_centres
    try:
        seconds = []
        for _ in range(runs):
            wrapper.evaluations = 0
            start = time.perf_counter()
            found = calibrate_balls(detections, GEOMETRY, nominal, max_error_deg=2.0)
            seconds.append(time.perf_counter() - start)
    finally:
        scipy.optimize.least_squares = original_fit
        balls_module.ellipse_centres = original_centres
    return statistics.median(seconds), wrapper.evaluations, found


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--views", type=int, default=36)
    parser.add_argument("--balls", type=int, default=9)
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)

    detections, nominal, truth = synthetic_scan(args.views, args.balls, args.seed)
    grouped_s, grouped_n, grouped = _timed(detections, nominal, peer=False, runs=args.runs)
    peer_s, peer_n, peer = _timed(detections, nominal, peer=True, runs=args.runs)
    apart = np.abs(view_errors_deg(grouped.corrected_deg, peer.corrected_deg)).max()
    print(f"{args.views} views, {args.balls} balls, seed {args.seed}; median of {args.runs} runs")
    print(f"  grouped differences (ctpipe): {grouped_s:6.2f} s, {grouped_n} residual evaluations; worst view "
          f"{np.abs(view_errors_deg(grouped.corrected_deg, truth)).max():.4f} deg; {grouped.reason[:60]}")
    print(f"  scipy's sparse differences (peer): {peer_s:6.2f} s, {peer_n} residual evaluations; worst view "
          f"{np.abs(view_errors_deg(peer.corrected_deg, truth)).max():.4f} deg")
    print(f"  ratio peer / ctpipe: {peer_s / grouped_s:.1f}x the time, {peer_n / max(grouped_n, 1):.1f}x the "
          f"evaluations; the two calibrations' angles {apart:.2g} deg apart (their common turn taken out)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
