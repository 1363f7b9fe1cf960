"""CUDA kernels (numba-cuda) of the voxel projector, its adjoint and the analytic projector.

Imported only when :func:`ctpipe.gpu.active` is ``"cuda"``; the public functions in
:mod:`ctpipe.sim.projectors` call these and keep their own checks and layouts, so the two
devices differ only in where the inner loops run (FDK's kernel: :mod:`ctpipe.recon._cuda`).

The ray set-up and the Joseph sums are the CPU kernels' own ``@njit`` helpers, which numba
compiles for the GPU when a CUDA kernel calls them (the simulator runs their Python). What differs:

- one thread per ray (a detector pixel of a view) instead of one per view;
- the adjoint scatters with atomic adds into one padded volume instead of one per thread;
- the analytic projector runs a block per (primitive, view), its threads sharing the pixels
  of the primitive's bounding rectangle and adding with atomics.

Work larger than the card's free memory is split into chunks of views; a volume whose layouts
alone do not fit raises :class:`~ctpipe._shared.device.DeviceMemoryError`, which the callers
answer by running on the CPU.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba import cuda

from ctpipe._shared.device import blocks_for, chunk_views, memory_budget, prepare_cuda
from ctpipe.sim._joseph import _pixel_ray, _ray_sum, _ray_sum_pair
from ctpipe.sim._chords import pixel_chords, primitive_pixels, unit_frame_ray

__all__ = ["back", "forward", "forward_pair", "project_primitives"]

prepare_cuda()

#: Under the simulator the kernels' Python runs as is, and array helpers must be Python too.
_SIMULATED = bool(numba.config.ENABLE_CUDASIM)
_ray_sum_d = _ray_sum.py_func if _SIMULATED else _ray_sum
_ray_sum_pair_d = _ray_sum_pair.py_func if _SIMULATED else _ray_sum_pair
_primitive_pixels_d = primitive_pixels.py_func if _SIMULATED else primitive_pixels
_unit_frame_ray_d = unit_frame_ray.py_func if _SIMULATED else unit_frame_ray

#: Threads of a ray block: columns, rows and views of the detector.
_BLOCK_2D = (32, 8, 1)


def _grid(shape: tuple[int, int, int]) -> tuple[int, ...]:
    """Ray blocks covering ``(cols, rows, views)``."""
    return blocks_for(shape, _BLOCK_2D)


# --------------------------------------------------------------------------- voxel projector


@cuda.jit(cache=True)
def _forward_kernel(out, vol_x, vol_z, vol_y, cos_t, sin_t, sod, sdd, pu, pv, u0, v0, ox, oy, oz, voxel, n_x, n_y,
                    n_z):
    col, row, v = cuda.grid(3)
    n_views, n_rows, n_cols = out.shape
    if v >= n_views or row >= n_rows or col >= n_cols:
        return
    axis, k0, k1, p0, dp, q0, dq, step, n_p, n_q = _pixel_ray(cos_t[v], sin_t[v], sod, sdd, pu, pv, u0, v0,
                                                              (ox, oy, oz), voxel, n_x, n_y, n_z, row, col)
    if axis == 0:
        total = _ray_sum_d(vol_x, k0, k1, p0, dp, q0, dq, n_p, n_q)
    elif axis == 1:
        total = _ray_sum_d(vol_z, k0, k1, p0, dp, q0, dq, n_p, n_q)
    else:
        total = _ray_sum_d(vol_y, k0, k1, p0, dp, q0, dq, n_p, n_q)
    out[v, row, col] = total * np.float32(step)


@cuda.jit(cache=True)
def _forward_pair_kernel(out_a, out_b, vol_x, vol_z, vol_y, cos_t, sin_t, sod, sdd, pu, pv, u0, v0, ox, oy, oz,
                         voxel, n_x, n_y, n_z):
    col, row, v = cuda.grid(3)
    n_views, n_rows, n_cols = out_a.shape
    if v >= n_views or row >= n_rows or col >= n_cols:
        return
    axis, k0, k1, p0, dp, q0, dq, step, n_p, n_q = _pixel_ray(cos_t[v], sin_t[v], sod, sdd, pu, pv, u0, v0,
                                                              (ox, oy, oz), voxel, n_x, n_y, n_z, row, col)
    if axis == 0:
        total_a, total_b = _ray_sum_pair_d(vol_x, k0, k1, p0, dp, q0, dq, n_p, n_q)
    elif axis == 1:
        total_a, total_b = _ray_sum_pair_d(vol_z, k0, k1, p0, dp, q0, dq, n_p, n_q)
    else:
        total_a, total_b = _ray_sum_pair_d(vol_y, k0, k1, p0, dp, q0, dq, n_p, n_q)
    out_a[v, row, col] = total_a * np.float32(step)
    out_b[v, row, col] = total_b * np.float32(step)


@cuda.jit(device=True, cache=True)
def _ray_scatter_atomic(vol, value, k0, k1, p0, dp, q0, dq, n_p, n_q):
    """:func:`ctpipe.sim.projectors._ray_scatter` with atomic adds: many rays share a voxel."""
    for k in range(k0, k1):
        p = p0 + k * dp
        q = q0 + k * dq
        ip = min(max(int(p), 0), n_p)
        iq = min(max(int(q), 0), n_q)
        fp = np.float32(p - ip)
        fq = np.float32(q - iq)
        w_hi = value * fp
        w_lo = value - w_hi
        cuda.atomic.add(vol, (ip, iq, k), w_lo - w_lo * fq)
        cuda.atomic.add(vol, (ip, iq + 1, k), w_lo * fq)
        cuda.atomic.add(vol, (ip + 1, iq, k), w_hi - w_hi * fq)
        cuda.atomic.add(vol, (ip + 1, iq + 1, k), w_hi * fq)


@cuda.jit(cache=True)
def _back_kernel(buf_x, buf_z, buf_y, proj, cos_t, sin_t, sod, sdd, pu, pv, u0, v0, ox, oy, oz, voxel, n_x, n_y, n_z):
    col, row, v = cuda.grid(3)
    n_views, n_rows, n_cols = proj.shape
    if v >= n_views or row >= n_rows or col >= n_cols:
        return
    value = proj[v, row, col]
    if value == 0.0:
        return
    axis, k0, k1, p0, dp, q0, dq, step, n_p, n_q = _pixel_ray(cos_t[v], sin_t[v], sod, sdd, pu, pv, u0, v0,
                                                              (ox, oy, oz), voxel, n_x, n_y, n_z, row, col)
    weighted = value * np.float32(step)
    if axis == 0:
        _ray_scatter_atomic(buf_x, weighted, k0, k1, p0, dp, q0, dq, n_p, n_q)
    elif axis == 1:
        _ray_scatter_atomic(buf_z, weighted, k0, k1, p0, dp, q0, dq, n_p, n_q)
    else:
        _ray_scatter_atomic(buf_y, weighted, k0, k1, p0, dp, q0, dq, n_p, n_q)


def _scalars(common) -> tuple:
    """The projector's constants with the grid origin spread into three floats."""
    sod, sdd, pu, pv, u0, v0, origin, voxel, n_x, n_y, n_z = common
    return (sod, sdd, pu, pv, u0, v0, float(origin[0]), float(origin[1]), float(origin[2]), voxel, n_x, n_y, n_z)


