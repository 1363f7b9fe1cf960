"""Both-ways brute-force neighbours against plain distance matrices and OpenCV's BFMatcher."""

from __future__ import annotations

import numpy as np
import pytest

from ctpipe.builtin import _opencv
from ctpipe.features.nearest import l2_neighbours


def _exact(a, b):
    return np.sqrt(((a[:, None, :].astype(np.float64) - b[None, :, :]) ** 2).sum(-1))


@pytest.mark.parametrize("k", [1, 2])
def test_neighbours_are_the_exact_ones_both_ways(k):
    rng = np.random.default_rng(3)
    a = (rng.random((300, 128)) * 100).astype(np.float32)
    b = np.concatenate([a[:150] + rng.normal(0, 3, (150, 128)), rng.random((200, 128)) * 100]).astype(np.float32)
    index, distance, back = l2_neighbours(a, b, k)
    d = _exact(a, b)
    order = np.argsort(d, axis=1)[:, :k]
    np.testing.assert_array_equal(index, order)
    np.testing.assert_allclose(distance, np.take_along_axis(d, order, 1), rtol=1e-6)
    np.testing.assert_array_equal(back, d.argmin(axis=0))
    # The same as OpenCV's brute force, asked twice.
    cv_index, cv_distance = _opencv.knn_match(a, b, "L2", k)
    np.testing.assert_array_equal(index, cv_index)
    np.testing.assert_array_equal(back, _opencv.knn_match(b, a, "L2", 1)[0][:, 0])


def test_missing_neighbours_are_minus_one_and_inf():
    a = np.ones((3, 8), np.float32)
    index, distance, back = l2_neighbours(a, a[:1], 2)
    assert (index[:, 0] == 0).all() and (index[:, 1] == -1).all() and np.isinf(distance[:, 1]).all()
    assert back.tolist() == [0]
    index, distance, back = l2_neighbours(a[:0], a, 2)
    assert index.shape == (0, 2) and back.tolist() == [-1, -1, -1]
    with pytest.raises(ValueError, match="k must be 1 or 2"):
        l2_neighbours(a, a, 3)
