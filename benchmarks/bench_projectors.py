"""Projector speed: the voxel (Joseph) projector against mbirjax's ``forward_project``, and the
analytic projector on the default phantom, in one run.

Voxel projector, two sizes as in ``bench_fdk.py``: a 128^3 volume into 180 views of 128^2 and
256^3 into 360 views of 256^2 (SOD 200 mm, SDD 400 mm, 80 mm detector, 32 mm cube of voxels),
the ellipsoid phantom of ``ctpipe.testing`` voxelised on the grid. Printed: ctpipe's warm
median, mbirjax's first call (with JAX compilation) and its best warm call, their ratio, and the
relative difference between the two projectors' outputs (both integrate the same voxels along
the same rays, with different interpolation: Joseph vs mbirjax's separable footprints).

Analytic projector: the built-in ``granular`` phantom (3000 grains in a tube) on the
``ctpipe validate`` geometry (512^2 detector), views per second at supersample 1 and 2.

The numba JIT warm-up is timed first on a tiny problem. Never fails on time. mbirjax comes with
the ``bench`` extra; install it in its own virtual environment (it brings about 1 GB of JAX)::

    python -m venv .venv-bench && .venv-bench/bin/pip install -e ".[bench]"
    .venv-bench/bin/python benchmarks/bench_projectors.py [--quick] [--no-mbirjax]
"""

from __future__ import annotations

import statistics
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from ctpipe.evaluate.validate import load_validate_settings
from ctpipe.geometry import Geometry
from ctpipe.plugins import get_registry
from ctpipe.sim.phantoms import load_phantom
from ctpipe.sim.projectors import VoxelProjector, project_analytic
from ctpipe.testing import phantom_volume

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_fdk import SIZES, load_mbirjax, parse_args, print_peer_timing, setup, time_call  # noqa: E402


def mbirjax_forward(mbirjax, volume, geometry, grid, angles_deg, repeats):
    """mbirjax's projection of ctpipe's volume, in ctpipe's (V, rows, cols) layout.

    The frames agree as derived in ``bench_fdk.mbirjax_recon``: ctpipe ``[iy, iz, ix]`` =
    mbirjax ``[n_z - 1 - iz, ix, iy]`` with ``phi = -theta``.
    """
    shape = (len(angles_deg), geometry.detector_rows, geometry.detector_cols)
    model = mbirjax.ConeBeamModel(shape, -np.deg2rad(angles_deg), source_detector_dist=geometry.source_to_detector_mm,
                                  source_iso_dist=geometry.source_to_object_mm)
    model.set_params(delta_det_channel=geometry.pixel_pitch_u_mm, delta_det_row=geometry.pixel_pitch_v_mm,
                     delta_voxel=grid.voxel_size_mm, recon_shape=(grid.n_z, grid.n_x, grid.n_y), verbose=0)
    theirs = np.ascontiguousarray(volume.transpose(1, 2, 0)[::-1])
    return time_call(lambda: np.asarray(model.forward_project(theirs)), repeats)


def bench_voxel(args) -> None:
    geometry, grid, angles = setup(16, 24)
    start = time.perf_counter()
    VoxelProjector(geometry, grid).forward(np.ones(grid.shape, np.float32), angles)
    print(f"numba warm-up (JIT compile or cache load, 16^3 into 24 views): {time.perf_counter() - start:.2f} s")

    mbirjax = None if args.no_mbirjax else load_mbirjax()
    if mbirjax is None and not args.no_mbirjax:
        print("mbirjax is not installed: peer figures skipped (pip install -e .[bench] in its own venv)")
    for n, n_views in SIZES[:1] if args.quick else SIZES:
        geometry, grid, angles = setup(n, n_views)
        volume = phantom_volume(grid)[0].astype(np.float32)
        projector = VoxelProjector(geometry, grid)
        print(f"\n== voxel projector: {n}^3 into {n_views} views of {n}^2 ==")
        projector.forward(volume, angles)  # first call at this size, not counted
        times, ours = time_call(lambda: projector.forward(volume, angles), args.repeats)
        warm = statistics.median(times)
        print(f"ctpipe VoxelProjector.forward  warm median {warm:7.2f} s  runs {', '.join(f'{t:.2f}' for t in times)}")
        if mbirjax is None:
            continue
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            peer_times, peer = mbirjax_forward(mbirjax, volume, geometry, grid, angles, args.mbirjax_repeats)
        print_peer_timing("forward_project", peer_times, warm)
        difference = np.linalg.norm(ours - peer) / np.linalg.norm(peer)
        print(f"relative difference ctpipe vs mbirjax projections: {difference:.4f}")


def bench_analytic(args) -> None:
    settings = load_validate_settings(None, get_registry())
    geometry: Geometry = settings.scan.geometry
    phantom = load_phantom("granular")
    n_views = 8 if args.quick else 36
    angles = np.arange(n_views) * 360.0 / n_views
    print(f"\n== analytic projector: granular ({len(phantom.primitives.kind)} primitives), "
          f"{geometry.detector_cols}x{geometry.detector_rows} detector, {n_views} views ==")
    project_analytic(phantom.primitives, geometry, angles[:2])  # warm-up
    for supersample in (1, 2):
        times, _ = time_call(lambda: project_analytic(phantom.primitives, geometry, angles, supersample=supersample),
                             args.repeats)
        warm = statistics.median(times)
        print(f"supersample {supersample}: {n_views / warm:7.1f} views/s  (warm median {warm:.2f} s for {n_views} views)")


def main() -> None:
    args = parse_args(__doc__.splitlines()[0], "only the 128^3 size and 8 analytic views")
    bench_voxel(args)
    bench_analytic(args)


if __name__ == "__main__":
    main()
