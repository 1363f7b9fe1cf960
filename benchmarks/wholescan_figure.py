"""Per-view angle error of every refiner on one scan: the figure and table of docs/wholescan.md.

Simulates an experiment (default: the built-in ``ctpipe validate`` one), detects, matches and
estimates its pairs once (:meth:`ctpipe.pipeline.Pipeline.observe`), then refines the same
observations with each refiner and plots the error of every view against the truth (common
offset removed). Also shown: the nominal angles, and the consecutive pairs chained without
loop closure (what ctpipe did before), with and without the static background removed.

    python benchmarks/wholescan_figure.py [EXPERIMENT.yaml] [--out docs/wholescan_errors.png]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from ctpipe.evaluate.report import _figure_png, _pyplot
from ctpipe.evaluate.scoring import view_errors_deg
from ctpipe.evaluate.validate import load_validate_settings, pair_chained_deg
from ctpipe.pipeline import Pipeline
from ctpipe.plugins import get_registry
from ctpipe.sim.simulator import simulate

REFINERS = {
    "least-squares (robust view graph + seam)": {"name": "least-squares", "weighting": "inliers"},
    "bundle-adjustment": {"name": "bundle-adjustment"},
    "projection-matching (the default)": {"name": "projection-matching"},
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("experiment", nargs="?", default=None)
    parser.add_argument("--out", default="docs/wholescan_errors.png")
    args = parser.parse_args()
    registry = get_registry()
    settings = load_validate_settings(args.experiment, registry)
    scan = simulate(settings.phantom, settings.scan, rng=np.random.default_rng(settings.seed))
    nominal, truth = scan.nominal_angles_deg, scan.true_angles_deg
    config = settings.pipeline.to_dict()
    curves = {"nominal angles": view_errors_deg(nominal, truth)}
    rows = []
    for background in ("off", "auto"):
        pipeline = Pipeline.from_config({**config, "preprocess": {"static_background": background}}, registry=registry)
        start = time.perf_counter()
        observations = pipeline.observe(scan.projections, scan.geometry, nominal_angles_deg=nominal)
        observed = time.perf_counter() - start
        pair_angles = np.array([np.rad2deg(e.angle_rad) if e else np.nan for e in observations.estimates])
        label = "pairs chained, no loop closure" + (", background removed" if background == "auto" else "")
        curves[label] = view_errors_deg(pair_chained_deg(observations.pairs, pair_angles, nominal), truth)
        rows.append((label, curves[label], observed))
        refiners = REFINERS if background == "auto" else {"least-squares, background kept": REFINERS[
            "least-squares (robust view graph + seam)"]}
        for name, stage in refiners.items():
            refined = Pipeline.from_config({**config, "refiner": stage}, registry=registry)
            start = time.perf_counter()
            result = refined.refine(observations)
            curves[name] = view_errors_deg(result.angles_deg, truth)
            rows.append((name, curves[name], time.perf_counter() - start))
    print(f"{'angles':55s} {'RMS deg':>8s} {'MAE deg':>8s} {'max deg':>8s} {'seconds':>8s}")
    print(f"{'nominal angles':55s} {np.sqrt(np.mean(curves['nominal angles'] ** 2)):8.4f} "
          f"{np.mean(np.abs(curves['nominal angles'])):8.4f} {np.max(np.abs(curves['nominal angles'])):8.4f}")
    for name, errors, seconds in rows:
        print(f"{name:55s} {np.sqrt(np.nanmean(errors ** 2)):8.4f} {np.nanmean(np.abs(errors)):8.4f} "
              f"{np.nanmax(np.abs(errors)):8.4f} {seconds:8.1f}")

    plt = _pyplot()
    fig, axes = plt.subplots(2, 1, figsize=(11, 7.5), sharex=True)
    for name, errors in curves.items():
        rms = np.sqrt(np.nanmean(errors ** 2))
        for ax in axes:
            ax.plot(errors, lw=0.9, label=f"{name} (RMS {rms:.3f})")
    axes[0].set_ylim(-6.5, 6.5)
    axes[1].set_ylim(-0.6, 0.6)
    axes[0].set_title(f"per-view angle error against the truth, {settings.source} ({len(truth)} views)")
    axes[1].set_title("the same, zoomed in")
    axes[1].set_xlabel("view")
    for ax in axes:
        ax.set_ylabel("error (deg)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7, loc="lower left")
    fig.tight_layout()
    with open(args.out, "wb") as handle:
        handle.write(_figure_png(fig))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
