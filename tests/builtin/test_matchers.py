"""Matchers at the edges: a view without keypoints on either side."""

import numpy as np
import pytest

from ctpipe.builtin.matchers import BruteForceMatcher, FlannMatcher
from ctpipe.data import Features


def features(n: int, seed: int = 0) -> Features:
    rng = np.random.default_rng(seed)
    return Features.build(xy=rng.uniform(0, 100, (n, 2)), size=np.full(n, 3.0), angle_deg=np.zeros(n),
                          response=rng.uniform(0, 1, n), descriptors=rng.uniform(0, 1, (n, 128)).astype(np.float32),
                          norm="L2")


@pytest.mark.parametrize("matcher", [BruteForceMatcher(mutual=True), BruteForceMatcher(mutual=True, ratio=None),
                                     FlannMatcher(mutual=True)])
def test_mutual_matching_against_a_view_without_keypoints_finds_nothing(matcher):
    some, none = features(20), features(0)
    for a, b in ((some, none), (none, some), (none, none)):
        matches = matcher.match(a, b)
        assert len(matches) == 0 and matches.index_ab.shape == (0, 2)
    assert len(matcher.match(some, features(20))) >= 0
