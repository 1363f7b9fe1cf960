"""Checks and conversions of input images, shared by every detector."""

from __future__ import annotations

import numpy as np

from ctpipe.errors import InputError

__all__ = ["check_image", "to_uint8", "block_mean"]


def check_image(image, name: str = "image") -> np.ndarray:
    """Return ``image`` as an ndarray after checking it is a usable 2-D picture.

    Raises :class:`InputError` naming what is wrong: not 2-D, empty, not numeric, or with
    NaN/inf pixels.
    """
    image = np.asarray(image)
    if image.ndim != 2:
        raise InputError(f"{name} must be a 2-dimensional array (rows, cols), got shape {image.shape}")
    if image.size == 0:
        raise InputError(f"{name} is empty (shape {image.shape}); it needs at least one pixel")
    if image.dtype == bool or not (np.issubdtype(image.dtype, np.integer) or np.issubdtype(image.dtype, np.floating)):
        raise InputError(f"{name} must have an integer or floating dtype, got {image.dtype}")
    if np.issubdtype(image.dtype, np.floating) and not np.isfinite(image).all():
        bad = int(np.count_nonzero(~np.isfinite(image)))
        raise InputError(f"{name} has {bad} NaN or infinite pixels; replace them (e.g. by interpolation) first")
    return image


def to_uint8(image) -> np.ndarray:
    """Map an image to uint8 for detectors that work on 8-bit grey levels.

    uint8 passes through unchanged. Any other integer or float image is mapped linearly from
    its own [min, max] to [0, 255] and rounded (a constant image becomes all zeros), which
    keeps the contrast of a ``-log`` projection whatever its units.
    """
    image = check_image(image)
    if image.dtype == np.uint8:
        return image
    image = image.astype(np.float64)
    low, high = image.min(), image.max()
    if high <= low:
        return np.zeros(image.shape, dtype=np.uint8)
    return np.rint((image - low) * (255.0 / (high - low))).astype(np.uint8)


def block_mean(image, factor: int) -> np.ndarray:
    """Means of ``factor`` x ``factor`` blocks of a 2-D image, float64; the last partial rows and columns dropped."""
    rows, cols = (image.shape[0] // factor) * factor, (image.shape[1] // factor) * factor
    blocks = np.asarray(image[:rows, :cols], dtype=np.float64).reshape(rows // factor, factor, cols // factor, factor)
    return blocks.mean(axis=(1, 3))
