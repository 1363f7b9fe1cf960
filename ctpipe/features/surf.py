"""SURF keypoints and descriptors, computed the way OpenCV's ``xfeatures2d::SURF`` computes them.

The OpenCV wheels on PyPI refuse SURF (patented, excluded from their build) and Debian's OpenCV
has no ``xfeatures2d``, yet the paper's pipeline and the results users compare with are
OpenCV's SURF. This module follows OpenCV's algorithm (``modules/xfeatures2d/src/surf.cpp``)
step by step, including the details that decide which keypoints come out:

Detection (fast Hessian)
    An integral image; per octave ``o`` and layer ``l`` box filters of size
    ``(9 + 6 l) << o`` sampled every ``1 << o`` pixels; each box weighted by ``1 / area`` and
    summed in double precision; ``det = Dxx Dyy - 0.81 Dxy^2`` and ``trace = Dxx + Dyy`` in
    single precision. A keypoint is a strict maximum of ``det`` over its 3x3x3 neighbourhood
    in the middle layers, above ``hessian_threshold``; its position and size are refined by one
    Newton step on the 3x3x3 samples (rejected if the step leaves the cell) and its size is
    rounded to a whole pixel. ``octave`` is the plain octave index, ``class_id`` the sign of the
    trace, ``response`` the determinant.
Orientation
    Haar wavelets of size ``4 s`` (``s = 1.2 size / 9``) at the grid points of a disc of radius
    ``6 s``, Gaussian weighted (sigma 2.5); a 60 deg window slid in 5 deg steps picks the
    direction of the largest summed response. ``upright`` skips this and stores OpenCV's
    ``270`` deg, the direction its descriptor window is then sampled in.
Descriptor
    Not the integral-image Haar version of the paper: OpenCV samples a square window of side
    ``21 s`` rotated to the orientation from the uint8 image (bilinear, rounded to uint8;
    upright: a clamped pixel copy), shrinks it to 21 x 21 with area interpolation, and sums
    Gaussian-weighted (sigma 3.3) 2x2 differences ``dx, dy`` over 4 x 4 cells of 5 x 5:
    ``(sum dx, sum dy, sum |dx|, sum |dy|)`` per cell (64 floats), or split by the sign of the
    other derivative (128 floats, ``extended``); L2-normalised.

OpenCV works on uint8 images; float images are mapped linearly from their own [min, max] to
[0, 255] and rounded (:func:`ctpipe.images.to_uint8`), so ``hessian_threshold`` keeps its
meaning on 8-bit grey levels whatever the units of a ``-log`` projection.

The loops run in numba. Detection keeps IEEE semantics (no ``fastmath``): a keypoint exists or
not by a strict comparison of single-precision determinants, and reassociated sums would move
that boundary away from OpenCV's.
"""

from __future__ import annotations

import math

import numpy as np
from numba import prange

from ctpipe._shared.jit import njit
from ctpipe.images import to_uint8

__all__ = ["integral_image", "fast_hessian", "surf_descriptors", "compute_surf"]


_HAAR_SIZE0 = 9
_HAAR_SIZE_INC = 6
_ORI_RADIUS = 6
_ORI_SIGMA = 2.5
_DESC_SIGMA = 3.3
_PATCH = 20

# Box patterns at the base size 9 (x0, y0, x1, y1, weight), OpenCV's dx_s, dy_s, dxy_s.
_DXX = np.array([[0, 2, 3, 7, 1], [3, 2, 6, 7, -2], [6, 2, 9, 7, 1]])
_DYY = np.array([[2, 0, 7, 3, 1], [2, 3, 7, 6, -2], [2, 6, 7, 9, 1]])
_DXY = np.array([[1, 1, 4, 4, 1], [5, 1, 8, 4, -1], [1, 5, 4, 8, -1], [5, 5, 8, 8, 1]])
# Gradient wavelets at the base size 4, for the orientation.
_GX = np.array([[0, 0, 2, 4, -1], [2, 0, 4, 4, 1]])
_GY = np.array([[0, 0, 4, 2, 1], [0, 2, 4, 4, -1]])


@njit(cache=True)
def _round(x):
    """cvRound: to nearest, ties to even (``lrint`` in the default rounding mode)."""
    return int(np.rint(x))