def _per_view_bytes(shape: tuple[int, int], n_out: int) -> float:
    return 4.0 * n_out * shape[0] * shape[1] + 16.0


def forward(layouts, cos_t: np.ndarray, sin_t: np.ndarray, common, detector_shape: tuple[int, int]) -> np.ndarray:
    """Line integrals (V, rows, cols) float32 of the padded layouts ``(vol_x, vol_z, vol_y)`` (host arrays)."""
    resident = sum(layout.nbytes for layout in layouts)
    budget = memory_budget(resident, "projecting the volume")
    device_layouts = [cuda.to_device(layout) for layout in layouts]
    scalars = _scalars(common)
    n_views = cos_t.size
    out = np.empty((n_views, *detector_shape), dtype=np.float32)
    chunk = chunk_views(_per_view_bytes(detector_shape, 1), budget, n_views)
    for start in range(0, n_views, chunk):
        part = slice(start, min(start + chunk, n_views))
        d_out = cuda.device_array((part.stop - start, *detector_shape), dtype=np.float32)
        grid = _grid((detector_shape[1], detector_shape[0], part.stop - start))
        _forward_kernel[grid, _BLOCK_2D](d_out, *device_layouts, cuda.to_device(np.ascontiguousarray(cos_t[part])),
                                         cuda.to_device(np.ascontiguousarray(sin_t[part])), *scalars)
        d_out.copy_to_host(out[part])
    return out


def forward_pair(layouts, cos_t: np.ndarray, sin_t: np.ndarray, common, detector_shape: tuple[int, int],
                 n_chunk: int):
    """Yield ``(views, first, second)`` chunks of the pair layouts' projections (the CPU's contract)."""
    resident = sum(layout.nbytes for layout in layouts)
    budget = memory_budget(resident, "projecting the two volumes")
    device_layouts = [cuda.to_device(layout) for layout in layouts]
    scalars = _scalars(common)
    n_views = cos_t.size
    n_chunk = min(n_chunk, chunk_views(_per_view_bytes(detector_shape, 2), budget, n_views))
    for start in range(0, n_views, n_chunk):
        views = slice(start, min(start + n_chunk, n_views))
        count = views.stop - start
        d_a = cuda.device_array((count, *detector_shape), dtype=np.float32)
        d_b = cuda.device_array((count, *detector_shape), dtype=np.float32)
        grid = _grid((detector_shape[1], detector_shape[0], count))
        _forward_pair_kernel[grid, _BLOCK_2D](d_a, d_b, *device_layouts,
                                              cuda.to_device(np.ascontiguousarray(cos_t[views])),
                                              cuda.to_device(np.ascontiguousarray(sin_t[views])), *scalars)
        yield views, d_a.copy_to_host(), d_b.copy_to_host()


