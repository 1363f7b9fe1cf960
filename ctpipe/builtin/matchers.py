"""Descriptor matchers: brute force and FLANN, with Lowe's ratio test and a mutual check.

The norm is the one the detector attached to its descriptors (``Features.norm``), so a
matcher never guesses whether descriptors are binary.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ctpipe.builtin import _opencv
from ctpipe.data import Features, Matches
from ctpipe.errors import InputError
from ctpipe.hookspecs import hookimpl
from ctpipe.stages import Matcher, param


class _NearestNeighbourMatcher(Matcher):
    def _knn(self, a: Features, b: Features, k: int) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError

    def match(self, features_a: Features, features_b: Features) -> Matches:
        if features_a.norm != features_b.norm or features_a.descriptors.shape[1] != features_b.descriptors.shape[1]:
            raise InputError(
                f"cannot match {features_a.norm} descriptors of width {features_a.descriptors.shape[1]} with "
                f"{features_b.norm} descriptors of width {features_b.descriptors.shape[1]}; use one detector for both views"
            )
        k = 2 if self.ratio is not None else 1
        index, distance = self._knn(features_a, features_b, k)
        keep = index[:, 0] >= 0
        if self.ratio is not None:
            # A missing second neighbour (inf) means the nearest one is unambiguous.
            keep &= distance[:, 0] < self.ratio * distance[:, 1]
        if self.mutual and keep.any():
            back, _ = self._knn(features_b, features_a, 1)
            forward = np.where(keep, index[:, 0], 0)
            keep &= back[forward, 0] == np.arange(len(index))
        rows = np.flatnonzero(keep)
        return Matches(
            index_ab=np.stack([rows, index[rows, 0]], axis=1).astype(np.int64).reshape(-1, 2),
            distance=distance[rows, 0].astype(np.float32),
        )


@dataclass(frozen=True)
class BruteForceMatcher(_NearestNeighbourMatcher):
    """Brute-force nearest neighbour with Lowe's ratio test and/or a mutual check."""

    ratio: float | None = param(0.8, doc="keep a match if d1 < ratio * d2 (null: no ratio test)", gt=0, le=1)
    mutual: bool = param(False, doc="keep only pairs that are each other's nearest neighbour")

    def _knn(self, a: Features, b: Features, k: int):
        return _opencv.knn_match(a.descriptors, b.descriptors, a.norm, k)


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


@hookimpl
def ctpipe_register_stages(registry) -> None:
    registry.add_matcher("brute-force", BruteForceMatcher)
    registry.add_matcher("flann", FlannMatcher)
