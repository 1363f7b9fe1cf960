"""One robust-loss module for every solver."""

from __future__ import annotations

import numpy as np
import pytest

from ctpipe.errors import InputError
from ctpipe.solve.losses import LOSSES, check_loss, robust_loss, robust_weight


@pytest.mark.parametrize("loss", LOSSES)
def test_each_loss_is_quadratic_near_zero_and_its_weight_is_the_derivative(loss):
    scale = 0.5
    squared = np.array([1e-8, 0.01, 0.2, 1.0, 4.0, 100.0])
    rho, weight = robust_loss(squared, loss, scale)
    assert rho[0] == pytest.approx(squared[0], rel=1e-6)
    step = 1e-7
    numeric = (robust_loss(squared + step, loss, scale)[0] - robust_loss(squared - step, loss, scale)[0]) / (2 * step)
    np.testing.assert_allclose(weight, numeric, rtol=1e-5)
    np.testing.assert_array_equal(weight, robust_weight(squared / scale**2, loss))
    assert np.all((weight > 0) & (weight <= 1))


def test_an_unknown_loss_is_refused_with_the_list():
    with pytest.raises(InputError, match=r"^loss: 'l2' is not supported. Try one of \('linear', 'soft-l1', 'huber', "
                                         r"'cauchy'\)$"):
        check_loss("l2")