@njit(cache=True)
def _resize_pattern(src, old_size, new_size):
    """OpenCV's resizeHaarPattern: boxes (x0, y0, x1, y1) scaled and rounded, weights / area."""
    n = src.shape[0]
    boxes = np.empty((n, 4), np.int64)
    weights = np.empty(n, np.float32)
    ratio = np.float32(new_size) / np.float32(old_size)
    for k in range(n):
        x0 = _round(ratio * np.float32(src[k, 0]))
        y0 = _round(ratio * np.float32(src[k, 1]))
        x1 = _round(ratio * np.float32(src[k, 2]))
        y1 = _round(ratio * np.float32(src[k, 3]))
        boxes[k, 0], boxes[k, 1], boxes[k, 2], boxes[k, 3] = x0, y0, x1, y1
        weights[k] = np.float32(src[k, 4]) / np.float32((x1 - x0) * (y1 - y0))
    return boxes, weights


@njit(cache=True)
def _flat_pattern(boxes, weights, width):
    """Box corners as offsets into the raveled integral image: OpenCV's SurfHF (p0..p3, w)."""
    offsets = np.empty((boxes.shape[0], 4), np.int64)
    for k in range(boxes.shape[0]):
        x0, y0, x1, y1 = boxes[k, 0], boxes[k, 1], boxes[k, 2], boxes[k, 3]
        offsets[k, 0] = y0 * width + x0
        offsets[k, 1] = y1 * width + x0
        offsets[k, 2] = y0 * width + x1
        offsets[k, 3] = y1 * width + x1
    return offsets, weights.astype(np.float64)


@njit(cache=True, inline="always")
def _haar(flat, origin, offsets, weights):
    """calcHaarPattern: weighted box sums at ``origin`` of the raveled integral image,
    accumulated in double and returned as float32."""
    d = 0.0
    for k in range(offsets.shape[0]):
        box = (flat[origin + offsets[k, 0]] + flat[origin + offsets[k, 3]]
               - flat[origin + offsets[k, 1]] - flat[origin + offsets[k, 2]])
        d += np.float64(box) * weights[k]
    return np.float32(d)


