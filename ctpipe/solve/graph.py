"""The view graph of a scan: which view pairs to estimate and how their angles add up.

Views are taken in acquisition order. A full turn closes on itself: the last views are
neighbours of the first ones, so pairing them ("loop closure") turns the chain of pair angles
into a ring whose angles must add up to 360 deg, which removes the linear drift a chain
accumulates.
"""

from __future__ import annotations

import numpy as np

from ctpipe.errors import InputError

__all__ = ["covers_full_turn", "view_pairs", "unwrap_pair_angles_deg"]


def covers_full_turn(nominal_angles_deg) -> bool:
    """True when the nominal angles go all the way round in order, e.g. 360 views over 360 deg.

    The views must be monotonic and the gap from the last view back to the first (plus one or
    more full turns) no wider than 1.5 typical steps, so the last view is a neighbour of the first.
    """
    nominal = np.asarray(nominal_angles_deg, dtype=np.float64)
    if nominal.ndim != 1 or nominal.size < 3 or not np.all(np.isfinite(nominal)):
        return False
    steps = np.diff(nominal)
    if not (np.all(steps > 0) or np.all(steps < 0)):
        return False
    step = float(np.median(np.abs(steps)))
    span = abs(float(nominal[-1] - nominal[0])) + step
    turns = round(span / 360.0)
    return turns >= 1 and abs(span - 360.0 * turns) <= 0.5 * step


def view_pairs(n_views: int, baselines=(1,), nominal_angles_deg=None, *, loop_closure: bool = True) -> np.ndarray:
    """View pairs ``(i, i + k)`` for every baseline ``k``, shape (P, 2), int64.

    With ``loop_closure`` and nominal angles that cover a full turn (:func:`covers_full_turn`),
    the pairs wrap around: ``(i, (i + k) mod n_views)`` for the last ``k`` views too, so that
    every view has the same neighbours and the ring of pair angles closes.
    """
    closed = loop_closure and nominal_angles_deg is not None and covers_full_turn(nominal_angles_deg)
    pairs = []
    for k in baselines:
        stop = n_views if closed and k < n_views else n_views - k
        pairs.extend((i, (i + k) % n_views) for i in range(max(stop, 0)))
    return np.array(pairs, dtype=np.int64).reshape(-1, 2)


def unwrap_pair_angles_deg(pairs, pair_angles_deg, nominal_angles_deg=None) -> np.ndarray:
    """Pair angles as differences ``theta_j - theta_i`` of unwrapped view angles, degrees, shape (P,).

    An estimator returns a pair's turn in (-180, 180]; across the seam of a full turn the view
    angles differ by about 360 deg less (or more) than that. Each angle is moved by the whole
    number of turns that brings it nearest to the nominal difference. Without nominal angles
    the angles are returned as they are (pairs are assumed to turn by less than 180 deg).
    """
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    angles = np.asarray(pair_angles_deg, dtype=np.float64).reshape(-1)
    if len(angles) != len(pairs):
        raise InputError(f"pair_angles_deg: must have one angle per pair ({len(pairs)}), got {len(angles)}")
    if nominal_angles_deg is None:
        return angles.copy()
    nominal = np.asarray(nominal_angles_deg, dtype=np.float64)
    expected = nominal[pairs[:, 1]] - nominal[pairs[:, 0]]
    return angles + 360.0 * np.round((expected - angles) / 360.0)
