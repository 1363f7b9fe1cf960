"""Matchers: brute force and FLANN on descriptors (Lowe's ratio test, mutual check), and all-pairs.

The norm is the one the detector attached to its descriptors (``Features.norm``), so a
matcher never guesses whether descriptors are binary. ``all-pairs`` ignores descriptors: for
identical objects (the balls of a calibration phantom) it proposes every pair the circular
motion allows and leaves the choice to the estimator's consensus.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ctpipe.builtin import _opencv
from ctpipe.data import Features, Matches
from ctpipe.errors import InputError
from ctpipe.features.nearest import l2_neighbours
from ctpipe.hookspecs import hookimpl
from ctpipe.stages import Matcher, param


class _NearestNeighbourMatcher(Matcher):
    def _knn(self, a: Features, b: Features, k: int) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError

    def _knn_and_back(self, a: Features, b: Features, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """``_knn(a, b, k)`` and, with ``mutual``, each of ``b``'s nearest in ``a`` (else None)."""
        index, distance = self._knn(a, b, k)
        return index, distance, self._knn(b, a, 1)[0][:, 0] if self.mutual else None

    def match(self, features_a: Features, features_b: Features) -> Matches:
        if not (features_a.has_descriptors and features_b.has_descriptors):
            raise InputError("cannot match features without descriptors (dropped once a pipeline matched its pairs, "
                             "Features.without_descriptors); match the detector's own features")
        if features_a.norm != features_b.norm or features_a.descriptors.shape[1] != features_b.descriptors.shape[1]:
            raise InputError(
                f"cannot match {features_a.norm} descriptors of width {features_a.descriptors.shape[1]} with "
                f"{features_b.norm} descriptors of width {features_b.descriptors.shape[1]}; use one detector for both views"
            )
        k = 2 if self.ratio is not None else 1
        index, distance, back = self._knn_and_back(features_a, features_b, k)
        keep = index[:, 0] >= 0
        if self.ratio is not None:
            # A missing second neighbour (inf) means the nearest one is unambiguous.
            keep &= distance[:, 0] < self.ratio * distance[:, 1]
        if self.mutual and keep.any():
            forward = np.where(keep, index[:, 0], 0)
            keep &= back[forward] == np.arange(len(index))
        rows = np.flatnonzero(keep)
        return Matches(
            index_ab=np.stack([rows, index[rows, 0]], axis=1).astype(np.int64).reshape(-1, 2),
            distance=distance[rows, 0].astype(np.float32),
        )


@dataclass(frozen=True)
class BruteForceMatcher(_NearestNeighbourMatcher):
    """Brute-force nearest neighbour with Lowe's ratio test and/or a mutual check.

    Exact; float (``L2``) descriptors are matched both ways from one matrix product
    (:mod:`ctpipe.features.nearest`), binary ones by OpenCV.
    """

    ratio: float | None = param(0.8, doc="keep a match if d1 < ratio * d2 (null: no ratio test)", gt=0, le=1)
    mutual: bool = param(False, doc="keep only pairs that are each other's nearest neighbour")

    def _knn(self, a: Features, b: Features, k: int):
        return _opencv.knn_match(a.descriptors, b.descriptors, a.norm, k)

    def _knn_and_back(self, a: Features, b: Features, k: int):
        if a.norm != "L2":
            return super()._knn_and_back(a, b, k)
        # Float descriptors: both directions from one matrix product (ctpipe.features.nearest).
        index, distance, back = l2_neighbours(a.descriptors, b.descriptors, k)
        return index, distance, back if self.mutual else None


@dataclass(frozen=True)
class FlannMatcher(_NearestNeighbourMatcher):
    """Approximate nearest neighbour (FLANN: KD-tree for float, LSH for binary descriptors)."""

    ratio: float | None = param(0.8, doc="keep a match if d1 < ratio * d2 (null: no ratio test)", gt=0, le=1)
    mutual: bool = param(False, doc="keep only pairs that are each other's nearest neighbour")
    trees: int = param(4, doc="randomised KD-trees (float descriptors)", ge=1, le=64)
    checks: int = param(64, doc="leaves visited per query", ge=1, le=100_000)
    lsh_tables: int = param(6, doc="LSH hash tables (binary descriptors)", ge=1, le=64)
    lsh_key_size: int = param(12, doc="LSH key bits", ge=1, le=31)
    lsh_probes: int = param(1, doc="LSH multi-probe level", ge=0, le=4)

    def _knn(self, a: Features, b: Features, k: int):
        return _opencv.knn_match(a.descriptors, b.descriptors, a.norm, k, flann=True, flann_trees=self.trees,
                                 flann_checks=self.checks, lsh_tables=self.lsh_tables,
                                 lsh_key_size=self.lsh_key_size, lsh_probes=self.lsh_probes)


@dataclass(frozen=True)
class AllPairsMatcher(Matcher):
    """Every keypoint pair the circular motion allows, without descriptors (for identical balls).

    A point on the turntable keeps its height: between two views only its depth changes, so its
    row moves by a fraction of its distance from the principal row (at most ``R / SOD`` of it
    for an object of radius ``R``), while its column can move anywhere across the object. Every
    pair within ``max_row_shift_px`` rows is proposed, and the estimator's consensus (1-point
    RANSAC with ``hypotheses: all``) finds the angle the most keypoints agree on. ``distance``
    is the row shift in pixels, smallest first for each keypoint of the first view.
    """

    max_row_shift_px: float = param(20.0, doc="largest change of row (pixels) between the two views of a point",
                                     gt=0, le=100_000)
    max_pairs: int = param(4_000_000, doc="refuse more candidate pairs than this (a detector with too many keypoints)",
                           ge=1, le=100_000_000)

    def match(self, features_a: Features, features_b: Features) -> Matches:
        n_a, n_b = len(features_a), len(features_b)
        if n_a * n_b > self.max_pairs:
            raise InputError(f"all-pairs: {n_a} x {n_b} keypoints make {n_a * n_b:,} candidate pairs, more than "
                             f"max_pairs {self.max_pairs:,}; use it with a detector of few keypoints (beads) or a "
                             "descriptor matcher")
        shift = np.abs(features_a.xy[:, None, 1].astype(np.float64) - features_b.xy[None, :, 1])
        rows, cols = np.nonzero(shift <= self.max_row_shift_px)
        order = np.lexsort((shift[rows, cols], rows))
        rows, cols = rows[order], cols[order]
        return Matches(index_ab=np.stack([rows, cols], axis=1).astype(np.int64).reshape(-1, 2),
                       distance=shift[rows, cols].astype(np.float32))


@hookimpl
def ctpipe_register_stages(registry) -> None:
    registry.add_matcher("brute-force", BruteForceMatcher)
    registry.add_matcher("flann", FlannMatcher)
    registry.add_matcher("all-pairs", AllPairsMatcher)
