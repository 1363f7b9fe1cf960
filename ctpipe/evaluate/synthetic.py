"""Synthetic correspondences of the paper's experiments.

Points uniform in a cylinder (axis at ``axis_distance`` from the source, ``height`` tall,
``radius`` wide, all in the same length unit), turned by ``alpha`` about the cylinder axis
(the convention of :mod:`ctpipe.model`), projected to normalised coordinates, with
N(0, sigma^2) noise on every coordinate. Outliers are either re-paired at random (the paper)
or placed a few pixels from their true partner (closer to real descriptor mismatches).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from ctpipe.model import rotation_matrix

__all__ = ["Cylinder", "cylinder_points", "project", "make_correspondences", "PIXEL_NORMALISED"]

#: One detector pixel in normalised units for the "near" outlier model: 0.1 mm pitch at
#: 1000 mm SDD, a typical micro-CT, which also makes the paper's sigma 1e-4 about one pixel.
PIXEL_NORMALISED = 1e-4


@dataclass(frozen=True)
class Cylinder:
    """The cloud the paper samples points from (lengths in one arbitrary unit)."""

    axis_distance: float = 200.0
    height: float = 230.0
    radius: float = 115.0


def cylinder_points(n: int, rng: np.random.Generator, cylinder: Cylinder = Cylinder()) -> np.ndarray:
    """``n`` points uniform in the cylinder, object frame centred on the axis, shape (n, 3)."""
    r = cylinder.radius * np.sqrt(rng.uniform(0.0, 1.0, n))
    phi = rng.uniform(0.0, 2.0 * np.pi, n)
    height = rng.uniform(-cylinder.height / 2.0, cylinder.height / 2.0, n)
    return np.stack([r * np.cos(phi), height, r * np.sin(phi)], axis=1)


def project(points: np.ndarray, alpha_rad: float, axis_distance: float) -> np.ndarray:
    """Normalised coordinates (N, 2) of object points after a turntable rotation ``alpha_rad``."""
    camera = points @ rotation_matrix(alpha_rad).T + np.array([0.0, 0.0, axis_distance])
    return camera[:, :2] / camera[:, 2:3]


def _derangement(n: int, rng: np.random.Generator) -> np.ndarray:
    """A random permutation with no fixed point, so no outlier keeps its true partner."""
    if n < 2:
        return np.arange(n)
    while True:  # about e draws on average
        perm = rng.permutation(n)
        if not np.any(perm == np.arange(n)):
            return perm


def make_correspondences(
    alpha_rad: float,
    rng: np.random.Generator,
    *,
    n_inliers: int = 30,
    n_outliers: int = 70,
    sigma: float = 1e-4,
    outliers: Literal["repaired", "near"] = "repaired",
    near_px: tuple[float, float] = (2.0, 6.0),
    cylinder: Cylinder = Cylinder(),
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One synthetic view pair.

    Returns
    -------
    q_a, q_b : ndarray of shape (N, 2)
        Noisy normalised coordinates in the first and second view, shuffled.
    is_inlier : ndarray of shape (N,), bool
    """
    n = n_inliers + n_outliers
    points = cylinder_points(n, rng, cylinder)
    q_a = project(points, 0.0, cylinder.axis_distance)
    q_b = project(points, alpha_rad, cylinder.axis_distance)
    if n_outliers:
        if outliers == "repaired":
            q_b[n_inliers:] = q_b[n_inliers:][_derangement(n_outliers, rng)]
        elif outliers == "near":
            offset = rng.uniform(*near_px, n_outliers) * PIXEL_NORMALISED
            direction = rng.uniform(0.0, 2.0 * np.pi, n_outliers)
            q_b[n_inliers:] += offset[:, None] * np.stack([np.cos(direction), np.sin(direction)], axis=1)
        else:
            raise ValueError(f"outliers must be 'repaired' or 'near', got {outliers!r}")
    q_a = q_a + rng.normal(0.0, sigma, q_a.shape)
    q_b = q_b + rng.normal(0.0, sigma, q_b.shape)
    is_inlier = np.arange(n) < n_inliers
    order = rng.permutation(n)
    return q_a[order], q_b[order], is_inlier[order]
