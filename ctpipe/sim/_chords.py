"""The analytic projector's geometry of one primitive in one view, for the CPU and the GPU kernels.

:func:`ctpipe.sim.projectors._project_primitives` (a view per thread) and
:func:`ctpipe.sim._cuda._primitives_kernel` (a block per primitive and view) both call these
``@njit`` functions (numba compiles them into the CUDA kernel), so the two devices bound,
transform and intersect every sub-ray the same way.
"""

from __future__ import annotations

import math

from ctpipe._shared.jit import njit
from ctpipe.sim.primitives import unit_interval

__all__ = ["pixel_chords", "primitive_pixels", "unit_frame_ray"]


@njit(cache=True, fastmath=False, inline="always")
def primitive_pixels(corners, n, c, s, sod, sdd, pu, pv, u0, v0, cos_tilt, sin_tilt, n_rows, n_cols):
    """The pixel rectangle ``(c0, c1, r0, r1)`` primitive ``n`` can cover in a view; empty (``c0 > c1``) if none.

    The perspective images of its box's corners bound it (a convex set in front of the source
    maps into the convex hull of its corners' images); a box across the source plane may cover
    the whole detector, one wholly behind it nothing. Also returns how many corners are behind.
    """
    col_lo = math.inf
    col_hi = -math.inf
    row_lo = math.inf
    row_hi = -math.inf
    n_behind = 0
    for k in range(8):
        x = corners[n, k, 0]
        y = corners[n, k, 1]
        z = corners[n, k, 2]
        depth = s * x + c * z + sod
        if depth <= 1e-9 * sod:
            n_behind += 1
            continue
        xd = (c * x - s * z) / depth * sdd
        yd = y / depth * sdd
        uu = u0 + (cos_tilt * xd + sin_tilt * yd) / pu
        vv = v0 + (cos_tilt * yd - sin_tilt * xd) / pv
        col_lo = min(col_lo, uu)
        col_hi = max(col_hi, uu)
        row_lo = min(row_lo, vv)
        row_hi = max(row_hi, vv)
    if n_behind == 8:
        # Wholly behind the source: no ray from the source to the detector reaches it.
        return 1, 0, 1, 0, n_behind
    if n_behind:  # across the source plane: its image is unbounded
        return 0, n_cols - 1, 0, n_rows - 1, n_behind
    # Sub-rays sit within half a pixel of the pixel centre.
    c0 = max(int(math.floor(max(col_lo - 0.5, -1.0))), 0)
    c1 = min(int(math.ceil(min(col_hi + 0.5, float(n_cols)))), n_cols - 1)
    r0 = max(int(math.floor(max(row_lo - 0.5, -1.0))), 0)
    r1 = min(int(math.ceil(min(row_hi + 0.5, float(n_rows)))), n_rows - 1)
    return c0, c1, r0, r1, n_behind


@njit(cache=True, fastmath=False, inline="always")
def unit_frame_ray(centre, maps, n, c, s, sod, sdd):
    """The view's rays in primitive ``n``'s unit frame: the source ``a = M (S - centre)`` and the
    columns of ``A = M R^T``, scaled so that a pixel offset ``(dx, dy)`` (mm) has direction
    ``b = A_x dx + A_y dy + A_z``; 12 floats ``a, A_x, A_y, A_z``."""
    # Source S = -R^T (0, 0, SOD) in the object frame.
    e0 = -s * sod - centre[n, 0]
    e1 = -centre[n, 1]
    e2 = -c * sod - centre[n, 2]
    a0 = maps[n, 0, 0] * e0 + maps[n, 0, 1] * e1 + maps[n, 0, 2] * e2
    a1 = maps[n, 1, 0] * e0 + maps[n, 1, 1] * e1 + maps[n, 1, 2] * e2
    a2 = maps[n, 2, 0] * e0 + maps[n, 2, 1] * e1 + maps[n, 2, 2] * e2
    # A = M R^T with R^T = [[c, 0, s], [0, 1, 0], [-s, 0, c]].
    ax0 = maps[n, 0, 0] * c - maps[n, 0, 2] * s
    ax1 = maps[n, 1, 0] * c - maps[n, 1, 2] * s
    ax2 = maps[n, 2, 0] * c - maps[n, 2, 2] * s
    ay0 = maps[n, 0, 1]
    ay1 = maps[n, 1, 1]
    ay2 = maps[n, 2, 1]
    az0 = (maps[n, 0, 0] * s + maps[n, 0, 2] * c) * sdd
    az1 = (maps[n, 1, 0] * s + maps[n, 1, 2] * c) * sdd
    az2 = (maps[n, 2, 0] * s + maps[n, 2, 2] * c) * sdd
    return a0, a1, a2, ax0, ax1, ax2, ay0, ay1, ay2, az0, az1, az2


@njit(cache=True, fastmath=False, inline="always")
def pixel_chords(k_n, ray, r, col, u0, v0, pu, pv, cos_tilt, sin_tilt, sdd, ss):
    """Sum over pixel ``(r, col)``'s ``ss x ss`` sub-rays of their chord (mm) through the primitive.

    ``ray`` is :func:`unit_frame_ray`'s; only the segment from the source (t = 0) to the
    detector (t = 1) counts.
    """
    a0, a1, a2, ax0, ax1, ax2, ay0, ay1, ay2, az0, az1, az2 = ray
    total = 0.0
    for jv in range(ss):
        bv = (r + (jv + 0.5) / ss - 0.5 - v0) * pv
        for ju in range(ss):
            au = (col + (ju + 0.5) / ss - 0.5 - u0) * pu
            dx = cos_tilt * au - sin_tilt * bv
            dy = sin_tilt * au + cos_tilt * bv
            b0 = ax0 * dx + ay0 * dy + az0
            b1 = ax1 * dx + ay1 * dy + az1
            b2 = ax2 * dx + ay2 * dy + az2
            t_in, t_out = unit_interval(k_n, a0, a1, a2, b0, b1, b2)
            t_in = max(t_in, 0.0)
            t_out = min(t_out, 1.0)
            if t_out > t_in:
                total += (t_out - t_in) * math.sqrt(dx * dx + dy * dy + sdd * sdd)
    return total
