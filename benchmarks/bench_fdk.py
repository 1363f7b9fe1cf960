"""FDK speed and accuracy against mbirjax's ``direct_recon`` on the same data, in the same run.

Data: exact line integrals through the ellipsoid phantom of ``ctpipe.testing`` (closed form,
no projector involved), a full circle of uniformly spaced views, SOD 200 mm, SDD 400 mm, an
80 mm square detector and a 32 mm cube of voxels. Two sizes: 128^3 from 180 views of 128^2 and
256^3 from 360 views of 256^2.

Printed per size: the warm median of ctpipe's ``fdk`` (default Hann window), mbirjax's
``direct_recon`` (its first call, which includes JAX compilation, and the best of the warm
calls), their ratio, and the relative RMSE of each against the phantom in the interior (voxels
at least 1 mm from every ellipsoid surface). mbirjax has only a ramp filter, so ctpipe's RMSE
is printed for both its ``ram-lak`` window (same filter) and its default ``hann``. The numba
JIT warm-up (compile, or load from numba's cache) is timed separately on a tiny problem first.

Never fails on time. mbirjax comes with the ``bench`` extra; install it in its own virtual
environment (``python -m venv .venv-bench && .venv-bench/bin/pip install -e .[bench]``).

    python benchmarks/bench_fdk.py [--quick] [--repeats 3] [--mbirjax-repeats 2] [--no-mbirjax]
"""

from __future__ import annotations

import argparse
import statistics
import time
import warnings

import numpy as np

from ctpipe.geometry import Geometry
from ctpipe.recon.feldkamp import fdk
from ctpipe.recon.volume import VolumeGrid
from ctpipe.testing import phantom_volume, project_ellipsoids, relative_rmse


SIZES = ((128, 180), (256, 360))


def setup(n: int, n_views: int):
    geometry = Geometry(source_to_object_mm=200.0, source_to_detector_mm=400.0, detector_cols=n,
                        detector_rows=n, pixel_pitch_u_mm=80.0 / n, pixel_pitch_v_mm=80.0 / n)
    grid = VolumeGrid.cube(n, 32.0 / n)
    angles_deg = np.arange(n_views) * 360.0 / n_views
    return geometry, grid, angles_deg


def time_call(fn, repeats: int) -> tuple[list[float], object]:
    times, out = [], None
    for _ in range(repeats):
        start = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - start)
    return times, out


def load_mbirjax():
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            import mbirjax
    except ImportError:
        return None
    return mbirjax


def mbirjax_recon(mbirjax, projections, geometry, grid, angles_deg, repeats):
    """mbirjax's FDK on ctpipe's data, returned in ctpipe's layout.

    mbirjax (cone_beam.py) puts a voxel ``(i, j, k)`` of its ``(rows, cols, slices)`` recon at
    ``x~ = j``, ``y~ = i`` (centred, times delta_voxel), turns it by ``phi``:
    ``x = cos x~ - sin y~``, ``y = sin x~ + cos y~``, and sees it at channel ``SDD x / (SOD - y)``
    and row ``SDD z / (SOD - y)``, z the slice axis: the source sits at ``+y``. ctpipe's camera
    has ``X = cos x - sin z`` and depth ``SOD + sin x + cos z``. The two agree with ``phi = -theta``,
    ``x~ = x``, ``y~ = -z`` and slices along ctpipe's ``y``: ctpipe ``[iy, iz, ix]`` =
    mbirjax ``[n_z - 1 - iz, ix, iy]``.
    """
    model = mbirjax.ConeBeamModel(projections.shape, -np.deg2rad(angles_deg),
                                  source_detector_dist=geometry.source_to_detector_mm,
                                  source_iso_dist=geometry.source_to_object_mm)
    model.set_params(delta_det_channel=geometry.pixel_pitch_u_mm, delta_det_row=geometry.pixel_pitch_v_mm,
                     delta_voxel=grid.voxel_size_mm, recon_shape=(grid.n_z, grid.n_x, grid.n_y), verbose=0)
    times, recon = time_call(lambda: np.asarray(model.direct_recon(projections)), repeats)
    return times, np.ascontiguousarray(recon.transpose(2, 0, 1)[:, ::-1, :])


def parse_args(description: str, quick_help: str) -> argparse.Namespace:
    """The options every mbirjax-peer benchmark takes."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--quick", action="store_true", help=quick_help)
    parser.add_argument("--repeats", type=int, default=3, help="warm ctpipe runs per size (median)")
    parser.add_argument("--mbirjax-repeats", type=int, default=2,
                        help="mbirjax calls per size; the first includes JAX compilation")
    parser.add_argument("--no-mbirjax", action="store_true", help="skip the peer")
    return parser.parse_args()


def print_peer_timing(call: str, peer_times: list[float], ours: float) -> None:
    """mbirjax's first call (JAX compilation included), its best warm call, and the ratios to ctpipe."""
    peer_warm = min(peer_times[1:]) if len(peer_times) > 1 else peer_times[0]
    print(f"mbirjax {call} first call {peer_times[0]:7.2f} s (with JAX compile), warm {peer_warm:.2f} s")
    print(f"ratio mbirjax warm / ctpipe warm: {peer_warm / ours:.1f}x (first call: {peer_times[0] / ours:.1f}x)")


def main() -> None:
    args = parse_args(__doc__.splitlines()[0], "only the 128^3 size")

    geometry, grid, angles = setup(16, 24)
    projections = project_ellipsoids(geometry, angles)
    start = time.perf_counter()
    fdk(projections, geometry, angles, grid)
    print(f"numba warm-up (JIT compile or cache load, 16^3 from 24 views): {time.perf_counter() - start:.2f} s")

    mbirjax = None if args.no_mbirjax else load_mbirjax()
    if mbirjax is None and not args.no_mbirjax:
        print("mbirjax is not installed: peer figures skipped (pip install -e .[bench])")

    sizes = SIZES[:1] if args.quick else SIZES
    for n, n_views in sizes:
        geometry, grid, angles = setup(n, n_views)
        projections = project_ellipsoids(geometry, angles)
        truth, interior = phantom_volume(grid)
        print(f"\n== {n}^3 from {n_views} views of {n}^2 ==")

        fdk(projections, geometry, angles, grid)  # first call at this size, not counted
        times, volume = time_call(lambda: fdk(projections, geometry, angles, grid), args.repeats)
        ours = statistics.median(times)
        rmse_hann = relative_rmse(volume, truth, interior)
        ramlak = fdk(projections, geometry, angles, grid, filter="ram-lak")
        rmse_ramlak = relative_rmse(ramlak, truth, interior)
        print(f"ctpipe fdk (hann)    warm median {ours:7.2f} s  runs {', '.join(f'{t:.2f}' for t in times)}")
        print(f"ctpipe interior relative RMSE: hann {rmse_hann:.4f}, ram-lak {rmse_ramlak:.4f}")

        if mbirjax is None:
            continue
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            peer_times, peer = mbirjax_recon(mbirjax, projections, geometry, grid, angles, args.mbirjax_repeats)
        print_peer_timing("direct_recon", peer_times, ours)
        rmse_peer = relative_rmse(peer, truth, interior)
        print(f"mbirjax interior relative RMSE: {rmse_peer:.4f}")
        print(f"RMSE ctpipe / mbirjax: ram-lak {rmse_ramlak / rmse_peer:.3f}, hann {rmse_hann / rmse_peer:.3f} "
              "(<= 1.02 is 'same accuracy or better')")


if __name__ == "__main__":
    main()
