"""Peak memory and time of ``ctpipe estimate`` against scan size: scans larger than memory stream.

Writes, once, two scan folders of the granular sample as a 16-bit scanner records them (Poisson
counts and flat frames): 2,000 views of 512^2 and 2,000 views of 2,048^2 pixels (16.8 GB of
uint16 TIFFs, about 34 GB as float32). They are projected, noised and written a few views at a
time, so writing them needs no more memory than reading them. The 2,048^2 views are synthesised
cheaply: the exact 512^2 line integrals magnified 4x (bilinear) before the Poisson noise, so
they hold the 512^2 detail on the larger detector. Smaller scans are every 8th or every
2nd view of the same files (a ``scan.yaml`` listing them), so all cover a full turn.

Each size runs ``ctpipe estimate FOLDER`` in a fresh process and reads its peak resident
memory from the kernel (``getrusage`` of the child). Printed per run: views, pixels, the scan's
size as stored and as float32, peak memory, wall time, and time per view; the peer is the scan
itself (peak memory over scan size) and the smallest run of the same detector (memory and time
ratios), measured in the same run. Two pipelines: a feature pipeline whose refiner works from
the features alone (ORB, least-squares), and the default (SIFT, projection matching), which
also keeps one binned copy of every view (at most 256^2 pixels).

Never fails on time or memory.

    python benchmarks/bench_streaming.py [--dir /tmp/ctpipe-streaming] [--sizes 512 2048]
                                         [--views 250 1000 2000] [--default-up-to 1000]
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import yaml

N_VIEWS = 2000
FEATURES = {
    "detector": {"name": "orb", "n_features": 1000},
    "matcher": {"name": "brute-force", "ratio": 0.8, "mutual": True},
    "estimator": {"name": "ransac-1pt", "sampson_threshold": 1.0e-3},
    "refiner": {"name": "least-squares"},
    "pairs": {"baselines": [1]},
}


def geometry_for(pixels: int):
    from ctpipe.geometry import Geometry

    # The same 200 mm detector and magnification at every size, so the object looks the same.
    pitch = 204.8 / pixels
    return Geometry(source_to_object_mm=190.0, source_to_detector_mm=390.0, detector_cols=pixels,
                    detector_rows=pixels, pixel_pitch_u_mm=pitch, pixel_pitch_v_mm=pitch)


def write_scan_once(folder: Path, pixels: int) -> Path:
    """The full 2,000-view scan folder, projected, noised and written one chunk of views at a time."""
    import tifffile
    from scipy.ndimage import zoom

    from ctpipe.sim import load_phantom, project_phantom

    done = folder / "scan.yaml"
    if done.is_file():
        return folder
    (folder / "projections").mkdir(parents=True, exist_ok=True)
    (folder / "flats").mkdir(exist_ok=True)
    geometry = geometry_for(pixels)
    projected = geometry_for(min(pixels, 512))
    phantom = load_phantom("granular")
    rng = np.random.default_rng(0)
    nominal = np.arange(N_VIEWS) * 360.0 / N_VIEWS
    truth = nominal + rng.normal(0.0, 0.2, N_VIEWS)
    photons = 20000.0
    start = time.perf_counter()
    for first in range(0, N_VIEWS, 16):
        views = range(first, min(first + 16, N_VIEWS))
        line_integrals = project_phantom(phantom, projected, truth[list(views)])
        for view, p in zip(views, line_integrals):
            if pixels != projected.detector_cols:
                p = zoom(p, pixels / projected.detector_cols, order=1)
            counts = rng.poisson(photons * np.exp(-p.astype(np.float64))).clip(0, 65535).astype(np.uint16)
            tifffile.imwrite(folder / "projections" / f"proj_{view:05d}.tif", counts)
    print(f"  wrote {folder.name}: {N_VIEWS} views in {time.perf_counter() - start:.0f} s")
    for i in range(4):
        tifffile.imwrite(folder / "flats" / f"flat_{i}.tif",
                         rng.poisson(photons, geometry.shape).clip(0, 65535).astype(np.uint16))
    document = {"format": "ctpipe-scan/1", "geometry": geometry.to_dict(),
                "angles": {"nominal_deg": nominal.tolist(), "true_deg": truth.tolist()},
                "projections": {"values": "intensities", "files": "projections/proj_{index:05d}.tif",
                                "count": N_VIEWS},
                "flats": {"files": "flats/flat_{index}.tif", "count": 4}}
    done.write_text(yaml.safe_dump(document, default_flow_style=None, width=100))
    return folder


def subset(full: Path, n_views: int) -> Path:
    """A scan folder of ``n_views`` views of ``full`` evenly spaced over its full turn, listing its files.

    250 and 1,000 views are every 8th and every 2nd view; a count that does not divide 2,000
    (360) still spans the whole turn.
    """
    if n_views == N_VIEWS:
        return full
    folder = full.parent / f"{full.name}-{n_views}views"
    folder.mkdir(exist_ok=True)
    document = yaml.safe_load((full / "scan.yaml").read_text())
    keep = np.round(np.arange(n_views) * N_VIEWS / n_views).astype(int).tolist()
    document["angles"] = {k: [v[i] for i in keep] for k, v in document["angles"].items()}
    document["projections"] = {"values": "intensities", "files": [f"../{full.name}/projections/proj_{i:05d}.tif"
                                                                  for i in keep]}
    document["flats"] = {"files": [f"../{full.name}/flats/flat_{i}.tif" for i in range(4)]}
    (folder / "scan.yaml").write_text(yaml.safe_dump(document, default_flow_style=None, width=100))
    return folder


def run_estimate(folder: Path, pipeline: Path) -> tuple[float, float, int]:
    """(wall seconds, peak RSS in MB, exit code) of ``ctpipe estimate folder`` in a fresh process."""
    start = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "ctpipe.cli", "estimate", str(folder), "--pipeline",
                             str(pipeline), "--json"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    wall = time.perf_counter() - start
    if proc.returncode != 0:
        print("   ", proc.stderr.read().decode(errors="replace").strip().splitlines()[-1:])
    return wall, usage.ru_maxrss / 1024.0, proc.returncode


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dir", type=Path, default=Path("/tmp/ctpipe-streaming"))
    parser.add_argument("--sizes", type=int, nargs="+", default=[512, 2048])
    parser.add_argument("--views", type=int, nargs="+", default=[250, 1000, 2000])
    parser.add_argument("--default-up-to", type=int, default=1000,
                        help="run the default pipeline (projection matching) up to this many views of 512^2")
    args = parser.parse_args(argv)
    args.dir.mkdir(parents=True, exist_ok=True)
    pipelines = {"features": args.dir / "features.yaml", "default": args.dir / "default.yaml"}
    pipelines["features"].write_text(yaml.safe_dump(FEATURES))
    pipelines["default"].write_text("{}\n")
    # Warm the numba cache so that no run pays for compilation.
    warm = subset(write_scan_once(args.dir / "scan-512", 512), 250)
    run_estimate(warm, pipelines["default"])

    print(f"{'pipeline':<9} {'views':>5} {'pixels':>9} {'stored GB':>9} {'float32 GB':>10} {'peak MB':>8} "
          f"{'peak/stored':>11} {'seconds':>8} {'ms/view':>8}")
    for pixels in args.sizes:
        full = write_scan_once(args.dir / f"scan-{pixels}", pixels)
        for name, pipeline in pipelines.items():
            first = last = None
            for n_views in args.views:
                if name == "default" and (pixels > 512 or n_views > args.default_up_to):
                    continue
                folder = subset(full, n_views)
                wall, peak_mb, code = run_estimate(folder, pipeline)
                stored_gb = n_views * pixels * pixels * 2 / 1e9
                first, last = first or (peak_mb, n_views), (peak_mb, n_views)
                print(f"{name:<9} {n_views:>5} {pixels:>4}^2    {stored_gb:>9.2f} {2 * stored_gb:>10.2f} "
                      f"{peak_mb:>8.0f} {peak_mb / (stored_gb * 1e3):>11.3f} {wall:>8.1f} "
                      f"{1e3 * wall / n_views:>8.1f}{'' if code == 0 else f'  (exit {code})'}", flush=True)
            if first and last[1] != first[1]:
                print(f"          ({name}, {pixels}^2: peak memory of the largest over the smallest run "
                      f"{last[0] / first[0]:.2f}x for {last[1] / first[1]:.0f}x the views)")
    print(f"machine: {os.cpu_count()} cores; peak of this script itself "
          f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB")


if __name__ == "__main__":
    main()
