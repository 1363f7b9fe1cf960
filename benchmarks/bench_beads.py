"""The ``beads`` detector: centre accuracy against analytic ball centres, and time per image.

Balls are rendered by :func:`ctpipe.testing.render_balls` (chord profiles of known sub-pixel
centres, Gaussian PSF of 0.7 px, pixel integration, Poisson counts) on 512^2 images of 30 balls
(a 6 x 5 grid with random sub-pixel offsets and radii within 5 %), peak line integral 1. For a
grid of diameters and noise levels, and both centre methods, prints:

- found / true balls; RMS and max centre error (px) of the balls found; median radius error;
- the Cramer-Rao bound of the centre (px, RMS over x and y) for that ball and noise: about the
  least RMS any unbiased estimator can reach, from the detector model's Jacobian (the PSF width,
  radius and height unknown too) and the Poisson statistics of each pixel;
- time per image (median of ``--repeats`` after a warm-up; never a pass/fail).

Then overlapping balls: pairs whose centres are 0.25, 0.6 and 0.9 diameters apart (0.25 and 0.6
show one peak), and a chain of seven balls seen end-on (a ball bar along its rod).

Noise levels: ``none`` (noise-free line integrals), ``1e5``/``3e4``/``1e4`` photons per
unattenuated pixel as ``-log`` line integrals (bright balls), and ``3e4 raw`` as uint16 counts
(dark balls, polarity decided by the detector).

    python benchmarks/bench_beads.py [--repeats 3] [--quick]
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from ctpipe.builtin.beads import BeadDetector
from ctpipe.features._disc_model import _Window
from ctpipe.testing import render_balls

SHAPE = (512, 512)
BLUR_PX = 0.7
NOISE_LEVELS = ("none", "1e5", "3e4", "1e4", "3e4 raw")


def ball_grid(diameter_px: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """30 centres on a 6 x 5 grid with sub-pixel offsets, radii within 5 % of ``diameter_px / 2``."""
    rng = np.random.default_rng(seed)
    cols, rows = np.meshgrid((np.arange(6) + 0.5) * SHAPE[1] / 6, (np.arange(5) + 0.5) * SHAPE[0] / 5)
    centres = np.column_stack([cols.ravel(), rows.ravel()]) + rng.uniform(-0.5, 0.5, (30, 2))
    return centres, 0.5 * diameter_px * rng.uniform(0.95, 1.05, 30)


def render(centres, radii, noise: str, seed: int) -> np.ndarray:
    if noise == "none":
        return render_balls(SHAPE, centres, radii, blur_sigma_px=BLUR_PX)
    photons = float(noise.split()[0])
    if noise.endswith("raw"):
        counts = render_balls(SHAPE, centres, radii, blur_sigma_px=BLUR_PX, photons=photons, intensities=True, rng=seed)
        return counts.astype(np.uint16)
    return render_balls(SHAPE, centres, radii, blur_sigma_px=BLUR_PX, photons=photons, rng=seed)


def cramer_rao_px(radius: float, noise: str) -> float:
    """RMS (over x and y) Cramer-Rao bound of the centre of one ball of peak 1 at this noise."""
    if noise == "none":
        return 0.0
    photons = float(noise.split()[0])
    half = int(np.ceil(1.3 * radius + 4.0))
    xs = np.arange(-half, half + 1, dtype=np.float64)
    start = np.array([[0.3, 0.2, radius, 1.0]])
    window = _Window(np.zeros((len(xs), len(xs))), xs, xs, np.ones((len(xs), len(xs)), bool), start)
    params = np.array([0.0, 0.0, 0.0, BLUR_PX, 0.3, 0.2, radius, 1.0])
    line_integral, jac = window._evaluate(params)
    # Counts N T with T = exp(-p) hold the same information as -log(counts / N), whose variance
    # is 1 / (N T): the Fisher matrix is J^T diag(N T) J for either.
    weight = photons * np.exp(-line_integral)
    fisher = jac.T @ (jac * weight[:, None])
    # The plane (3 columns) is known here; sigma, centre, radius and height are not.
    covariance = np.linalg.inv(fisher[3:, 3:])
    return float(np.sqrt(0.5 * (covariance[1, 1] + covariance[2, 2])))


def measure(detector: BeadDetector, image: np.ndarray, centres: np.ndarray, radii: np.ndarray, repeats: int):
    detector.detect(image)  # warm-up (numba cache load)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        features = detector.detect(image)
        times.append(time.perf_counter() - start)
    distance = np.linalg.norm(features.xy[:, None, :].astype(np.float64) - centres[None], axis=2)
    nearest, index = distance.min(axis=0), distance.argmin(axis=0)
    found = nearest < 0.5 * radii
    radius_error = np.median(features.size[index[found]] / 2 / radii[found] - 1) if found.any() else np.nan
    rms = float(np.sqrt(np.mean(nearest[found] ** 2))) if found.any() else np.nan
    top = float(nearest[found].max()) if found.any() else np.nan
    return int(found.sum()), len(features), rms, top, radius_error, statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3, help="timed runs per image (median)")
    parser.add_argument("--quick", action="store_true", help="diameters 8 and 20 only, one timed run")
    args = parser.parse_args()
    diameters = (8, 20) if args.quick else (8, 12, 20, 30, 40)
    repeats = 1 if args.quick else args.repeats

    print(f"{SHAPE[0]}x{SHAPE[1]} images of 30 balls, peak line integral 1, Gaussian PSF {BLUR_PX} px; "
          f"centre errors in px against the rendered centres")
    print(f"{'diam px':>7} {'noise':>8} {'method':>8} {'found':>7} {'rms px':>8} {'max px':>8} {'CRLB px':>8} "
          f"{'r err':>7} {'time s':>7}")
    for diameter in diameters:
        centres, radii = ball_grid(diameter, seed=diameter)
        for k, noise in enumerate(NOISE_LEVELS):
            image = render(centres, radii, noise, seed=k)
            bound = cramer_rao_px(0.5 * diameter, noise)
            for method in ("fit", "centroid"):
                detector = BeadDetector(min_diameter_px=6.0, max_diameter_px=48.0, centre_method=method)
                found, n, rms, top, radius_error, seconds = measure(detector, image, centres, radii, repeats)
                extra = "" if n == found else f"  ({n} keypoints)"
                print(f"{diameter:>7} {noise:>8} {method:>8} {found:>3}/{len(centres):<3} {rms:>8.4f} {top:>8.4f} "
                      f"{bound:>8.4f} {radius_error:>+7.3f} {seconds:>7.3f}{extra}")

    print()
    print("overlapping balls (fit), 1e5 photons, -log line integrals, all flagged 1 expected")
    print(f"{'case':>28} {'found':>7} {'rms px':>8} {'max px':>8} {'flag 1':>7} {'time s':>7}")
    rng = np.random.default_rng(1)
    for diameter in (8, 12, 20):
        first, _ = ball_grid(diameter, seed=100 + diameter)
        first = first[:15]
        angle = rng.uniform(0, np.pi, len(first))
        for separation in (0.25, 0.6, 0.9):
            offset = separation * diameter * np.column_stack([np.cos(angle), np.sin(angle)])
            centres = np.concatenate([first, first + offset])
            radii = np.full(len(centres), 0.5 * diameter)
            image = render_balls(SHAPE, centres, radii, blur_sigma_px=BLUR_PX, photons=1e5, rng=2)
            detector = BeadDetector(min_diameter_px=6.0, max_diameter_px=48.0)
            found, n, rms, top, _, seconds = measure(detector, image, centres, radii, repeats)
            flagged = int(np.sum(detector.detect(image).class_id == 1))
            print(f"{f'd={diameter} pairs {separation:g} d apart':>28} {found:>3}/{len(centres):<3} {rms:>8.4f} "
                  f"{top:>8.4f} {flagged:>7} {seconds:>7.3f}")
    step = 0.78 * 24.0 * np.array([0.36, 0.93])
    centres = np.array([200.3, 160.6]) + np.arange(7)[:, None] * step
    radii = np.linspace(12.5, 11.5, 7)
    image = render_balls(SHAPE, centres, radii, peak=1.25, blur_sigma_px=BLUR_PX, photons=5e4, rng=3)
    found, n, rms, top, _, seconds = measure(BeadDetector(), image, centres, radii, repeats)
    print(f"{'chain of 7, 0.78 d apart':>28} {found:>3}/{len(centres):<3} {rms:>8.4f} {top:>8.4f} "
          f"{int(np.sum(BeadDetector().detect(image).class_id == 1)):>7} {seconds:>7.3f}")


if __name__ == "__main__":
    main()
