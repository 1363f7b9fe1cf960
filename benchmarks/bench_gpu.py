"""ctpipe's GPU kernels against its CPU kernels and a GPU peer (diffct), measured in the same run.

For each size N: a cone-beam scan of N views of N x N pixels and an (N/2)^3 volume. Timed,
host array in to host array out (transfers included, on both sides):

- forward projection of the volume: ctpipe's Joseph projector (:class:`VoxelProjector`) on the
  GPU and on the CPU; diffct's ``ConeProjectorFunction`` (Siddon, numba-cuda) as the GPU peer;
- FDK: ctpipe's :func:`fdk` on the GPU and on the CPU; diffct's ``fdk`` as the GPU peer;
- the analytic projector (:func:`project_analytic`) of the default phantom, GPU and CPU;
- ``--phases``: FDK on the GPU taken apart (host checks, views sent, ramp filter by FFT and by
  direct convolution, backprojection, volume back), each phase synchronised and timed warm.

Warm figures are the median of ``--repeats`` runs; the compile (the first call's extra time) is
printed apart. The CPU runs only up to ``--cpu-up-to`` (it is tens of times slower). Ratios are
to ctpipe's GPU time in the same run. Never fails on time; a peer that cannot run says why.

    python benchmarks/bench_gpu.py [--sizes 256 512 1024] [--repeats 3] [--cpu-up-to 512] [--no-peer] [--phases]
"""

from __future__ import annotations

import argparse
import contextlib
import statistics
import time

import numpy as np

from ctpipe import gpu
from ctpipe.geometry import Geometry
from ctpipe.recon.feldkamp import fdk
from ctpipe.recon.volume import VolumeGrid
from ctpipe.sim.projectors import VoxelProjector, project_analytic


def scene(n: int):
    """N views of N x N pixels, magnification 2, an (N/2)^3 volume filling the field of view."""
    pitch = 0.2 * 512 / n
    geometry = Geometry(source_to_object_mm=200.0, source_to_detector_mm=400.0, detector_cols=n, detector_rows=n,
                        pixel_pitch_u_mm=pitch, pixel_pitch_v_mm=pitch, u0_px=(n - 1) / 2, v0_px=(n - 1) / 2)
    m = n // 2
    voxel = n * pitch / 2 / m * 0.9
    grid = VolumeGrid(n_x=m, n_y=m, n_z=m, voxel_size_mm=voxel)
    rng = np.random.default_rng(0)
    volume = rng.random(grid.shape, dtype=np.float32)
    angles = np.linspace(0.0, 360.0, n, endpoint=False)
    return geometry, grid, volume, angles


def timed(run, repeats: int) -> tuple[float, float]:
    """(first call, median of ``repeats`` more) in seconds."""
    start = time.perf_counter()
    run()
    first = time.perf_counter() - start
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        run()
        times.append(time.perf_counter() - start)
    return first, statistics.median(times)


def diffct_runs(geometry: Geometry, grid: VolumeGrid, volume: np.ndarray, angles: np.ndarray):
    """Host-to-host forward projection and FDK with diffct, or the reason it cannot run."""
    try:
        import diffct
        import torch
    except Exception as exc:  # noqa: BLE001
        return None, f"diffct not importable ({type(exc).__name__}: {exc})"
    n = geometry.detector_cols
    theta = torch.tensor(np.deg2rad(angles), dtype=torch.float32, device="cuda")
    trajectory = diffct.circular_trajectory_3d(theta, sid=geometry.source_to_object_mm,
                                               sdd=geometry.source_to_detector_mm, device="cuda")
    pitch = geometry.pixel_pitch_u_mm

    def forward():
        vol = torch.from_numpy(volume).cuda()
        sino = diffct.ConeProjectorFunction.apply(vol, *trajectory, n, n, pitch, pitch, grid.voxel_size_mm)
        return sino.cpu().numpy()

    sino_host = forward()

    def reconstruct():
        sino = torch.from_numpy(sino_host).cuda()
        rec = diffct.fdk(sino, trajectory, grid.shape, theta, detector_spacing=(pitch, pitch),
                         voxel_spacing=grid.voxel_size_mm)
        return rec.cpu().numpy()

    return {"forward": forward, "fdk": reconstruct}, ""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[256, 512, 1024])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--cpu-up-to", type=int, default=512)
    parser.add_argument("--no-peer", action="store_true")
    parser.add_argument("--kernels", nargs="+", choices=("forward", "fdk", "analytic"),
                        default=["forward", "fdk", "analytic"])
    parser.add_argument("--phases", action="store_true", help="also time FDK's phases on the GPU")
    args = parser.parse_args()
    selection = gpu.select("cuda")
    if selection.device != "cuda":
        print(f"no GPU here ({selection.reason}): nothing to measure")
        return
    from numba import cuda

    name = getattr(cuda.get_current_device(), "name", "the simulator")
    print(f"device: {name.decode() if isinstance(name, bytes) else name}")
    print(f"{'size':>6} {'kernel':<10} {'who':<14} {'first s':>9} {'warm s':>9} {'/ ctpipe gpu':>13}")
    for n in args.sizes:
        geometry, grid, volume, angles = scene(n)
        projector = VoxelProjector(geometry, grid)
        sino = None
        rows = []
        for device in ("cuda", "cpu"):
            if device == "cpu" and n > args.cpu_up_to:
                continue
            repeats = args.repeats if device == "cuda" else 1
            with gpu.use(device):
                if sino is None:
                    sino = projector.forward(volume, angles)
                if "forward" in args.kernels:
                    first, warm = timed(lambda: projector.forward(volume, angles), repeats)
                    rows.append(("forward", f"ctpipe {device}", first, warm))
                if "fdk" in args.kernels:
                    first, warm = timed(lambda: fdk(sino, geometry, angles, grid), repeats)
                    rows.append(("fdk", f"ctpipe {device}", first, warm))
        if not args.no_peer:
            runs, why = diffct_runs(geometry, grid, volume, angles)
            if runs is None:
                print(f"{n:>6} peer: {why}")
            else:
                for kernel, run in runs.items():
                    if kernel not in args.kernels:
                        continue
                    try:
                        first, warm = timed(run, args.repeats)
                        rows.append((kernel, "diffct", first, warm))
                    except Exception as exc:  # noqa: BLE001 - a peer's failure is reported, not fatal
                        print(f"{n:>6} {kernel:<10} diffct failed: {type(exc).__name__}: {str(exc)[:200]}")
        reference = {kernel: warm for kernel, who, _, warm in rows if who == "ctpipe cuda"}
        for kernel, who, first, warm in rows:
            print(f"{n:>6} {kernel:<10} {who:<14} {first:9.3f} {warm:9.3f} {warm / reference[kernel]:13.2f}")
        if args.phases:
            fdk_phases(geometry, grid, sino, angles, args.repeats)
    if "analytic" in args.kernels:
        analytic(args.repeats)


