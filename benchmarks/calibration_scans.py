"""Calibration scans of the ball phantoms: scan folders with known angles, and where balls overlap.

Simulates the built-in ball phantoms (``ball-bar``, ``bead-cloud-10``, ``bead-cloud-30``) over 16
and 32 views per turn in the geometry of ``configs/experiments/calibration-16-views.yaml`` (read
from that file: source 250 mm from the axis and 500 mm from a 512^2 detector of 0.2 mm pixels,
0.2 deg Gaussian stage error plus one 0.5 deg jump, 50,000 photons per pixel), writes each scan
as a ctpipe scan folder (``OUT/<phantom>-<views>-views``, raw counts with flats and darks, true
angles in ``scan.yaml``) and prints, for each, how many views have balls overlapping on the
detector at the true angles (:func:`ctpipe.testing.overlapping_spheres`), which views, and the
largest raw count (a 16-bit detector holds 65,535).

Exits with status 1 when a phantom has overlapping balls in fewer than 2 views of a 16-view
turn: the calibration phantoms are meant to have some.

    python benchmarks/calibration_scans.py --out /tmp/calibration-scans [--pixels 512]
                                           [--jitter-deg 0.2] [--seed 0] [--overwrite]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from ctpipe.config import load_yaml
from ctpipe.sim import ScanSpec, SimulatedScan, load_phantom, parse_scan_spec, simulate, write_simulated_scan
from ctpipe.testing import overlapping_spheres, phantom_spheres

EXPERIMENT = Path(__file__).resolve().parents[1] / "configs" / "experiments" / "calibration-16-views.yaml"
PHANTOMS = ("ball-bar", "bead-cloud-10", "bead-cloud-30")
VIEW_COUNTS = (16, 32)
#: Views of a 16-view turn that must show overlapping balls.
MIN_OVERLAP_VIEWS = 2
UINT16_MAX = 65535


def calibration_scan_spec(n_views: int, *, jitter_deg: float = 0.2, seed: int = 0, pixels: int = 512) -> ScanSpec:
    """The calibration experiments' scan with ``n_views`` per full turn.

    ``pixels`` changes the detector's size in pixels, not its field of view: the pitch scales so
    the phantom looks the same at any size. ``jitter_deg`` is the Gaussian stage error (sigma,
    degrees); the one 0.5 deg jump is kept.
    """
    scan = load_yaml(EXPERIMENT)["scan"]
    geometry = dict(scan["geometry"])
    for axis, count in (("u", "detector_cols"), ("v", "detector_rows")):
        geometry[f"pixel_pitch_{axis}_mm"] = geometry[f"pixel_pitch_{axis}_mm"] * geometry[count] / pixels
        geometry[count] = pixels
    jitter = [c for c in scan.get("jitter") or [] if "gaussian" not in c]
    if jitter_deg > 0:
        jitter.insert(0, {"gaussian": {"sigma_deg": jitter_deg}})
    return parse_scan_spec({**scan, "geometry": geometry, "jitter": jitter,
                            "angles": {"n_views": n_views, "range_deg": 360.0, "start_deg": 0.0}, "seed": seed},
                           path=f"{EXPERIMENT.name}.scan")


def simulate_calibration_scan(phantom_name: str, n_views: int, *, jitter_deg: float = 0.2, seed: int = 0,
                              pixels: int = 512) -> tuple[SimulatedScan, ScanSpec]:
    """Simulate a built-in phantom in the calibration geometry (:func:`calibration_scan_spec`).

    Returns
    -------
    scan : SimulatedScan
        What :func:`ctpipe.sim.simulate` returns: projections (-log), raw counts, flats, darks,
        nominal and true angles, geometry.
    spec : ScanSpec
        The scan it was simulated from (for :func:`ctpipe.sim.write_simulated_scan`).
    """
    spec = calibration_scan_spec(n_views, jitter_deg=jitter_deg, seed=seed, pixels=pixels)
    return simulate(load_phantom(phantom_name), spec, rng=np.random.default_rng(seed)), spec


def overlap_views(phantom_name: str, scan: SimulatedScan) -> list[np.ndarray]:
    """Per view of ``scan``, the pairs of the phantom's balls that overlap at the true angles."""
    centres, radii = phantom_spheres(load_phantom(phantom_name))
    return overlapping_spheres(centres, radii, scan.geometry, scan.true_angles_deg)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True, type=Path, help="folder for the scan folders")
    parser.add_argument("--pixels", type=int, default=512, help="detector size in pixels (same field of view)")
    parser.add_argument("--jitter-deg", type=float, default=0.2, help="Gaussian stage error, degrees")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--overwrite", action="store_true", help="replace existing scan folders")
    args = parser.parse_args(argv)

    print(f"geometry of {EXPERIMENT.relative_to(EXPERIMENT.parents[2])}, {args.pixels}^2 pixels, "
          f"Gaussian {args.jitter_deg:g} deg + one 0.5 deg jump, seed {args.seed}")
    print(f"{'phantom':<14} {'views':>5} {'balls':>5}  {'overlap views':>13}  {'max pairs':>9}  {'max count':>9}  "
          f"{'time s':>6}  views with overlapping balls")
    short = []
    for name in PHANTOMS:
        for n_views in VIEW_COUNTS:
            start = time.perf_counter()
            scan, spec = simulate_calibration_scan(name, n_views, jitter_deg=args.jitter_deg, seed=args.seed,
                                                   pixels=args.pixels)
            folder = write_simulated_scan(args.out / f"{name}-{n_views}-views", scan, phantom=load_phantom(name),
                                          spec=spec, seed=args.seed, overwrite=args.overwrite)
            elapsed = time.perf_counter() - start
            pairs = overlap_views(name, scan)
            views = [v for v, p in enumerate(pairs) if len(p)]
            n_balls = len(phantom_spheres(load_phantom(name))[1])
            max_count = float(max(scan.intensities.max(), scan.flats.max()))
            print(f"{name:<14} {n_views:>5} {n_balls:>5}  {len(views):>6} of {n_views:<4}  "
                  f"{max(len(p) for p in pairs):>9}  {max_count:>9.0f}  {elapsed:>6.1f}  {views}")
            if n_views == 16 and len(views) < MIN_OVERLAP_VIEWS:
                short.append(name)
            if max_count > UINT16_MAX:
                print(f"  {folder}: counts up to {max_count:.0f} do not fit a 16-bit detector")
    print(f"scan folders in {args.out}")
    if short:
        print(f"fewer than {MIN_OVERLAP_VIEWS} of 16 views with overlapping balls: {', '.join(short)}")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
