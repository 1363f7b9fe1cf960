"""Robust losses, one definition for every solver: the view graph and bundle adjustment.

The losses of ``scipy.optimize.least_squares``, as functions of ``z = |r|^2 / scale^2``:
``rho(z)`` equals ``z`` for small residuals and grows more slowly for large ones, so a gross
outlier stops dominating; iteratively reweighted least squares weighs each residual by
``rho'(z)``.

========  ===============================  ====================================
loss      ``rho(z)``                       ``rho'(z)``
========  ===============================  ====================================
linear    ``z``                            ``1``
soft-l1   ``2 (sqrt(1 + z) - 1)``          ``1 / sqrt(1 + z)``
huber     ``z`` below 1, ``2 sqrt(z) - 1``  ``1`` below 1, ``1 / sqrt(z)``
cauchy    ``log(1 + z)``                   ``1 / (1 + z)``
========  ===============================  ====================================
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from ctpipe.errors import InputError

__all__ = ["LOSSES", "Loss", "check_loss", "robust_weight", "robust_loss"]

#: Every robust loss, by its ``scipy.optimize.least_squares`` name.
LOSSES = ("linear", "soft-l1", "huber", "cauchy")

Loss = Literal["linear", "soft-l1", "huber", "cauchy"]


def check_loss(loss: str) -> str:
    """``loss`` if it is one of :data:`LOSSES`, else an :class:`~ctpipe.errors.InputError` listing them."""
    if loss not in LOSSES:
        raise InputError(f"loss: {loss!r} is not supported. Try one of {LOSSES}")
    return loss


def robust_weight(z: np.ndarray, loss: str) -> np.ndarray:
    """``rho'(z)`` of ``z = |r|^2 / scale^2``: the IRLS weight of each residual, in (0, 1]."""
    if loss == "linear":
        return np.ones_like(z)
    if loss == "soft-l1":
        return 1.0 / np.sqrt(1.0 + z)
    if loss == "huber":
        return 1.0 / np.sqrt(np.maximum(z, 1.0))
    if loss == "cauchy":
        return 1.0 / (1.0 + z)
    raise InputError(f"loss: {loss!r} is not supported. Try one of {LOSSES}")


def robust_loss(squared: np.ndarray, loss: str, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """Robust cost ``scale^2 rho(z)`` and weight ``rho'(z)`` of squared residual norms.

    Parameters
    ----------
    squared : ndarray of shape (N,)
        ``|r|^2`` (pixels squared in bundle adjustment).
    loss : str
        One of :data:`LOSSES`.
    scale : float
        Residual norm where the loss starts to flatten, in the unit of ``r``.

    Returns
    -------
    rho : ndarray of shape (N,)
        In the unit of ``squared``; equals ``squared`` for small residuals.
    weight : ndarray of shape (N,)
        ``d rho / d |r|^2``, the weight of each residual in a Gauss-Newton step.
    """
    if loss == "linear":
        return squared, np.ones_like(squared)
    z = squared / scale**2
    weight = robust_weight(z, loss)
    if loss == "soft-l1":
        return 2.0 * scale**2 * (np.sqrt(1.0 + z) - 1.0), weight
    if loss == "huber":
        return np.where(z <= 1.0, squared, scale**2 * (2.0 * np.sqrt(np.maximum(z, 1.0)) - 1.0)), weight
    return scale**2 * np.log1p(z), weight
