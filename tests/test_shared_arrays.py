"""The whole-array helpers give numpy's answers: :func:`all_finite` and :func:`percentile_in_place`."""

from __future__ import annotations

import numpy as np
import pytest

from ctpipe._shared.arrays import all_finite, percentile_in_place


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_one_bad_value_in_a_large_array_is_found(dtype, bad):
    values = np.random.default_rng(0).random((40, 160, 200)).astype(dtype)   # above the threaded size
    assert all_finite(values)
    values[17, 3, 199] = bad
    assert not all_finite(values)
    assert not all_finite(values[::-1])   # not contiguous: numpy's own check


def test_small_and_integer_arrays_are_checked_too():
    assert all_finite(np.arange(5)) and not all_finite(np.array([1.0, np.nan]))


@pytest.mark.parametrize("n", [1, 2, 11, 1000, 4097])
@pytest.mark.parametrize("q", [0, 1, 37.5, 50, 99, 100])
def test_the_percentile_is_numpys_linear_one(n, q):
    values = np.random.default_rng(n).normal(size=n).astype(np.float32)
    assert percentile_in_place(values.copy(), q) == pytest.approx(float(np.percentile(values, q)), rel=1e-6, abs=1e-7)
