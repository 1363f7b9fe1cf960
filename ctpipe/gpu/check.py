"""Do the GPU kernels give the CPU's answers? Every kernel on one small scene, both devices, compared.

Run ``python -m ctpipe.gpu.check`` on a machine with a GPU after installing ``ctpipe[gpu]``, or
with ``NUMBA_ENABLE_CUDASIM=1`` anywhere (numba-cuda's simulator runs the kernels' Python; this
is how the test suite checks them without a GPU). Prints one JSON object: for each kernel the
largest absolute difference and the largest magnitude of the CPU's answer; exit status 1 when a
difference exceeds :data:`RELATIVE_TOLERANCE` of that magnitude.
"""

from __future__ import annotations

import json
import sys

import numpy as np

from ctpipe import gpu
from ctpipe._shared import device
from ctpipe.geometry import Geometry
from ctpipe.recon.feldkamp import fdk
from ctpipe.recon.volume import VolumeGrid
from ctpipe.sim.primitives import Primitives
from ctpipe.sim.projectors import VoxelProjector, project_analytic

__all__ = ["RELATIVE_TOLERANCE", "compare", "main"]

#: float32 sums in another order, fused multiply-adds and atomics: a few ulps of the largest value.
RELATIVE_TOLERANCE = 1e-4


def _scene(size: int, n_views: int, seed: int):
    rng = np.random.default_rng(seed)
    geometry = Geometry(source_to_object_mm=60.0, source_to_detector_mm=120.0, detector_cols=size + 3,
                        detector_rows=size, pixel_pitch_u_mm=0.5, pixel_pitch_v_mm=0.55,
                        u0_px=(size + 3) / 2 - 0.3, v0_px=size / 2 + 0.2)
    grid = VolumeGrid(n_x=size, n_y=size - 1, n_z=size + 1, voxel_size_mm=0.26)
    volume = rng.random(grid.shape, dtype=np.float32)
    angles = np.sort(rng.uniform(0.0, 360.0, n_views))
    return geometry, grid, volume, angles, rng


def _both(run):
    with gpu.use("cpu"):
        cpu = run()
    with gpu.use("cuda") as selection:
        if selection.device != "cuda":
            raise RuntimeError(f"no GPU to compare with: {selection.reason}")
        on_gpu = run()
    return cpu, on_gpu


def compare(size: int = 8, n_views: int = 3, seed: int = 0) -> dict[str, dict[str, float]]:
    """``{kernel: {"max_abs_diff", "max_abs", "ok"}}`` of every GPU kernel against the CPU's on a small scene."""
    geometry, grid, volume, angles, rng = _scene(size, n_views, seed)
    projector = VoxelProjector(geometry, grid)
    second = rng.random(grid.shape, dtype=np.float32)
    views = rng.random((n_views, *geometry.shape), dtype=np.float32)
    # An ellipsoid, a cylinder and a box (kinds 0, 1, 2), turned, inside the field of view.
    turn = np.linalg.qr(rng.normal(size=(3, 3, 3)))[0]
    primitives = Primitives(np.array([0, 1, 2], np.int32), np.array([[0.3, -0.2, 0.1], [-0.4, 0.3, 0.2],
                                                                      [0.2, 0.1, -0.5]]),
                            np.array([[1.0, 0.7, 0.8], [0.5, 0.9, 0.5], [0.4, 0.4, 0.6]]), turn,
                            np.array([0.5, 0.3, 0.2]))

    def pair():
        return np.concatenate([np.stack([a, b]) for _, a, b in projector.forward_pair(volume, second, angles,
                                                                                      chunk_views=2)], axis=1)

    # A wide, short detector: the FFT's rows of 512 samples, the direct filter's 128-sample tiles crossed.
    wide = Geometry(source_to_object_mm=60.0, source_to_detector_mm=120.0, detector_cols=150, detector_rows=3,
                    pixel_pitch_u_mm=0.05, pixel_pitch_v_mm=0.5, u0_px=74.2, v0_px=1.1)
    wide_views = rng.random((n_views, 3, 150), dtype=np.float32)
    wide_grid = VolumeGrid(n_x=size, n_y=2, n_z=size, voxel_size_mm=0.6 / size)
    short = np.linspace(0.0, 250.0, max(n_views, 24))
    short_views = rng.random((short.size, *geometry.shape), dtype=np.float32)

    def direct_filter():
        """The wide extended scan through the GPU's direct convolution, the filter of rows too long for its FFT."""
        if device.active() != "cuda":
            return fdk(wide_views, wide, angles, wide_grid, truncation="extend")
        from ctpipe.recon._cuda import direct_filter

        with direct_filter():
            return fdk(wide_views, wide, angles, wide_grid, truncation="extend")

    runs = {
        "forward": lambda: projector.forward(volume, angles),
        "forward_pair": pair,
        "back": lambda: projector.back(views, angles),
        "fdk": lambda: fdk(views, geometry, angles, grid),
        "fdk_wide_extended": lambda: fdk(wide_views, wide, angles, wide_grid, truncation="extend"),
        "fdk_wide_extended_direct_filter": direct_filter,
        "fdk_short_scan": lambda: fdk(short_views, geometry, short, grid, short_scan=True),
        "analytic": lambda: project_analytic(primitives, geometry, angles, supersample=2, detector_tilt_deg=0.7),
    }
    report = {}
    for name, run in runs.items():
        fallbacks = len(device.FALLBACKS)
        cpu, on_gpu = _both(run)
        if len(device.FALLBACKS) > fallbacks:
            what, why = device.FALLBACKS[-1]
            raise RuntimeError(f"{name}: {what} did not run on the GPU: {why}")
        scale = float(np.max(np.abs(cpu)))
        diff = float(np.max(np.abs(cpu.astype(np.float64) - on_gpu)))
        ok = bool(diff <= RELATIVE_TOLERANCE * max(scale, 1e-30))
        report[name] = {"max_abs_diff": diff, "max_abs": scale, "ok": ok}
    return report


def main(argv: list[str] | None = None) -> int:
    size = int(argv[0]) if argv else 8
    report = compare(size=size)
    print(json.dumps(report))
    return 0 if all(entry["ok"] for entry in report.values()) else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
