"""Flat/dark correction: raw detector counts to line integrals, for simulated and real scans.

A projection ``I``, flat fields ``F`` (beam, no object) and dark fields ``D`` (no beam) give the
line integrals::

    p_hat = -log((I - mean(D)) / (mean(F) - mean(D)))

Photon starvation makes ``I - D`` zero or negative, whose log is undefined: the transmission
is clipped from below at ``min_transmission`` (default 1e-6, i.e. ``p_hat <= 13.8``). Pixels
whose flat is not above their dark (dead pixels) carry no information and get ``p_hat = 0``;
when more than half the pixels are so, the flats and darks are refused (swapped, or mislabelled).
Noise can make the transmission exceed 1: those ``p_hat`` stay negative, unbiased. The noise
model the simulator records with is :mod:`ctpipe.sim.acquisition`.

The result is float32; the arithmetic is float64, one view at a time.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np

from ctpipe._shared.resources import available_cores
from ctpipe.errors import InputError

__all__ = ["log_transform", "mean_frame", "MAX_DEAD_FRACTION"]

#: The largest fraction of pixels whose flat is not above their dark that :func:`log_transform`
#: takes as dead pixels; beyond it the flats and darks cannot correct the scan.
MAX_DEAD_FRACTION = 0.5


def mean_frame(frames, shape: tuple[int, int], name: str) -> np.ndarray:
    """Calibration frames ``(F, rows, cols)`` averaged (float64), or one frame ``(rows, cols)`` as it is."""
    frames = np.asarray(frames, dtype=np.float64)
    if frames.ndim == 3:
        frames = frames.mean(axis=0)
    if frames.shape != shape:
        raise InputError(f"{name}: each frame must have the projections' shape {shape}, got {frames.shape}")
    return frames


def log_transform(intensities, flats=None, darks=None, *, photons_per_pixel: float | None = None,
                  min_transmission: float = 1e-6) -> np.ndarray:
    """Flat/dark-corrected line integrals ``-log((I - D) / (F - D))`` (see the module docstring).

    Parameters
    ----------
    intensities : ndarray of shape (V, rows, cols)
        Raw counts (any real dtype, e.g. uint16 or float32).
    flats : ndarray of shape (F, rows, cols) or (rows, cols), or None
        Flat fields, averaged over frames. None needs ``photons_per_pixel``, a uniform flat.
    darks : ndarray of shape (D, rows, cols) or (rows, cols), or None
        Dark fields, averaged over frames; None means no offset.
    photons_per_pixel : float or None
        The flat level when ``flats`` is None.
    min_transmission : float
        Lower clip of the transmission, > 0: bounds ``p`` at ``-log(min_transmission)``.

    Returns
    -------
    ndarray of shape (V, rows, cols), float32
    """
    counts = np.asarray(intensities)
    if counts.ndim != 3 or not (np.issubdtype(counts.dtype, np.integer) or np.issubdtype(counts.dtype, np.floating)):
        raise InputError(f"intensities: must be a real array of shape (views, rows, cols), "
                         f"got {counts.dtype} of shape {counts.shape}")
    if not min_transmission > 0:
        raise InputError(f"min_transmission: must be > 0, got {min_transmission!r}")
    shape = counts.shape[1:]

    flat = None if flats is None else mean_frame(flats, shape, "flats")
    dark = None if darks is None else mean_frame(darks, shape, "darks")
    if flat is None:
        if photons_per_pixel is None:
            raise InputError("log_transform: give flats or photons_per_pixel (the unattenuated counts)")
        flat = np.full(shape, float(photons_per_pixel))
    if dark is None:
        dark = np.zeros(shape)
    beam = flat - dark
    alive = beam > 0
    # A few dead pixels are normal; most of the detector dark is not: every line integral would
    # be 0, and the failure would only surface far downstream ("0 keypoints per view").
    dead = 1.0 - float(np.count_nonzero(alive)) / alive.size
    if dead > MAX_DEAD_FRACTION:
        raise InputError(f"flats must be brighter than darks: {100.0 * dead:.0f} % of pixels have dark >= flat "
                         f"(mean flat {float(flat.mean()):.4g}, mean dark {float(dark.mean()):.4g}; at most "
                         f"{100.0 * MAX_DEAD_FRACTION:.0f} % may be dead pixels), so the flat/dark correction is "
                         "impossible; are the flats and darks swapped?")
    beam = np.where(alive, beam, 1.0)
    out = np.empty(counts.shape, np.float32)

    def view(v: int) -> None:
        transmission = np.maximum((counts[v].astype(np.float64) - dark) / beam, min_transmission)
        out[v] = np.where(alive, -np.log(transmission), 0.0)

    # One view at a time in float64 (no float64 copy of the stack), the views in threads: numpy
    # lets go of the GIL in these element-wise loops.
    with ThreadPoolExecutor(max_workers=available_cores()) as pool:
        list(pool.map(view, range(len(counts))))
    return out
