"""Diagnosis before cure: does the refiner stay at the truth, walk away from it, or see nothing?

For every scenario of a sweep (``ctpipe experiment sweep --out DIR``) that does not end at half
its nominal per-view RMS or less, the scan is simulated again exactly as ``validate`` does, and
projection matching (the default refiner, gate off) is started at the TRUE angles:

- **stays**: it ends within a quarter of the nominal RMS of the truth; the failure was the start
  or its basin (the features, the capture range);
- **walks away**: it moves further, its cost falling as it goes, so the cost is lower away from
  the truth: a model error (what the reference volume and the data disagree on);
- **flat**: the data do not tell the truth from the nominal angles: their consistency costs
  (:func:`ctpipe.solve.reprojection.consistency_costs`, at the coarse level) differ by less than
  twice what fitting the unknowns to noise takes off (the refiner's own threshold); the nominal
  angles are right to keep.

Prints one markdown row per scenario: the table of ``docs/wholescan.md``.

    python benchmarks/diagnose_refiner.py results/sweep [--only 3,7,21]
"""

from __future__ import annotations

import argparse
import csv
import time
from pathlib import Path

import numpy as np

from ctpipe.builtin.projection_matching import ProjectionMatchingRefiner
from ctpipe.evaluate.scoring import view_errors_deg
from ctpipe.evaluate.validate import parse_validate
from ctpipe.config import load_yaml
from ctpipe.plugins import get_registry
from ctpipe.sim.simulator import simulate
from ctpipe.solve.reprojection import consistency_costs, matching_levels, projection_matching, static_part_applies


def rms(angles_deg, truth_deg) -> float:
    return float(np.sqrt(np.nanmean(view_errors_deg(angles_deg, truth_deg) ** 2)))


def diagnose(path: Path) -> dict:
    registry = get_registry()
    settings = parse_validate(load_yaml(path), registry, base_dir=path.parent, path=str(path))
    scan = simulate(settings.phantom, settings.scan, rng=np.random.default_rng(settings.seed))
    geometry, truth, nominal = scan.geometry, scan.true_angles_deg, scan.nominal_angles_deg
    refiner = ProjectionMatchingRefiner()
    levels = matching_levels(geometry.shape, refiner.iterations, level_px=refiner.level_px)
    static = refiner.static and static_part_applies(nominal)
    start = time.perf_counter()
    walk = projection_matching(scan.projections, geometry, truth, binning=[b for b, _ in levels],
                               iterations=[n for _, n in levels], band_px=(refiner.band_low_px, refiner.band_high_px),
                               max_voxels=refiner.max_voxels, shifts=refiner.shifts, detector=refiner.detector,
                               static=static)
    seconds = time.perf_counter() - start
    costs = consistency_costs(scan.projections, geometry, {"truth": truth, "nominal": nominal}, binning=levels[0][0],
                              max_voxels=refiner.max_voxels, static=static)
    first = walk.history[0]
    kept = [h for h in walk.history if h["accepted"] and h["kind"] != "start"]
    nominal_rms, walked = rms(nominal, truth), rms(walk.angles_deg, truth)
    separation = (costs["nominal"] - costs["truth"]) / max(2.0 * first.get("noise_drop", 0.0), 1e-300)
    if walked <= 0.25 * nominal_rms:
        verdict = "stays"
    elif kept:
        verdict = "walks away"
    else:
        verdict = "stays"
    if abs(separation) < 1.0:
        verdict = "flat" if verdict == "stays" else verdict + " (flat)"
    return {"nominal_rms_deg": nominal_rms, "from_truth_rms_deg": walked, "steps_kept": len(kept),
            "cost_nominal_over_truth": costs["nominal"] / costs["truth"] - 1.0, "separation": separation,
            "axis_px": walk.axis_offset_px, "tilt_deg": walk.tilt_deg, "verdict": verdict, "seconds": seconds}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sweep", type=Path, help="a sweep's output folder (sweep.csv, scenarios/)")
    parser.add_argument("--only", default="", help="comma-separated scenario numbers (default: the failing ones)")
    args = parser.parse_args()
    rows = list(csv.DictReader(open(args.sweep / "sweep.csv", encoding="utf-8")))
    only = {int(k) for k in args.only.split(",") if k}
    print("| # | phantom | views | range | nominal | estimated | before the gate | from the truth | steps kept | "
          "cost at nominal vs truth | in noise units | axis px | tilt deg | verdict |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for row in rows:
        index = int(row["scenario"])
        if only and index not in only:
            continue
        if not only:
            if row["status"] != "ok" or float(row["estimated_rms_deg"]) <= 0.5 * float(row["nominal_rms_deg"]):
                continue
        found = diagnose(args.sweep / "scenarios" / f"{index:03d}.yaml")
        axis = "" if found["axis_px"] is None else f"{found['axis_px']:+.2f}"
        tilt = "" if found["tilt_deg"] is None else f"{found['tilt_deg']:+.3f}"
        print(f"| {index} | {row['phantom']} | {row['scan.angles.n_views']} | {float(row['scan.angles.range_deg']):.0f} | "
              f"{found['nominal_rms_deg']:.3f} | {float(row['estimated_rms_deg']):.3f} | "
              f"{float(row['ungated_rms_deg']):.3f} | {found['from_truth_rms_deg']:.3f} | {found['steps_kept']} | "
              f"{found['cost_nominal_over_truth']:+.2%} | {found['separation']:+.1f} | {axis} | {tilt} | "
              f"{found['verdict']} |", flush=True)


if __name__ == "__main__":
    main()
