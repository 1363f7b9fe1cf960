"""Scans of synthetic 3-D points: features, matches and pair estimates with a known truth.

Shared by the tests of :mod:`ctpipe.solve.tracks` / :mod:`ctpipe.solve.bundle` and by
``benchmarks/bench_refiners.py``: points in a cylinder about the rotation axis are projected
with :func:`ctpipe.solve.camera.project_points`, each seen in a run of consecutive views, with
Gaussian pixel noise, wrong matches that passed verification, and optionally static features
(fixed image positions, like the silhouette of a rotationally symmetric container).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ctpipe.data import Features, Matches, PairEstimate, ScanObservations
from ctpipe.geometry import Geometry
from ctpipe.model import fit_angle
from ctpipe.solve.camera import project_points
from ctpipe.solve.graph import view_pairs

__all__ = ["SyntheticScan", "synthetic_scan"]


@dataclass(frozen=True, eq=False)
class SyntheticScan:
    """A synthetic scan and its truth.

    Attributes
    ----------
    observations : ScanObservations
    true_angles_rad : ndarray of shape (V,)
        Relative to view 0.
    points_mm : ndarray of shape (T, 3)
        The rigid object points.
    n_static : int
        Static features among the keypoints (they come after the rigid points' keypoints).
    """

    observations: ScanObservations
    true_angles_rad: np.ndarray
    points_mm: np.ndarray
    n_static: int


def synthetic_scan(n_views: int, n_points: int, *, rng: np.random.Generator | int | None = None,
                   geometry: Geometry | None = None, range_deg: float = 360.0, jitter_deg: float = 0.2,
                   track_length: tuple[int, int] = (3, 12), noise_px: float = 0.0, outlier_fraction: float = 0.0,
                   n_static: int = 0, baselines=(1, 2), outliers_verified: bool = True) -> SyntheticScan:
    """Project random object points into a scan and match them like a pipeline would.

    Parameters
    ----------
    n_views, n_points : int
    rng : numpy.random.Generator or int or None
    geometry : Geometry, optional
        Default 256^2 pixels of 0.8 mm, SOD 150, SDD 390 mm.
    range_deg : float
        The nominal angles span this range (360: a full turn, whose seam is paired).
    jitter_deg : float
        Gaussian error of the true angles about the nominal ones.
    track_length : (int, int)
        Each point is seen in a run of consecutive views of a length drawn uniformly from this
        range (inclusive).
    noise_px : float
        Gaussian keypoint position noise.
    outlier_fraction : float
        Share of each pair's verified matches that pair a keypoint with a random other one (the
        pair angle is fitted without them, as a RANSAC would).
    n_static : int
        Features at fixed image positions, seen and matched in every view.
    baselines : sequence of int
        View pairs ``(i, i + k)`` to match.
    outliers_verified : bool
        Wrong matches are flagged as inliers (they slipped through verification, the hard
        case); False flags them as outliers, as a RANSAC that caught them would.

    Returns
    -------
    SyntheticScan
    """
    rng = np.random.default_rng(rng)
    geometry = geometry or Geometry(150.0, 390.0, 256, 256, 0.8, 0.8)
    step = range_deg / n_views
    nominal = np.arange(n_views) * step
    true_deg = nominal + rng.normal(0.0, jitter_deg, n_views)
    true = np.deg2rad(true_deg - true_deg[0])
    full_turn = abs(range_deg - 360.0) < 1e-9
    # Points in a cylinder whose projection stays on the detector.
    half_width_mm = 0.42 * geometry.detector_cols * geometry.pixel_pitch_u_mm * geometry.source_to_object_mm / geometry.source_to_detector_mm
    half_height_mm = 0.42 * geometry.detector_rows * geometry.pixel_pitch_v_mm * (geometry.source_to_object_mm - half_width_mm) / geometry.source_to_detector_mm
    radius = 0.8 * half_width_mm * np.sqrt(rng.uniform(0, 1, n_points))
    phase = rng.uniform(0, 2 * np.pi, n_points)
    points = np.stack([radius * np.cos(phase), rng.uniform(-half_height_mm, half_height_mm, n_points),
                       radius * np.sin(phase)], axis=1)
    lengths = rng.integers(track_length[0], track_length[1] + 1, n_points)
    first = rng.integers(0, n_views, n_points) if full_turn else rng.integers(0, np.maximum(n_views - lengths, 0) + 1)
    obs_point = np.repeat(np.arange(n_points), lengths)
    obs_view = np.repeat(first, lengths) + np.concatenate([np.arange(n) for n in lengths])
    keep = obs_view < n_views if not full_turn else np.ones(obs_view.size, bool)
    obs_point, obs_view = obs_point[keep], np.mod(obs_view[keep], n_views)
    xy = project_points(points[obs_point], true[obs_view], geometry) + rng.normal(0.0, noise_px, (obs_point.size, 2))
    static_xy = np.stack([rng.uniform(0.1, 0.9, n_static) * geometry.detector_cols,
                          rng.uniform(0.1, 0.9, n_static) * geometry.detector_rows], axis=1)
    descriptor_of = rng.normal(0.0, 1.0, (n_points + n_static, 32)).astype(np.float32)
    features, keypoint_of = [], {}
    order = np.lexsort((obs_point, obs_view))
    bounds = np.searchsorted(obs_view[order], np.arange(n_views + 1))
    for v in range(n_views):
        here = order[bounds[v]:bounds[v + 1]]
        ids = np.concatenate([obs_point[here], n_points + np.arange(n_static)])
        view_xy = np.concatenate([xy[here], static_xy + rng.normal(0.0, noise_px, (n_static, 2))])
        descriptors = descriptor_of[ids] + rng.normal(0.0, 0.05, (ids.size, 32)).astype(np.float32)
        # Strictly decreasing responses keep the keypoints in this order through Features.build.
        features.append(Features.build(xy=view_xy, size=np.full(ids.size, 4.0), angle_deg=np.zeros(ids.size),
                                       response=-np.arange(ids.size, dtype=np.float64), descriptors=descriptors,
                                       norm="L2"))
        keypoint_of[v] = dict(zip(ids.tolist(), range(ids.size)))
    pairs = view_pairs(n_views, tuple(baselines), nominal if full_turn else None)
    matches, points_a, points_b, estimates = [], [], [], []
    for i, j in pairs:
        common = sorted(set(keypoint_of[i]) & set(keypoint_of[j]))
        index = np.array([[keypoint_of[i][p], keypoint_of[j][p]] for p in common], dtype=np.int64).reshape(-1, 2)
        # The pair angle is fitted to the right matches (as a RANSAC would find them); the wrong
        # ones stay flagged as inliers, like wrong matches that happen to fit the epipolar line.
        angle = fit_angle(geometry.pixels_to_normalised(features[i].xy[index[:, 0]]),
                          geometry.pixels_to_normalised(features[j].xy[index[:, 1]]))
        n_wrong = int(round(outlier_fraction * len(index)))
        if n_wrong:
            wrong = rng.choice(len(index), n_wrong, replace=False)
            index[wrong, 1] = rng.integers(0, len(features[j]), n_wrong)
        distance = np.linalg.norm(features[i].descriptors[index[:, 0]].astype(np.float64)
                                  - features[j].descriptors[index[:, 1]], axis=1)
        q_a = geometry.pixels_to_normalised(features[i].xy[index[:, 0]])
        q_b = geometry.pixels_to_normalised(features[j].xy[index[:, 1]])
        mask = np.ones(len(index), bool)
        if n_wrong and not outliers_verified:
            mask[wrong] = False
        matches.append(Matches(index, distance.astype(np.float32)))
        points_a.append(q_a)
        points_b.append(q_b)
        estimates.append(PairEstimate(float(angle), mask, 0.0) if angle else angle)
    observations = ScanObservations(geometry=geometry, n_views=n_views, features=tuple(features), pairs=pairs,
                                    matches=tuple(matches), points_a=tuple(points_a), points_b=tuple(points_b),
                                    estimates=tuple(estimates), nominal_angles_deg=nominal)
    return SyntheticScan(observations, true, points, n_static)