def fdk_phases(geometry: Geometry, grid: VolumeGrid, sino: np.ndarray, angles: np.ndarray, repeats: int) -> None:
    """FDK on the GPU phase by phase, through the accumulator :func:`ctpipe.recon.feldkamp.fdk` uses, each synchronised."""
    from numba import cuda

    from ctpipe.recon import _cuda, feldkamp

    n_views, _, cols = sino.shape
    theta = np.deg2rad(angles)
    intervals, _ = feldkamp._scan_weights(theta, geometry, None)
    n_pad, _ = feldkamp.ramp_filter(cols, "hann")
    extend = feldkamp.is_truncated(sino)
    chunk = feldkamp._CHUNK_VIEWS
    parts = [slice(start, min(start + chunk, n_views)) for start in range(0, n_views, chunk)]

    def accumulator(direct: bool):
        with _cuda.direct_filter() if direct else contextlib.nullcontext():
            return feldkamp._gpu_accumulator(geometry, grid, "hann", extend)

    on_device = [cuda.to_device(np.ascontiguousarray(sino[part])) for part in parts]
    ones = {len(views): cuda.to_device(np.ones((len(views), cols), dtype=np.float32)) for views in on_device}
    trig = [[cuda.to_device(np.ascontiguousarray(a[part], dtype=np.float64))
             for a in (np.cos(theta), np.sin(theta), intervals)] for part in parts]

    def synced(run):
        def go():
            run()
            cuda.synchronize()
        return timed(go, repeats)[1]

    def send():
        for part in parts:
            cuda.to_device(np.ascontiguousarray(sino[part]))

    def filter_with(acc):
        def go():
            for views in on_device:
                acc.filter(views, ones[len(views)])
        return go

    fft_acc, direct_acc, back_acc = accumulator(False), accumulator(True), accumulator(False)
    back_acc.filter(on_device[0], ones[len(on_device[0])])   # a whole chunk in its buffer, filtered once

    def backproject():
        for angles_on_device in trig:
            back_acc.backproject(*angles_on_device)

    phases = {
        "host checks (finite, truncated)": lambda: (feldkamp._validate(sino, geometry, angles, grid, "hann", None,
                                                                       None), feldkamp.is_truncated(sino)),
        "views to the GPU": send,
        f"ramp filter, FFT ({n_pad} samples)": filter_with(fft_acc),
        f"ramp filter, direct ({n_pad} taps)": filter_with(direct_acc),
        "backprojection": backproject,
        "volume reordered and back": back_acc.result,
    }
    for name, run in phases.items():
        print(f"{n_views:>6} fdk phase  {name:<34} {synced(run):9.3f} s (extended rows: {extend})")


def analytic(repeats: int) -> None:
    """The analytic projector on the default validate scene (granular phantom, 360 views of 512^2, supersample 2)."""
    from ctpipe.sim.phantoms import load_phantom

    primitives = load_phantom("granular").primitives
    geometry = Geometry(source_to_object_mm=150.0, source_to_detector_mm=390.0, detector_cols=512, detector_rows=512,
                        pixel_pitch_u_mm=0.8, pixel_pitch_v_mm=0.8, u0_px=255.5, v0_px=255.5)
    angles = np.linspace(0.0, 360.0, 360, endpoint=False)
    times = {}
    for device in ("cuda", "cpu"):
        with gpu.use(device):
            times[device] = timed(lambda: project_analytic(primitives, geometry, angles, supersample=2),
                                  repeats if device == "cuda" else 1)
    for device, (first, warm) in times.items():
        print(f"analytic {device:<5} 360 views of 512 x 512, {len(primitives)} primitives, supersample 2: "
              f"first {first:.3f} s, warm {warm:.3f} s, {warm / times['cuda'][1]:.2f} x ctpipe gpu")


if __name__ == "__main__":
    main()
