"""CUDA kernels (numba-cuda) of FDK's ramp filter and backprojection, for :func:`ctpipe.recon.feldkamp.fdk` on the GPU.

The views go to the GPU as they are; there they are weighted, filtered and backprojected, and
only the volume comes back. The first try filtered on the CPU (FFTs over all cores) and sent the
filtered views over: on an H100 that made FDK of 512 views of 512^2 take 2.6 s against the GPU
peer's 0.30 s, nearly all of it the host's filtering and transposing.

- The ramp filter is the convolution of each row with the filter's spatial taps,
  ``irfft(response, n_pad)``: exactly what the CPU's FFT computes (a circular convolution over
  ``n_pad >= 2 cols`` samples), as a direct sum of ``cols`` products per pixel, with the row in
  shared memory a tile at a time. numba-cuda has no FFT; the direct sum costs ``cols`` multiply-
  adds a pixel, a few milliseconds a view at 2048 columns.
- The backprojection is voxel-driven, one thread per voxel: each sums a chunk of filtered views
  in a register and adds the sum to the accumulator, where the CPU kernel adds view by view into
  memory; the two agree to float32 rounding.

Imported only when :func:`ctpipe.gpu.active` is ``"cuda"``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import cuda

from ctpipe._shared.device import blocks_for, memory_budget, prepare_cuda

__all__ = ["FdkAccumulator"]

prepare_cuda()

#: Threads of a filter block: the output columns it computes and the row samples it stages at a time.
_FILTER_THREADS = 128


@cuda.jit(cache=True)
def _ramp_kernel(out_t, views, cosine, redundancy, taps, fall, rise, n_edge):
    """``out_t[v, 1 + col, 1 + row]`` = the weighted row ``views[v, row] * cosine[row] * redundancy[v]``,
    extended past its ends when ``fall`` and ``rise`` are not empty, circularly convolved with
    ``taps`` (length a power of two), for every column ``col``.

    The extension is :func:`ctpipe.recon.feldkamp._extended_rows`': the mean of the ``n_edge``
    outermost weighted samples at each end, times the roll-off ``fall`` after the right end and
    ``rise`` before the left one (the left part wraps round the padded row).
    """
    tile = cuda.shared.array(_FILTER_THREADS, np.float32)
    t = cuda.threadIdx.x
    col = cuda.blockIdx.x * _FILTER_THREADS + t
    row = cuda.blockIdx.y
    v = cuda.blockIdx.z
    n_cols = views.shape[2]
    n_fall = fall.shape[0]
    extended = n_fall + rise.shape[0] > 0
    n_in = taps.shape[0] if extended else n_cols
    right = np.float32(0.0)
    left = np.float32(0.0)
    if extended:
        for k in range(n_edge):
            right += views[v, row, n_cols - 1 - k] * cosine[row, n_cols - 1 - k] * redundancy[v, n_cols - 1 - k]
            left += views[v, row, k] * cosine[row, k] * redundancy[v, k]
        right /= n_edge
        left /= n_edge
    mask = taps.shape[0] - 1
    acc = np.float32(0.0)
    for start in range(0, n_in, _FILTER_THREADS):
        j = start + t
        if j < n_cols:
            tile[t] = views[v, row, j] * cosine[row, j] * redundancy[v, j]
        elif j < n_cols + n_fall and j < n_in:
            tile[t] = right * fall[j - n_cols]
        elif j < n_in:
            tile[t] = left * rise[j - n_cols - n_fall]
        else:
            tile[t] = np.float32(0.0)
        cuda.syncthreads()
        for k in range(min(_FILTER_THREADS, n_in - start)):
            acc += tile[k] * taps[(col - start - k) & mask]
        cuda.syncthreads()
    if col < n_cols:
        out_t[v, 1 + col, 1 + row] = acc


@cuda.jit(cache=True)
def _fdk_kernel(acc, proj_t, cos_t, sin_t, weight, xs, zs, y0, dy, sod, su, sv, u0, v0):
    """:func:`ctpipe.recon.feldkamp._backproject`, one thread per voxel, the chunk's views summed in a register."""
    iy, iz, ix = cuda.grid(3)
    n_x, n_z, n_y = acc.shape
    if ix >= n_x or iz >= n_z or iy >= n_y:
        return
    n_views, n_u, n_v = proj_t.shape
    u_hi = n_u - 1.0
    v_hi = n_v - 1.0 - 1e-3
    x = xs[ix]
    z = zs[iz]
    y = y0 + iy * dy
    total = np.float32(0.0)
    for k in range(n_views):
        c = cos_t[k]
        s = sin_t[k]
        depth = s * x + c * z + sod
        if depth <= 0.0:
            continue
        inv = 1.0 / depth
        u = u0 + (c * x - s * z) * inv * su
        if u < 0.0 or u >= u_hi:
            continue
        v = np.float32(v0 + y * inv * sv)
        if v < 0.0 or v >= v_hi:
            continue
        ui = int(u)
        fu = u - ui
        wd = weight[k] * sod * sod * inv * inv
        a0 = np.float32(wd * (1.0 - fu))
        a1 = np.float32(wd * fu)
        vi = int(v)
        fv = v - np.float32(vi)
        p00 = proj_t[k, ui, vi]
        p01 = proj_t[k, ui, vi + 1]
        p10 = proj_t[k, ui + 1, vi]
        p11 = proj_t[k, ui + 1, vi + 1]
        total += a0 * (p00 + fv * (p01 - p00)) + a1 * (p10 + fv * (p11 - p10))
    acc[ix, iz, iy] += total


