"""Pair estimates: an angle packaged with its inliers, and inliers that use each point once.

Shared by the estimators that produce pair estimates and the refiners that refit or replace
them (:mod:`ctpipe.builtin`), so that no plugin needs another plugin's helpers.
"""

from __future__ import annotations

import numpy as np

from ctpipe.data import PairEstimate
from ctpipe.model import sampson_distance

__all__ = ["pair_estimate", "one_to_one"]


def pair_estimate(angle_rad: float, inlier_mask: np.ndarray, q_a: np.ndarray, q_b: np.ndarray) -> PairEstimate:
    """Package an angle and its inliers with their RMS Sampson residual."""
    inlier_mask = np.asarray(inlier_mask, dtype=bool)
    d = sampson_distance(angle_rad, q_a[inlier_mask], q_b[inlier_mask])
    residual = float(np.sqrt(np.mean(d * d))) if d.size else float("nan")
    return PairEstimate(angle_rad=float(angle_rad), inlier_mask=inlier_mask, residual=residual)


def one_to_one(mask: np.ndarray, distance: np.ndarray, q_a: np.ndarray, q_b: np.ndarray) -> np.ndarray:
    """``mask`` with every point of either view used once: the inlier of smallest distance wins.

    Correspondences of one keypoint share its coordinates, so points are told apart by them.
    Greedy in order of distance: an inlier is kept while neither of its points is taken.
    """
    inliers = np.flatnonzero(mask)
    _, point_a = np.unique(q_a[inliers], axis=0, return_inverse=True)
    _, point_b = np.unique(q_b[inliers], axis=0, return_inverse=True)
    taken_a, taken_b = set(), set()
    keep = np.zeros_like(mask)
    for k in np.argsort(distance[inliers], kind="stable"):
        a, b = int(point_a.ravel()[k]), int(point_b.ravel()[k])
        if a not in taken_a and b not in taken_b:
            taken_a.add(a)
            taken_b.add(b)
            keep[inliers[k]] = True
    return keep
