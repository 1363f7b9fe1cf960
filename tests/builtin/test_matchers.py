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


def test_sift_keeps_opencvs_descriptor_values_as_bytes():
    from ctpipe.builtin import _opencv
    from ctpipe.images import to_uint8
    from ctpipe.plugins import get_registry
    from ctpipe.testing import textured_image

    detector = get_registry().get("detector", "sift").cls()
    image = textured_image((160, 200))
    found = detector.detect(image)
    keypoints, raw = _opencv.raw_detect_and_compute("sift", detector.params())(to_uint8(image))
    assert found.descriptors.dtype == np.uint8 and raw.dtype == np.float32 and len(found) == len(raw) > 20
    # The same values, in Features' order (strongest first, then y, then x).
    xy = np.array([k.pt for k in keypoints], np.float32)
    order = np.lexsort((xy[:, 0], xy[:, 1], -np.array([k.response for k in keypoints], np.float32)))
    np.testing.assert_array_equal(found.descriptors.astype(np.float32), raw[order])


@pytest.mark.parametrize("matcher", [BruteForceMatcher(mutual=True), BruteForceMatcher(ratio=0.9),
                                     FlannMatcher(mutual=True)])
def test_byte_descriptors_match_as_their_float_values(matcher):
    rng = np.random.default_rng(3)

    def pair(dtype):
        values = rng.integers(0, 256, (60, 128))
        return Features.build(xy=rng.uniform(0, 100, (60, 2)), size=np.full(60, 3.0), angle_deg=np.zeros(60),
                              response=np.arange(60.0, 0, -1), descriptors=values.astype(dtype), norm="L2")

    a8, b8 = pair(np.uint8), pair(np.uint8)
    a32 = Features.build(xy=a8.xy, size=a8.size, angle_deg=a8.angle_deg, response=a8.response,
                         descriptors=a8.descriptors.astype(np.float32), norm="L2")
    assert a8.descriptors.dtype == np.uint8 and a32.descriptors.dtype == np.float32
    # Near neighbours exist: b holds a's descriptors plus a little noise, shuffled.
    b_values = np.clip(a8.descriptors[rng.permutation(60)].astype(int) + rng.integers(-3, 4, (60, 128)), 0, 255)
    b8 = Features.build(xy=b8.xy, size=b8.size, angle_deg=b8.angle_deg, response=b8.response,
                        descriptors=b_values.astype(np.uint8), norm="L2")
    b32 = Features.build(xy=b8.xy, size=b8.size, angle_deg=b8.angle_deg, response=b8.response,
                         descriptors=b_values.astype(np.float32), norm="L2")
    for a, b in ((a8, b8), (a8, b32), (a32, b8)):
        got, want = matcher.match(a, b), matcher.match(a32, b32)
        assert len(want) > 40
        np.testing.assert_array_equal(got.index_ab, want.index_ab)
        np.testing.assert_allclose(got.distance, want.distance, rtol=1e-6)


def test_features_take_float32_or_byte_descriptors_for_float_norms():
    from ctpipe.errors import InputError

    base = dict(xy=np.zeros((2, 2), np.float32), size=np.ones(2, np.float32), angle_deg=np.zeros(2, np.float32),
                response=np.ones(2, np.float32), octave=np.zeros(2, np.int32), class_id=np.zeros(2, np.int32))
    for dtype in (np.float32, np.uint8):
        assert Features(**base, descriptors=np.zeros((2, 4), dtype), norm="L2").descriptors.dtype == dtype
    with pytest.raises(InputError, match="float32 .or whole-number uint8. descriptors"):
        Features(**base, descriptors=np.zeros((2, 4), np.float64), norm="L2")