def back(projections: np.ndarray, layout_shapes, cos_t: np.ndarray, sin_t: np.ndarray, common):
    """Scatter ``projections`` (V, rows, cols) into zeroed padded layouts; returns them on the host."""
    resident = sum(4.0 * math.prod(shape) for shape in layout_shapes)
    budget = memory_budget(resident, "back-projecting onto the volume")
    buffers = [cuda.to_device(np.zeros(shape, dtype=np.float32)) for shape in layout_shapes]
    scalars = _scalars(common)
    n_views = projections.shape[0]
    chunk = chunk_views(_per_view_bytes(projections.shape[1:], 1), budget, n_views)
    for start in range(0, n_views, chunk):
        part = slice(start, min(start + chunk, n_views))
        d_proj = cuda.to_device(np.ascontiguousarray(projections[part], dtype=np.float32))
        grid = _grid((projections.shape[2], projections.shape[1], part.stop - start))
        _back_kernel[grid, _BLOCK_2D](*buffers, d_proj, cuda.to_device(np.ascontiguousarray(cos_t[part])),
                                      cuda.to_device(np.ascontiguousarray(sin_t[part])), *scalars)
    return [buffer.copy_to_host() for buffer in buffers]


# --------------------------------------------------------------------------- analytic projector


@cuda.jit(cache=True)
def _primitives_kernel(out, cos_t, sin_t, kind, centre, maps, corners, density, sod, sdd, pu, pv, u0_v, v0_v,
                       cos_tilt, sin_tilt, ss):
    """:func:`ctpipe.sim.projectors._project_primitives` with a block per (primitive, view).

    Every thread works out the primitive's pixel rectangle and the ray in its unit frame (the
    CPU kernel's helpers), then takes every ``blockDim``-th pixel of the rectangle. The CPU
    kernel's tighter column span of an ellipsoid's rows is left out: pixels outside it add 0.
    """
    n = cuda.blockIdx.x
    v = cuda.blockIdx.y
    n_views, n_rows, n_cols = out.shape
    c = cos_t[v]
    s = sin_t[v]
    u0 = u0_v[v]
    v0 = v0_v[v]
    c0, c1, r0, r1, _ = _primitive_pixels_d(corners, n, c, s, sod, sdd, pu, pv, u0, v0, cos_tilt, sin_tilt, n_rows,
                                            n_cols)
    if c0 > c1 or r0 > r1:
        return
    ray = _unit_frame_ray_d(centre, maps, n, c, s, sod, sdd)
    k_n = kind[n]
    rho = density[n] / (ss * ss)
    width = c1 - c0 + 1
    for index in range(cuda.threadIdx.x, width * (r1 - r0 + 1), cuda.blockDim.x):
        r = r0 + index // width
        col = c0 + index % width
        total = pixel_chords(k_n, ray, r, col, u0, v0, pu, pv, cos_tilt, sin_tilt, sdd, ss)
        if total != 0.0:
            cuda.atomic.add(out, (v, r, col), np.float32(rho * total))


def project_primitives(out: np.ndarray, cos_t: np.ndarray, sin_t: np.ndarray, shapes: tuple, constants: tuple,
                       u0_v: np.ndarray, v0_v: np.ndarray, cos_tilt: float, sin_tilt: float, ss: int) -> None:
    """Add the primitives' line integrals to ``out`` (V, rows, cols), as the CPU kernel does."""
    kind, centre, maps, corners, density = shapes
    if len(kind) == 0 or out.shape[0] == 0:
        return
    shape_arrays = [cuda.to_device(np.ascontiguousarray(a)) for a in (kind, centre, maps, corners, density)]
    budget = memory_budget(sum(np.asarray(a).nbytes for a in shapes), "projecting the primitives")
    n_views = out.shape[0]
    chunk = chunk_views(_per_view_bytes(out.shape[1:], 1), budget, n_views, most=65535)
    for start in range(0, n_views, chunk):
        part = slice(start, min(start + chunk, n_views))
        d_out = cuda.to_device(np.ascontiguousarray(out[part]))
        views = [cuda.to_device(np.ascontiguousarray(a[part], dtype=np.float64)) for a in (cos_t, sin_t, u0_v, v0_v)]
        _primitives_kernel[(len(kind), part.stop - start), 128](d_out, views[0], views[1], *shape_arrays,
                                                                *(float(value) for value in constants), views[2],
                                                                views[3], float(cos_tilt), float(sin_tilt), int(ss))
        d_out.copy_to_host(out[part])
