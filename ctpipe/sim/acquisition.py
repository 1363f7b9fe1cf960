"""The X-ray detector: Beer-Lambert counts with Poisson noise, flat and dark fields, ``-log``.

A pixel whose ray has line integral ``p`` (the sum of attenuation x length, dimensionless)
sees, in one frame::

    I = Poisson(I0 exp(-p)) + Poisson(dark_counts)      (a projection)
    F = Poisson(I0)         + Poisson(dark_counts)      (a flat field: no object)
    D =                       Poisson(dark_counts)      (a dark field: no beam)

with ``I0 = photons_per_pixel``, the unattenuated photons a pixel counts in one frame. The
reconstruction starts from the flat/dark-corrected line integrals::

    p_hat = -log((I - mean(D)) / (mean(F) - mean(D)))

Photon starvation makes ``I - D`` zero or negative, whose log is undefined: the transmission
is clipped from below at ``min_transmission`` (default 1e-6, i.e. ``p_hat <= 13.8``). Pixels
whose flat is not above their dark (dead pixels) carry no information and get ``p_hat = 0``;
when more than half the pixels are so, the flats and darks are refused (swapped, or mislabelled).
Noise can make the transmission exceed 1: those ``p_hat`` stay negative, unbiased.

Every array this module returns is float32 (Poisson counts below 2^24 are exact in it); the
arithmetic is float64, one view at a time, so that a 360-view 512^2 scan needs no float64
copy of the whole stack.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ctpipe.config import check_keys
from ctpipe.errors import InputError
from ctpipe.stages import ParamSpec, check_value

__all__ = ["NoiseModel", "parse_noise", "beer_lambert", "acquire", "log_transform", "MAX_DEAD_FRACTION"]

#: The largest fraction of pixels whose flat is not above their dark that :func:`log_transform`
#: takes as dead pixels; beyond it the flats and darks cannot correct the scan.
MAX_DEAD_FRACTION = 0.5


@dataclass(frozen=True)
class NoiseModel:
    """Detector exposure and the calibration frames of a noisy acquisition.

    Parameters
    ----------
    photons_per_pixel : float
        ``I0``: mean counts of an unattenuated pixel in one frame (> 0).
    flat_frames : int
        Flat fields recorded (>= 1); their mean is the reference ``I0``.
    dark_frames : int
        Dark fields recorded (>= 0); with 0 the offset is taken as 0.
    dark_counts : float
        Mean dark-current counts per pixel and frame (>= 0), added to every frame.
    """

    photons_per_pixel: float
    flat_frames: int = 8
    dark_frames: int = 4
    dark_counts: float = 0.0

    def __post_init__(self) -> None:
        for key, spec in _NOISE_FIELDS.items():
            object.__setattr__(self, key, check_value(spec, getattr(self, key), f"noise.{key}"))

    def to_dict(self) -> dict:
        return {key: getattr(self, key) for key in _NOISE_FIELDS}


#: Largest photon count per pixel and frame: numpy's Poisson sampler refuses means beyond ~1e19
#: ("lam value too large"), and real detectors count well under 1e6.
MAX_PHOTONS = 1e12

_NOISE_FIELDS = {
    "photons_per_pixel": ParamSpec("photons_per_pixel", float, None, "", gt=0, le=MAX_PHOTONS),
    "flat_frames": ParamSpec("flat_frames", int, 8, "", ge=1, le=10_000),
    "dark_frames": ParamSpec("dark_frames", int, 4, "", ge=0, le=10_000),
    "dark_counts": ParamSpec("dark_counts", float, 0.0, "", ge=0, le=MAX_PHOTONS),
}


def parse_noise(value: Any, path: str = "noise") -> NoiseModel | None:
    """Validate a ``noise`` mapping; ``null`` or ``photons_per_pixel: null`` means noise-free."""
    if value is None:
        return None
    check_keys(value, path, allowed=tuple(_NOISE_FIELDS), required=("photons_per_pixel",))
    spec = ParamSpec("photons_per_pixel", float | None, None, "", gt=0, le=MAX_PHOTONS)
    if check_value(spec, value["photons_per_pixel"], f"{path}.photons_per_pixel") is None:
        return None
    values = {key: check_value(_NOISE_FIELDS[key], raw, f"{path}.{key}") for key, raw in value.items()}
    return NoiseModel(**values)


def _stack(line_integrals) -> np.ndarray:
    p = np.asarray(line_integrals)
    if p.ndim not in (2, 3) or not np.issubdtype(p.dtype, np.floating):
        raise InputError(f"line_integrals: must be a float array of shape (views, rows, cols) or (rows, cols), "
                         f"got {p.dtype} of shape {p.shape}")
    return p


def beer_lambert(line_integrals, photons_per_pixel: float, dark_counts: float = 0.0) -> np.ndarray:
    """Noise-free mean counts ``I0 exp(-p) + dark_counts``, float32 of the input's shape."""
    p = _stack(line_integrals)
    return (photons_per_pixel * np.exp(-p.astype(np.float64)) + dark_counts).astype(np.float32)


def acquire(line_integrals, noise: NoiseModel, rng: np.random.Generator
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Record a scan with Poisson noise (see the module docstring).

    Parameters
    ----------
    line_integrals : ndarray of shape (V, rows, cols)
        Exact line integrals at the true angles.
    noise : NoiseModel
    rng : numpy.random.Generator
        Draws the projections view by view, then the flats, then the darks.

    Returns
    -------
    intensities : ndarray of shape (V, rows, cols), float32
    flats : ndarray of shape (flat_frames, rows, cols), float32
    darks : ndarray of shape (dark_frames, rows, cols), float32, or None when dark_frames is 0
    """
    p = _stack(line_integrals)
    if p.ndim == 2:
        p = p[None]
    i0, dark = noise.photons_per_pixel, noise.dark_counts
    shape = p.shape[1:]

    def frame(mean: np.ndarray | float) -> np.ndarray:
        counts = rng.poisson(mean, size=shape).astype(np.float64)
        if dark > 0:
            counts += rng.poisson(dark, size=shape)
        return counts.astype(np.float32)

    intensities = np.empty(p.shape, np.float32)
    for v in range(len(p)):
        intensities[v] = frame(i0 * np.exp(-p[v].astype(np.float64)))
    flats = np.stack([frame(i0) for _ in range(noise.flat_frames)])
    darks = None
    if noise.dark_frames:
        darks = np.stack([rng.poisson(dark, size=shape).astype(np.float32) for _ in range(noise.dark_frames)])
    return intensities, flats, darks


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

    def mean_frame(frames, name: str) -> np.ndarray | None:
        if frames is None:
            return None
        frames = np.asarray(frames, dtype=np.float64)
        if frames.ndim == 3:
            frames = frames.mean(axis=0)
        if frames.shape != shape:
            raise InputError(f"{name}: each frame must have the projections' shape {shape}, got {frames.shape}")
        return frames

    flat = mean_frame(flats, "flats")
    dark = mean_frame(darks, "darks")
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
    for v in range(len(counts)):
        transmission = np.maximum((counts[v].astype(np.float64) - dark) / beam, min_transmission)
        out[v] = np.where(alive, -np.log(transmission), 0.0)
    return out