class FdkAccumulator:
    """FDK on the GPU: :meth:`add` chunks of views (weighted, filtered and backprojected there), :meth:`result`.

    Parameters
    ----------
    shape : (n_x, n_z, n_y)
        The accumulator's shape (y contiguous, as the CPU kernel's).
    xs, zs, y0, dy
        Voxel centres along x and z, the first along y and the step, mm.
    constants : (sod, su, sv, u0, v0)
        As :func:`ctpipe.recon.feldkamp._backproject` takes them (principal point padded).
    taps : ndarray of shape (n_pad,)
        The ramp filter's spatial taps, scale included.
    cosine : ndarray of shape (rows, cols)
        Feldkamp's cosine pre-weight.
    chunk_views : int
        The most views one :meth:`add` takes (room is planned for a chunk of views, filtered
        views and weights).
    roll_offs, n_edge
        :func:`ctpipe.recon.feldkamp._roll_offs`' fall and rise and the edge samples averaged,
        to extend truncated rows; None: rows not extended.
    """

    def __init__(self, shape: tuple[int, int, int], xs: np.ndarray, zs: np.ndarray, y0: float, dy: float,
                 constants: tuple, taps: np.ndarray, cosine: np.ndarray, chunk_views: int,
                 roll_offs: tuple[np.ndarray, np.ndarray] | None = None, n_edge: int = 3) -> None:
        rows, cols = cosine.shape
        filtered = 3 * chunk_views * (rows + 2) * (cols + 2)
        memory_budget(4.0 * (math.prod(shape) + filtered + taps.size + cosine.size), "reconstructing the volume")
        self._acc = cuda.to_device(np.zeros(shape, dtype=np.float32))
        self._xs = cuda.to_device(np.ascontiguousarray(xs, dtype=np.float64))
        self._zs = cuda.to_device(np.ascontiguousarray(zs, dtype=np.float64))
        self._rest = (float(y0), float(dy), *(float(value) for value in constants))
        self._taps = cuda.to_device(np.ascontiguousarray(taps, dtype=np.float32))
        self._cosine = cuda.to_device(np.ascontiguousarray(cosine, dtype=np.float32))
        empty = np.zeros(0, dtype=np.float32)
        self._roll = [cuda.to_device(np.ascontiguousarray(a, dtype=np.float32))
                      for a in (roll_offs if roll_offs is not None else (empty, empty))]
        self._n_edge = int(n_edge)
        self._ones = None
        self._filtered = None

    def add(self, views: np.ndarray, redundancy: np.ndarray | None, cos_t: np.ndarray, sin_t: np.ndarray,
            weight: np.ndarray) -> None:
        """Weight, filter and backproject a chunk of views (V, rows, cols) as recorded.

        ``redundancy`` (V, cols) Parker's weights of a short scan, or None; ``weight`` (V,) each
        view's angular interval.
        """
        n_views, rows, cols = views.shape
        if self._filtered is None or self._filtered.shape[0] != n_views:
            self._filtered = cuda.to_device(np.zeros((n_views, cols + 2, rows + 2), dtype=np.float32))
        if redundancy is None:
            if self._ones is None or self._ones.shape[0] != n_views:
                self._ones = cuda.to_device(np.ones((n_views, cols), dtype=np.float32))
            share = self._ones
        else:
            share = cuda.to_device(np.ascontiguousarray(redundancy, dtype=np.float32))
        grid = blocks_for((cols, rows, n_views), (_FILTER_THREADS, 1, 1))
        _ramp_kernel[grid, _FILTER_THREADS](self._filtered, cuda.to_device(np.ascontiguousarray(views,
                                                                                                dtype=np.float32)),
                                            self._cosine, share, self._taps, *self._roll, self._n_edge)
        n_x, n_z, n_y = self._acc.shape
        block = (64, 4, 1)
        grid = blocks_for((n_y, n_z, n_x), block)
        _fdk_kernel[grid, block](self._acc, self._filtered,
                                 cuda.to_device(np.ascontiguousarray(cos_t, dtype=np.float64)),
                                 cuda.to_device(np.ascontiguousarray(sin_t, dtype=np.float64)),
                                 cuda.to_device(np.ascontiguousarray(weight, dtype=np.float64)),
                                 self._xs, self._zs, *self._rest)

    def result(self) -> np.ndarray:
        return self._acc.copy_to_host()
