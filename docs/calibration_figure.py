"""Draw docs/calibration-beads.png: the balls found in one view of a ball-bar scan, and their tracks.

    python docs/calibration_figure.py [--out docs/calibration-beads.png]

Simulates the ball bar of ``configs/experiments/calibration-16-views.yaml`` (16 views, 22.5 deg
steps, stage errors of 0.2 deg plus a 0.5 deg jump), runs ``configs/calibration-beads.yaml`` on
it, and draws: left, view 1 (where balls overlap on the detector) with every ball the ``beads``
detector found (circle: its fitted diameter; orange: flagged as overlapping or truncated);
right, the position of every ball in every view, joined along the tracks bundle adjustment
fitted; below, each view's angle error after the common offset against the nominal angles'.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))


def draw(out: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from calibration_scans import simulate_calibration_scan
    from matplotlib.patches import Circle

    from ctpipe.evaluate.scoring import view_errors_deg
    from ctpipe.pipeline import Pipeline
    from ctpipe.builtin.bundle import _without_deviating_pairs
    from ctpipe.solve.bundle import BundleSettings, solve_bundle

    scan, _ = simulate_calibration_scan("ball-bar", 16, seed=0)
    pipeline = Pipeline.from_config(ROOT / "configs" / "calibration-beads.yaml")
    observations = pipeline.observe(scan.projections, scan.geometry, nominal_angles_deg=scan.nominal_angles_deg)
    result = pipeline.refine(observations)
    nominal = scan.nominal_angles_deg
    # The tracks the refiner adjusted: the same settings, the same pairs left out.
    refiner = pipeline.refiner
    kept = _without_deviating_pairs(observations, refiner.max_pair_deviation_deg)
    tracks = solve_bundle(kept, BundleSettings(outlier_threshold_px=refiner.outlier_threshold_px),
                          start_angles_rad=np.deg2rad(nominal - nominal[0])).tracks
    errors = view_errors_deg(result.angles_deg, scan.true_angles_deg)
    nominal_errors = view_errors_deg(nominal, scan.true_angles_deg)

    fig = plt.figure(figsize=(12, 8.5))
    grid = fig.add_gridspec(2, 2, height_ratios=(3, 1.3))
    view = 1
    ax = fig.add_subplot(grid[0, 0])
    ax.imshow(scan.projections[view], cmap="gray")
    features = observations.features[view]
    for (x, y), size, flag in zip(features.xy, features.size, features.class_id):
        ax.add_patch(Circle((x, y), size / 2, fill=False, lw=1.2, color="tab:orange" if flag else "tab:cyan"))
    ax.set_title(f"view {view}: {len(features)} balls found (orange: overlapping or truncated)", fontsize=10)
    ax.set_axis_off()

    ax = fig.add_subplot(grid[0, 1])
    ax.set_facecolor("black")
    for t in range(tracks.n_tracks):
        mine = tracks.track == t
        order = np.argsort(tracks.view[mine])
        xy = tracks.xy_px[mine][order]
        ax.plot(xy[:, 0], xy[:, 1], "-o", ms=3, lw=1)
    ax.set_xlim(0, scan.geometry.detector_cols)
    ax.set_ylim(scan.geometry.detector_rows, 0)
    ax.set_aspect("equal")
    ax.set_title(f"{tracks.n_tracks} ball tracks over {len(nominal)} views (each ball's centre in every view)",
                 fontsize=10)

    ax = fig.add_subplot(grid[1, :])
    ax.plot(nominal_errors, "s-", color="tab:gray", label=f"nominal (max {np.abs(nominal_errors).max():.3f} deg)")
    ax.plot(errors, "o-", color="tab:blue", label=f"estimated (max {np.nanmax(np.abs(errors)):.4f} deg)")
    ax.axhline(0.0, color="k", lw=0.5)
    ax.set_xlabel("view")
    ax.set_ylabel("angle error (deg)")
    ax.legend(fontsize=9)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100)
    plt.close(fig)
    return out


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path(__file__).with_name("calibration-beads.png"))
    print(draw(parser.parse_args(argv).out))


if __name__ == "__main__":
    main()
