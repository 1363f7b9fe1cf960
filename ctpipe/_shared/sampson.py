"""The Sampson distances of many hypotheses at once, for :func:`ctpipe.model.sampson_distance` (numba: kept out of the model, which every format reader imports)."""

from __future__ import annotations

import numpy as np

from ctpipe._shared.jit import njit

__all__ = ["hypotheses_sampson"]


@njit(cache=True)
def hypotheses_sampson(half_c, half_s, x, y, xp, yp):
    """:func:`~ctpipe.model.sampson_distance` of every correspondence under each of H angles, (H, N): the same operations in the same order."""
    out = np.empty((half_c.size, x.size))
    for h in range(half_c.size):
        c = half_c[h]
        s = half_s[h]
        for k in range(x.size):
            numerator = c * (y[k] - yp[k]) - s * (xp[k] * y[k] + x[k] * yp[k])
            denominator = (s * y[k]) ** 2 + (s * x[k] + c) ** 2 + (s * yp[k]) ** 2 + (c - s * xp[k]) ** 2
            out[h, k] = abs(numerator) / np.sqrt(denominator)
    return out
