"""The bands a per-view angle correction is split into: fast, slow-odd and slow-even.

The gate (:mod:`ctpipe.solve.gate`) adds them one at a time where the projections show them
better, and projection matching (:mod:`ctpipe.solve.reprojection`) judges the slow-even band,
which conjugate rays see only through the fan, on views held out of its reference.
"""

from __future__ import annotations

import numpy as np

__all__ = ["BANDS", "split_bands"]

#: The bands of a correction, in the order they are reported.
BANDS = ("fast", "slow-odd", "slow-even")


def split_bands(correction_deg: np.ndarray, nominal_deg: np.ndarray, harmonics: int,
                fit: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """The ``fast``, ``slow-odd`` and ``slow-even`` parts of a per-view correction, each shape (V,).

    The slow parts are the least-squares fit of ``cos(k theta), sin(k theta)`` for odd and even
    ``k`` up to ``harmonics`` (``theta`` the nominal angles; the constant goes with the even
    part), the fast part what the fit leaves. They add up to the correction. On a short scan the
    harmonics are not orthogonal over its range; they still span its smooth errors. ``fit``, a
    boolean mask of shape (V,), fits the harmonics to those views only (the others' values do not
    pull the fit).
    """
    correction = np.asarray(correction_deg, dtype=np.float64)
    theta = np.deg2rad(np.asarray(nominal_deg, dtype=np.float64))
    columns = {"slow-odd": [], "slow-even": [np.ones_like(theta)]}
    for k in range(1, harmonics + 1):
        columns["slow-odd" if k % 2 else "slow-even"] += [np.cos(k * theta), np.sin(k * theta)]
    names = [name for name in ("slow-odd", "slow-even") if columns[name]]
    basis = np.stack([column for name in names for column in columns[name]], axis=1)
    rows = slice(None) if fit is None else np.asarray(fit, dtype=bool)
    coeffs, *_ = np.linalg.lstsq(basis[rows], correction[rows], rcond=None)
    parts, first = {}, 0
    for name in names:
        count = len(columns[name])
        parts[name] = basis[:, first:first + count] @ coeffs[first:first + count]
        first += count
    parts.setdefault("slow-odd", np.zeros_like(correction))
    return {"fast": correction - parts["slow-odd"] - parts["slow-even"], "slow-odd": parts["slow-odd"],
            "slow-even": parts["slow-even"]}
