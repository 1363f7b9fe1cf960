"""CUDA kernels (numba-cuda) of FDK's ramp filter and backprojection, for :func:`ctpipe.recon.feldkamp.fdk` on the GPU.

The views go to the GPU as they are; there they are weighted, filtered and backprojected, and
only the volume comes back. The first try filtered on the CPU (FFTs over all cores) and sent the
filtered views over: on an H100 that made FDK of 512 views of 512^2 take 2.6 s against the GPU
peer's 0.30 s, nearly all of it the host's filtering and transposing.

- The ramp filter is what the CPU computes: each weighted (and, for truncated scans, extended)
  row zero-padded to ``n_pad`` samples, Fourier transformed, multiplied by the filter's response
  and transformed back. numba-cuda has no FFT, so :func:`_ramp_fft_kernel` is one: a radix-2
  FFT of ``n_pad`` samples in shared memory, one block per pair of rows (two real rows as the
  real and imaginary parts of one complex row: the response is real and even, so the two never
  mix), ``n_pad log2 n_pad`` operations a row. Rows too long for shared memory
  (``n_pad > 4096``, detectors over 2048 columns) take :func:`_ramp_kernel`, the same circular
  convolution as a direct sum of ``n_pad`` products a pixel by the filter's spatial taps. On
  an H200, 1,024 views of 1024^2 (rows extended to 2,048 samples): 0.082 s by the FFT, 3.05 s
  by the direct sum (``benchmarks/bench_gpu.py --phases``).
- The backprojection is voxel-driven, one thread per voxel: each sums a chunk of filtered views
  in a register and adds the sum to the accumulator, where the CPU kernel adds view by view into
  memory; the two agree to float32 rounding.

Imported only when :func:`ctpipe.gpu.active` is ``"cuda"``.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator

import numpy as np
from numba import cuda

from ctpipe._shared.device import blocks_for, memory_budget, prepare_cuda

__all__ = ["FdkAccumulator", "direct_filter"]

prepare_cuda()

#: Threads of a filter block: the output columns it computes and the row samples it stages at a time.
_FILTER_THREADS = 128

#: The longest padded row the FFT filter holds in shared memory (two float32 arrays: 32 KiB).
FFT_SAMPLES = 4096

#: Rows padded to more samples than this take the direct convolution (a variable: see :func:`direct_filter`).
fft_longest = FFT_SAMPLES


@contextlib.contextmanager
def direct_filter() -> Iterator[None]:
    """Within the block, every row takes the direct convolution (the check and the benchmark run both filters)."""
    global fft_longest
    saved, fft_longest = fft_longest, 0
    try:
        yield
    finally:
        fft_longest = saved

#: Threads of an FFT block: each does ``n_pad / 2 / threads`` butterflies a stage.
_FFT_THREADS = 256


@cuda.jit(device=True, inline=True)
def _weighted_sample(views, cosine, redundancy, fall, rise, v, row, j, n_cols, left, right):
    """Sample ``j`` of the weighted row ``row`` of view ``v``, extended past its ends by the roll-offs."""
    n_fall = fall.shape[0]
    if j < n_cols:
        return views[v, row, j] * cosine[row, j] * redundancy[v, j]
    if j < n_cols + n_fall:
        return right * fall[j - n_cols]
    if j < n_cols + n_fall + rise.shape[0]:
        return left * rise[j - n_cols - n_fall]
    return np.float32(0.0)


@cuda.jit(device=True, inline=True)
def _edge_means(views, cosine, redundancy, v, row, n_cols, n_edge):
    """The mean of the ``n_edge`` outermost weighted samples at the left and at the right end of a row."""
    left = np.float32(0.0)
    right = np.float32(0.0)
    for k in range(n_edge):
        right += views[v, row, n_cols - 1 - k] * cosine[row, n_cols - 1 - k] * redundancy[v, n_cols - 1 - k]
        left += views[v, row, k] * cosine[row, k] * redundancy[v, k]
    return left / n_edge, right / n_edge


@cuda.jit(device=True, inline=True)
def _butterfly(p, half, half_n):
    """Butterfly ``p`` of a radix-2 stage whose pairs are ``half`` apart: its two indices and its twiddle's index."""
    k = p % half
    i = (p - k) * 2 + k
    return i, i + half, k * (half_n // half)


@cuda.jit(cache=True)
def _ramp_fft_kernel(out_t, views, cosine, redundancy, gain, twiddle_re, twiddle_im, fall, rise, n_edge):
    """:func:`_ramp_kernel`'s output through the FFT: block ``(p, v)`` filters rows ``2p`` and ``2p + 1`` of view ``v``.

    The two rows are the real and imaginary parts of one complex row of ``n = gain.shape[0]``
    samples. A decimation-in-frequency pass (natural order in, bit-reversed out) transforms it;
    ``gain`` holds the response over ``n`` (the inverse's scale) in that bit-reversed order; a
    decimation-in-time pass with the conjugate twiddles (bit-reversed in, natural out) brings it
    back. ``twiddle_re + 1j twiddle_im`` = ``exp(-2 pi i m / n)``, ``m < n / 2``. No bit
    reversal is ever done.
    """
    re = cuda.shared.array(FFT_SAMPLES, np.float32)
    im = cuda.shared.array(FFT_SAMPLES, np.float32)
    t = cuda.threadIdx.x
    n_threads = cuda.blockDim.x
    v = cuda.blockIdx.y
    row0 = 2 * cuda.blockIdx.x
    n_rows = views.shape[1]
    n_cols = views.shape[2]
    has_second = row0 + 1 < n_rows
    row1 = row0 + 1 if has_second else row0
    n = gain.shape[0]
    half_n = n // 2
    extended = fall.shape[0] + rise.shape[0] > 0
    left0 = right0 = left1 = right1 = np.float32(0.0)
    if extended:
        left0, right0 = _edge_means(views, cosine, redundancy, v, row0, n_cols, n_edge)
        left1, right1 = _edge_means(views, cosine, redundancy, v, row1, n_cols, n_edge)
    for j in range(t, n, n_threads):
        re[j] = _weighted_sample(views, cosine, redundancy, fall, rise, v, row0, j, n_cols, left0, right0)
        im[j] = (_weighted_sample(views, cosine, redundancy, fall, rise, v, row1, j, n_cols, left1, right1)
                 if has_second else np.float32(0.0))
    cuda.syncthreads()
    half = half_n
    while half >= 1:  # forward, decimation in frequency
        for p in range(t, half_n, n_threads):
            i, j, w = _butterfly(p, half, half_n)
            wr = twiddle_re[w]
            wi = twiddle_im[w]
            ar = re[i]
            ai = im[i]
            dr = ar - re[j]
            di = ai - im[j]
            re[i] = ar + re[j]
            im[i] = ai + im[j]
            re[j] = dr * wr - di * wi
            im[j] = dr * wi + di * wr
        cuda.syncthreads()
        half //= 2
    for j in range(t, n, n_threads):
        re[j] *= gain[j]
        im[j] *= gain[j]
    cuda.syncthreads()
    half = 1
    while half < n:  # inverse, decimation in time, conjugate twiddles
        for p in range(t, half_n, n_threads):
            i, j, w = _butterfly(p, half, half_n)
            wr = twiddle_re[w]
            wi = -twiddle_im[w]
            tr = re[j] * wr - im[j] * wi
            ti = re[j] * wi + im[j] * wr
            re[j] = re[i] - tr
            im[j] = im[i] - ti
            re[i] += tr
            im[i] += ti
        cuda.syncthreads()
        half *= 2
    for col in range(t, n_cols, n_threads):
        out_t[v, 1 + col, 1 + row0] = re[col]
        if has_second:
            out_t[v, 1 + col, 1 + row1] = im[col]


def fft_tables(response: np.ndarray, n_pad: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_ramp_fft_kernel`'s ``gain`` (bit-reversed, over ``n_pad``) and twiddles, float32.

    ``response`` is the real response of :func:`scipy.fft.rfft`'s ``n_pad // 2 + 1`` frequencies
    (scale included); the full length's is even: ``G[k] = response[min(k, n_pad - k)]``.
    """
    k = np.arange(n_pad)
    full = np.asarray(response, dtype=np.float64)[np.minimum(k, n_pad - k)] / n_pad
    bits = n_pad.bit_length() - 1
    reversed_k = np.zeros(n_pad, dtype=np.int64)
    for bit in range(bits):
        reversed_k |= ((k >> bit) & 1) << (bits - 1 - bit)
    angle = -2.0 * np.pi * np.arange(n_pad // 2) / n_pad
    return full[reversed_k].astype(np.float32), np.cos(angle).astype(np.float32), np.sin(angle).astype(np.float32)


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
    extended = fall.shape[0] + rise.shape[0] > 0
    n_in = taps.shape[0] if extended else n_cols
    left = right = np.float32(0.0)
    if extended:
        left, right = _edge_means(views, cosine, redundancy, v, row, n_cols, n_edge)
    mask = taps.shape[0] - 1
    acc = np.float32(0.0)
    for start in range(0, n_in, _FILTER_THREADS):
        tile[t] = _weighted_sample(views, cosine, redundancy, fall, rise, v, row, start + t, n_cols, left, right)
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


@cuda.jit(cache=True)
def _zero_kernel(flat):
    """``flat[:] = 0``."""
    i = cuda.grid(1)
    if i < flat.size:
        flat[i] = np.float32(0.0)


def _device_zeros(shape: tuple[int, ...]):
    """A float32 device array of ``shape``, zeroed where it lives: not made on the host and sent
    (a 256^3 accumulator sent was some 30 ms of a 0.27 s FDK on an H200)."""
    out = cuda.device_array(shape, dtype=np.float32)
    flat = out.reshape(math.prod(shape))
    _zero_kernel[blocks_for((flat.size,), (256,)), 256](flat)
    return out


@cuda.jit(cache=True)
def _volume_layout_kernel(out, acc):
    """``out[iy, iz, ix] = acc[ix, iz, iy]``: :func:`ctpipe.recon.feldkamp._to_volume_layout` on the GPU."""
    ix, iz, iy = cuda.grid(3)
    n_x, n_z, n_y = acc.shape
    if ix < n_x and iz < n_z and iy < n_y:
        out[iy, iz, ix] = acc[ix, iz, iy]


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
    response : ndarray of shape (n_pad // 2 + 1,)
        The ramp filter's real response (:func:`ctpipe.recon.feldkamp.ramp_filter`), scale included.
    n_pad : int
        The padded row length, a power of two.
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
                 constants: tuple, response: np.ndarray, n_pad: int, cosine: np.ndarray, chunk_views: int,
                 roll_offs: tuple[np.ndarray, np.ndarray] | None = None, n_edge: int = 3) -> None:
        rows, cols = cosine.shape
        filtered = 3 * chunk_views * (rows + 2) * (cols + 2)
        memory_budget(4.0 * (2 * math.prod(shape) + filtered + 3 * n_pad + cosine.size), "reconstructing the volume")
        self._acc = _device_zeros(shape)
        self._xs = cuda.to_device(np.ascontiguousarray(xs, dtype=np.float64))
        self._zs = cuda.to_device(np.ascontiguousarray(zs, dtype=np.float64))
        self._rest = (float(y0), float(dy), *(float(value) for value in constants))
        self._fft = n_pad <= min(fft_longest, FFT_SAMPLES)
        if self._fft:
            self._tables = [cuda.to_device(table) for table in fft_tables(response, n_pad)]
        else:
            taps = np.fft.irfft(np.asarray(response, dtype=np.float64), n=n_pad)
            self._tables = [cuda.to_device(taps.astype(np.float32))]
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
        if redundancy is None:
            if self._ones is None or self._ones.shape[0] != len(views):
                self._ones = cuda.to_device(np.ones((len(views), views.shape[2]), dtype=np.float32))
            share = self._ones
        else:
            share = cuda.to_device(np.ascontiguousarray(redundancy, dtype=np.float32))
        self.filter(cuda.to_device(np.ascontiguousarray(views, dtype=np.float32)), share)
        self.backproject(*(cuda.to_device(np.ascontiguousarray(a, dtype=np.float64)) for a in (cos_t, sin_t, weight)))

    def filter(self, views, share) -> None:
        """Weight and ramp-filter a chunk of views already on the GPU (``share``: their redundancy weights) into the buffer."""
        n_views, rows, cols = views.shape
        if self._filtered is None or self._filtered.shape[0] != n_views:
            self._filtered = _device_zeros((n_views, cols + 2, rows + 2))
        if self._fft:
            threads = min(_FFT_THREADS, self._tables[0].shape[0] // 2)
            _ramp_fft_kernel[((rows + 1) // 2, n_views), threads](self._filtered, views, self._cosine, share,
                                                                   *self._tables, *self._roll, self._n_edge)
        else:
            grid = blocks_for((cols, rows, n_views), (_FILTER_THREADS, 1, 1))
            _ramp_kernel[grid, _FILTER_THREADS](self._filtered, views, self._cosine, share, *self._tables,
                                                *self._roll, self._n_edge)

    def backproject(self, cos_t, sin_t, weight) -> None:
        """Backproject the first ``len(cos_t)`` filtered views of the buffer (device arrays of their angles' cos, sin, weight)."""
        n_x, n_z, n_y = self._acc.shape
        block = (64, 4, 1)
        _fdk_kernel[blocks_for((n_y, n_z, n_x), block), block](self._acc, self._filtered[: cos_t.shape[0]], cos_t,
                                                               sin_t, weight, self._xs, self._zs, *self._rest)

    def result(self) -> np.ndarray:
        """The volume in :class:`ctpipe.recon.volume.VolumeGrid`'s layout ``(n_y, n_z, n_x)``, reordered on the GPU."""
        n_x, n_z, n_y = self._acc.shape
        out = cuda.device_array((n_y, n_z, n_x), dtype=np.float32)
        block = (32, 4, 2)
        _volume_layout_kernel[blocks_for((n_x, n_z, n_y), block), block](out, self._acc)
        return out.copy_to_host()