@njit(cache=True, parallel=True)
def _hessian_layer(sums, size, step, det, trace):
    """calcLayerDetAndTrace: det and trace of one layer, written at OpenCV's offsets."""
    rows, cols = sums.shape[0] - 1, sums.shape[1] - 1
    if size > rows or size > cols:
        return
    width = sums.shape[1]
    flat = sums.ravel()
    dxx_o, dxx_w = _flat_pattern(*_resize_pattern(_DXX, 9, size), width)
    dyy_o, dyy_w = _flat_pattern(*_resize_pattern(_DYY, 9, size), width)
    dxy_o, dxy_w = _flat_pattern(*_resize_pattern(_DXY, 9, size), width)
    samples_i = 1 + (rows - size) // step
    samples_j = 1 + (cols - size) // step
    margin = (size // 2) // step
    c081 = np.float32(0.81)
    for i in prange(samples_i):
        det_row = det[i + margin]
        trace_row = trace[i + margin]
        for j in range(samples_j):
            origin = i * step * width + j * step
            dxx = _haar(flat, origin, dxx_o, dxx_w)
            dyy = _haar(flat, origin, dyy_o, dyy_w)
            dxy = _haar(flat, origin, dxy_o, dxy_w)
            det_row[j + margin] = dxx * dyy - c081 * dxy * dxy
            trace_row[j + margin] = dxx + dyy


@njit(cache=True)
def _interpolate(n9):
    """One Newton step on the 3x3x3 det samples, solved by Cramer's rule in float32 as OpenCV's
    ``Matx33f::solve(DECOMP_LU)``; returns (ok, dx, dy, ds)."""
    half = np.float32(2.0)
    quarter = np.float32(4.0)
    b0 = -(n9[1, 5] - n9[1, 3]) / half
    b1 = -(n9[1, 7] - n9[1, 1]) / half
    b2 = -(n9[2, 4] - n9[0, 4]) / half
    a00 = n9[1, 3] - np.float32(2.0) * n9[1, 4] + n9[1, 5]
    a01 = (n9[1, 8] - n9[1, 6] - n9[1, 2] + n9[1, 0]) / quarter
    a02 = (n9[2, 5] - n9[2, 3] - n9[0, 5] + n9[0, 3]) / quarter
    a11 = n9[1, 1] - np.float32(2.0) * n9[1, 4] + n9[1, 7]
    a12 = (n9[2, 7] - n9[2, 1] - n9[0, 7] + n9[0, 1]) / quarter
    a22 = n9[0, 4] - np.float32(2.0) * n9[1, 4] + n9[2, 4]
    a10, a20, a21 = a01, a02, a12
    det = np.float32(np.float64(a00) * (np.float64(a11) * a22 - np.float64(a21) * a12)
                     - np.float64(a01) * (np.float64(a10) * a22 - np.float64(a20) * a12)
                     + np.float64(a02) * (np.float64(a10) * a21 - np.float64(a20) * a11))
    if det == 0:
        return False, np.float32(0), np.float32(0), np.float32(0)
    d = np.float32(1.0) / det
    x0 = d * (b0 * (a11 * a22 - a12 * a21) - a01 * (b1 * a22 - a12 * b2) + a02 * (b1 * a21 - a11 * b2))
    x1 = d * (a00 * (b1 * a22 - a12 * b2) - b0 * (a10 * a22 - a12 * a20) + a02 * (a10 * b2 - b1 * a20))
    x2 = d * (a00 * (a11 * b2 - b1 * a21) - a01 * (a10 * b2 - b1 * a20) + b0 * (a10 * a21 - a11 * a20))
    ok = (x0 != 0 or x1 != 0 or x2 != 0) and abs(x0) <= 1 and abs(x1) <= 1 and abs(x2) <= 1
    return ok, x0, x1, x2


@njit(cache=True)
def _find_maxima(det_lo, det_mid, det_hi, trace_mid, size, size_lo, size_hi, step, rows, cols, threshold, out):
    """findMaximaInLayer: strict 3x3x3 maxima above the threshold, interpolated.

    Writes rows (x, y, size, response, class_id) into ``out`` and returns how many.
    """
    layer_rows = rows // step
    layer_cols = cols // step
    margin = (size_hi // 2) // step + 1
    n9 = np.empty((3, 9), np.float32)
    count = 0
    ds = size - size_lo
    for i in range(margin, layer_rows - margin):
        for j in range(margin, layer_cols - margin):
            val0 = det_mid[i, j]
            if not val0 > threshold:
                continue
            k = 0
            for di in range(-1, 2):
                for dj in range(-1, 2):
                    n9[0, k] = det_lo[i + di, j + dj]
                    n9[1, k] = det_mid[i + di, j + dj]
                    n9[2, k] = det_hi[i + di, j + dj]
                    k += 1
            is_max = True
            for layer in range(3):
                for k in range(9):
                    if (layer != 1 or k != 4) and not val0 > n9[layer, k]:
                        is_max = False
                        break
                if not is_max:
                    break
            if not is_max:
                continue
            sum_i = step * (i - (size // 2) // step)
            sum_j = step * (j - (size // 2) // step)
            centre_i = np.float32(sum_i) + np.float32(size - 1) * np.float32(0.5)
            centre_j = np.float32(sum_j) + np.float32(size - 1) * np.float32(0.5)
            ok, x0, x1, x2 = _interpolate(n9)
            if not ok:
                continue
            t = trace_mid[i, j]
            out[count, 0] = centre_j + x0 * np.float32(step)
            out[count, 1] = centre_i + x1 * np.float32(step)
            out[count, 2] = np.float32(_round(np.float32(size) + x2 * np.float32(ds)))
            out[count, 3] = val0
            out[count, 4] = np.float32(1.0) if t > 0 else (np.float32(-1.0) if t < 0 else np.float32(0.0))
            count += 1
    return count


_ATAN_P1 = np.float32(0.9997878412794807 * 180.0 / math.pi)
_ATAN_P3 = np.float32(-0.3258083974640975 * 180.0 / math.pi)
_ATAN_P5 = np.float32(0.1555786518463281 * 180.0 / math.pi)
_ATAN_P7 = np.float32(-0.04432655554792128 * 180.0 / math.pi)


@njit(cache=True)
def _fast_atan2(y, x):
    """cv::fastAtan2 in degrees [0, 360): OpenCV's 7th-order polynomial, float32."""
    ax, ay = abs(x), abs(y)
    eps = np.float32(2.220446049250313e-16)
    if ax >= ay:
        c = ay / (ax + eps)
        c2 = c * c
        a = (((_ATAN_P7 * c2 + _ATAN_P5) * c2 + _ATAN_P3) * c2 + _ATAN_P1) * c
    else:
        c = ax / (ay + eps)
        c2 = c * c
        a = np.float32(90.0) - (((_ATAN_P7 * c2 + _ATAN_P5) * c2 + _ATAN_P3) * c2 + _ATAN_P1) * c
    if x < 0:
        a = np.float32(180.0) - a
    if y < 0:
        a = np.float32(360.0) - a
    return a


@njit(cache=True)
def _area_table(src_size, dst_size):
    """cv::resize INTER_AREA weights along one axis: (dst index, src index, weight) rows."""
    scale = src_size / dst_size
    table = np.empty((2 * src_size + 2 * dst_size, 3), np.float64)
    k = 0
    for dx in range(dst_size):
        fsx1 = dx * scale
        fsx2 = fsx1 + scale
        cell = min(scale, src_size - fsx1)
        sx1 = math.ceil(fsx1)
        sx2 = math.floor(fsx2)
        sx2 = min(sx2, src_size - 1)
        sx1 = min(sx1, sx2)
        if sx1 - fsx1 > 1e-3:
            table[k, 0], table[k, 1], table[k, 2] = dx, sx1 - 1, (sx1 - fsx1) / cell
            k += 1
        for sx in range(sx1, sx2):
            table[k, 0], table[k, 1], table[k, 2] = dx, sx, 1.0 / cell
            k += 1
        if fsx2 - sx2 > 1e-3:
            table[k, 0], table[k, 1], table[k, 2] = dx, sx2, min(min(fsx2 - sx2, 1.0), cell) / cell
            k += 1
    return table[:k]


@njit(cache=True)
def _resize_area(win, size, out):
    """Shrink the (size, size) uint8 window to ``out`` (21, 21) by area averaging, rounded."""
    n = out.shape[0]
    table = _area_table(size, n)
    rows = np.zeros((size, n), np.float32)
    for sy in range(size):
        for k in range(table.shape[0]):
            rows[sy, int(table[k, 0])] += np.float32(win[sy, int(table[k, 1])]) * np.float32(table[k, 2])
    acc = np.zeros((n, n), np.float32)
    for k in range(table.shape[0]):
        dy, sy, beta = int(table[k, 0]), int(table[k, 1]), np.float32(table[k, 2])
        for dx in range(n):
            acc[dy, dx] += beta * rows[sy, dx]
    for dy in range(n):
        for dx in range(n):
            v = _round(acc[dy, dx])
            out[dy, dx] = min(max(v, 0), 255)


@njit(cache=True, parallel=True)
def _describe(image, sums, kp_x, kp_y, kp_size, upright, extended, apt, aptw, dw, angles, descriptors, valid):
    """SURFInvoker: orientation and descriptor of every keypoint (in place)."""
    n_kp = kp_x.shape[0]
    rows, cols = image.shape
    sum_rows, sum_cols = sums.shape
    flat = sums.ravel()
    n_ori = apt.shape[0]
    dsize = descriptors.shape[1]
    for k in prange(n_kp):
        valid[k] = False
        size = kp_size[k]
        cx, cy = kp_x[k], kp_y[k]
        s = size * np.float32(1.2) / np.float32(9.0)
        grad_wav_size = 2 * _round(np.float32(2.0) * s)
        if sum_rows < grad_wav_size or sum_cols < grad_wav_size:
            continue
        direction = np.float32(270.0)
        if not upright:
            gx_o, gx_w = _flat_pattern(*_resize_pattern(_GX, 4, grad_wav_size), sum_cols)
            gy_o, gy_w = _flat_pattern(*_resize_pattern(_GY, 4, grad_wav_size), sum_cols)
            xs = np.empty(n_ori, np.float32)
            ys = np.empty(n_ori, np.float32)
            ang = np.empty(n_ori, np.int64)
            n_angle = 0
            half = np.float32(grad_wav_size - 1) / np.float32(2.0)
            for kk in range(n_ori):
                x = _round(cx + np.float32(apt[kk, 0]) * s - half)
                y = _round(cy + np.float32(apt[kk, 1]) * s - half)
                if y < 0 or y >= sum_rows - grad_wav_size or x < 0 or x >= sum_cols - grad_wav_size:
                    continue
                vx = _haar(flat, y * sum_cols + x, gx_o, gx_w)
                vy = _haar(flat, y * sum_cols + x, gy_o, gy_w)
                xs[n_angle] = vx * aptw[kk]
                ys[n_angle] = vy * aptw[kk]
                ang[n_angle] = _round(_fast_atan2(ys[n_angle], xs[n_angle]))
                n_angle += 1
            if n_angle == 0:
                continue
            best_x = np.float32(0.0)
            best_y = np.float32(0.0)
            best_mod = np.float32(0.0)
            for i in range(0, 360, 5):
                sum_x = np.float32(0.0)
                sum_y = np.float32(0.0)
                for j in range(n_angle):
                    d = abs(ang[j] - i)
                    if d < 30 or d > 330:
                        sum_x += xs[j]
                        sum_y += ys[j]
                mod = sum_x * sum_x + sum_y * sum_y
                if mod > best_mod:
                    best_mod, best_x, best_y = mod, sum_x, sum_y
            direction = _fast_atan2(-best_y, best_x)
        angles[k] = direction

        # The window of side 21 s around the keypoint, turned to its direction.
        win_size = int(np.float32(_PATCH + 1) * s)
        win = np.empty((win_size, win_size), np.uint8)
        win_offset = -np.float32(win_size - 1) / np.float32(2.0)
        if not upright:
            rad = direction * np.float32(math.pi / 180.0)
            sin_dir = -np.float32(math.sin(rad))
            cos_dir = np.float32(math.cos(rad))
            start_x = cx + win_offset * cos_dir + win_offset * sin_dir
            start_y = cy - win_offset * sin_dir + win_offset * cos_dir
            for i in range(win_size):
                pixel_x = np.float64(start_x)
                pixel_y = np.float64(start_y)
                for j in range(win_size):
                    ix = int(math.floor(pixel_x))
                    iy = int(math.floor(pixel_y))
                    if 0 <= ix < cols - 1 and 0 <= iy < rows - 1:
                        a = np.float32(pixel_x - ix)
                        b = np.float32(pixel_y - iy)
                        one = np.float32(1.0)
                        v = (np.float32(image[iy, ix]) * (one - a) * (one - b)
                             + np.float32(image[iy, ix + 1]) * a * (one - b)
                             + np.float32(image[iy + 1, ix]) * (one - a) * b
                             + np.float32(image[iy + 1, ix + 1]) * a * b)
                        win[i, j] = _round(v)
                    else:
                        x = min(max(_round(pixel_x), 0), cols - 1)
                        y = min(max(_round(pixel_y), 0), rows - 1)
                        win[i, j] = image[y, x]
                    pixel_x += cos_dir
                    pixel_y -= sin_dir
                start_x += sin_dir
                start_y += cos_dir
        else:
            start_x = _round(cx + win_offset)
            start_y = _round(cy - win_offset)
            for i in range(win_size):
                x = min(max(start_x + i, 0), cols - 1)
                for j in range(win_size):
                    y = min(max(start_y - j, 0), rows - 1)
                    win[i, j] = image[y, x]

        patch = np.empty((_PATCH + 1, _PATCH + 1), np.int64)
        _resize_area(win, win_size, patch)
        vec = descriptors[k]
        for kk in range(dsize):
            vec[kk] = 0.0
        square_mag = 0.0
        per_cell = 8 if extended else 4
        for ci in range(4):
            for cj in range(4):
                base = (ci * 4 + cj) * per_cell
                for y in range(ci * 5, ci * 5 + 5):
                    for x in range(cj * 5, cj * 5 + 5):
                        w = dw[y, x]
                        tx = np.float32(patch[y, x + 1] - patch[y, x] + patch[y + 1, x + 1] - patch[y + 1, x]) * w
                        ty = np.float32(patch[y + 1, x] - patch[y, x] + patch[y + 1, x + 1] - patch[y, x + 1]) * w
                        if extended:
                            # dx sums split by the sign of dy, and dy sums by the sign of dx.
                            o = 0 if ty >= 0 else 2
                            vec[base + o] += tx
                            vec[base + o + 1] += abs(tx)
                            o = 4 if tx >= 0 else 6
                            vec[base + o] += ty
                            vec[base + o + 1] += abs(ty)
                        else:
                            vec[base + 0] += tx
                            vec[base + 1] += ty
                            vec[base + 2] += abs(tx)
                            vec[base + 3] += abs(ty)
                for kk in range(per_cell):
                    square_mag += np.float64(vec[base + kk]) * np.float64(vec[base + kk])
        scale = np.float32(1.0 / (math.sqrt(square_mag) + 1.1920928955078125e-07))
        for kk in range(dsize):
            vec[kk] *= scale
        valid[k] = True


def _gaussian_kernel(n: int, sigma: float) -> np.ndarray:
    """cv::getGaussianKernel(n, sigma, CV_32F)."""
    x = np.arange(n) - (n - 1) * 0.5
    kernel = np.exp(-0.5 / sigma**2 * x * x).astype(np.float32)
    return (kernel * (1.0 / kernel.astype(np.float64).sum())).astype(np.float32)


def _orientation_samples() -> tuple[np.ndarray, np.ndarray]:
    """Grid points of the disc of radius 6 and their Gaussian weights, in OpenCV's order."""
    g = _gaussian_kernel(2 * _ORI_RADIUS + 1, _ORI_SIGMA)
    points, weights = [], []
    for i in range(-_ORI_RADIUS, _ORI_RADIUS + 1):
        for j in range(-_ORI_RADIUS, _ORI_RADIUS + 1):
            if i * i + j * j <= _ORI_RADIUS**2:
                points.append((i, j))
                weights.append(g[i + _ORI_RADIUS] * g[j + _ORI_RADIUS])
    return np.array(points, np.int64), np.array(weights, np.float32)


_APT, _APTW = _orientation_samples()
_G_DESC = _gaussian_kernel(_PATCH, _DESC_SIGMA)
_DW = (_G_DESC[:, None] * _G_DESC[None, :]).astype(np.float32)


def integral_image(image_u8: np.ndarray) -> np.ndarray:
    """Summed-area table of an 8-bit image, with a leading row and column of zeros.

    Parameters
    ----------
    image_u8 : ndarray of shape (rows, cols)
        The image (uint8, or any integer dtype whose sums fit int64).

    Returns
    -------
    ndarray of shape (rows + 1, cols + 1), int64
        ``sums[i, j]`` is the sum of ``image_u8[:i, :j]``.
    """
    sums = np.zeros((image_u8.shape[0] + 1, image_u8.shape[1] + 1), np.int64)
    np.cumsum(np.cumsum(image_u8, axis=0, dtype=np.int64), axis=1, out=sums[1:, 1:])
    return sums


def fast_hessian(sums: np.ndarray, rows: int, cols: int, n_octaves: int, n_octave_layers: int,
                 threshold: float) -> np.ndarray:
    """SURF keypoints: OpenCV's ``fastHessianDetector`` on an integral image.

    Parameters
    ----------
    sums : ndarray of shape (rows + 1, cols + 1), int64
        The image's :func:`integral_image`.
    rows, cols : int
        The image's shape.
    n_octaves, n_octave_layers : int
        Octaves of box-filter sizes, and the layers per octave searched for maxima.
    threshold : float
        Keep maxima whose Hessian determinant exceeds this.

    Returns
    -------
    ndarray of shape (n, 6), float32
        Rows ``(x, y, size, response, class_id, octave)``, octave by octave and layer by layer
        (not sorted by response).
    """
    found = []
    step = 1
    for octave in range(n_octaves):
        sizes = [(_HAAR_SIZE0 + _HAAR_SIZE_INC * layer) << octave for layer in range(n_octave_layers + 2)]
        dets, traces = [], []
        for size in sizes:
            det = np.zeros((rows // step, cols // step), np.float32)
            trace = np.zeros_like(det)
            _hessian_layer(sums, size, step, det, trace)
            dets.append(det)
            traces.append(trace)
        for layer in range(1, n_octave_layers + 1):
            out = np.empty((max(dets[layer].size // 4, 1), 5), np.float32)
            n = _find_maxima(dets[layer - 1], dets[layer], dets[layer + 1], traces[layer], sizes[layer],
                             sizes[layer - 1], sizes[layer + 1], step, rows, cols, np.float32(threshold), out)
            rows_found = np.empty((n, 6), np.float32)
            rows_found[:, :5] = out[:n]
            rows_found[:, 5] = octave
            found.append(rows_found)
        step *= 2
    return np.concatenate(found) if found else np.empty((0, 6), np.float32)


def surf_descriptors(image_u8: np.ndarray, sums: np.ndarray, keypoints: np.ndarray, *, extended: bool = False,
                     upright: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Orientation and descriptor of each keypoint: OpenCV's ``SURFInvoker``.

    Parameters
    ----------
    image_u8 : ndarray of shape (rows, cols), uint8
        The image, C-contiguous.
    sums : ndarray of shape (rows + 1, cols + 1), int64
        Its :func:`integral_image`.
    keypoints : ndarray of shape (n, >= 3)
        Rows starting ``(x, y, size)``, as :func:`fast_hessian` gives.
    extended : bool
        128-float descriptors instead of 64.
    upright : bool
        Skip the orientation (angle 270 deg, as OpenCV stores it).

    Returns
    -------
    angles : ndarray of shape (n,), float32
        Orientation in degrees, [0, 360).
    descriptors : ndarray of shape (n, 64 or 128), float32
        L2-normalised.
    valid : ndarray of shape (n,), bool
        False for keypoints too large for the image (their rows are not meaningful).
    """
    keypoints = np.asarray(keypoints, np.float32)
    n = len(keypoints)
    angles = np.zeros(n, np.float32)
    descriptors = np.zeros((n, 128 if extended else 64), np.float32)
    valid = np.zeros(n, np.bool_)
    if n:
        _describe(image_u8, sums, np.ascontiguousarray(keypoints[:, 0]), np.ascontiguousarray(keypoints[:, 1]),
                  np.ascontiguousarray(keypoints[:, 2]), bool(upright), bool(extended), _APT, _APTW, _DW, angles,
                  descriptors, valid)
    return angles, descriptors, valid


def compute_surf(image, *, hessian_threshold: float = 100.0, n_octaves: int = 4, n_octave_layers: int = 3,
                 extended: bool = False, upright: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """SURF keypoints and descriptors of one image, as OpenCV's ``SURF_create(...).detectAndCompute``.

    Parameters
    ----------
    image : ndarray of shape (rows, cols)
        uint8, or any integer/float image (mapped linearly from its [min, max] to uint8).
    hessian_threshold : float
        Keep maxima whose Hessian determinant exceeds this (OpenCV's and the paper's 100).
    n_octaves, n_octave_layers : int
        Octaves of box-filter sizes, and the layers per octave searched for maxima.
    extended : bool
        128-float descriptors instead of 64.
    upright : bool
        Skip the orientation (angle stored as 270 deg, as OpenCV does).

    Returns
    -------
    keypoints : ndarray of shape (n, 6), float32
        Rows ``(x, y, size, response, class_id, octave)`` (see :func:`fast_hessian`), unsorted.
    angles : ndarray of shape (n,), float32
        Orientations in degrees.
    descriptors : ndarray of shape (n, 64 or 128), float32
        L2-normalised.

    Raises
    ------
    InputError
        Not 2-D, empty, non-numeric, or with NaN/inf pixels.
    """
    image_u8 = np.ascontiguousarray(to_uint8(image))
    rows, cols = image_u8.shape
    sums = integral_image(image_u8)
    found = fast_hessian(sums, rows, cols, int(n_octaves), int(n_octave_layers), float(hessian_threshold))
    angles, descriptors, valid = surf_descriptors(image_u8, sums, found, extended=extended, upright=upright)
    return found[valid], angles[valid], descriptors[valid]
