"""Joseph's ray stepping through a padded voxel volume: the helpers of the CPU and the GPU projectors.

Compiled into :mod:`ctpipe.sim.projectors`' parallel kernels and into the CUDA kernels of
:mod:`ctpipe.sim._cuda` (numba compiles an ``@njit`` function for the GPU when a CUDA kernel
calls it), so the two devices step every ray through the same planes with the same weights.
The layouts they read are described in :func:`ctpipe.sim.projectors._to_layouts`.
"""

from __future__ import annotations

import math

import numpy as np

from ctpipe._shared.jit import FASTMATH, njit


@njit(cache=True, fastmath=FASTMATH, inline="always")
def _range_within(k_lo, k_hi, f0, f1, upper):
    """Narrow ``[k_lo, k_hi]`` to the ``k`` with ``0 <= f0 + k f1 <= upper``."""
    if f1 == 0.0:
        if f0 < 0.0 or f0 > upper:
            return 1.0, 0.0
        return k_lo, k_hi
    k_a = -f0 / f1
    k_b = (upper - f0) / f1
    return max(k_lo, min(k_a, k_b)), min(k_hi, max(k_a, k_b))


@njit(cache=True, fastmath=FASTMATH, inline="always")
def _ray_setup(s_a, s_p, s_q, d_a, d_p, d_q, n_a, n_p, n_q, norm, voxel):
    """Joseph stepping of the ray ``index(t) = s + t d`` (voxel-index units, unpadded) along axis a.

    Returns the integer plane range ``[k0, k1)``, the padded positions ``p = p0 + k dp`` and
    ``q = q0 + k dq`` on plane ``k``, and the step length in mm.
    """
    dp = d_p / d_a
    dq = d_q / d_a
    p0 = s_p - s_a * dp + 1.0
    q0 = s_q - s_a * dq + 1.0
    # Planes between the source (t = 0) and the detector (t = 1), inside the grid.
    k_lo = min(s_a, s_a + d_a)
    k_hi = max(s_a, s_a + d_a)
    k_lo = max(k_lo, 0.0)
    k_hi = min(k_hi, n_a - 1.0)
    # Padded positions in [0, n + 1]: outside that both bilinear neighbours are zero.
    k_lo, k_hi = _range_within(k_lo, k_hi, p0, dp, n_p + 1.0)
    k_lo, k_hi = _range_within(k_lo, k_hi, q0, dq, n_q + 1.0)
    k0 = int(math.ceil(k_lo)) if k_lo <= k_hi else 0
    k1 = int(math.floor(k_hi)) + 1 if k_lo <= k_hi else 0
    # d_a is in voxels, so |d| (mm) / |d_a| is the mm advanced per plane.
    step = norm / abs(d_a)
    return k0, k1, p0, dp, q0, dq, step


@njit(cache=True, fastmath=FASTMATH, inline="always")
def _ray_sum(vol, k0, k1, p0, dp, q0, dq, n_p, n_q):
    acc = np.float32(0.0)
    for k in range(k0, k1):
        p = p0 + k * dp
        q = q0 + k * dq
        ip = min(max(int(p), 0), n_p)
        iq = min(max(int(q), 0), n_q)
        fp = np.float32(p - ip)
        fq = np.float32(q - iq)
        v00 = vol[ip, iq, k]
        v01 = vol[ip, iq + 1, k]
        v10 = vol[ip + 1, iq, k]
        v11 = vol[ip + 1, iq + 1, k]
        lo = v00 + fq * (v01 - v00)
        hi = v10 + fq * (v11 - v10)
        acc += lo + fp * (hi - lo)
    return acc


@njit(cache=True, fastmath=FASTMATH, inline="always")
def _view_ray(c, s, sod, sdd, pu, pv, u0, v0, origin, voxel, row, col):
    """Source and direction of a pixel's ray in voxel-index units (unpadded), and ``|d|`` in mm."""
    dxc = (col - u0) * pu
    dyc = (row - v0) * pv
    d_x = c * dxc + s * sdd
    d_y = dyc
    d_z = -s * dxc + c * sdd
    norm = math.sqrt(dxc * dxc + dyc * dyc + sdd * sdd)
    inv = 1.0 / voxel
    s_x = (-s * sod - origin[0]) * inv
    s_y = (0.0 - origin[1]) * inv
    s_z = (-c * sod - origin[2]) * inv
    return s_x, s_y, s_z, d_x * inv, d_y * inv, d_z * inv, norm


@njit(cache=True, fastmath=FASTMATH, inline="always")
def _pixel_ray(c, s, sod, sdd, pu, pv, u0, v0, origin, voxel, n_x, n_y, n_z, row, col):
    """The ray of pixel ``(row, col)`` stepped along its dominant axis.

    Returns the layout it reads (0: ``vol_x``, 1: ``vol_z``, 2: ``vol_y``), :func:`_ray_setup`'s
    plane range, positions and step, and the sizes ``(n_p, n_q)`` of the layout's other two axes.
    """
    s_x, s_y, s_z, d_x, d_y, d_z, norm = _view_ray(c, s, sod, sdd, pu, pv, u0, v0, origin, voxel, row, col)
    ax, ay, az = abs(d_x), abs(d_y), abs(d_z)
    if ax >= az and ax >= ay:
        k0, k1, p0, dp, q0, dq, step = _ray_setup(s_x, s_y, s_z, d_x, d_y, d_z, n_x, n_y, n_z, norm, voxel)
        return 0, k0, k1, p0, dp, q0, dq, step, n_y, n_z
    if az >= ay:
        k0, k1, p0, dp, q0, dq, step = _ray_setup(s_z, s_y, s_x, d_z, d_y, d_x, n_z, n_y, n_x, norm, voxel)
        return 1, k0, k1, p0, dp, q0, dq, step, n_y, n_x
    k0, k1, p0, dp, q0, dq, step = _ray_setup(s_y, s_z, s_x, d_y, d_z, d_x, n_y, n_z, n_x, norm, voxel)
    return 2, k0, k1, p0, dp, q0, dq, step, n_z, n_x


@njit(cache=True, fastmath=FASTMATH, inline="always")
def _ray_sum_pair(vol, k0, k1, p0, dp, q0, dq, n_p, n_q):
    """:func:`_ray_sum` of both volumes of a pair layout, with the weights computed once."""
    acc_a = np.float32(0.0)
    acc_b = np.float32(0.0)
    for k in range(k0, k1):
        p = p0 + k * dp
        q = q0 + k * dq
        ip = min(max(int(p), 0), n_p)
        iq = min(max(int(q), 0), n_q)
        fp = np.float32(p - ip)
        fq = np.float32(q - iq)
        a00 = vol[ip, iq, k, 0]
        b00 = vol[ip, iq, k, 1]
        a01 = vol[ip, iq + 1, k, 0]
        b01 = vol[ip, iq + 1, k, 1]
        a10 = vol[ip + 1, iq, k, 0]
        b10 = vol[ip + 1, iq, k, 1]
        a11 = vol[ip + 1, iq + 1, k, 0]
        b11 = vol[ip + 1, iq + 1, k, 1]
        lo = a00 + fq * (a01 - a00)
        hi = a10 + fq * (a11 - a10)
        acc_a += lo + fp * (hi - lo)
        lo = b00 + fq * (b01 - b00)
        hi = b10 + fq * (b11 - b10)
        acc_b += lo + fp * (hi - lo)
    return acc_a, acc_b
