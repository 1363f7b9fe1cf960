"""Pair estimators: the paper's 1-point RANSAC, its two baselines, and OpenCV's 5-point method.

All take normalised coordinates ``q_a``, ``q_b`` of shape (M, 2) and return a
:class:`~ctpipe.data.PairEstimate` (angle, inlier mask, RMS Sampson residual of the inliers)
or a falsy :class:`~ctpipe.model.FailedEstimation` saying why not.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from ctpipe.hookspecs import hookimpl
from ctpipe.model import (FailedEstimation, angles_from_correspondences, correspondence_terms, fit_angle,
                          sampson_distance)
from ctpipe.solve.pairs import one_to_one, pair_estimate
from ctpipe.stages import Estimator, param

_Refit = Literal["sampson", "tls"]


def _informative(q_a: np.ndarray, q_b: np.ndarray) -> np.ndarray:
    """Correspondences that constrain the angle at all (not on the principal row, a = b = 0)."""
    a, b = correspondence_terms(q_a, q_b)
    return a * a + b * b > 1e-24


def ransac_iterations(probability: float, outlier_fraction: float, sample_size: int = 1) -> int:
    """``N >= log(1 - p) / log(1 - (1 - eps)^s)``, at least 1."""
    inlier_sample = (1.0 - outlier_fraction) ** sample_size
    if inlier_sample >= 1.0:
        return 1
    return max(1, math.ceil(math.log(1.0 - probability) / math.log(1.0 - inlier_sample)))


@dataclass(frozen=True)
class Ransac1ptEstimator(Estimator):
    """1-point RANSAC on the circular-motion model with Sampson distance and least-squares refit."""

    probability: float = param(0.999, doc="confidence p of drawing at least one all-inlier sample", gt=0, lt=1)
    outlier_fraction: float = param(0.7, doc="expected outlier fraction eps (sets the iteration count)", ge=0, lt=1)
    sampson_threshold: float = param(
        8e-4, doc="inlier if Sampson distance below this (normalised units); 8e-4 is about 2 px at 0.4 mm pitch and "
                  "1 m SDD, the real-data setting every shipped config uses (the paper's synthetic study used 0.01)",
        gt=0, le=1)
    min_consensus: float = param(0.25, doc="a consensus is valid if its inlier fraction exceeds this", ge=0, lt=1)
    max_iterations: int = param(100000, doc="upper bound on drawn hypotheses", ge=1, le=10_000_000)
    hypotheses: Literal["random", "all"] = param(
        "random", doc="'random': draw N from p and eps (the paper); 'all': try every correspondence")
    scoring: Literal["count", "msac"] = param(
        "count", doc="rank consensus sets by inlier count (the paper) or by truncated squared Sampson distance")
    refit: Literal["sampson", "tls", "none"] = param(
        "sampson", doc="least-squares refit of each consensus: Sampson, closed-form TLS, or none")
    local_optimisations: int = param(1, doc="distinct consensus sets refit and re-scored (best first)", ge=1,
                                     le=1000)
    noise_scale_factor: float | None = param(
        3.0, doc="after the refit keep only inliers within this many robust noise scales "
                  "(1.4826 x median Sampson distance of the consensus) and refit again; null: the paper's plain refit", gt=0, le=1000)
    one_to_one: bool = param(
        False, doc="a keypoint supports the angle once: of inliers sharing a point, keep the closest (identical balls)")
    min_inliers: int = param(1, doc="a consensus needs at least this many inliers (with min_consensus)", ge=1,
                             le=1_000_000)

    def estimate(self, q_a: np.ndarray, q_b: np.ndarray, *, rng: np.random.Generator):
        m = len(q_a)
        if m == 0:
            return FailedEstimation("no correspondences")
        usable = np.flatnonzero(_informative(q_a, q_b))
        if usable.size == 0:
            return FailedEstimation(f"all {m} correspondences lie on the principal row and carry no angle")
        if self.hypotheses == "all":
            drawn = usable
        else:
            n = min(ransac_iterations(self.probability, self.outlier_fraction), self.max_iterations, usable.size)
            # Draw without replacement: the first n are the paper's N hypotheses; the rest are
            # only tried (in batches) while no valid consensus has been found, so an unlucky
            # draw of outliers only becomes a failure once every correspondence was tried.
            drawn = rng.permutation(usable)[: min(usable.size, self.max_iterations)]
        start, stop = 0, len(drawn) if self.hypotheses == "all" else n
        while True:
            alphas = angles_from_correspondences(q_a[drawn[start:stop]], q_b[drawn[start:stop]])
            distances = sampson_distance(alphas[:, None], q_a, q_b)
            inliers = distances < self.sampson_threshold
            counts = inliers.sum(axis=1)
            valid = (counts > self.min_consensus * m) & (counts >= self.min_inliers)
            if valid.any() or stop >= len(drawn):
                break
            start, stop = stop, min(len(drawn), stop + max(n, 16))
        if not valid.any():
            return FailedEstimation(
                f"no consensus: the best of {stop} hypotheses had {int(counts.max())}/{m} inliers, need more "
                f"than {self.min_consensus:.0%} and at least {self.min_inliers} (sampson_threshold "
                f"{self.sampson_threshold:g})")
        # Many hypotheses share one consensus set: rank the distinct sets by their score at the
        # hypothesis angle and locally optimise (refit, re-select) only the most promising.
        candidates = np.flatnonzero(valid)
        candidates = candidates[_first_of_each_set(np.packbits(inliers[candidates], axis=1))]
        ranking = self._ranking(inliers[candidates], distances[candidates])
        best = None
        for k in np.argsort(ranking, kind="stable")[: self.local_optimisations]:
            h = candidates[k]
            alpha, mask = self._refit_consensus(alphas[h], inliers[h], q_a, q_b)
            if mask.sum() <= self.min_consensus * m or mask.sum() < self.min_inliers:
                continue
            score = self._score(alpha, mask, sampson_distance(alpha, q_a, q_b))
            if best is None or score < best[0]:
                best = (score, alpha, mask)
        if best is None:
            return FailedEstimation("no consensus survived the least-squares refit")
        _, alpha, mask = best
        if self.one_to_one:
            mask = one_to_one(mask, sampson_distance(alpha, q_a, q_b), q_a, q_b)
        if self.noise_scale_factor is not None and self.refit != "none":
            alpha, mask = self._tighten(alpha, mask, q_a, q_b)
        if self.refit == "sampson":
            final = fit_angle(q_a[mask], q_b[mask])
            alpha = alpha if isinstance(final, FailedEstimation) else final
        return pair_estimate(alpha, mask, q_a, q_b)

    def _refit_consensus(self, alpha: float, mask: np.ndarray, q_a, q_b) -> tuple[float, np.ndarray]:
        if self.refit == "none":
            return float(alpha), mask
        # Refit, re-select the inliers of the refit angle, repeat while the set changes.
        for _ in range(4):
            fitted = fit_angle(q_a[mask], q_b[mask], objective=self.refit, iterations=2, polish=False)
            if isinstance(fitted, FailedEstimation):
                break
            alpha = fitted
            new_mask = sampson_distance(alpha, q_a, q_b) < self.sampson_threshold
            if np.array_equal(new_mask, mask) or not new_mask.any():
                break
            mask = new_mask
        return float(alpha), mask

    def _tighten(self, alpha: float, mask: np.ndarray, q_a, q_b) -> tuple[float, np.ndarray]:
        # The consensus threshold must admit every inlier at any angle, so it also admits a few
        # mismatches, each of which pulls a least-squares fit. The inliers' own spread (a robust
        # scale of their Sampson distances) says how tight the final set can be. The tightened
        # set must keep at least half of the consensus, or the consensus is kept.
        for _ in range(4):
            d = sampson_distance(alpha, q_a, q_b)
            scale = 1.4826 * float(np.median(d[mask]))
            tight = mask & (d < self.noise_scale_factor * scale)
            if tight.sum() < max(2, mask.sum() // 2):
                break
            fitted = fit_angle(q_a[tight], q_b[tight], objective=self.refit, iterations=2, polish=False)
            if isinstance(fitted, FailedEstimation):
                break
            alpha = fitted
            if np.array_equal(tight, mask):
                break
            mask = tight
        return float(alpha), mask

    def _ranking(self, masks: np.ndarray, d: np.ndarray) -> np.ndarray:
        """The first term of :meth:`_score` for each row of ``masks`` and ``d`` (H, N), in one pass: what the candidates are ranked by."""
        if self.scoring == "msac":
            return np.minimum(d * d, self.sampson_threshold ** 2).sum(axis=1)
        return -masks.sum(axis=1)

    def _score(self, alpha: float, mask: np.ndarray, d: np.ndarray) -> tuple:
        """Smaller is better: MSAC cost, or (-inlier count, squared distances of the inliers)."""
        if self.scoring == "msac":
            return (float(np.minimum(d * d, self.sampson_threshold ** 2).sum()),)
        return (-int(mask.sum()), float((d[mask] ** 2).sum()))


def _first_of_each_set(packed: np.ndarray) -> np.ndarray:
    """Index of the first row of each distinct row of ``packed`` (uint8), the rows in byte order.

    What ``np.unique(packed, axis=0, return_index=True)[1]`` gives, by a dictionary of the rows'
    bytes instead of a sort of the rows as records (a third of the estimator's time).
    """
    first: dict[bytes, int] = {}
    for index, row in enumerate(packed):
        first.setdefault(row.tobytes(), index)
    return np.array([first[key] for key in sorted(first)], dtype=np.intp)


@dataclass(frozen=True)
class HistogramEstimator(Estimator):
    """Vote per-correspondence angles into intervals; least squares on the fullest one (paper's baseline)."""

    bin_width_deg: float = param(1.0, doc="width of the voting intervals, degrees", gt=0, le=90)
    refit: _Refit = param("sampson", doc="least-squares refit of the fullest interval")

    def estimate(self, q_a: np.ndarray, q_b: np.ndarray, *, rng: np.random.Generator):
        usable = _informative(q_a, q_b)
        if not usable.any():
            return FailedEstimation(f"none of {len(q_a)} correspondences carries an angle")
        angles_deg = np.rad2deg(angles_from_correspondences(q_a, q_b))
        n_bins = int(math.ceil(360.0 / self.bin_width_deg))
        bins = np.clip(((angles_deg + 180.0) // self.bin_width_deg).astype(np.int64), 0, n_bins - 1)
        fullest = np.bincount(bins[usable], minlength=n_bins).argmax()
        members = usable & (bins == fullest)
        alpha = fit_angle(q_a[members], q_b[members], objective=self.refit)
        if isinstance(alpha, FailedEstimation):
            return alpha
        return pair_estimate(alpha, members, q_a, q_b)


@dataclass(frozen=True)
class MedianEstimator(Estimator):
    """Median of the per-correspondence angles (paper's baseline)."""

    sampson_threshold: float = param(
        0.01, doc="correspondences within this Sampson distance of the median angle are reported as inliers", gt=0, le=1)

    def estimate(self, q_a: np.ndarray, q_b: np.ndarray, *, rng: np.random.Generator):
        usable = _informative(q_a, q_b)
        if not usable.any():
            return FailedEstimation(f"none of {len(q_a)} correspondences carries an angle")
        alpha = float(np.median(angles_from_correspondences(q_a[usable], q_b[usable])))
        return pair_estimate(alpha, usable & (sampson_distance(alpha, q_a, q_b) < self.sampson_threshold), q_a, q_b)


@dataclass(frozen=True)
class OpenCV5ptEstimator(Estimator):
    """Generic 5-point essential matrix (cv2.findEssentialMat + recoverPose), angle about the vertical axis."""

    method: Literal["ransac", "lmeds", "usac-default", "usac-accurate", "usac-magsac"] = param(
        "ransac", doc="OpenCV robust method")
    probability: float = param(0.999, doc="RANSAC confidence", gt=0, lt=1)
    threshold: float = param(1e-3, doc="epipolar distance threshold, normalised units", gt=0, le=1)
    max_iters: int = param(1000, doc="maximum RANSAC iterations", ge=1, le=1_000_000)

    def estimate(self, q_a: np.ndarray, q_b: np.ndarray, *, rng: np.random.Generator):
        if len(q_a) < 5:
            return FailedEstimation(f"the 5-point method needs at least 5 correspondences, got {len(q_a)}")
        from ctpipe.builtin import _opencv  # only this estimator needs OpenCV

        pose = _opencv.essential_pose(q_a, q_b, method=self.method, probability=self.probability,
                                      threshold=self.threshold, max_iters=self.max_iters,
                                      seed=int(rng.integers(2**31 - 1)))
        if pose is None:
            return FailedEstimation("OpenCV found no essential matrix")
        rotation, mask = pose
        # R(alpha) = [[c, 0, -s], [0, 1, 0], [s, 0, c]]; read the part about the vertical axis.
        alpha = math.atan2(rotation[2, 0] - rotation[0, 2], rotation[0, 0] + rotation[2, 2])
        return pair_estimate(alpha, mask, q_a, q_b)


@hookimpl
def ctpipe_register_stages(registry) -> None:
    registry.add_estimator("ransac-1pt", Ransac1ptEstimator)
    registry.add_estimator("histogram", HistogramEstimator)
    registry.add_estimator("median", MedianEstimator)
    registry.add_estimator("opencv-5pt", OpenCV5ptEstimator)
