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


def test_all_pairs_proposes_every_pair_within_the_row_band_closest_first():
    from ctpipe.builtin.matchers import AllPairsMatcher
    from ctpipe.errors import InputError

    def at(xy):
        xy = np.asarray(xy, dtype=float)
        return Features.build(xy=xy, size=np.full(len(xy), 10.0), angle_deg=np.full(len(xy), np.nan),
                              response=np.arange(len(xy), 0, -1), descriptors=np.zeros((len(xy), 2)), norm="L2")

    a = at([[10.0, 50.0], [200.0, 100.0]])
    b = at([[300.0, 52.0], [20.0, 60.0], [150.0, 101.0], [40.0, 200.0]])
    matches = AllPairsMatcher(max_row_shift_px=10.0).match(a, b)
    # Keypoint 0 (row 50) pairs with rows 52 and 60; keypoint 1 (row 100) with row 101; row 200 with none.
    assert matches.index_ab.tolist() == [[0, 0], [0, 1], [1, 2]]
    np.testing.assert_allclose(matches.distance, [2.0, 10.0, 1.0])
    assert len(AllPairsMatcher().match(a, at(np.zeros((0, 2))))) == 0
    with pytest.raises(InputError, match="all-pairs: 2 x 4 keypoints make 8 candidate pairs, more than max_pairs 5"):
        AllPairsMatcher(max_pairs=5).match(a, b)
