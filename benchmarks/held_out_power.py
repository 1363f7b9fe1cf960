"""How well could a perfect answer do? The held-out test scored with the TRUE angles against the nominal ones.

The projection-matching refiner returns its angles only where they predict views held out of
the reference better than the nominal angles do, beyond noise (z < -2,
:func:`ctpipe.solve.reprojection.held_out_scores`). This script asks what that test would say of
the true angles themselves, on every scenario of a sweep (``ctpipe experiment sweep --out DIR``)
in the issue's population (jitter visible, ``visible_db >= 1``, and 64 views or more) or those
named: where even the truth does not reach z < -2, no refiner can be returned there, and the
nominal angles are what the evidence supports.

Each scenario is simulated again exactly as ``validate`` does; the views are prepared as the
refiner prepares them (line integrals, the static part out where it applies) and aligned on the
TRUE detector (the axis column and the tilt of the simulation, what the refiner fits). Printed
per scenario and level: the z of the true angles and of the angles half-way from the nominal to
the true ones, with 2 folds (the refiner's) and with ``--folds`` more.

    python benchmarks/held_out_power.py results/sweep [--only 1,7,26] [--folds 4]
"""

from __future__ import annotations

import argparse
import csv
import time
from pathlib import Path

import numpy as np

import ctpipe.solve.reprojection as reprojection
from ctpipe.builtin.projection_matching import ProjectionMatchingRefiner
from ctpipe.config import load_yaml
from ctpipe.evaluate.validate import parse_validate
from ctpipe.plugins import get_registry
from ctpipe.sim.simulator import simulate


def held_out_z(level, nominal, truth, folds: int) -> tuple[float, float]:
    """z of the true and of the half-way angles against the nominal ones, with ``folds`` folds."""
    scores = reprojection.held_out_scores(level, {"nominal": nominal, "truth": truth,
                                                  "half": nominal + 0.5 * (truth - nominal)}, "nominal", folds)
    return scores["truth"].z, scores["half"].z


def power(path: Path, more_folds: int) -> list[str]:
    settings = parse_validate(load_yaml(path), get_registry(), base_dir=path.parent, path=str(path))
    scan = simulate(settings.phantom, settings.scan, rng=np.random.default_rng(settings.seed))
    geometry, truth, nominal = scan.geometry, scan.true_angles_deg, scan.nominal_angles_deg
    refiner = ProjectionMatchingRefiner()
    data, _ = reprojection.as_line_integrals(scan.projections)
    if refiner.static and reprojection.static_part_applies(nominal):
        data = data - reprojection.static_part(data, nominal)
    axis_px = 0.0 if scan.true_detector_offsets_px is None else float(np.mean(scan.true_detector_offsets_px[:, 0]))
    tilt_rad = -np.deg2rad(scan.true_detector_tilt_deg)          # the camera convention the refiner fits in
    cells = []
    for binning, _ in reprojection.matching_levels(geometry.shape, refiner.iterations, level_px=refiner.level_px):
        start = time.perf_counter()
        level = reprojection._Level(data, geometry, binning, refiner.max_voxels,
                                    (refiner.band_low_px, refiner.band_high_px), refiner.filter)
        shifts = np.zeros((len(nominal), 2))
        shifts[:, 0] = axis_px / binning
        level.align(shifts, tilt_rad)
        two = held_out_z(level, nominal, truth, 2)
        more = held_out_z(level, nominal, truth, more_folds)
        cells.append(f"binning {binning}: truth {two[0]:+.1f} / {more[0]:+.1f}, half-way {two[1]:+.1f} / {more[1]:+.1f}"
                     f" ({time.perf_counter() - start:.0f} s)")
    return cells


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sweep", type=Path, help="a sweep's output folder (sweep.csv, scenarios/)")
    parser.add_argument("--only", default="", help="comma-separated scenario numbers (default: the population)")
    parser.add_argument("--folds", type=int, default=4, help="the second fold count scored beside the refiner's 2")
    args = parser.parse_args()
    only = {int(k) for k in args.only.split(",") if k}
    print(f"held-out z against the nominal angles (2 folds / {args.folds} folds); below -2 the refiner may return them")
    for row in csv.DictReader(open(args.sweep / "sweep.csv", encoding="utf-8")):
        index = int(row["scenario"])
        population = (row["status"] == "ok" and row["visible_db"] and float(row["visible_db"]) >= 1
                      and int(row["scan.angles.n_views"]) >= 64)
        if (only and index not in only) or (not only and not population):
            continue
        cells = power(args.sweep / "scenarios" / f"{index:03d}.yaml", args.folds)
        print(f"{index:3d} {row['phantom']:<15} {row['scan.angles.n_views']:>4} views "
              f"{float(row['scan.angles.range_deg']):3.0f} deg: " + "; ".join(cells), flush=True)


if __name__ == "__main__":
    main()
